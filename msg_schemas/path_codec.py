"""A vector codec over any stock message, one field path per vector field, and a robot's topic schema.

:class:`FieldPathCodec` is what a system file (``docs/your_robot.md``) turns its ``state`` / ``control``
sections into: each vector field reads one scalar of the message by a field path (:mod:`msg_schemas.field_path`),
validated against the message type when the codec is built. Messages without a header (``geometry_msgs/Twist``
on ``cmd_vel``) are *unstamped*: :meth:`FieldPathCodec.from_msg` then takes the receipt time from the caller
(``receipt_ns``: the subscriber's receive time, or a bag's log time).

:func:`robot_schema` wraps a state and a command codec into a :class:`~msg_schemas.base.SystemSchema` (topics
relative to the robot's namespace or absolute; the target is the next state), so the learner, the bag tools and
the docs treat a user's robot like a built-in system.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from msg_schemas.base import (
    DATA_QOS,
    RCLPY,
    FieldDoc,
    MessageFactory,
    QosSpec,
    SchemaError,
    SystemSchema,
    TopicSpec,
    VectorCodec,
    as_vector,
    make_header,
    read_stamp,
)
from msg_schemas.field_path import FieldPathError, ResolvedPath, default_message, has_header, pad_named_arrays, resolve


@dataclass(frozen=True)
class PathField:
    """One vector field read from a message: ``name``, SI ``unit`` and the field ``path``."""

    name: str
    unit: str
    path: str


class FieldPathCodec(VectorCodec):
    """Vector <-> ``msg_type`` message, field ``i`` at ``fields[i].path``.

    Args:
        msg_type: stock message type (``nav_msgs/msg/Odometry``; ``nav_msgs/Odometry`` is accepted).
        fields: the vector fields in order.
        frame_id / child_frame_id: written into built messages (for message types that have them).

    Raises:
        FieldPathError: a path does not fit ``msg_type`` (the message names the vector field and the path).
    """

    def __init__(self, msg_type: str, fields: Sequence[PathField], *, frame_id: str = "",
                 child_frame_id: str = "") -> None:
        resolved: list[ResolvedPath] = []
        for f in fields:
            try:
                resolved.append(resolve(f.path, msg_type))
            except FieldPathError as exc:
                raise FieldPathError(exc.path, exc.msg_type, f"(vector field {f.name!r}) {exc.detail}") from None
        self.paths = tuple(resolved)
        self.msg_type = resolved[0].msg_type if resolved else msg_type
        self.fields = tuple(fields)
        self.field_names = tuple(f.name for f in fields)
        self.units = tuple(f.unit for f in fields)
        self.stamped = has_header(self.msg_type)
        self.frame_id = frame_id
        self.child_frame_id = child_frame_id
        self.convention = f"{self.msg_type}: " + ", ".join(f"{f.name} = {f.path}" for f in fields) + (
            "" if self.stamped else " (unstamped: stamped on receipt)")

    def field_docs(self) -> tuple[FieldDoc, ...]:
        return tuple(FieldDoc(f.name, f.unit, str(p), "/" + str(p).replace(".", "/"),
                              "" if p.path.conversion is None else f"{p.path.conversion} of the quaternion")
                     for f, p in zip(self.fields, self.paths, strict=True))

    # ------------------------------------------------------------------------------------------ read
    def from_msg(self, msg: Any, topic: str = "", receipt_ns: int | None = None) -> tuple[np.ndarray, int]:
        """Message -> ``(vector, stamp_ns)``: the header stamp, or ``receipt_ns`` for an unstamped type.

        Raises :class:`SchemaError` naming the field (reasons ``shape``, ``names``, ``nan``, ``quaternion``,
        ``stamp``); an unstamped message without ``receipt_ns`` is a ``stamp`` error.
        """
        if self.stamped:
            stamp = read_stamp(msg.header.stamp, topic or self.msg_type)
        elif receipt_ns is None or int(receipt_ns) < 0:
            raise SchemaError(topic or self.msg_type, "(receipt time)", "stamp",
                              f"{self.msg_type} has no header: it needs the time it was received")
        else:
            stamp = int(receipt_ns)
        return np.array([p.read(msg, topic) for p in self.paths], dtype=np.float64), stamp

    # ------------------------------------------------------------------------------------------ write
    def to_msg(self, x: Any, stamp_ns: int, *, factory: MessageFactory = RCLPY, frame_id: str | None = None,
               child_frame_id: str | None = None, topic: str = "") -> Any:
        """Vector -> message (every other field zero); ``stamp_ns`` goes into the header of stamped types."""
        vec = as_vector(x, self.size, topic)
        msg = default_message(factory, self.msg_type)
        if self.stamped:
            msg.header = make_header(factory, stamp_ns, self.frame_id if frame_id is None else frame_id, topic)
        if hasattr(msg, "child_frame_id"):
            msg.child_frame_id = self.child_frame_id if child_frame_id is None else child_frame_id
        for p, v in zip(self.paths, vec, strict=True):
            p.write(msg, float(v))
        pad_named_arrays(msg, self.paths)
        return msg

    def _build(self, vec: np.ndarray, header: Any, factory: MessageFactory, child_frame_id: str | None) -> Any:
        raise NotImplementedError("FieldPathCodec overrides to_msg")  # pragma: no cover - never called


def robot_schema(system: str, state_topic: str, state: FieldPathCodec, cmd_topic: str, control: FieldPathCodec,
                 description: str = "", *, state_qos: QosSpec = DATA_QOS, cmd_qos: QosSpec = DATA_QOS) -> SystemSchema:
    """The :class:`SystemSchema` of a robot whose state comes on ``state_topic`` and whose commands go on
    ``cmd_topic`` (the learner listens to the commands the robot is sent: they are its applied commands)."""
    if state_topic == cmd_topic:
        raise ValueError(f"{system}: the state and command topics must differ, both are {state_topic!r}")
    topics = (
        TopicSpec(state_topic, state.msg_type, state_qos, "the robot", "learner, record",
                  "the robot's state x_t" + ("" if state.stamped else " (unstamped)"), codec=state),
        TopicSpec(cmd_topic, control.msg_type, cmd_qos, "the robot's controller / teleop / mpc", "the robot, learner, "
                  "record", "commands u_t the robot is sent" + ("" if control.stamped else " (unstamped: the "
                                                                                            "learner stamps them on receipt)"),
                  codec=control),
    )
    return SystemSchema(system=system, state=state, control=control, target=state, topics=topics,
                        target_topic=state_topic, target_pairing="next", description=description,
                        state_topic=state_topic, cmd_topic=cmd_topic, applied_cmd_topic=cmd_topic)


def robot_schema_from_definition(definition: Mapping[str, Any]) -> SystemSchema:
    """The :class:`SystemSchema` of a robot from its parsed system file (``saml_ros.systems.system_file``):
    the ``state`` and ``control`` sections' topics, message types, field paths, frames and QoS."""

    def codec(sec: Mapping[str, Any]) -> FieldPathCodec:
        return FieldPathCodec(sec["type"], [PathField(f["name"], f["unit"], f["path"]) for f in sec["fields"]],
                              frame_id=sec.get("frame_id", ""), child_frame_id=sec.get("child_frame_id", ""))

    def qos(sec: Mapping[str, Any]) -> QosSpec:
        q = sec.get("qos") or {}
        return QosSpec(reliable=bool(q.get("reliable", True)), depth=int(q.get("depth", DATA_QOS.depth)))

    st, ct = definition["state"], definition["control"]
    return robot_schema(str(definition["name"]), st["topic"], codec(st), ct["topic"], codec(ct),
                        str(definition.get("description", "")), state_qos=qos(st), cmd_qos=qos(ct))
