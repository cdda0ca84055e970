"""Decoding the learner's raw (serialized CDR) messages into vectors, in its training process.

:func:`make_decoder` is the :data:`~saml_ros.core.online.process.DecoderFactory` the learner node hands its training
process (``LearnerSetup.decoder``). Importing this module imports neither rclpy nor torch; the decoder it builds
uses ``rclpy.serialization``.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from msg_schemas import RCLPY, SchemaError, get_schema


def make_decoder(args: tuple[str, list[tuple[str, str]]]) -> Callable[[int, bytes], tuple[Any, int]]:
    """Decoder of the learner node's raw messages, built in the training process (``LearnerSetup.decoder``).

    ``args = (system, [(kind, topic) per channel])``; the returned ``decode(channel, payload)`` deserializes the
    CDR bytes into the channel's stock message and converts it with msg_schemas, returning ``(vector, stamp_ns)``
    or raising :class:`msg_schemas.SchemaError` (reason ``shape``, ``names``, ``nan``, ...).
    """
    from rclpy.serialization import deserialize_message

    system, channels = args
    sc = get_schema(system)
    codecs = {"state": (sc.state, sc.state_from_msg), "applied_cmd": (sc.control, sc.control_from_msg),
              "target": (sc.target, sc.target_from_msg)}
    table = [(RCLPY.cls(codecs[kind][0].msg_type), codecs[kind][1], topic) for kind, topic in channels]

    def decode(channel: int, payload: bytes) -> tuple[Any, int]:
        cls, from_msg, topic = table[channel]
        try:
            msg = deserialize_message(payload, cls)
        except Exception as exc:  # noqa: BLE001 - malformed CDR
            raise SchemaError(topic, "(serialized)", "format", f"cannot deserialize: {exc}") from None
        vec, stamp = from_msg(msg, topic)
        return vec, stamp

    return decode
