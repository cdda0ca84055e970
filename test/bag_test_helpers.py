"""Shared by the bag tests: a private ROS domain fixture, the publisher process, the recorder process and the
transitions a correct learner pairs from a roll-out (see bag_publisher.py)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from bag_publisher import save_events
from ros_helpers import RosDomain, ros_domain, wait_for

PUBLISHER = Path(__file__).resolve().parent / "bag_publisher.py"


@pytest.fixture(name="ros_env")
def ros_env_fixture(request: pytest.FixtureRequest) -> Iterator[RosDomain]:
    """``ros_env``: a private ROS domain (ros_helpers); processes launched through it are stopped after the test.

    Import ``ros_env_fixture`` into a test module to use it."""
    with ros_domain(request.node.name) as dom:
        yield dom


def unique_ns(system: str = "friction") -> str:
    """A namespace no other run uses: processes of other test suites in the same domain stay out of the bag."""
    return f"/{system}_{os.getpid()}_{time.monotonic_ns() % 10**6}"


def start_publisher(events: list[dict], tmp: Path, *args: str) -> subprocess.Popen[str]:
    """A bag_publisher.py process publishing the saved roll-out ``events`` (no torch in that process)."""
    path = tmp / f"events-{time.monotonic_ns()}.npz"
    save_events(path, events)
    return subprocess.Popen([sys.executable, str(PUBLISHER), "--events", str(path), *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=dict(os.environ))


def publish(events: list[dict], tmp: Path, *args: str, timeout: float = 90.0, recorder: Any = None) -> dict:
    """Publish ``events`` with a bag_publisher.py process in this test's ROS domain; returns its JSON report.

    With ``recorder`` (a ``record`` process) and ``--wait-subscribers``, the publisher sends only after the recorder
    announced the match of each of its topics (``record: matched``): under load the recorder's side of a match can
    lag the publisher's by more than any fixed settle time, and DDS drops what a volatile reader gets before it."""
    go = tmp / f"go-{time.monotonic_ns()}"
    if recorder is not None:
        args = (*args, "--go-file", str(go))
        before = recorder.output()
    proc = start_publisher(events, tmp, *args)
    if recorder is not None:
        ready = go.with_name(go.name + ".ready")
        wait_for(lambda: ready.exists() or proc.poll() is not None, timeout=60.0, what="the publisher's match")
        assert proc.poll() is None, proc.communicate()
        topics = json.loads(ready.read_text())

        def matched() -> bool:
            out = recorder.output()
            return all(out.count(f"record: matched {t} (") > before.count(f"record: matched {t} (") for t in topics)

        wait_for(lambda: matched() or not recorder.alive(), timeout=60.0, what="the recorder to match every topic")
        assert recorder.alive(), recorder.output()
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
