"""Decoding the learner's raw (serialized CDR) messages into vectors, in its training process.

:func:`make_decoder` is the :data:`~saml_ros.core.online.process.DecoderFactory` the learner node hands its training
process (``LearnerSetup.decoder``). Importing this module imports neither rclpy nor torch; the decoder it builds
uses ``rclpy.serialization``.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from msg_schemas import RCLPY, SchemaError, get_schema
from msg_schemas.path_codec import FieldPathCodec, robot_schema_from_definition


def make_decoder(args: tuple[Any, ...]) -> Callable[[int, Any], tuple[Any, int]]:
    """Decoder of the learner node's raw messages, built in the training process (``LearnerSetup.decoder``).

    ``args = (system, [(kind, topic) per channel])``, or ``(system, channels, definition)`` for a robot described
    by a system file (``definition``: its parsed file, whose field paths give the codecs; ``None`` = a built-in
    system). The returned ``decode(channel, payload)`` deserializes the CDR bytes into the channel's stock message
    and converts it with msg_schemas, returning ``(vector, stamp_ns)`` or raising :class:`msg_schemas.SchemaError`
    (reason ``shape``, ``names``, ``nan``, ...). A message without a header comes as ``(CDR bytes, receipt time
    ns)`` and is stamped with that time.
    """
    from rclpy.serialization import deserialize_message

    system, channels, *rest = args
    definition = rest[0] if rest else None
    sc = robot_schema_from_definition(definition) if definition else get_schema(system)
    codecs = {"state": (sc.state, sc.state_from_msg), "applied_cmd": (sc.control, sc.control_from_msg),
              "target": (sc.target, sc.target_from_msg)}
    table = [(RCLPY.cls(codecs[kind][0].msg_type), codecs[kind][1], topic, codecs[kind][0])
             for kind, topic in channels]

    def decode(channel: int, payload: Any) -> tuple[Any, int]:
        cls, from_msg, topic, codec = table[channel]
        receipt = None
        if isinstance(payload, tuple):  # (CDR bytes, receipt time ns) of an unstamped message
            payload, receipt = payload
        try:
            msg = deserialize_message(payload, cls)
        except Exception as exc:  # noqa: BLE001 - malformed CDR
            raise SchemaError(topic, "(serialized)", "format", f"cannot deserialize: {exc}") from None
        if isinstance(codec, FieldPathCodec):
            return codec.from_msg(msg, topic, receipt_ns=receipt)
        vec, stamp = from_msg(msg, topic)
        return vec, stamp

    return decode
