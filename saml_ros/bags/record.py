"""``ros2 run saml_ros record``: record a closed loop's topics into a rosbag2 bag (version 9, MCAP).

    record --system friction                       # /friction/** + /clock + /diagnostics -> rosbag2_<time>/
    record --system quadrotor --namespace /q1 /q2 -o runs/flight1
    record --topics /friction/state /clock -o bag  # exactly these topics
    record --topics /dd/odom:nav_msgs/msg/Odometry -o bag   # ... subscribed at once, before anyone publishes
    record --all -o bag                            # every topic

Messages are recorded with *raw* subscriptions: the CDR bytes DDS delivered are written as they are
(never deserialised and serialised again), so the bag holds exactly what was published. The graph is
polled every ``--poll-period`` s, so topics that appear late are picked up; topics that disappear keep
their subscription (and resume if they come back). Each topic is subscribed with the QoS its publishers
offer (reliable / transient local when all of them are), and their offered profiles go into metadata.yaml.

Topics that appear after the recorder started keep their first message when the recorder can subscribe
*before* their publisher starts, as a subscriber that was there first does: a selected topic whose type is
known, from ``--topics NAME:TYPE`` or from another node's subscription seen in the graph (the learner
listening for the robot's odometry), is subscribed at once (reliable, volatile, keep all: the QoS every reliable
publisher matches, volatile or transient local); the publisher then finds the recorder when it starts. When the
publishers show up, a subscription they cannot match (they offer best effort) is made again with their QoS,
and one that has received nothing yet from transient-local publishers is made again transient local (so it
gets their history). A topic seen only once it is published is subscribed at the next poll: its first
messages may be lost.
Each new publisher is announced (``record: matched TOPIC ...``, counted as ``publishers_matched`` on
/diagnostics): a publisher that starts sending before that line may lose its first messages to DDS (it
sees the recorder a moment before the recorder sees it, and a volatile reader drops what comes between).

The log time of a message is when it arrived at the recorder (the middleware's receive time on the wall
clock; the recorder's simulated time with ``--use-sim-time`` or ``--ros-args -p use_sim_time:=true``). ``play`` replays with those times.

Durability: the pending MCAP chunk is written and the file flushed every ``--flush-period`` s (default
0.5), so a crash (SIGKILL, power cut aside) loses at most that much. A write that fails (a full or read-only disk)
stops the recording at once (one error line, ERROR on /diagnostics) and the recorder exits 1; where the bag can no
longer be finished it says so and the messages flushed before are recovered with ``bag_info --repair``. SIGINT / SIGTERM first write what the
middleware already delivered (until nothing new arrived for 0.3 s, at most 5 s), then finish the bag
(footer + metadata.yaml) and exit 0. A bag of a killed recorder is recovered with ``bag_info --repair``.
"""

from __future__ import annotations

import argparse
import re
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from msg_schemas.names import normalize_namespace
from saml_ros.bags.io import (
    CUSTOM_NAMESPACES,
    CUSTOM_SCHEMA_HASH,
    CUSTOM_SYSTEM,
    DEFAULT_FLUSH_PERIOD,
    BagError,
    BagWriter,
    jazzy_typestore,
    message_class,
    qos_from_rclpy,
    saml_topics,
)
from saml_ros.nodes.runtime import catch_stop_signals, full_argv, init_rclpy, process_main, shutdown, spin_until_stopped

#: topics recorded next to the namespaces' topics by default
GLOBAL_DEFAULT_TOPICS = ("/clock", "/diagnostics")


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="record",
        description="Record saml_ros topics (raw CDR) into a rosbag2 bag: format version 9, MCAP storage.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    p.add_argument("-o", "--output", type=Path, help="bag directory to create (default: rosbag2_<date-time>)")
    p.add_argument("--system", help="system whose closed loop is recorded (friction, quadrotor, paddle_ball); "
                   "default namespace /<system>; stored in metadata.yaml custom_data")
    p.add_argument("--namespace", nargs="+", default=[], metavar="NS",
                   help="system namespace(s) to record (every topic under each, plus /clock and /diagnostics)")
    p.add_argument("--topics", nargs="+", default=[], metavar="TOPIC",
                   help="record exactly these topics; TOPIC:TYPE (e.g. /odom:nav_msgs/msg/Odometry) subscribes at "
                        "once, before the topic has a publisher, so its first message is kept")
    p.add_argument("--regex", help="also record topics matching this regular expression")
    p.add_argument("--all", action="store_true", help="record every topic")
    p.add_argument("--exclude", help="never record topics matching this regular expression")
    p.add_argument("--poll-period", type=float, default=0.5, help="graph poll period for new topics (s)")
    p.add_argument("--flush-period", type=float, default=DEFAULT_FLUSH_PERIOD,
                   help="write the pending MCAP chunk and flush at least this often (s)")
    p.add_argument("--queue-depth", type=int, default=1000, help="subscription queue depth (messages)")
    p.add_argument("--duration", type=float, default=0.0, help="stop after this many wall seconds (0 = until Ctrl-C)")
    p.add_argument("--use-sim-time", action="store_true", help="log times from /clock instead of the wall clock")
    return p


class TopicSelector:
    """Decides which discovered topics to record."""

    def __init__(self, *, namespaces: Sequence[str], topics: Sequence[str], regex: str | None,
                 all_topics: bool, exclude: str | None) -> None:
        self.prefixes = tuple(normalize_namespace(ns).rstrip("/") + "/" for ns in namespaces)
        #: ``--topics NAME:TYPE``: the types given (subscribed before the topic exists in the graph)
        self.types: dict[str, str] = {}
        names = []
        for t in topics:
            name, sep, msg_type = str(t).partition(":")
            if sep:
                from msg_schemas.field_path import FieldPathError, check_message_type

                try:
                    self.types[name] = check_message_type(msg_type)
                except FieldPathError as exc:
                    raise ValueError(f"--topics {t}: {exc}") from None
            names.append(name)
        self.exact = set(names) | (set(GLOBAL_DEFAULT_TOPICS) if namespaces else set())
        self.regex = re.compile(regex) if regex else None
        self.all = all_topics
        self.exclude = re.compile(exclude) if exclude else None

    def __call__(self, topic: str) -> bool:
        if self.exclude is not None and self.exclude.search(topic):
            return False
        return (
            self.all
            or topic in self.exact
            or topic.startswith(self.prefixes)
            or (self.regex is not None and self.regex.search(topic) is not None)
        )


class Recorder:
    """The recording node: discovers topics, subscribes raw, writes to a :class:`BagWriter`.

    Args:
        node: an rclpy node (the recorder owns its subscriptions and timers).
        writer: the open bag.
        select: topic filter.
        poll_period / flush_period: seconds.
        queue_depth: subscription history depth.
    """

    def __init__(self, node: Any, writer: BagWriter, select: TopicSelector, *, poll_period: float,
                 flush_period: float, queue_depth: int) -> None:
        self.node = node
        self.writer = writer
        self.select = select
        self.queue_depth = int(queue_depth)
        self.subscriptions: dict[tuple[str, str], Any] = {}
        #: subscriptions made before their topic had a publisher: their QoS is settled when publishers show up
        self.early: dict[tuple[str, str], str] = {}
        self.received: dict[tuple[str, str], int] = {}
        self.skipped: set[tuple[str, str]] = set()
        self.counters: dict[str, int] = {"messages": 0, "bytes": 0, "topics": 0, "skipped_topics": 0,
                                         "write_errors": 0, "publishers_matched": 0}
        self.error: str | None = None
        self._clock = node.get_clock()
        self._diag_pub = self._make_diagnostics_publisher()
        # wall-clock (steady) timers: with use_sim_time, ROS-time timers would not fire before /clock runs, and a
        # lockstep simulator waits for this recorder's subscriptions before it publishes /clock
        from rclpy.clock import Clock, ClockType

        steady = Clock(clock_type=ClockType.STEADY_TIME)
        node.create_timer(poll_period, self.poll, clock=steady)
        node.create_timer(flush_period, self.flush, clock=steady)
        node.create_timer(1.0, self.publish_diagnostics, clock=steady)
        self.poll()

    def _make_diagnostics_publisher(self) -> Any:
        from diagnostic_msgs.msg import DiagnosticArray

        from msg_schemas.base import TELEMETRY_QOS

        return self.node.create_publisher(DiagnosticArray, "/diagnostics", TELEMETRY_QOS.to_rclpy())

    # -- discovery
    def poll(self) -> None:
        """Subscribe to every selected topic with a known type that is not yet subscribed: with its publishers'
        QoS if it has publishers, else at once (see the module docstring); settle early subscriptions' QoS."""
        graph = {topic: list(types) for topic, types in self.node.get_topic_names_and_types()}
        for topic, msg_type in self.select.types.items():
            if msg_type not in graph.setdefault(topic, []):
                graph[topic].append(msg_type)
        for topic, types in graph.items():
            if not self.select(topic):
                continue
            for msg_type in types:
                key = (topic, msg_type)
                if key in self.skipped or (key in self.subscriptions and key not in self.early):
                    continue
                publishers = self.node.get_publishers_info_by_topic(topic)
                publishers = [p for p in publishers if p.topic_type == msg_type]
                if key in self.early:
                    if publishers:
                        self._settle(topic, msg_type, publishers)
                elif publishers:
                    self._subscribe(topic, msg_type, publishers)
                else:  # nobody publishes it yet: be there when its publisher starts
                    self._subscribe(topic, msg_type, [])

    def _settle(self, topic: str, msg_type: str, publishers: list[Any]) -> None:
        """An early subscription's publishers have shown up: make it again with their QoS if it cannot match them
        (best effort), or to get their history (transient local) while it has received nothing."""
        from rclpy.qos import DurabilityPolicy, ReliabilityPolicy

        key = (topic, msg_type)
        offered = [p.qos_profile for p in publishers]
        # before any publisher (offered = []): reliable, volatile, the default of ROS 2 publishers
        reliable = all(q.reliability == ReliabilityPolicy.RELIABLE for q in offered)
        transient = bool(offered) and all(q.durability == DurabilityPolicy.TRANSIENT_LOCAL for q in offered)
        del self.early[key]
        if reliable and not (transient and not self.received.get(key)):
            return
        self.node.destroy_subscription(self.subscriptions.pop(key))
        self.counters["topics"] -= 1
        why = "best effort" if not reliable else "transient local (for their history)"
        print(f"record: subscribing {topic} again: its publishers offer {why}", flush=True)
        self._subscribe(topic, msg_type, publishers)

    def _subscribe(self, topic: str, msg_type: str, publishers: list[Any]) -> None:
        from rclpy.event_handler import SubscriptionEventCallbacks
        from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

        key = (topic, msg_type)
        cls = message_class(msg_type)
        if cls is None or msg_type not in jazzy_typestore().types:
            self.skipped.add(key)
            self.counters["skipped_topics"] += 1
            self.node.get_logger().warning(f"not recording {topic}: message type {msg_type} is not available")
            return
        offered = [p.qos_profile for p in publishers]
        # before any publisher (offered = []): reliable, volatile, the default of ROS 2 publishers
        reliable = all(q.reliability == ReliabilityPolicy.RELIABLE for q in offered)
        transient = bool(offered) and all(q.durability == DurabilityPolicy.TRANSIENT_LOCAL for q in offered)
        # Reliable topics are read KEEP_ALL: DDS then acknowledges a sample only once it fits in the queue,
        # so a writer that waits for acknowledgements (``play --rate 0``) is slowed down instead of losing data.
        qos = QoSProfile(
            history=HistoryPolicy.KEEP_ALL if reliable else HistoryPolicy.KEEP_LAST,
            depth=self.queue_depth,
            reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT,
            durability=DurabilityPolicy.TRANSIENT_LOCAL if transient else DurabilityPolicy.VOLATILE,
        )
        if publishers and not self._declare(key, publishers):
            return

        def on_message(data: bytes, info: Any, _key: tuple[str, str] = key) -> None:
            self._write(_key, data, info)

        def on_matched(status: Any, _topic: str = topic) -> None:
            self._matched(_topic, status)

        self.subscriptions[key] = self.node.create_subscription(
            cls, topic, on_message, qos, raw=True, event_callbacks=SubscriptionEventCallbacks(matched=on_matched))
        self.counters["topics"] += 1
        if not publishers:
            self.early[key] = ""
        print(f"record: recording {topic} ({msg_type}, {'reliable' if reliable else 'best effort'}"
              f"{', transient local' if transient else ''}{'' if publishers else ', before it has a publisher'})",
              flush=True)

    def _declare(self, key: tuple[str, str], publishers: list[Any]) -> bool:
        """Declare the topic in the bag with its publishers' offered QoS (once); ``False`` if it cannot be."""
        topic, msg_type = key
        if self.writer.has_topic(topic, msg_type):
            return True
        from rclpy.qos import QoSProfile

        offered = [p.qos_profile for p in publishers] or [QoSProfile(depth=10)]  # unknown yet: ROS 2's default
        type_hash = str(getattr(publishers[0], "topic_type_hash", "") or "") if publishers else ""
        try:
            self.writer.add_topic(topic, msg_type, [qos_from_rclpy(q) for q in offered],
                                  type_hash=type_hash if type_hash.startswith("RIHS01_") else None)
        except BagError as exc:
            self.skipped.add(key)
            self.counters["skipped_topics"] += 1
            self.node.get_logger().warning(f"not recording {topic}: {exc}")
            if key in self.subscriptions:
                self.node.destroy_subscription(self.subscriptions.pop(key))
                self.counters["topics"] -= 1
                self.early.pop(key, None)
            return False
        return True

    def _matched(self, topic: str, status: Any) -> None:
        """The subscription's matched status changed. Only from a "matched" line on is a publisher's data recorded:
        a publisher sees this recorder a little before this recorder sees it, and DDS drops, for a volatile reader,
        what the publisher sent in between (scripts that must lose nothing wait for this line)."""
        if int(status.total_count_change) > 0:
            self.counters["publishers_matched"] += int(status.total_count_change)
            print(f"record: matched {topic} ({int(status.current_count)} publishers, "
                  f"{int(status.total_count)} so far)", flush=True)

    # -- data
    def _write(self, key: tuple[str, str], data: bytes, info: Any = None) -> None:
        if self.error is not None:
            return
        # on the system clock, the middleware's receive time (not when this callback ran): unstamped messages
        # (a robot's cmd_vel) are paired on it, as the learner does live
        use_rmw = info is not None and not getattr(self._clock, "ros_time_is_active", False)
        t = int(info["received_timestamp"]) if use_rmw else self._clock.now().nanoseconds
        self.received[key] = self.received.get(key, 0) + 1
        if not self.writer.has_topic(*key):  # subscribed before its publisher: declared with the first message
            publishers = [p for p in self.node.get_publishers_info_by_topic(key[0]) if p.topic_type == key[1]]
            if not self._declare(key, publishers):
                return
        try:
            self.writer.write(key[0], key[1], data, t)
        except Exception as exc:  # disk full, ...: stop cleanly so the data already written stays readable
            self.counters["write_errors"] += 1
            self.error = f"cannot write to {self.writer.path}: {exc}"
            self.node.get_logger().error(self.error)
            return
        self.counters["messages"] += 1
        self.counters["bytes"] += len(data)

    def flush(self) -> None:
        if self.error is None:
            try:
                self.writer.flush()
            except Exception as exc:
                self.counters["write_errors"] += 1
                self.error = f"cannot flush {self.writer.path}: {exc}"
                self.node.get_logger().error(self.error)

    def publish_diagnostics(self) -> None:
        from msg_schemas.telemetry import ERROR, OK, DiagnosticEntry, diagnostics_to_msg

        entry = DiagnosticEntry(
            name=self.node.get_fully_qualified_name(),
            level=ERROR if self.error else OK,
            message=self.error or f"recording {self.counters['topics']} topics to {self.writer.path}",
            values=dict(self.counters),
        )
        self._diag_pub.publish(diagnostics_to_msg([entry], self._clock.now().nanoseconds))


def default_output() -> Path:
    """``rosbag2_YYYY_MM_DD-HH_MM_SS`` (rosbag2's default name)."""
    return Path(time.strftime("rosbag2_%Y_%m_%d-%H_%M_%S"))


@process_main
def main(argv: Sequence[str] | None = None) -> int:
    from rclpy.node import Node
    from rclpy.parameter import Parameter
    from rclpy.utilities import remove_ros_args

    from saml_ros.nodes.ros_params import check_startup

    full = full_argv("record", argv)
    args = build_parser().parse_args(remove_ros_args(full)[1:])
    init_rclpy(full)
    stop = catch_stop_signals()
    node = Node("record")
    writer: BagWriter | None = None
    try:
        try:  # the recorder's options are its command-line arguments; ROS parameters only rclpy's own
            check_startup(node, ())
        except ValueError as exc:
            print(f"record: {exc}", file=sys.stderr)
            return 2
        if args.use_sim_time:
            node.set_parameters([Parameter("use_sim_time", Parameter.Type.BOOL, True)])
        namespaces = list(args.namespace)
        if not namespaces and args.system:
            node_ns = node.get_namespace()
            namespaces = [node_ns if node_ns != "/" else f"/{args.system}"]
        if not (namespaces or args.topics or args.regex or args.all):
            print("record: nothing to record: give --system, --namespace, --topics, --regex or --all", file=sys.stderr)
            return 2
        custom: dict[str, str] = {}
        if args.system:
            from msg_schemas import get_schema

            try:
                custom = {CUSTOM_SYSTEM: args.system, CUSTOM_SCHEMA_HASH: get_schema(args.system).schema_hash(),
                          CUSTOM_NAMESPACES: ",".join(normalize_namespace(n) for n in namespaces)}
                saml_topics(args.system)
            except ValueError as exc:
                print(f"record: {exc}", file=sys.stderr)
                return 2
        try:
            select = TopicSelector(namespaces=namespaces, topics=args.topics, regex=args.regex,
                                   all_topics=args.all, exclude=args.exclude)
        except ValueError as exc:
            print(f"record: {exc}", file=sys.stderr)
            return 2
        out = args.output or default_output()
        try:
            writer = BagWriter(out, custom_data=custom, flush_period=args.flush_period)
        except BagError as exc:
            print(f"record: {exc}", file=sys.stderr)
            return 1
        rec = Recorder(node, writer, select, poll_period=args.poll_period, flush_period=args.flush_period,
                       queue_depth=args.queue_depth)
        print(f"record: writing {out} (Ctrl-C to stop)", flush=True)
        deadline = time.monotonic() + args.duration if args.duration > 0 else float("inf")
        # after the stop, what DDS already delivered (acknowledged to the publishers) is still written
        spin_until_stopped(node, stop, lambda: rec.error is None and time.monotonic() < deadline, announce=False,
                           drain=lambda: sum(writer.counts.values()) if rec.error is None else -1)
        try:
            writer.close()
        except OSError as exc:  # a full or read-only disk: the footer and metadata.yaml cannot be written either
            why = f"{rec.error}; the bag cannot be finished either" if rec.error else f"the bag cannot be finished ({exc})"
            print(f"record: {why}: the messages flushed before the error are recovered with `bag_info --repair {out}`",
                  file=sys.stderr, flush=True)
            return 1
        counts = writer.counts
        print(f"record: wrote {sum(counts.values())} messages on {len(counts)} topics to {out}", flush=True)
        return 1 if rec.error else 0
    finally:
        if writer is not None and not writer.closed:
            writer.close()
        shutdown(node)


if __name__ == "__main__":
    raise SystemExit(main())
