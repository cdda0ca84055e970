"""Stock ROS 2 messages for saml_ros vectors: the single place that maps vectors to messages and back.

Per system (``friction``, ``quadrotor``, ``paddle_ball``) a :class:`SystemSchema` names the topics
(relative to the system namespace), their message types and QoS, and converts the state / control / target
vectors (layouts of ``saml_ros.core.systems``) to messages and back::

    schema = get_schema("quadrotor")
    msg = schema.state_to_msg(x, stamp_ns)                 # rclpy message (default factory)
    x, stamp_ns = schema.state_from_msg(msg)               # SchemaError if malformed
    bag_msg = schema.state_to_msg(x, stamp_ns, factory=TypestoreFactory())   # rosbags dataclass

Telemetry (``learner/model_error``, ``learner/checkpoint``, ``mpc/status``, ``/diagnostics``, ``/clock``) is in
:mod:`msg_schemas.telemetry`. ``python -m msg_schemas.docs`` prints the topic reference (docs/topics.md).
Importing this package imports neither rclpy nor rosbags nor torch.
"""

from __future__ import annotations

from msg_schemas.base import (
    CHECKPOINT_QOS,
    CLOCK_QOS,
    DATA_QOS,
    RCLPY,
    TELEMETRY_QOS,
    FieldDoc,
    MessageFactory,
    QosSpec,
    RclpyFactory,
    SchemaError,
    SystemSchema,
    TopicSpec,
    TypestoreFactory,
    VectorCodec,
)
from msg_schemas.friction import SCHEMA as FRICTION
from msg_schemas.paddle_ball import SCHEMA as PADDLE_BALL
from msg_schemas.quadrotor import SCHEMA as QUADROTOR

_SCHEMAS: dict[str, SystemSchema] = {s.system: s for s in (FRICTION, QUADROTOR, PADDLE_BALL)}
#: systems with a schema, in a stable order
SYSTEM_NAMES: tuple[str, ...] = tuple(_SCHEMAS)


def get_schema(system: str) -> SystemSchema:
    """The :class:`SystemSchema` of ``system``; ``ValueError`` listing the valid names otherwise."""
    try:
        return _SCHEMAS[system]
    except (KeyError, TypeError):
        raise ValueError(f"no message schema for system {system!r}; valid names are {list(SYSTEM_NAMES)}") from None


__all__ = [
    "CHECKPOINT_QOS",
    "CLOCK_QOS",
    "DATA_QOS",
    "RCLPY",
    "SYSTEM_NAMES",
    "TELEMETRY_QOS",
    "FieldDoc",
    "MessageFactory",
    "QosSpec",
    "RclpyFactory",
    "SchemaError",
    "SystemSchema",
    "TopicSpec",
    "TypestoreFactory",
    "VectorCodec",
    "get_schema",
]
