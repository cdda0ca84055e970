"""Building blocks shared by every schema: errors, QoS, message factories, stamps, topic and codec types.

Nothing here imports rclpy or rosbags at module level: a *message factory* supplies the message classes,
so the same conversion code builds rclpy messages (nodes) and rosbags typestore dataclasses (bag tools).
Reading needs no factory at all: both kinds are read by attribute access (``msg.header.stamp.sec``,
``msg.position``), and their arrays convert with ``numpy.asarray``.
"""

from __future__ import annotations

import abc
import hashlib
import importlib
import json
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from saml_ros.core.errors import SamlError

#: version of the vector <-> message conventions; part of every schema hash
CONVENTIONS_VERSION = 1

NS_PER_S = 1_000_000_000
_INT32_MAX = 2**31 - 1


class SchemaError(SamlError, ValueError):
    """A message does not match its schema (wrong length, unexpected names, NaN/Inf, bad stamp, ...).

    Attributes:
        topic: topic (or schema) the message came from, e.g. ``"quadrotor/state"``.
        field: the offending message field path, e.g. ``"twist.twist.linear.x"`` or ``"name"``.
        reason: a short counter key: ``shape``, ``names``, ``nan``, ``quaternion``, ``stamp``, ``format``.
            Nodes count rejections as ``rejected/<reason>``.
    """

    def __init__(self, topic: str, field: str, reason: str, detail: str) -> None:
        super().__init__(f"{topic}: {field}: {detail}")
        self.topic = topic
        self.field = field
        self.reason = reason


# ------------------------------------------------------------------------------------------------ QoS
#: rosbag2 (Jazzy) writes "infinite" QoS durations as RMW_DURATION_INFINITE split into sec / nsec
_INFINITE_SEC, _INFINITE_NSEC = 9223372036, 854775807


@dataclass(frozen=True)
class QosSpec:
    """A ROS-free QoS description (history is always keep-last ``depth``).

    Nodes turn it into an rclpy ``QoSProfile`` with :meth:`to_rclpy`; bag writers put :meth:`to_rosbags`
    into metadata.yaml's ``offered_qos_profiles`` so ``ros2 bag play`` offers the same QoS.
    """

    reliable: bool = True
    transient_local: bool = False
    depth: int = 10

    def __post_init__(self) -> None:
        if self.depth < 1:
            raise ValueError(f"QosSpec.depth must be >= 1, got {self.depth}")

    def describe(self) -> str:
        """``"reliable, volatile, keep last 10"``."""
        return (
            f"{'reliable' if self.reliable else 'best effort'}, "
            f"{'transient local' if self.transient_local else 'volatile'}, keep last {self.depth}"
        )

    def to_rclpy(self) -> Any:
        """The equivalent ``rclpy.qos.QoSProfile``."""
        from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

        return QoSProfile(
            history=HistoryPolicy.KEEP_LAST,
            depth=self.depth,
            reliability=ReliabilityPolicy.RELIABLE if self.reliable else ReliabilityPolicy.BEST_EFFORT,
            durability=DurabilityPolicy.TRANSIENT_LOCAL if self.transient_local else DurabilityPolicy.VOLATILE,
        )

    def to_rosbags(self) -> Any:
        """The equivalent ``rosbags.interfaces.Qos`` for ``Writer.add_connection(offered_qos_profiles=[...])``."""
        from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime

        infinite = QosTime(_INFINITE_SEC, _INFINITE_NSEC)
        return Qos(
            history=QosHistory.KEEP_LAST,
            depth=self.depth,
            reliability=QosReliability.RELIABLE if self.reliable else QosReliability.BEST_EFFORT,
            durability=QosDurability.TRANSIENT_LOCAL if self.transient_local else QosDurability.VOLATILE,
            deadline=infinite,
            lifespan=infinite,
            liveliness=QosLiveliness.AUTOMATIC,
            liveliness_lease_duration=infinite,
            avoid_ros_namespace_conventions=False,
        )


#: simulator / robot data (state, commands, impact targets): nothing may be lost, bursts are buffered
DATA_QOS = QosSpec(reliable=True, transient_local=False, depth=100)
#: live telemetry (model error, MPC status, diagnostics)
TELEMETRY_QOS = QosSpec(reliable=True, transient_local=False, depth=10)
#: newest checkpoint: a late-joining MPC still receives the last announcement
CHECKPOINT_QOS = QosSpec(reliable=True, transient_local=True, depth=1)
#: /clock from a lockstep simulator (rclpy's TimeSource subscribes best effort, depth 1; a reliable
#: publisher serves both it and reliable subscribers such as the recorder)
CLOCK_QOS = QosSpec(reliable=True, transient_local=False, depth=10)


# ------------------------------------------------------------------------------------------ factories
class MessageFactory(abc.ABC):
    """Supplies message classes by full type name (``"sensor_msgs/msg/JointState"``)."""

    @abc.abstractmethod
    def cls(self, type_name: str) -> Any:
        """The message class of ``type_name``."""

    def make(self, type_name: str, **fields: Any) -> Any:
        """An instance of ``type_name`` with every field given as a keyword (rosbags has no defaults)."""
        return self.cls(type_name)(**fields)

    @abc.abstractmethod
    def byte(self, value: int) -> Any:
        """A value for a ROS ``byte`` field (rclpy wants ``bytes``, rosbags an ``int``)."""


class RclpyFactory(MessageFactory):
    """rclpy message classes (imported on first use, then cached)."""

    def __init__(self) -> None:
        self._cache: dict[str, Any] = {}

    def cls(self, type_name: str) -> Any:
        found = self._cache.get(type_name)
        if found is None:
            package, kind, name = type_name.split("/")
            found = getattr(importlib.import_module(f"{package}.{kind}"), name)
            self._cache[type_name] = found
        return found

    def byte(self, value: int) -> bytes:
        return bytes([value])


class TypestoreFactory(MessageFactory):
    """rosbags typestore dataclasses (``get_typestore(Stores.ROS2_JAZZY)`` unless one is given)."""

    def __init__(self, typestore: Any = None) -> None:
        if typestore is None:
            from rosbags.typesys import Stores, get_typestore

            typestore = get_typestore(Stores.ROS2_JAZZY)
        self.typestore = typestore

    def cls(self, type_name: str) -> Any:
        return self.typestore.types[type_name]

    def byte(self, value: int) -> int:
        return int(value)


#: the factory nodes use by default
RCLPY = RclpyFactory()


# --------------------------------------------------------------------------------------------- stamps
def full_topic(namespace: str, name: str) -> str:
    """The absolute name of topic ``name`` in ``namespace``: an absolute name as it is, a relative one under the
    namespace (``full_topic("/dd", "odom") == "/dd/odom"``, ``full_topic("/dd/", "/clock") == "/clock"``)."""
    return name if name.startswith("/") else f"{namespace.rstrip('/')}/{name}"


def make_header(factory: MessageFactory, stamp_ns: int, frame_id: str, topic: str) -> Any:
    """A ``std_msgs/msg/Header`` for ``stamp_ns`` (int nanoseconds, >= 0, < 2^31 s)."""
    sec, nanosec = split_stamp(stamp_ns, topic)
    time = factory.make("builtin_interfaces/msg/Time", sec=sec, nanosec=nanosec)
    return factory.make("std_msgs/msg/Header", stamp=time, frame_id=frame_id)


def split_stamp(stamp_ns: int, topic: str) -> tuple[int, int]:
    """``stamp_ns`` -> ``(sec, nanosec)``; raises :class:`SchemaError` (reason ``stamp``) when out of range."""
    if isinstance(stamp_ns, bool) or not isinstance(stamp_ns, int | np.integer):
        raise SchemaError(topic, "header.stamp", "stamp", f"stamp must be an int in ns, got {stamp_ns!r}")
    sec, nanosec = divmod(int(stamp_ns), NS_PER_S)
    if not 0 <= sec <= _INT32_MAX:
        raise SchemaError(topic, "header.stamp", "stamp", f"stamp {stamp_ns} ns is outside [0, 2^31) s")
    return sec, nanosec


def read_stamp(stamp: Any, topic: str, path: str = "header.stamp") -> int:
    """``builtin_interfaces/Time`` -> int nanoseconds; rejects negative seconds and nanosec >= 1e9."""
    sec, nanosec = int(stamp.sec), int(stamp.nanosec)
    if sec < 0 or not 0 <= nanosec < NS_PER_S:
        raise SchemaError(topic, path, "stamp", f"invalid stamp sec={sec} nanosec={nanosec}")
    return sec * NS_PER_S + nanosec


# -------------------------------------------------------------------------------------- vector checks
def as_vector(x: Any, size: int, topic: str) -> np.ndarray:
    """``x`` as a float64 vector of ``size`` elements; :class:`SchemaError` (reason ``shape``) otherwise."""
    arr = np.asarray(x, dtype=np.float64)
    if arr.shape != (size,):
        raise SchemaError(topic, "vector", "shape", f"expected a vector of shape ({size},), got shape {arr.shape}")
    return arr


def check_finite(topic: str, path: str, field_name: str, value: float) -> float:
    """``value`` if finite, else :class:`SchemaError` (reason ``nan``) naming the message and vector field."""
    if not math.isfinite(value):
        raise SchemaError(topic, path, "nan", f"field {field_name!r} is {value}")
    return value


# ------------------------------------------------------------------------------------ schema objects
@dataclass(frozen=True)
class FieldDoc:
    """Where one named value sits in a message (for docs, hashes and plot paths).

    Attributes:
        name: vector field or metric name (``"vx"``, ``"objective"``).
        unit: SI unit (``"m/s"``), ``"1"`` for dimensionless, ``"count"`` for counters.
        path: message field path, ROS style (``"twist.twist.linear.x"``, ``"position[0]"``).
        plotjuggler: PlotJuggler series suffix after the topic (``"/twist/twist/linear/x"``, ``"/cart/position"``).
        note: conversion note (``"body frame: R(q)^T v"``), empty when the value is copied as is.
    """

    name: str
    unit: str
    path: str
    plotjuggler: str
    note: str = ""


class VectorCodec(abc.ABC):
    """Maps one vector layout (ordered named fields) to one stock message type and back."""

    #: full message type name, e.g. ``"sensor_msgs/msg/JointState"``
    msg_type: str
    #: the vector's field names, in vector order (equal to the core.systems layout's names)
    field_names: tuple[str, ...]
    #: the vector's field units, in vector order
    units: tuple[str, ...]
    #: one line on the representation (frames, which array, ...) for the docs and the schema hash
    convention: str
    #: header frame_id of built messages unless :meth:`to_msg` is given one
    frame_id: str = ""

    @property
    def size(self) -> int:
        return len(self.field_names)

    @abc.abstractmethod
    def field_docs(self) -> tuple[FieldDoc, ...]:
        """One :class:`FieldDoc` per vector field, in vector order."""

    def to_msg(
        self,
        x: Any,
        stamp_ns: int,
        *,
        factory: MessageFactory = RCLPY,
        frame_id: str | None = None,
        child_frame_id: str | None = None,
        topic: str = "",
    ) -> Any:
        """Vector ``x`` (shape ``(size,)``) stamped ``stamp_ns`` (int ns) -> message built by ``factory``.

        Non-finite values are published as they are (receivers count and drop them); a wrong shape or an
        invalid stamp raises :class:`SchemaError`. ``frame_id`` / ``child_frame_id`` override the defaults.
        """
        vec = as_vector(x, self.size, topic)
        header = make_header(factory, stamp_ns, self.frame_id if frame_id is None else frame_id, topic)
        return self._build(vec, header, factory, child_frame_id)

    @abc.abstractmethod
    def _build(self, vec: np.ndarray, header: Any, factory: MessageFactory, child_frame_id: str | None) -> Any:
        """The message of the checked float64 vector ``vec`` ``(size,)`` with the built ``header``
        (``child_frame_id``: :meth:`to_msg`'s override, for message types that have one)."""

    @abc.abstractmethod
    def from_msg(self, msg: Any, topic: str = "") -> tuple[np.ndarray, int]:
        """Message (rclpy or rosbags) -> ``(x, stamp_ns)``; :class:`SchemaError` naming the field if malformed."""

    def schema_hash(self) -> str:
        """Hash of the message type, the field mapping with units, and the conventions (16 hex chars)."""
        blob = {
            "conventions": CONVENTIONS_VERSION,
            "msg_type": self.msg_type,
            "fields": [[d.name, d.unit, d.path, d.plotjuggler, d.note] for d in self.field_docs()],
            "convention": self.convention,
        }
        return hashlib.sha256(json.dumps(blob, sort_keys=True).encode()).hexdigest()[:16]


@dataclass(frozen=True)
class TopicSpec:
    """One topic: name relative to the system namespace (or absolute), type, QoS and who uses it.

    Attributes:
        name: ``"state"``, ``"learner/model_error"`` (relative) or ``"/clock"`` (absolute).
        msg_type: full message type name.
        qos: the QoS publishers offer and subscribers request.
        publisher / subscribers: node roles, for the docs.
        description: one or two sentences.
        codec: the vector codec for data topics, ``None`` for telemetry.
        fields: documented values for telemetry topics (codec topics take them from the codec).
        required: ``False`` for optional topics (nodes may not publish them).
    """

    name: str
    msg_type: str
    qos: QosSpec
    publisher: str
    subscribers: str
    description: str
    codec: VectorCodec | None = None
    fields: tuple[FieldDoc, ...] = ()
    required: bool = True

    def field_docs(self) -> tuple[FieldDoc, ...]:
        return self.codec.field_docs() if self.codec is not None else self.fields


@dataclass(frozen=True)
class SystemSchema:
    """Everything a node needs to put one system's vectors on topics and read them back.

    The learner builds a transition from ``state`` (x_t) and ``applied_cmd`` (u_t, stamped like x_t) plus the
    target message on ``target_topic``: for time-stepped systems (``target_pairing == "next"``) that is the
    next ``state`` message (x_{t+1}); for the paddle ball (``"same"``) it is ``post_impact`` with the same
    stamp as x_t.
    """

    system: str
    state: VectorCodec
    control: VectorCodec
    target: VectorCodec
    topics: tuple[TopicSpec, ...]
    target_topic: str
    target_pairing: str  # "next" | "same"
    description: str = ""
    state_topic: str = "state"
    cmd_topic: str = "cmd"
    applied_cmd_topic: str = "applied_cmd"
    _by_name: dict[str, TopicSpec] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        by_name = {t.name: t for t in self.topics}
        if len(by_name) != len(self.topics):
            raise ValueError(f"{self.system}: duplicate topic names")
        for name in (self.state_topic, self.cmd_topic, self.applied_cmd_topic, self.target_topic):
            if name not in by_name:
                raise ValueError(f"{self.system}: topic {name!r} is not declared")
        if self.target_pairing not in ("next", "same"):
            raise ValueError(f"{self.system}: target_pairing must be 'next' or 'same'")
        object.__setattr__(self, "_by_name", by_name)

    def topic(self, name: str) -> TopicSpec:
        """The :class:`TopicSpec` called ``name``; ``KeyError`` listing the valid names otherwise."""
        try:
            return self._by_name[name]
        except KeyError:
            raise KeyError(f"{self.system} has no topic {name!r}; topics are {list(self._by_name)}") from None

    def _topic_label(self, name: str, topic: str | None) -> str:
        return topic if topic else f"{self.system}/{name}"

    # -- state x_t
    def state_to_msg(self, x: Any, stamp_ns: int, *, factory: MessageFactory = RCLPY, **frames: str) -> Any:
        """State vector -> message for ``state`` (see :meth:`VectorCodec.to_msg`)."""
        return self.state.to_msg(
            x, stamp_ns, factory=factory, topic=self._topic_label(self.state_topic, None), **frames
        )

    def state_from_msg(self, msg: Any, topic: str | None = None) -> tuple[np.ndarray, int]:
        """``state`` message -> ``(x, stamp_ns)``; :class:`SchemaError` if malformed."""
        return self.state.from_msg(msg, self._topic_label(self.state_topic, topic))

    # -- control u_t (cmd and applied_cmd)
    def control_to_msg(self, u: Any, stamp_ns: int, *, factory: MessageFactory = RCLPY, **frames: str) -> Any:
        """Control vector -> message for ``cmd`` / ``applied_cmd``."""
        return self.control.to_msg(
            u, stamp_ns, factory=factory, topic=self._topic_label(self.cmd_topic, None), **frames
        )

    def control_from_msg(self, msg: Any, topic: str | None = None) -> tuple[np.ndarray, int]:
        """``cmd`` / ``applied_cmd`` message -> ``(u, stamp_ns)``; :class:`SchemaError` if malformed."""
        return self.control.from_msg(msg, self._topic_label(self.applied_cmd_topic, topic))

    # -- target (x_{t+1} or the post-impact velocity)
    def target_to_msg(self, y: Any, stamp_ns: int, *, factory: MessageFactory = RCLPY, **frames: str) -> Any:
        """Target vector -> message for ``target_topic``."""
        label = self._topic_label(self.target_topic, None)
        return self.target.to_msg(y, stamp_ns, factory=factory, topic=label, **frames)

    def target_from_msg(self, msg: Any, topic: str | None = None) -> tuple[np.ndarray, int]:
        """``target_topic`` message -> ``(y, stamp_ns)``; :class:`SchemaError` if malformed."""
        return self.target.from_msg(msg, self._topic_label(self.target_topic, topic))

    def schema_hash(self) -> str:
        """Hash of the data topics (names, types, codecs) and the pairing rule (16 hex chars)."""
        blob = {
            "system": self.system,
            "pairing": [self.state_topic, self.applied_cmd_topic, self.target_topic, self.target_pairing],
            "topics": [[t.name, t.msg_type, t.codec.schema_hash() if t.codec else ""] for t in self.topics],
        }
        return hashlib.sha256(json.dumps(blob, sort_keys=True).encode()).hexdigest()[:16]


def names_equal(topic: str, got: Sequence[str], expected: Sequence[str]) -> None:
    """Raise :class:`SchemaError` (reason ``names``) unless ``got`` equals ``expected`` in order."""
    if list(got) != list(expected):
        raise SchemaError(topic, "name", "names", f"expected names {list(expected)}, got {list(got)}")
