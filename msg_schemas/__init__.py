"""Stock ROS 2 messages for saml_ros vectors: the single place that maps vectors to messages and back.

Per system (``friction``, ``quadrotor``, ``paddle_ball``: one module each) a :class:`SystemSchema` names the topics
(relative to the system namespace), their message types and QoS, and converts the state / control / target
vectors (layouts of ``saml_ros.core.systems``) to messages and back::

    schema = get_schema("quadrotor")
    msg = schema.state_to_msg(x, stamp_ns)                 # rclpy message (default factory)
    x, stamp_ns = schema.state_from_msg(msg)               # SchemaError if malformed
    bag_msg = schema.state_to_msg(x, stamp_ns, factory=TypestoreFactory())   # rosbags dataclass

Telemetry (``learner/model_error``, ``learner/checkpoint``, ``mpc/status``, ``/diagnostics``, ``/clock``) is in
:mod:`msg_schemas.telemetry`. ``python -m msg_schemas.docs`` prints the topic reference (docs/topics.md).
Importing this package imports neither rclpy nor rosbags nor torch. Which system has which schema is its
registry entry's (``saml_ros.core.systems.registry``, ``SystemEntry.schema``): :func:`get_schema` asks it.
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


def get_schema(system: str) -> SystemSchema:
    """The :class:`SystemSchema` of registered system ``system``; ``ValueError`` listing the valid names otherwise.

    The registry (torch-free) is imported here, not at the top, so that this package stays the lower layer:
    its modules import nothing of ``saml_ros``.
    """
    from saml_ros.core.systems.registry import get_entry

    schema = get_entry(system).schema()
    if schema.system != system:
        raise ValueError(f"the registry's schema for {system!r} is the schema of {schema.system!r}")
    return schema


__all__ = [
    "CHECKPOINT_QOS",
    "CLOCK_QOS",
    "DATA_QOS",
    "RCLPY",
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
