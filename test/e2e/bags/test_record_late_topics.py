"""The recorder keeps late topics from their first message (saml_ros.bags.record; issue 27 item 5).

Real processes: ``record`` is started first, then a plain rclpy publisher process on a topic that did not exist
when the recorder started. The recorder subscribes to a topic as soon as its type is known (``--topics
NAME:TYPE``, or another node's subscription in the graph, such as the learner listening for the robot's
odometry), so the publisher finds it when it starts and the bag holds its first message.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

from helpers import ros_helpers
from helpers.ros_helpers import RosDomain, TestNode, wait_for

from saml_ros.bags.io import Bag

PUBLISHER = """
import json, sys, time
import rclpy
from rclpy.qos import QoSProfile, ReliabilityPolicy
from std_msgs.msg import Int64
topic, n, subs, reliable = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), sys.argv[4] == "1"
rclpy.init()
node = rclpy.create_node("late_publisher")
qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT)
pub = node.create_publisher(Int64, topic, qos)
deadline = time.monotonic() + 30.0
while pub.get_subscription_count() < subs and time.monotonic() < deadline:
    time.sleep(0.01)
matched = pub.get_subscription_count()
for i in range(n):
    pub.publish(Int64(data=i))
    time.sleep(0.05)
time.sleep(0.5)
print(json.dumps({"published": n, "matched_at_first": matched}))
"""


def publish(topic: str, n: int, subscribers: int, reliable: bool = True) -> dict:
    res = subprocess.run([sys.executable, "-c", PUBLISHER, topic, str(n), str(subscribers), "1" if reliable else "0"],
                         capture_output=True, text=True, timeout=120, env=dict(os.environ))
    assert res.returncode == 0, res.stderr
    return dict(json.loads(res.stdout.strip().splitlines()[-1]))


def recorded(bag: Path, topic: str) -> list[int]:
    with Bag(bag) as b:
        return [int(b.decode(m).data) for m in b.messages([topic])]


def unique(name: str) -> str:
    return f"/late_{os.getpid()}_{time.monotonic_ns() % 10**6}/{name}"


def stop(rec: ros_helpers.Process) -> None:
    rec.signal(signal.SIGINT)
    assert rec.wait(30) == 0, rec.output()


def test_typed_topic_is_subscribed_before_it_exists(ros_env: RosDomain, tmp_path: Path) -> None:
    topic, bag = unique("a"), tmp_path / "bag"
    rec = ros_env.launch("record", args=["-o", str(bag), "--topics", f"{topic}:std_msgs/msg/Int64"])
    wait_for(lambda: "before it has a publisher" in rec.output() or not rec.alive(), what="the early subscription")
    assert rec.alive(), rec.output()
    # the publisher starts after the recorder and sends as soon as it has a subscriber: the recorder
    report = publish(topic, 40, subscribers=1)
    assert report["matched_at_first"] == 1
    stop(rec)
    assert recorded(bag, topic) == list(range(40)), rec.output()
    with Bag(bag) as b:  # declared with its publisher's QoS when its first message came
        assert b.topics[topic].qos and b.topics[topic].qos[0].reliability.name == "RELIABLE"


def test_topic_another_node_listens_to_is_kept_from_its_first_message(ros_env: RosDomain, ros_node: TestNode,
                                                                      tmp_path: Path) -> None:
    """The issue's case: ``record --topics`` beside a learner already listening; the robot starts later."""
    from std_msgs.msg import Int64

    topic, bag = unique("b"), tmp_path / "bag"
    got: list[int] = []
    ros_node.subscribe(Int64, topic, callback=lambda m: got.append(int(m.data)))  # the learner, listening
    rec = ros_env.launch("record", args=["-o", str(bag), "--topics", topic])
    # the recorder sees the listener in the graph, so the topic's type: it subscribes before any publisher
    wait_for(lambda: "before it has a publisher" in rec.output() or not rec.alive(), what="the early subscription")
    assert rec.alive(), rec.output()
    report = publish(topic, 40, subscribers=2)
    assert report["matched_at_first"] == 2
    stop(rec)
    wait_for(lambda: len(got) == 40, what="the listener's messages")
    assert recorded(bag, topic) == got == list(range(40)), rec.output()


def test_best_effort_publisher_of_an_early_topic_is_subscribed_again(ros_env: RosDomain, tmp_path: Path) -> None:
    """A reliable early subscription cannot match a best-effort publisher: made again with its QoS."""
    topic, bag = unique("c"), tmp_path / "bag"
    rec = ros_env.launch("record", args=["-o", str(bag), "--topics", f"{topic}:std_msgs/msg/Int64"])
    wait_for(lambda: "before it has a publisher" in rec.output() or not rec.alive(), what="the early subscription")
    report = publish(topic, 30, subscribers=1, reliable=False)
    assert report["matched_at_first"] == 1
    stop(rec)
    out = rec.output()
    assert f"record: subscribing {topic} again: its publishers offer best effort" in out, out
    assert recorded(bag, topic) == list(range(30)), out  # best effort on one host: nothing dropped here


def test_unknown_type_is_refused() -> None:
    res = subprocess.run([sys.executable, "-m", "saml_ros.executables", "record", "--topics", "/x:std_msgs/msg/Int46",
                          "-o", "/nonexistent/never"], capture_output=True, text=True, timeout=120,
                         env=dict(os.environ))
    assert res.returncode == 2
    assert "--topics /x:std_msgs/msg/Int46: message type 'std_msgs/msg/Int46': unknown message type" in res.stderr
    assert "did you mean" in res.stderr
