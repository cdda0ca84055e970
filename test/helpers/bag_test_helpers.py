"""Shared by the bag tests: the publisher process, the recorder process, the transitions a correct learner pairs
from a roll-out (see bag_publisher.py) and bags written in-process like a simulator + recorder write them."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from helpers.bag_publisher import rollout, save_events
from helpers.ros_helpers import RosDomain, dying_with_test, wait_for
from msg_schemas import CHECKPOINT_QOS, DATA_QOS, TELEMETRY_QOS, TypestoreFactory, get_schema
from msg_schemas.telemetry import CheckpointInfo, checkpoint_to_msg, model_error_to_msg
from saml_ros.bags.io import BagWriter, jazzy_typestore, saml_topics

PUBLISHER = Path(__file__).resolve().parent / "bag_publisher.py"


def unique_ns(system: str = "friction") -> str:
    """A namespace no other run uses: processes of other test suites in the same domain stay out of the bag."""
    return f"/{system}_{os.getpid()}_{time.monotonic_ns() % 10**6}"


def start_publisher(events: list[dict], tmp: Path, *args: str) -> subprocess.Popen[str]:
    """A bag_publisher.py process publishing the saved roll-out ``events`` (no torch in that process)."""
    path = tmp / f"events-{time.monotonic_ns()}.npz"
    save_events(path, events)
    return subprocess.Popen(dying_with_test([sys.executable, str(PUBLISHER), "--events", str(path), *args]),
                            stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=dict(os.environ))


def publish(events: list[dict], tmp: Path, *args: str, timeout: float = 90.0, recorder: Any = None,
            ready: Callable[[], bool] | None = None) -> dict:
    """Publish ``events`` with a bag_publisher.py process in this test's ROS domain; returns its JSON report.

    With ``recorder`` (a ``record`` process) and ``--wait-subscribers``, the publisher sends only after the recorder
    announced the match of each of its topics (``record: matched``) and ``ready()`` (another reader's own side of
    the match, e.g. a learner's /diagnostics) is true: under load a reader's side of a match can lag the
    publisher's by more than any fixed settle time, and DDS drops what a volatile reader gets before it."""
    go = tmp / f"go-{time.monotonic_ns()}"
    if recorder is not None:
        args = (*args, "--go-file", str(go))
        before = recorder.output()
    proc = start_publisher(events, tmp, *args)
    if recorder is not None:
        ready_file = go.with_name(go.name + ".ready")
        wait_for(lambda: ready_file.exists() or proc.poll() is not None, timeout=60.0, what="the publisher's match")
        assert proc.poll() is None, proc.communicate()
        topics = json.loads(ready_file.read_text())

        def matched() -> bool:
            out = recorder.output()
            return all(out.count(f"record: matched {t} (") > before.count(f"record: matched {t} (") for t in topics)

        wait_for(lambda: matched() or not recorder.alive(), timeout=60.0, what="the recorder to match every topic")
        assert recorder.alive(), recorder.output()
        if ready is not None:
            wait_for(ready, timeout=60.0, what="the other readers to match the publisher")
        go.touch()
    out, err = proc.communicate(timeout=timeout)
    assert proc.returncode == 0, err
    return dict(json.loads(out.strip().splitlines()[-1]))


def start_recorder(ros_env: RosDomain, out: Path, *args: str) -> Any:
    """``record -o out ARGS`` in the test's domain, once it has opened the bag (a ros_helpers.Process)."""
    rec = ros_env.launch("record", args=["-o", str(out), *args])
    wait_for(lambda: "record: writing" in rec.output() or not rec.alive(), what="the recorder to start")
    assert rec.alive(), rec.output()
    return rec


def expected(events: list[dict]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The transitions a correct learner pairs from ``events`` (bag_publisher.rollout), in order."""
    xs, us, ys = [], [], []
    for k, ev in enumerate(events):
        if "u" in ev:
            xs.append(ev["x"])
            us.append(ev["u"])
            ys.append(ev["y"] if "y" in ev else events[k + 1]["x"])
    return np.array(xs), np.array(us), np.array(ys)


FACTORY = TypestoreFactory(jazzy_typestore())
#: the first stamp of the bags the tests write (ns)
T0 = 2 * 10**9


def write_rollout(path: Path, system: str, events: list[dict], *, namespace: str | None = None,
                  writer: BagWriter | None = None, extra: bool = False) -> None:
    """Write ``events`` (bag_publisher.rollout) like a simulator + recorder would: log time = stamp + 1 ms."""
    schema = get_schema(system)
    ns = namespace or f"/{system}"
    own = writer is None
    w = writer if writer is not None else BagWriter(path)
    topics = saml_topics(system, ns)
    names = [f"{ns}/{schema.state_topic}", f"{ns}/{schema.applied_cmd_topic}", f"{ns}/{schema.target_topic}",
             "/clock"]
    for name in dict.fromkeys(names):
        w.add_topic(name, topics[name].msg_type, topics[name].qos)
    if extra:
        w.add_topic(f"{ns}/learner/model_error", "sensor_msgs/msg/JointState", TELEMETRY_QOS)
        w.add_topic(f"{ns}/learner/checkpoint", "std_msgs/msg/String", CHECKPOINT_QOS)
    from msg_schemas.telemetry import clock_to_msg

    for k, ev in enumerate(events):
        t = ev["stamp"]
        w.write_msg("/clock", clock_to_msg(t, factory=FACTORY), t + 1_000_000)
        w.write_msg(f"{ns}/{schema.state_topic}", schema.state_to_msg(ev["x"], t, factory=FACTORY), t + 1_000_000)
        if "u" in ev:
            w.write_msg(f"{ns}/{schema.applied_cmd_topic}", schema.control_to_msg(ev["u"], t, factory=FACTORY),
                        t + 1_000_000)
        if "y" in ev:
            w.write_msg(f"{ns}/{schema.target_topic}", schema.target_to_msg(ev["y"], t, factory=FACTORY),
                        t + 1_000_000)
        if extra and k % 5 == 0:
            metrics = {"objective": 1.0 / (k + 1), "lambda/near_origin": 0.1 * k, "buffer_size": float(k),
                       "error_in/near_origin": float("nan") if k < 10 else 0.5}
            w.write_msg(f"{ns}/learner/model_error", model_error_to_msg(metrics, t, factory=FACTORY), t + 2_000_000)
    if extra:
        info = CheckpointInfo("/tmp/ckpt-000001.saml", 1, "abc", 1.0)
        w.write_msg(f"{ns}/learner/checkpoint", checkpoint_to_msg(info, factory=FACTORY), T0)
    if own:
        w.close()


# ------------------------------------------------------------------------------ bag fixtures (conftest.py)
@pytest.fixture(scope="module")


def friction_bag(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, list[dict]]:
    """A friction bag (120 states, 40 of them after a reset) with telemetry, and its events (one per module)."""
    path = tmp_path_factory.mktemp("bags") / "friction"
    events = rollout("friction", 120, 40, seed=3, t0_ns=T0)
    write_rollout(path, "friction", events, extra=True)
    return path, events


# ------------------------------------------------------------------------------------------ bad bags


def make_bad_bags(root: Path, good: Path) -> dict[str, tuple[Path, str]]:
    """Bad bags and a fragment their error message must contain."""
    bad: dict[str, tuple[Path, str]] = {}
    # truncated: metadata.yaml intact, MCAP file cut in the middle
    trunc = root / "truncated"
    shutil.copytree(good, trunc)
    mcap = trunc / f"{good.name}.mcap"
    mcap.rename(trunc / "truncated.mcap")
    meta = (trunc / "metadata.yaml").read_text().replace(f"{good.name}.mcap", "truncated.mcap")
    (trunc / "metadata.yaml").write_text(meta)
    data = (trunc / "truncated.mcap").read_bytes()
    (trunc / "truncated.mcap").write_bytes(data[: len(data) // 2])
    bad["truncated"] = (trunc, "truncated")
    # no metadata.yaml: a recorder that was killed
    unfinished = root / "unfinished"
    unfinished.mkdir()
    shutil.copy(trunc / "truncated.mcap", unfinished / "unfinished.mcap")
    bad["unfinished"] = (unfinished, "--repair")
    # bag without the needed topics
    with BagWriter(root / "notopics") as w:
        w.add_topic("/clock", "rosgraph_msgs/msg/Clock", DATA_QOS)
        from msg_schemas.telemetry import clock_to_msg

        w.write_msg("/clock", clock_to_msg(5, factory=FACTORY), 5)
    bad["notopics"] = (root / "notopics", "missing topic(s) /friction/state, /friction/applied_cmd")
    # state recorded as Odometry: the type does not match the schema
    with BagWriter(root / "wrongtype") as w:
        w.add_topic("/friction/state", "nav_msgs/msg/Odometry", DATA_QOS)
        w.add_topic("/friction/applied_cmd", "sensor_msgs/msg/JointState", DATA_QOS)
        odom = get_schema("quadrotor").state_to_msg(np.r_[np.zeros(6), 1.0, np.zeros(6)], 7, factory=FACTORY)
        w.write_msg("/friction/state", odom, 7)
    bad["wrongtype"] = (root / "wrongtype", "/friction/state has message type nav_msgs/msg/Odometry")
    # empty: a finished bag without a single message
    with BagWriter(root / "empty") as w:
        w.add_topic("/friction/state", "sensor_msgs/msg/JointState", DATA_QOS)
    bad["empty"] = (root / "empty", "empty")
    bad["missing"] = (root / "does_not_exist", "does not exist")
    # messages present, but no transition in them (only states)
    with BagWriter(root / "nopairs") as w:
        for t in ("/friction/state", "/friction/applied_cmd"):
            w.add_topic(t, "sensor_msgs/msg/JointState", DATA_QOS)
        w.write_msg("/friction/state", get_schema("friction").state_to_msg([0.0, 0.0], 9, factory=FACTORY), 9)
    bad["nopairs"] = (root / "nopairs", "no complete friction transition")
    return bad


@pytest.fixture(scope="module")


def bad_bags(tmp_path_factory: pytest.TempPathFactory, friction_bag: tuple[Path, list[dict]]) -> dict:
    """:func:`make_bad_bags` from :func:`friction_bag` (one set per module)."""
    return make_bad_bags(tmp_path_factory.mktemp("bad"), friction_bag[0])
