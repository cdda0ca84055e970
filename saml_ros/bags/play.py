"""``ros2 run saml_ros play BAG``: republish a bag's messages with their original timing (or faster).

    play runs/flight1                          # original timing, /clock from the bag's timestamps
    play runs/flight1 --rate 4                 # four times faster
    play runs/flight1 --rate 0 --wait-for-subscribers /friction/state /friction/applied_cmd
                                               # as fast as possible without loss, once a learner listens

Messages are published raw (the recorded CDR bytes) with the QoS recorded in metadata.yaml (reliable
unless every recorded publisher was best effort; transient local if every one was; keep last >= 100).
Timing comes from the messages' log times (when the recorder received them): message k is published
``(log_time_k - log_time_0) / rate`` wall seconds after the start. ``/clock`` is published from the same
log times before each message that advances them (so nodes with ``use_sim_time`` follow the bag); the
bag's own ``/clock`` topic is then not republished (``--no-clock`` republishes it instead).

``--rate 0`` publishes as fast as the subscribers receive the data: after every ``--ack-batch`` messages
(and at the end) the player waits until every reliable subscriber acknowledged them (Fast DDS: the player
uses a writer profile with 2 ms heartbeats, see :func:`use_fast_heartbeats`). DDS acknowledges on receipt,
not when the node has processed a message, so a subscriber must drain its queue about as fast as DDS fills
it; the saml_ros recorder does (see docs/bags.md for measured rates). SIGINT / SIGTERM stop playback (exit 0).
"""

from __future__ import annotations

import argparse
import re
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from saml_ros.bags.io import Bag, BagError, message_class, rclpy_qos_for_playback
from saml_ros.nodes.runtime import catch_stop_signals, full_argv, init_rclpy, process_main, shutdown

CLOCK_TOPIC = "/clock"

#: Fast DDS writers announce (heartbeat) every 3 s by default and readers acknowledge only then, so waiting
#: for acknowledgements would stall ~3 s per batch; the player's writers heartbeat every 2 ms instead.
_FASTDDS_PROFILE = """<?xml version="1.0" encoding="UTF-8" ?>
<profiles xmlns="http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles">
  <data_writer profile_name="saml_ros_play" is_default_profile="true">
    <times><heartbeatPeriod><sec>0</sec><nanosec>2000000</nanosec></heartbeatPeriod></times>
  </data_writer>
</profiles>
"""
_PROFILE_ENV = "FASTRTPS_DEFAULT_PROFILES_FILE"


def use_fast_heartbeats() -> Path | None:
    """Point Fast DDS at a profile with fast writer heartbeats (before ``rclpy.init``).

    Returns the temporary profile file to delete at exit, or ``None`` when the user set their own profile
    file or another RMW is selected (then acknowledgements arrive at that RMW's pace).
    """
    import os
    import tempfile

    if os.environ.get(_PROFILE_ENV) or os.environ.get("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp") != "rmw_fastrtps_cpp":
        return None
    fd, name = tempfile.mkstemp(prefix="saml_play_", suffix=".xml")
    with os.fdopen(fd, "w") as f:
        f.write(_FASTDDS_PROFILE)
    os.environ[_PROFILE_ENV] = name
    return Path(name)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="play",
        description="Republish a rosbag2 bag with its original timing (or faster), publishing /clock from it.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    p.add_argument("bag", type=Path, help="bag directory")
    p.add_argument("--rate", type=float, default=1.0,
                   help="speed factor (2 = twice as fast); 0 = as fast as possible without loss")
    p.add_argument("--topics", nargs="+", metavar="TOPIC", help="play only these topics")
    p.add_argument("--exclude", help="do not play topics matching this regular expression")
    p.add_argument("--no-clock", action="store_true",
                   help="do not publish /clock from the bag's timestamps (republish a recorded /clock instead)")
    p.add_argument("--wait-for-subscribers", nargs="*", metavar="TOPIC",
                   help="before playing, wait until these topics (no names: every played topic and /clock) have a "
                        "subscriber")
    p.add_argument("--wait-timeout", type=float, default=30.0, help="give up waiting for subscribers after (s)")
    p.add_argument("--delay", type=float, default=0.0,
                   help="sleep this long (s) before playing (after --wait-for-subscribers): a subscriber's side of "
                        "a match can lag the player's, and DDS drops what a volatile reader gets before it")
    p.add_argument("--ack-batch", type=int, default=50,
                   help="--rate 0: wait for acknowledgements after this many messages")
    p.add_argument("--ack-timeout", type=float, default=10.0, help="longest wait for acknowledgements (s)")
    return p


class Player:
    """Publishes a bag's messages; owns one publisher per played topic (+ /clock)."""

    def __init__(self, node: Any, bag: Bag, topics: list[str], *, clock: bool) -> None:
        from msg_schemas.base import CLOCK_QOS

        self.node = node
        self.bag = bag
        self.publishers: dict[str, Any] = {}
        self.skipped: list[str] = []
        for topic in topics:
            info = bag.topics[topic]
            cls = message_class(info.msg_type)
            if cls is None or "," in info.msg_type:
                self.skipped.append(topic)
                continue
            self.publishers[topic] = node.create_publisher(cls, topic, rclpy_qos_for_playback(info.qos))
        self.clock_pub = None
        if clock:
            from rosgraph_msgs.msg import Clock

            self.clock_pub = node.create_publisher(Clock, CLOCK_TOPIC, CLOCK_QOS.to_rclpy())
        self.published = 0
        #: topics whose subscribers had not acknowledged every message within ``ack_timeout`` (reliable QoS)
        self.unacked: set[str] = set()

    def wait_for_subscribers(self, topics: Sequence[str], timeout: float, stop: dict[str, int]) -> list[str]:
        """Wait until each of ``topics`` has a subscriber; returns the ones still without one."""
        deadline = time.monotonic() + timeout
        pubs = dict(self.publishers)
        if self.clock_pub is not None:
            pubs[CLOCK_TOPIC] = self.clock_pub
        waiting = [t for t in topics if t in pubs]
        while waiting and not stop["signal"] and time.monotonic() < deadline:
            waiting = [t for t in waiting if pubs[t].get_subscription_count() == 0]
            time.sleep(0.02)
        if not waiting:
            time.sleep(0.2)  # the subscriber side finishes matching too
        return waiting

    def play(self, rate: float, stop: dict[str, int], *, ack_batch: int, ack_timeout: float) -> None:
        """Publish every message (in log-time order) paced by ``rate`` (0 = acknowledgement paced)."""
        from rclpy.duration import Duration

        from msg_schemas.telemetry import clock_to_msg

        ack = Duration(seconds=ack_timeout)
        first: int | None = None
        start = time.monotonic()
        last_clock = -1
        dirty: set[str] = set()
        for msg in self.bag.messages(self.publishers):
            if stop["signal"]:
                break
            if first is None:
                first = msg.log_time_ns
            if rate > 0:
                due = start + (msg.log_time_ns - first) / 1e9 / rate
                while not stop["signal"]:
                    delay = due - time.monotonic()
                    if delay <= 0:
                        break
                    time.sleep(min(delay, 0.1))
            if self.clock_pub is not None and msg.log_time_ns > last_clock:
                self.clock_pub.publish(clock_to_msg(msg.log_time_ns))
                last_clock = msg.log_time_ns
            self.publishers[msg.topic].publish(msg.data)
            self.published += 1
            if rate <= 0:
                dirty.add(msg.topic)
                if self.published % max(1, ack_batch) == 0:
                    for topic in dirty:
                        if not self.publishers[topic].wait_for_all_acked(ack):
                            self.unacked.add(topic)
                    dirty.clear()
        for topic, pub in self.publishers.items():
            if not pub.wait_for_all_acked(ack):
                self.unacked.add(topic)


@process_main
def main(argv: Sequence[str] | None = None) -> int:
    from rclpy.node import Node
    from rclpy.utilities import remove_ros_args

    from saml_ros.nodes.ros_params import check_startup

    full = full_argv("play", argv)
    args = build_parser().parse_args(remove_ros_args(full)[1:])
    if args.rate < 0:
        print("play: --rate must be >= 0", file=sys.stderr)
        return 2
    if not args.delay >= 0:
        print(f"play: --delay must be >= 0 s, got {args.delay}", file=sys.stderr)
        return 2
    try:
        bag = Bag(args.bag)
    except BagError as exc:
        print(f"play: {exc}", file=sys.stderr)
        return 1
    exclude = re.compile(args.exclude) if args.exclude else None
    wanted = args.topics or list(bag.topics)
    unknown = [t for t in wanted if t not in bag.topics]
    if unknown:
        print(f"play: bag {bag.path} has no topic(s) {unknown}; it has {list(bag.topics)}", file=sys.stderr)
        return 2
    clock = not args.no_clock
    topics = [t for t in wanted if not (exclude and exclude.search(t)) and not (clock and t == CLOCK_TOPIC)]

    profile = use_fast_heartbeats()
    init_rclpy(full)
    stop = catch_stop_signals()
    node = Node("play")
    try:
        try:  # the player's options are its command-line arguments; ROS parameters only rclpy's own
            check_startup(node, ())
        except ValueError as exc:
            print(f"play: {exc}", file=sys.stderr)
            return 2
        player = Player(node, bag, topics, clock=clock)
        for t in player.skipped:
            print(f"play: skipping {t}: message type {bag.topics[t].msg_type} is not available", file=sys.stderr)
        if args.wait_for_subscribers is not None:
            played = list(player.publishers) + ([CLOCK_TOPIC] if player.clock_pub is not None else [])
            want = args.wait_for_subscribers or played
            missing = [t for t in want if t not in played]
            if missing:
                print(f"play: --wait-for-subscribers: {missing} are not played topics", file=sys.stderr)
                return 2
            still = player.wait_for_subscribers(want, args.wait_timeout, stop)
            if still and not stop["signal"]:
                print(f"play: no subscriber on {still} after {args.wait_timeout} s", file=sys.stderr)
                return 1
        if args.delay > 0 and not stop["signal"]:
            deadline = time.monotonic() + args.delay
            while not stop["signal"] and time.monotonic() < deadline:
                time.sleep(min(0.05, max(deadline - time.monotonic(), 0.0)))
        print(f"play: {bag.path}: {bag.message_count} messages over {bag.duration_ns / 1e9:.3f} s at rate "
              f"{args.rate if args.rate > 0 else 'max'}", flush=True)
        t0 = time.monotonic()
        player.play(args.rate, stop, ack_batch=args.ack_batch, ack_timeout=args.ack_timeout)
        print(f"play: published {player.published} messages in {time.monotonic() - t0:.3f} s", flush=True)
        if player.unacked:
            print(f"play: not every message on {sorted(player.unacked)} was acknowledged within {args.ack_timeout} s "
                  f"(--ack-timeout): a subscriber may have missed some", file=sys.stderr)
        return 0
    except BagError as exc:
        print(f"play: {exc}", file=sys.stderr)
        return 1
    finally:
        bag.close()
        shutdown(node)
        if profile is not None:
            profile.unlink(missing_ok=True)


if __name__ == "__main__":
    raise SystemExit(main())
