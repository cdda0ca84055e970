"""The lockstep path's messages as CDR bytes, without message objects: ``nav_msgs/Odometry`` and
``sensor_msgs/JointState`` (:class:`CdrCodec`).

rclpy turns every received message into Python objects (an Odometry: nine nested objects and two 36-element
covariance arrays) and every published one back; per lockstep step that cost about as much as the simulation
step itself (docs/performance.md, "The loop"). A node that subscribes with ``raw=True`` gets the CDR bytes DDS
delivered, and ``Publisher.publish`` takes bytes too, so the vector codecs' messages can be written and read
directly:

* :meth:`CdrCodec.encode` writes exactly the bytes ``rclpy.serialization.serialize_message`` writes for the
  message :meth:`~msg_schemas.base.VectorCodec.to_msg` builds (``test/test_msg_schemas.py`` checks byte
  equality);
* :meth:`CdrCodec.decode` reads a well-formed little-endian message's vector and stamp; anything else (a
  big-endian sender, a malformed or truncated message, a value the codec's ``from_msg`` would reject: NaN, a
  bad stamp, a bad quaternion, wrong joint names or array sizes) takes the object path (deserialize, then
  ``from_msg``), so errors are reported exactly as before.

Layout (plain CDR, XCDR1, ROS 2's default): a 4-byte encapsulation header (``00 01 00 00`` = little endian),
then the fields in order, each aligned to its own size relative to the end of that header; strings are a
uint32 length (with the terminating NUL), the bytes and the NUL; sequences a uint32 count, then the elements.
"""

from __future__ import annotations

import math
import os
import struct
from typing import Any

import numpy as np

from msg_schemas.base import NS_PER_S, VectorCodec
from msg_schemas.codecs import QUAT_NORM_TOL, JointStateCodec, OdometryCodec, rotation_matrix

#: encapsulation header of little-endian plain CDR
_LE = b"\x00\x01\x00\x00"
_STAMP = struct.Struct("<iI")
_U32 = struct.Struct("<I")
#: doubles of an Odometry after its two strings: pose (3 + 4), covariance 36, twist (3 + 3), covariance 36
_ODOM_DOUBLES = 85


def _string(text: str, pos: int) -> tuple[bytes, int]:
    """CDR of ``text`` written at body offset ``pos`` (4-aligned first): the bytes (with any padding before the
    length) and the offset after them."""
    pad = -pos % 4
    raw = text.encode() + b"\x00"
    return b"\x00" * pad + _U32.pack(len(raw)) + raw, pos + pad + 4 + len(raw)


def _read_string(data: bytes | memoryview, pos: int) -> tuple[bytes, int]:
    """The string at body offset ``pos`` (4-aligned first) of the message ``data`` (``pos`` counts from the
    end of the encapsulation header) without its NUL, and the offset after it; ``ValueError`` if truncated."""
    pos += -pos % 4
    (n,) = _U32.unpack_from(data, 4 + pos)
    end = pos + 4 + n
    if n == 0 or 4 + end > len(data):
        raise ValueError("string out of range")
    return bytes(data[4 + pos + 4 : 4 + end - 1]), end


class CdrCodec:
    """The CDR fast path of one vector codec (an :class:`~msg_schemas.codecs.OdometryCodec` or a
    :class:`~msg_schemas.codecs.JointStateCodec`; see the module docstring). Any other codec works too, on the
    object path (``to_msg`` + ``serialize_message``, ``deserialize_message`` + ``from_msg``).

    ``encode(x, stamp_ns)`` -> bytes for ``Publisher.publish``; ``decode(data, topic)`` -> ``(x, stamp_ns)``
    (a :class:`~msg_schemas.base.SchemaError` as ``from_msg`` raises it).
    """

    def __init__(self, codec: VectorCodec) -> None:
        self.codec = codec
        self._msg_cls: Any = None
        #: False for a codec without a fast path (e.g. TwistStamped): its messages take the object path; the
        #: environment variable SAML_CDR=0 turns every fast path off (to measure the object path, bench_closed_loop)
        self.fast = isinstance(codec, OdometryCodec | JointStateCodec) and os.environ.get("SAML_CDR", "1") != "0"
        if isinstance(codec, OdometryCodec):
            self._init_odometry(codec)
        elif isinstance(codec, JointStateCodec):
            self._init_joint_state(codec)

    # ------------------------------------------------------------------------------------------ Odometry
    def _init_odometry(self, codec: OdometryCodec) -> None:
        frame, pos = _string(codec.frame_id, 8)
        child, pos = _string(codec.child_frame_id, pos)
        pad = -pos % 8
        self._prefix = frame + child + b"\x00" * pad
        self._body = np.zeros(_ODOM_DOUBLES)  # covariances stay zero, as to_msg builds them
        if not codec.rigid_body:
            self._body[6] = 1.0  # identity orientation (w is the pose's 7th double: x, y, z, qx, qy, qz, qw)

    def _encode_odometry(self, x: np.ndarray) -> bytes:
        body = self._body
        codec = self.codec
        assert isinstance(codec, OdometryCodec)
        body[0:3] = x[0:3]
        if codec.rigid_body:
            q = x[6:10]
            with np.errstate(invalid="ignore"):
                body[43:46] = rotation_matrix(q).T @ x[3:6]
            body[3:6] = q[1:4]
            body[6] = q[0]
            body[46:49] = x[10:13]
        else:
            body[43:46] = x[3:6]
        return self._prefix + body.tobytes()

    def _decode_odometry(self, data: bytes | memoryview, stamp: int) -> np.ndarray | None:
        codec = self.codec
        assert isinstance(codec, OdometryCodec)
        _, pos = _read_string(data, 8)
        _, pos = _read_string(data, pos)
        pos += -pos % 8
        if 4 + pos + 8 * _ODOM_DOUBLES != len(data):
            return None
        d = np.frombuffer(data, dtype="<f8", count=_ODOM_DOUBLES, offset=4 + pos)
        p, q_xyzw, v_child, w = d[0:3], d[3:7], d[43:46], d[46:49]
        used = np.concatenate((p, q_xyzw, v_child, w))
        if not np.isfinite(used).all():
            return None
        q = np.array((q_xyzw[3], q_xyzw[0], q_xyzw[1], q_xyzw[2]))
        if abs(math.sqrt(float(q @ q)) - 1.0) > QUAT_NORM_TOL:
            return None
        v = rotation_matrix(q) @ v_child
        if not codec.rigid_body:
            return np.concatenate((p, v))
        return np.concatenate((p, v, q, w))

    # ---------------------------------------------------------------------------------------- JointState
    def _init_joint_state(self, codec: JointStateCodec) -> None:
        frame, pos = _string(codec.frame_id, 8)
        pad = -pos % 4
        pos += pad + 4
        names = b""
        for joint in codec.joints:
            raw, pos = _string(joint, pos)
            names += raw
        self._prefix = frame + b"\x00" * pad + _U32.pack(len(codec.joints)) + names
        self._after_names = pos
        self._index = [(("position", "velocity", "effort").index(array), j) for array, j in codec._slots]

    def _encode_joint_state(self, x: np.ndarray) -> bytes:
        codec = self.codec
        assert isinstance(codec, JointStateCodec)
        n = len(codec.joints)
        arrays = [np.zeros(n if a in codec.arrays else 0) for a in ("position", "velocity", "effort")]
        for value, (a, j) in zip(x, self._index, strict=True):
            arrays[a][j] = value
        out = [self._prefix]
        pos = self._after_names
        for arr in arrays:
            pad = -pos % 4
            out.append(b"\x00" * pad + _U32.pack(arr.size))
            pos += pad + 4
            if arr.size:
                pad = -pos % 8
                out.append(b"\x00" * pad + arr.tobytes())
                pos += pad + 8 * arr.size
        return b"".join(out)

    def _decode_joint_state(self, data: bytes | memoryview, stamp: int) -> np.ndarray | None:
        codec = self.codec
        assert isinstance(codec, JointStateCodec)
        _, pos = _read_string(data, 8)
        pos += -pos % 4
        (count,) = _U32.unpack_from(data, 4 + pos)
        pos += 4
        n = len(codec.joints)
        if count != n:
            return None
        for joint in codec.joints:
            name, pos = _read_string(data, pos)
            if name != joint.encode():
                return None
        arrays: list[np.ndarray | None] = []
        for array in ("position", "velocity", "effort"):
            pos += -pos % 4
            (size,) = _U32.unpack_from(data, 4 + pos)
            pos += 4
            if size not in ((n,) if array in codec.arrays else (0, n)):
                return None
            if size:
                pos += -pos % 8
                if 4 + pos + 8 * size > len(data):
                    return None
                arrays.append(np.frombuffer(data, dtype="<f8", count=size, offset=4 + pos))
                pos += 8 * size
            else:
                arrays.append(None)
        if 4 + pos != len(data):
            return None
        out = np.empty(codec.size)
        for i, (a, j) in enumerate(self._index):
            arr = arrays[a]
            if arr is None:
                return None
            out[i] = arr[j]
        if not np.isfinite(out).all():
            return None
        return out

    # ---------------------------------------------------------------------------------------- interface
    def encode(self, x: Any, stamp_ns: int, topic: str = "") -> bytes:
        """The CDR bytes of the message ``to_msg(x, stamp_ns)`` (checked as there: shape, stamp range; ``topic``
        names the topic in the error)."""
        from msg_schemas.base import as_vector, split_stamp

        if not self.fast:
            from rclpy.serialization import serialize_message

            return bytes(serialize_message(self.codec.to_msg(x, stamp_ns, topic=topic)))
        vec = as_vector(x, self.codec.size, topic)
        sec, nanosec = split_stamp(stamp_ns, topic)
        head = _LE + _STAMP.pack(sec, nanosec)
        if isinstance(self.codec, OdometryCodec):
            return head + self._encode_odometry(vec)
        return head + self._encode_joint_state(vec)

    def decode(self, data: bytes, topic: str = "") -> tuple[np.ndarray, int]:
        """``(x, stamp_ns)`` of the CDR message ``data``; see the module docstring for the fallback."""
        x: np.ndarray | None = None
        stamp = 0
        if self.fast and len(data) >= 16 and data[:4] == _LE:
            sec, nanosec = _STAMP.unpack_from(data, 4)
            if sec >= 0 and nanosec < NS_PER_S:
                stamp = sec * NS_PER_S + nanosec
                try:
                    if isinstance(self.codec, OdometryCodec):
                        x = self._decode_odometry(data, stamp)
                    else:
                        x = self._decode_joint_state(data, stamp)
                except (ValueError, struct.error):
                    x = None
        if x is not None:
            return x, stamp
        return self.codec.from_msg(self._deserialize(data, topic), topic)

    def _deserialize(self, data: bytes, topic: str) -> Any:
        """The message of ``data``; bytes that are no such message raise a ``SchemaError`` (reason ``format``), as
        the learner's decoder (:func:`msg_schemas.decode.make_decoder`) does: a node rejects them and counts it."""
        from rclpy.serialization import deserialize_message

        from msg_schemas.base import RCLPY, SchemaError

        if self._msg_cls is None:
            self._msg_cls = RCLPY.cls(self.codec.msg_type)
        try:
            return deserialize_message(data, self._msg_cls)
        except Exception as exc:  # noqa: BLE001 - malformed CDR (rclpy raises RMWError)
            raise SchemaError(topic, "(serialized)", "format", f"cannot deserialize: {exc}") from None


class NamedVectorCdr:
    """``{name: value}`` as the CDR bytes of the ``sensor_msgs/JointState`` that
    :func:`~msg_schemas.telemetry.named_vector_to_msg` builds (``name`` = keys, ``position`` = values, ``velocity``
    and ``effort`` empty): the names' bytes are written once and reused while the names stay the same (the MPC's
    ``mpc/status``, one message per control step)."""

    def __init__(self, frame_id: str = "") -> None:
        self.frame_id = frame_id
        #: as :attr:`CdrCodec.fast` (SAML_CDR=0: the message is built and serialized instead)
        self.fast = os.environ.get("SAML_CDR", "1") != "0"
        self._names: tuple[str, ...] | None = None
        self._prefix = b""
        self._pad = b""
        self._tail = b""

    def _layout(self, names: tuple[str, ...]) -> None:
        from msg_schemas.base import SchemaError

        if any(not isinstance(n, str) or not n for n in names):
            raise SchemaError("", "name", "names", f"metric names must be non-empty strings, got {list(names)}")
        frame, pos = _string(self.frame_id, 8)
        pad = -pos % 4
        pos += pad + 4
        parts = [frame, b"\x00" * pad, _U32.pack(len(names))]
        for name in names:
            raw, pos = _string(name, pos)
            parts.append(raw)
        pad = -pos % 4
        pos += pad + 4  # the position count
        parts.append(b"\x00" * pad + _U32.pack(len(names)))
        self._pad = b"\x00" * (-pos % 8) if names else b""
        pos += len(self._pad) + 8 * len(names)
        # velocity and effort: empty sequences (a count of 0 each, 4-aligned)
        self._tail = b"\x00" * (-pos % 4) + _U32.pack(0) + _U32.pack(0)
        self._prefix = b"".join(parts)
        self._names = names

    def encode(self, values: dict[str, float], stamp_ns: int, topic: str = "") -> bytes:
        """The CDR bytes of ``named_vector_to_msg(values, stamp_ns, frame_id=self.frame_id)``."""
        from msg_schemas.base import split_stamp

        if not self.fast:
            from rclpy.serialization import serialize_message

            from msg_schemas.telemetry import named_vector_to_msg

            return bytes(serialize_message(named_vector_to_msg(values, stamp_ns, frame_id=self.frame_id,
                                                               topic=topic)))

        names = tuple(values)
        if names != self._names:
            self._layout(names)
        sec, nanosec = split_stamp(stamp_ns, topic)
        body = np.fromiter(values.values(), dtype=np.float64, count=len(names))
        return _LE + _STAMP.pack(sec, nanosec) + self._prefix + self._pad + body.tobytes() + self._tail
