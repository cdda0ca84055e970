"""The simulator node's publishers, one emitter per output kind of the core (:mod:`saml_ros.core.worlds.sim_core`).

``state`` and ``applied_cmd`` are published as CDR bytes written without message objects (:mod:`msg_schemas.cdr`,
byte-identical to the messages' own serialization). Publishers skip rclpy's default QoS-event handlers: each one is an extra entity in every executor wait, and
reliable + volatile offers are compatible with every volatile subscriber (the ``cmd`` subscription keeps them: a
best-effort ``cmd`` publisher would be incompatible, and says so).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.event_handler import PublisherEventCallbacks
from rclpy.node import Node
from rosgraph_msgs.msg import Clock as ClockMsg

from msg_schemas import CLOCK_QOS, DATA_QOS, RCLPY, TELEMETRY_QOS
from msg_schemas.base import SystemSchema
from msg_schemas.cdr import CdrCodec
from msg_schemas.telemetry import CLOCK_TOPIC, DIAGNOSTICS_TOPIC, clock_to_msg
from saml_ros.core.worlds.sim_core import APPLIED, CLOCK, FLIGHT, STATE, TARGET

#: ``emit(vector or None, stamp ns)``: publish one output of the core
Emit = Callable[[np.ndarray | None, int], None]


@dataclass
class Emitters:
    """The publishers of a simulator node and an emitter per output kind (``STATE``, ``APPLIED``, ...)."""

    emit: dict[str, Emit] = field(default_factory=dict)
    state_pub: Any = None
    applied_pub: Any = None
    diag_pub: Any = None


def make_emitters(node: Node, schema: SystemSchema, publish_clock: bool) -> Emitters:
    """Create ``node``'s publishers for ``schema``'s state, applied command, separate target and flight topics,
    ``/clock`` (when ``publish_clock``; otherwise the clock emitter does nothing) and ``/diagnostics``."""
    data_qos = DATA_QOS.to_rclpy()
    lean = PublisherEventCallbacks(use_default_callbacks=False)
    out = Emitters()
    state_pub = node.create_publisher(RCLPY.cls(schema.state.msg_type), schema.state_topic, data_qos,
                                      event_callbacks=lean)
    applied_pub = node.create_publisher(RCLPY.cls(schema.control.msg_type), schema.applied_cmd_topic, data_qos,
                                        event_callbacks=lean)
    out.state_pub, out.applied_pub = state_pub, applied_pub
    # state and applied_cmd are written as CDR bytes directly (msg_schemas.cdr; the message path where the codec
    # has no fast one)
    state_cdr, control_cdr = CdrCodec(schema.state), CdrCodec(schema.control)
    state_topic, applied_topic = state_pub.topic_name, applied_pub.topic_name
    out.emit[STATE] = lambda x, t: state_pub.publish(state_cdr.encode(x, t, state_topic))
    out.emit[APPLIED] = lambda u, t: applied_pub.publish(control_cdr.encode(u, t, applied_topic))
    if schema.target_topic != schema.state_topic:
        target_pub = node.create_publisher(RCLPY.cls(schema.target.msg_type), schema.target_topic, data_qos,
                                           event_callbacks=lean)
        out.emit[TARGET] = lambda y, t: target_pub.publish(schema.target_to_msg(y, t))
    flight = next((t for t in schema.topics if t.name == "flight"), None)
    if flight is not None and flight.codec is not None:
        codec, label = flight.codec, f"{schema.system}/flight"
        flight_pub = node.create_publisher(RCLPY.cls(flight.msg_type), flight.name, flight.qos.to_rclpy(),
                                           event_callbacks=lean)
        out.emit[FLIGHT] = lambda x, t: flight_pub.publish(codec.to_msg(x, t, topic=label))
    if publish_clock:
        clock_pub = node.create_publisher(ClockMsg, CLOCK_TOPIC, CLOCK_QOS.to_rclpy(), event_callbacks=lean)
        out.emit[CLOCK] = lambda _, t: clock_pub.publish(clock_to_msg(t))
    else:
        out.emit[CLOCK] = lambda _, t: None
    out.diag_pub = node.create_publisher(DiagnosticArray, DIAGNOSTICS_TOPIC, TELEMETRY_QOS.to_rclpy(),
                                         event_callbacks=lean)
    return out
