"""``play`` with real processes: a bag written by BagWriter is played into the recorder (private ROS domain)."""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from helpers.bag_publisher import rollout
from helpers.bag_test_helpers import start_recorder, unique_ns
from helpers.ros_helpers import RosDomain

from msg_schemas import CHECKPOINT_QOS, DATA_QOS, TELEMETRY_QOS, TypestoreFactory, get_schema
from msg_schemas.telemetry import CheckpointInfo, checkpoint_to_msg, clock_from_msg, model_error_to_msg
from saml_ros.bags.io import Bag, BagWriter, jazzy_typestore

FACTORY = TypestoreFactory(jazzy_typestore())


def make_play_bag(path: Path, ns: str) -> tuple[list[dict], int]:
    """A 2-s friction bag written directly (log time = stamp), with telemetry and a transient-local topic."""
    events = rollout("friction", 21, 0, seed=7, t0_ns=10**9)  # dt 0.1 s: 2 s of log time
    schema = get_schema("friction")
    n = 0
    with BagWriter(path) as w:
        w.add_topic(f"{ns}/state", "sensor_msgs/msg/JointState", DATA_QOS)
        w.add_topic(f"{ns}/applied_cmd", "sensor_msgs/msg/JointState", DATA_QOS)
        w.add_topic(f"{ns}/learner/model_error", "sensor_msgs/msg/JointState", TELEMETRY_QOS)
        w.add_topic(f"{ns}/learner/checkpoint", "std_msgs/msg/String", CHECKPOINT_QOS)
        info = CheckpointInfo("/tmp/ckpt-000001.saml", 1, "abc", 1.0)
        w.write_msg(f"{ns}/learner/checkpoint", checkpoint_to_msg(info, factory=FACTORY), events[0]["stamp"])
        n += 1
        for k, ev in enumerate(events):
            t = ev["stamp"]
            w.write_msg(f"{ns}/state", schema.state_to_msg(ev["x"], t, factory=FACTORY), t)
            n += 1
            if "u" in ev:
                w.write_msg(f"{ns}/applied_cmd", schema.control_to_msg(ev["u"], t, factory=FACTORY), t)
                n += 1
            if k % 4 == 0:
                w.write_msg(f"{ns}/learner/model_error",
                            model_error_to_msg({"objective": float(k)}, t, factory=FACTORY), t)
                n += 1
    return events, n


def test_play_republishes_identical_bytes_with_clock_and_timing(ros_env: RosDomain, tmp_path: Path) -> None:
    src, ns = tmp_path / "src", unique_ns()
    events, n = make_play_bag(src, ns)
    # 1) as fast as possible, once the recorder listens: nothing lost, the same bytes, /clock = log times. The
    # player waits for a subscriber on each topic (its side of the match), then 3 s for the recorder's side, which
    # lags under load (a reader drops what it gets before it has matched)
    rec = start_recorder(ros_env, tmp_path / "fast", "--system", "friction", "--namespace", ns)
    play = ros_env.launch("play", args=[str(src), "--rate", "0", "--wait-for-subscribers", "--delay", "3"])
    assert play.wait(60) == 0, play.output()
    time.sleep(0.5)
    assert rec.stop() == 0, rec.output()
    with Bag(src) as a, Bag(tmp_path / "fast") as b:
        for topic in a.topics:
            assert [m.data for m in a.messages([topic])] == [m.data for m in b.messages([topic])], (
                topic, play.output(), rec.output())
        clocks = [clock_from_msg(b.decode(m)) for m in b.messages(["/clock"])]
        assert clocks == sorted({m.log_time_ns for m in a.messages()})
        assert b.topics[f"{ns}/learner/checkpoint"].qos[0].durability.name == "TRANSIENT_LOCAL"
    # 2) original timing at twice the speed: 2 s of bag in about 1 s
    rec = start_recorder(ros_env, tmp_path / "timed", "--system", "friction", "--namespace", ns)
    play = ros_env.launch("play", args=[str(src), "--rate", "2", "--wait-for-subscribers", "--delay", "3"])
    assert play.wait(60) == 0, play.output()
    time.sleep(0.5)
    assert rec.stop() == 0, rec.output()
    with Bag(tmp_path / "timed") as b:
        times = [m.log_time_ns for m in b.messages([f"{ns}/state"])]
    assert len(times) == len(events)
    span = (times[-1] - times[0]) / 1e9
    assert 0.85 < span < 1.9, span  # at rate 1 it would be 2 s
    gaps = np.diff(times) / 1e9
    assert np.median(gaps) == pytest.approx(0.05, abs=0.02)




@pytest.mark.parametrize("delay", ["-1", "nan"])
def test_play_refuses_a_negative_or_undefined_delay(tmp_path: Path, delay: str) -> None:
    out = subprocess.run([sys.executable, "-m", "saml_ros.executables", "play", str(tmp_path / "bag"), "--delay",
                          delay], capture_output=True, text=True, timeout=60)
    assert out.returncode == 2 and "--delay must be >= 0 s" in out.stderr, out.stderr
