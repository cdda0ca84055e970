"""The online learner's test set-up shared by its in-process tests (test/unit/core/online/) and the tests of its
training process (test/ros/core/online/): the friction system and paper spec, a small configuration, true
transitions, learners (optionally checkpointed)."""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from saml_ros.core.data.pairing import Transition
from saml_ros.core.model.checkpoint import CheckpointStore
from saml_ros.core.online import HeldoutConfig, OnlineConfig, OnlineLearner
from saml_ros.core.spec import ProblemSpec
from saml_ros.core.systems import get_system
from saml_ros.core.training import TrainConfig

SYSTEM = get_system("friction")
SPEC = ProblemSpec.for_system(SYSTEM.paper_spec(), SYSTEM)
DT = 100_000_000  # friction dt = 0.1 s


def config(**kw: object) -> OnlineConfig:
    """The tests' online configuration (small batches, fast learning rates), with ``kw`` replaced."""
    base: dict[str, object] = {
        "min_transitions": 200,
        "train": TrainConfig(batch_size=64, primal_lr=3e-3, dual_lr=1e-2),
        "buffer_capacity": 5000,
        "telemetry_window": 300,
        "heldout": HeldoutConfig(fraction=0.0),  # these tests count transitions: none held out (test_heldout_online)
    }
    base.update(kw)
    return OnlineConfig(**base)  # type: ignore[arg-type]


def transitions(n: int, seed: int = 0, source: int = 0) -> list[Transition]:
    """``n`` true friction transitions of the paper's distribution from ``source``, stamps 3 dt apart."""
    rng = np.random.default_rng(seed)
    x, u = SYSTEM.sample_inputs(n, rng)
    y = SYSTEM.true_step_np(x, u)
    return [Transition(x[i], u[i], y[i], 10**9 + i * 3 * DT, source) for i in range(n)]


def new_learner(tmp_path: Path | None = None, resume: bool = True, **kw: object) -> OnlineLearner:
    """An online friction learner (checkpoints in ``tmp_path / "run"`` if given), configured by :func:`config`."""
    store = None if tmp_path is None else CheckpointStore(tmp_path / "run", keep=kw.pop("keep", 5))  # type: ignore[arg-type]
    return OnlineLearner(SYSTEM, SPEC, config(**kw), store=store, resume=resume)


def checkpointed_learner(tmp_path: Path, seed: int, updates: int) -> OnlineLearner:
    """A learner trained ``updates`` steps on 300 transitions, saved as checkpoint version 1 in ``tmp_path / "run"``."""
    learner = new_learner(tmp_path)
    for tr in transitions(300, seed=seed):
        learner.add(tr)
    learner.update(updates)
    assert learner.save_checkpoint() == (tmp_path / "run" / "ckpt-000001.saml", 1)
    return learner


def wait_until(pred: Callable[[], bool], timeout: float = 60.0) -> None:
    """Poll ``pred`` every 20 ms; fails the test after ``timeout`` s."""
    deadline = time.monotonic() + timeout
    while not pred():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.02)
