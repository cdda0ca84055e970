"""The MPC node and its model watcher.

ROS-free part: :class:`~saml_ros.core.mpc.follower.ModelWatcher` (loading, refusing, handing over).
Node part (real processes, private ROS_DOMAIN_ID): the node answers states with the right stamps and bounds,
starts on the base model, switches to checkpoints that appear while it runs, refuses corrupt and foreign
checkpoints and keeps running.
"""

from __future__ import annotations

import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from helpers.checkpoints import save_model, write_corrupt

from saml_ros.core.model.checkpoint import CheckpointStore
from saml_ros.core.mpc.config import make_goal, parse_solver_options
from saml_ros.core.mpc.follower import ModelWatcher, checkpoint_gate
from saml_ros.core.systems import get_system

# ------------------------------------------------------------------------------------ ModelWatcher


def test_watcher_starts_empty_then_loads_each_new_checkpoint_once(tmp_path: Path) -> None:
    system = get_system("quadrotor")
    watcher = ModelWatcher(system, tmp_path / "run")  # the directory does not exist yet
    assert watcher.poll_once() is None and watcher.take() is None
    store = CheckpointStore(tmp_path / "run")
    path1, v1 = save_model(store, "quadrotor", seed=1)
    ready = watcher.poll_once()
    assert ready is not None and ready.version == v1 == 1 and ready.path == path1
    assert watcher.take() is ready and watcher.take() is None
    assert watcher.poll_once() is None  # nothing new
    _, v2 = save_model(store, "quadrotor", seed=2)
    _, v3 = save_model(store, "quadrotor", seed=3)
    ready = watcher.poll_once()
    assert ready is not None and ready.version == v3 == 3  # the newest, not every one in between
    stats = watcher.stats()
    assert stats["loaded"] == 2 and stats["refused"] == 0 and stats["newest_version"] == 3


def test_watcher_refuses_corrupt_and_foreign_checkpoints_and_keeps_its_model(tmp_path: Path) -> None:
    system = get_system("quadrotor")
    store = CheckpointStore(tmp_path / "run")
    good, _ = save_model(store, "quadrotor")
    watcher = ModelWatcher(system, store.run_dir)
    assert watcher.poll_once() is not None
    write_corrupt(store, good)
    assert watcher.poll_once() is None
    assert watcher.poll_once() is None  # refused once, not on every poll
    stats = watcher.stats()
    assert stats["refused/corrupt"] == 1 and stats["newest_version"] == 1
    assert "truncated" in stats["last_refusal"] or "damaged" in stats["last_refusal"]
    save_model(store, "friction")  # another system's checkpoint becomes `latest` (version 3)
    assert watcher.poll_once() is None
    stats = watcher.stats()
    assert stats["refused/incompatible"] == 1 and "expected 'quadrotor'" in stats["last_refusal"]
    store.latest_path.write_text("garbage\n")  # a malformed pointer
    assert watcher.poll_once() is None and watcher.stats()["refused/corrupt"] == 2
    _, v4 = save_model(store, "quadrotor", seed=4)  # a good one after all that is taken
    ready = watcher.poll_once()
    assert ready is not None and ready.version == v4 == 4
    assert watcher.stats()["refused"] == 3


def test_watcher_notifications(tmp_path: Path) -> None:
    system = get_system("quadrotor")
    store = CheckpointStore(tmp_path / "elsewhere")
    path, version = save_model(store, "quadrotor")
    watcher = ModelWatcher(system)  # notifications only
    watcher.notify(path, version, "0123456789abcdef")  # announced with a wrong schema hash
    assert watcher.poll_once() is None and watcher.stats()["refused/incompatible"] == 1
    watcher.notify(tmp_path / "nope.saml", 7, system.schema_hash())
    assert watcher.poll_once() is None and watcher.stats()["refused/missing"] == 1
    path2, v2 = save_model(store, "quadrotor", seed=2)
    watcher.notify(path2, v2, system.schema_hash())
    ready = watcher.poll_once()
    assert ready is not None and ready.version == 2 and ready.source == "notification"
    watcher.notify(path, version, system.schema_hash())  # an older one: ignored, not refused
    assert watcher.poll_once() is None and watcher.stats()["refused"] == 2


def test_watcher_background_thread_hands_over_without_blocking(tmp_path: Path) -> None:
    """take() never waits for the watcher's thread: while that thread is stuck preparing a checkpoint, take()
    answers None at once (a blocking take() would wait for the release, 30 s away)."""
    system = get_system("quadrotor")
    store = CheckpointStore(tmp_path / "run")
    prepared: list[int] = []
    entered, release = threading.Event(), threading.Event()

    def prepare(lm: Any) -> str:
        entered.set()
        release.wait(30.0)
        prepared.append(lm.version)
        return "ok"

    with ModelWatcher(system, store.run_dir, poll_period=0.05, prepare=prepare) as watcher:
        assert watcher.take() is None
        save_model(store, "quadrotor")
        assert entered.wait(30.0), "the watcher never prepared the checkpoint"
        t0 = time.perf_counter()
        assert watcher.take() is None  # still being prepared
        waited = time.perf_counter() - t0
        release.set()
        ready = watcher.wait_ready(10.0)
    assert waited < 5.0, waited
    assert ready is not None and ready.version == 1 and ready.prepared == "ok" and prepared == [1]
    assert ready.load_seconds > 0


def test_gate_holds_back_checkpoints_the_learner_reports_as_infeasible(tmp_path: Path) -> None:
    system = get_system("quadrotor")
    store = CheckpointStore(tmp_path / "run")
    assert checkpoint_gate(float("inf"), 0) is None
    watcher = ModelWatcher(system, store.run_dir, accept=checkpoint_gate(0.002, 0))
    save_model(store, "quadrotor", metrics={"constraint/near_ground": 0.05})  # far from eps: held back
    assert watcher.poll_once() is None and watcher.poll_once() is None
    stats = watcher.stats()
    assert stats["gated"] == 1 and stats["refused"] == 0 and "gate.max_constraint" in stats["last_gated"]
    save_model(store, "quadrotor")  # no metrics at all: held back too
    assert watcher.poll_once() is None and watcher.stats()["gated"] == 2
    save_model(store, "quadrotor", metrics={"constraint/near_ground": 0.001})
    ready = watcher.poll_once()
    assert ready is not None and ready.version == 3
    strict = ModelWatcher(system, store.run_dir, accept=checkpoint_gate(float("inf"), 10))  # 0 updates in the file
    assert strict.poll_once() is None and "gate.min_updates" in strict.stats()["last_gated"]


def test_goal_and_solver_option_parsing() -> None:
    np.testing.assert_array_equal(make_goal("quadrotor", {"position": [1.0, 2.0, 0.5]}), [1.0, 2.0, 0.5])
    np.testing.assert_array_equal(make_goal("friction", {"position": 0.25}), [0.25])
    with pytest.raises(ValueError, match="goal.position"):
        make_goal("quadrotor", {"position": [1.0, 2.0]})
    with pytest.raises(ValueError, match="goal.position"):
        make_goal("friction", {"position": float("nan")})
    assert parse_solver_options("{max_iter: 20, tol: 1.0e-6}") == {"max_iter": 20, "tol": 1e-6}
    assert parse_solver_options("") == {}
    with pytest.raises(ValueError):
        parse_solver_options("[1, 2]")
