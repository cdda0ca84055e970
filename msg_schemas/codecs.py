"""The three vector codecs the systems use: JointState arrays, Odometry (rigid body or point mass), TwistStamped.

All of them take and return float64 numpy vectors, build messages with a :class:`~msg_schemas.base.MessageFactory`
and read rclpy messages and rosbags dataclasses alike.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from msg_schemas.base import (
    FieldDoc,
    MessageFactory,
    SchemaError,
    VectorCodec,
    check_finite,
    names_equal,
    read_stamp,
)

JOINT_STATE = "sensor_msgs/msg/JointState"
ODOMETRY = "nav_msgs/msg/Odometry"
TWIST_STAMPED = "geometry_msgs/msg/TwistStamped"

_ARRAYS = ("position", "velocity", "effort")
#: a received orientation quaternion must have a norm within 1 +- this tolerance
QUAT_NORM_TOL = 1e-3


# -------------------------------------------------------------------------------------- JointState
class JointStateCodec(VectorCodec):
    """A vector as ``sensor_msgs/JointState``: each vector field is one joint's position, velocity or effort.

    Args:
        fields: ``(vector field, unit, joint name, array)`` per vector field, in vector order; ``array`` is
            ``"position"``, ``"velocity"`` or ``"effort"``. Several fields may share a joint (different arrays).
        convention: one line for the docs.

    Arrays that carry values have exactly one entry per joint; the others are sent empty and, when received,
    must be empty or one per joint (the JointState rule).
    """

    msg_type = JOINT_STATE

    def __init__(self, fields: Sequence[tuple[str, str, str, str]], convention: str) -> None:
        self._fields = tuple(fields)
        self.field_names = tuple(f[0] for f in self._fields)
        self.units = tuple(f[1] for f in self._fields)
        self.convention = convention
        self.joints: tuple[str, ...] = tuple(dict.fromkeys(f[2] for f in self._fields))
        self._slots = [(array, self.joints.index(joint)) for _, _, joint, array in self._fields]
        for array, _ in self._slots:
            if array not in _ARRAYS:
                raise ValueError(f"array must be one of {_ARRAYS}, got {array!r}")
        self.arrays = tuple(a for a in _ARRAYS if any(s[0] == a for s in self._slots))
        if len(set(self._slots)) != len(self._slots):
            raise ValueError("two vector fields map to the same joint array entry")
        if set(self._slots) != {(a, j) for a in self.arrays for j in range(len(self.joints))}:
            raise ValueError("every used array must carry a value for every joint")

    def field_docs(self) -> tuple[FieldDoc, ...]:
        return tuple(
            FieldDoc(name, unit, f"{array}[{self.joints.index(joint)}]", f"/{joint}/{array}")
            for name, unit, joint, array in self._fields
        )

    def _build(self, vec: np.ndarray, header: Any, factory: MessageFactory, child_frame_id: str | None) -> Any:
        arrays = {a: np.zeros(len(self.joints) if a in self.arrays else 0) for a in _ARRAYS}
        for value, (array, j) in zip(vec, self._slots, strict=True):
            arrays[array][j] = value
        return factory.make(JOINT_STATE, header=header, name=list(self.joints), **arrays)

    def from_msg(self, msg: Any, topic: str = "") -> tuple[np.ndarray, int]:
        stamp = read_stamp(msg.header.stamp, topic)
        names_equal(topic, msg.name, self.joints)
        n = len(self.joints)
        values = {}
        for array in _ARRAYS:
            arr = np.asarray(getattr(msg, array), dtype=np.float64)
            allowed = (n,) if array in self.arrays else (0, n)
            if arr.shape[0] not in allowed:
                raise SchemaError(
                    topic, array, "shape", f"expected {' or '.join(map(str, allowed))} values, got {arr.shape[0]}"
                )
            values[array] = arr
        out = np.empty(self.size)
        for i, (name, (array, j)) in enumerate(zip(self.field_names, self._slots, strict=True)):
            out[i] = check_finite(topic, f"{array}[{j}]", name, float(values[array][j]))
        return out, stamp


# ------------------------------------------------------------------------------------------ rotations
def rotation_matrix(q_wxyz: np.ndarray) -> np.ndarray:
    """Rotation matrix (body -> world, ``v_w = R v_b``) of quaternion ``[w, x, y, z]``, normalised first.

    A zero or non-finite quaternion gives a NaN matrix (so a broken state publishes NaN velocities that
    receivers reject, instead of raising inside a simulator).
    """
    norm = float(np.linalg.norm(q_wxyz))
    if not np.isfinite(norm) or norm == 0.0:
        return np.full((3, 3), np.nan)
    w, x, y, z = np.asarray(q_wxyz, dtype=np.float64) / norm
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def _vec3(factory: MessageFactory, v: np.ndarray) -> Any:
    return factory.make("geometry_msgs/msg/Vector3", x=float(v[0]), y=float(v[1]), z=float(v[2]))


def _read3(topic: str, obj: Any, path: str, names: Sequence[str]) -> np.ndarray:
    return np.array(
        [check_finite(topic, f"{path}.{a}", n, float(getattr(obj, a))) for a, n in zip("xyz", names, strict=True)]
    )


# ----------------------------------------------------------------------------------------- Odometry
_P = ("px", "py", "pz")
_V = ("vx", "vy", "vz")
_Q = ("qw", "qx", "qy", "qz")
_W = ("wx", "wy", "wz")


class OdometryCodec(VectorCodec):
    """A rigid body or a point mass as ``nav_msgs/Odometry`` (REP 105: twist in the child frame).

    ``rigid_body=True`` (quadrotor): vector ``[px, py, pz, vx, vy, vz (world), qw, qx, qy, qz, wx, wy, wz (body)]``;
    the pose carries position and orientation, ``twist.linear`` the body-frame velocity ``R(q)^T v`` and
    ``twist.angular`` the body rates. ``rigid_body=False`` (ball): vector ``[px, py, pz, vx, vy, vz (world)]``;
    orientation identity, so the child frame is parallel to the world and ``twist.linear`` is the world velocity.
    Reading always applies ``v = R(q) twist.linear`` with the received orientation, so both read any
    correctly framed odometry; the quaternion must be finite with norm 1 +- :data:`QUAT_NORM_TOL`.
    """

    msg_type = ODOMETRY

    def __init__(self, *, rigid_body: bool, frame_id: str, child_frame_id: str, units: Sequence[str]) -> None:
        self.rigid_body = rigid_body
        self.field_names = _P + _V + (_Q + _W if rigid_body else ())
        self.units = tuple(units)
        if len(self.units) != len(self.field_names):
            raise ValueError("one unit per field")
        self.frame_id = frame_id
        self.child_frame_id = child_frame_id
        self.convention = (
            f"Odometry frame_id={frame_id!r} child_frame_id={child_frame_id!r}; twist in the child frame; "
            + ("velocity rotated into the body frame" if rigid_body else "orientation identity")
        )

    def field_docs(self) -> tuple[FieldDoc, ...]:
        unit = dict(zip(self.field_names, self.units, strict=True))
        docs = [
            FieldDoc(n, unit[n], f"pose.pose.position.{a}", f"/pose/pose/position/{a}")
            for n, a in zip(_P, "xyz", strict=True)
        ]
        if self.rigid_body:
            note = "body frame: twist.linear = R(q)^T [vx, vy, vz]; read back as R(q) twist.linear"
            docs += [
                FieldDoc(n, unit[n], f"twist.twist.linear.{a}", f"/twist/twist/linear/{a}", note)
                for n, a in zip(_V, "xyz", strict=True)
            ]
            docs += [
                FieldDoc(n, unit[n], f"pose.pose.orientation.{a}", f"/pose/pose/orientation/{a}")
                for n, a in zip(_Q, "wxyz", strict=True)
            ]
            docs += [
                FieldDoc(n, unit[n], f"twist.twist.angular.{a}", f"/twist/twist/angular/{a}")
                for n, a in zip(_W, "xyz", strict=True)
            ]
        else:
            docs += [
                FieldDoc(
                    n,
                    unit[n],
                    f"twist.twist.linear.{a}",
                    f"/twist/twist/linear/{a}",
                    "world frame (identity orientation)",
                )
                for n, a in zip(_V, "xyz", strict=True)
            ]
        return tuple(docs)

    def _build(self, vec: np.ndarray, header: Any, factory: MessageFactory, child_frame_id: str | None) -> Any:
        p, v = vec[0:3], vec[3:6]
        if self.rigid_body:
            q, w = vec[6:10], vec[10:13]
            with np.errstate(invalid="ignore"):
                v_child = rotation_matrix(q).T @ v
        else:
            q, w, v_child = np.array([1.0, 0.0, 0.0, 0.0]), np.zeros(3), v
        pose = factory.make(
            "geometry_msgs/msg/Pose",
            position=factory.make("geometry_msgs/msg/Point", x=float(p[0]), y=float(p[1]), z=float(p[2])),
            orientation=factory.make(
                "geometry_msgs/msg/Quaternion", x=float(q[1]), y=float(q[2]), z=float(q[3]), w=float(q[0])
            ),
        )
        twist = factory.make("geometry_msgs/msg/Twist", linear=_vec3(factory, v_child), angular=_vec3(factory, w))
        return factory.make(
            ODOMETRY,
            header=header,
            child_frame_id=self.child_frame_id if child_frame_id is None else child_frame_id,
            pose=factory.make("geometry_msgs/msg/PoseWithCovariance", pose=pose, covariance=np.zeros(36)),
            twist=factory.make("geometry_msgs/msg/TwistWithCovariance", twist=twist, covariance=np.zeros(36)),
        )

    def from_msg(self, msg: Any, topic: str = "") -> tuple[np.ndarray, int]:
        stamp = read_stamp(msg.header.stamp, topic)
        pose, twist = msg.pose.pose, msg.twist.twist
        p = _read3(topic, pose.position, "pose.pose.position", _P)
        o = pose.orientation
        q = np.array(
            [
                check_finite(topic, f"pose.pose.orientation.{a}", n, float(getattr(o, a)))
                for a, n in zip("wxyz", _Q, strict=True)
            ]
        )
        norm = float(np.linalg.norm(q))
        if abs(norm - 1.0) > QUAT_NORM_TOL:
            raise SchemaError(topic, "pose.pose.orientation", "quaternion", f"quaternion norm {norm:.6g} is not 1")
        v = rotation_matrix(q) @ _read3(topic, twist.linear, "twist.twist.linear", _V)
        if not self.rigid_body:
            return np.concatenate((p, v)), stamp
        w = _read3(topic, twist.angular, "twist.twist.angular", _W)
        return np.concatenate((p, v, q, w)), stamp


# ------------------------------------------------------------------------------------- TwistStamped
class LinearVelocityCodec(VectorCodec):
    """A world-frame velocity ``[vx, vy, vz]`` as ``geometry_msgs/TwistStamped`` (``twist.linear``; angular 0)."""

    msg_type = TWIST_STAMPED

    def __init__(self, *, frame_id: str, units: Sequence[str] = ("m/s", "m/s", "m/s")) -> None:
        self.field_names = _V
        self.units = tuple(units)
        self.frame_id = frame_id
        self.convention = f"TwistStamped frame_id={frame_id!r}; twist.linear = velocity, twist.angular = 0"

    def field_docs(self) -> tuple[FieldDoc, ...]:
        return tuple(
            FieldDoc(n, u, f"twist.linear.{a}", f"/twist/linear/{a}")
            for n, u, a in zip(self.field_names, self.units, "xyz", strict=True)
        )

    def _build(self, vec: np.ndarray, header: Any, factory: MessageFactory, child_frame_id: str | None) -> Any:
        twist = factory.make("geometry_msgs/msg/Twist", linear=_vec3(factory, vec), angular=_vec3(factory, np.zeros(3)))
        return factory.make(TWIST_STAMPED, header=header, twist=twist)

    def from_msg(self, msg: Any, topic: str = "") -> tuple[np.ndarray, int]:
        stamp = read_stamp(msg.header.stamp, topic)
        return _read3(topic, msg.twist.linear, "twist.linear", _V), stamp
