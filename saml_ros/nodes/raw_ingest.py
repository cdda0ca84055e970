"""Serialized-message subscriptions that only count and forward (the learner's ingest side, rclpy).

Each channel's callback gets the *serialized* message (``raw=True``): decoding happens in the training process,
and building Python message objects is most of a bare subscriber's per-message cost. ``KEEP_ALL`` history: a
burst that outruns the callbacks (e.g. while the training process imports torch) waits in the reader queue
instead of overwriting older transitions; reliable writers are slowed, never dropped.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

from rclpy.event_handler import SubscriptionEventCallbacks
from rclpy.node import Node
from rclpy.qos import HistoryPolicy

from msg_schemas import RCLPY, QosSpec
from saml_ros.core.online.config import Channel

#: ``submit(channel, payload)``: ``payload`` is the serialized message, or ``(message, receive stamp ns)``
Submit = Callable[[int, Any], None]


def subscribe_raw(node: Node, channels: Sequence[Channel], qos: Sequence[QosSpec], unstamped: Sequence[bool],
                  submit: Submit, received: list[int], group: Any,
                  admit: Callable[[int], bool] | None = None,
                  on_matched: Callable[[int, int], None] | None = None) -> list[Any]:
    """One subscription per channel of ``channels`` (``(namespace, kind, topic, message type)``) with its
    topic's ``qos`` (history made KEEP_ALL), counting into ``received[channel]`` and handing each message to
    ``submit``; a channel whose messages have no header (``unstamped``: a robot's ``cmd_vel``) is stamped on
    receipt: the middleware's receive time (the system clock, like the robot's own stamps), or the node's
    clock on simulated time. ``admit`` / ``on_matched``: see the module docstring."""
    sim_time = bool(node.get_parameter("use_sim_time").value)
    clock = node.get_clock()

    def make(channel: int) -> Callable[..., None]:
        if not unstamped[channel]:
            def callback(data: bytes) -> None:
                received[channel] += 1
                if admit is None or admit(channel):
                    submit(channel, data)

            return callback

        def stamp_on_receipt(data: bytes, info: Any) -> None:
            t = int(info["received_timestamp"]) if not sim_time and info else clock.now().nanoseconds
            received[channel] += 1
            if admit is None or admit(channel):
                submit(channel, (data, t))

        return stamp_on_receipt

    def keep_all(spec: QosSpec) -> Any:
        profile = spec.to_rclpy()
        profile.history = HistoryPolicy.KEEP_ALL
        return profile

    def events(channel: int) -> SubscriptionEventCallbacks | None:
        if on_matched is None:
            return None

        def matched(status: Any) -> None:
            on_matched(channel, int(status.current_count))

        return SubscriptionEventCallbacks(matched=matched)

    return [node.create_subscription(RCLPY.cls(msg_type), topic, make(ch), keep_all(qos[ch]), callback_group=group,
                                     event_callbacks=events(ch), raw=True)
            for ch, (_, _, topic, msg_type) in enumerate(channels)]
