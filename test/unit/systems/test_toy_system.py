"""A fourth system added from a folder of the test tree (``test/helpers/toy_system/``, laid out like
``saml_ros/systems/<name>/``) with one registry line: the registry, the message schemas, its simulator world, the
online learner, checkpoints and the MPC reach it as they reach the built-in three (issue 31 item 1)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from helpers import toy_system
from helpers.toy_system.model import DragCart
from helpers.toy_system.schema import SCHEMA

from msg_schemas import get_schema
from saml_ros.core.data.pairing import Transition
from saml_ros.core.model.checkpoint import CheckpointStore
from saml_ros.core.model.io import load_model
from saml_ros.core.mpc import closed_loop, make_controller
from saml_ros.core.online import HeldoutConfig, OnlineConfig, OnlineLearner
from saml_ros.core.spec import ProblemSpec
from saml_ros.core.systems import SYSTEM_NAMES, get_entry, get_system, register_system, system_names
from saml_ros.core.training import TrainConfig
from saml_ros.core.worlds.sim_core import SimConfig, SteppedSim, build_stepped_sim


def _transitions(system: DragCart, n: int, seed: int) -> list[Transition]:
    x, u = system.sample_inputs(n, np.random.default_rng(seed))
    y = system.true_step_np(x, u)
    return [Transition(x[i], u[i], y[i], 10**9 + i * 300_000_000, 0) for i in range(n)]


def test_a_system_from_a_folder_learns_and_plans(restore_registry: None, tmp_path: Path) -> None:
    entry = register_system(toy_system.ENTRY)  # the one registry line
    assert system_names()[-1] == "toy_drag_cart" not in SYSTEM_NAMES and get_entry("toy_drag_cart") is entry
    assert get_schema("toy_drag_cart") is SCHEMA
    system = get_system("toy_drag_cart", drag=3.0)
    assert isinstance(system, DragCart) and system.drag == 3.0
    assert isinstance(build_stepped_sim(system, SimConfig(mode="lockstep", seed=1)), SteppedSim)  # its world

    # the online learner on its transitions: the residual learns the drag f_hat does not know
    spec = ProblemSpec.for_system(system.paper_spec(), system)
    config = OnlineConfig(min_transitions=200, train=TrainConfig(batch_size=64, primal_lr=1e-2, seed=0),
                          heldout=HeldoutConfig(fraction=0.0))
    learner = OnlineLearner(system, spec, config, store=CheckpointStore(tmp_path / "run"))
    for tr in _transitions(system, 800, seed=0):
        learner.add(tr)
    assert learner.update(800) == 800
    x, u = system.sample_inputs(500, np.random.default_rng(1))
    y = system.true_step_np(x, u)
    model = learner.published_model()
    err_model = float(np.mean(np.linalg.norm(model.predict_np(x, u) - y, axis=1)))
    err_fhat = float(np.mean(np.linalg.norm(system.base_step_np(x, u) - y, axis=1)))
    assert err_model < 0.5 * err_fhat, (err_model, err_fhat)

    # its checkpoint is loaded back through the registry (the system rebuilt by name)
    saved = learner.save_checkpoint()
    assert saved is not None
    loaded = load_model(saved[0])
    assert isinstance(loaded.system, DragCart)
    np.testing.assert_array_equal(loaded.model.predict_np(x, u), model.predict_np(x, u))

    # the MPC with the learned model drives the cart from 1.5 m to the goal 0 m and holds it there
    ctrl = make_controller(system, loaded.model, "fast", horizon=10)
    run = closed_loop(system, ctrl, np.array([1.5, 0.0]), 40, goal=entry.make_goal({"position": 0.0}))
    assert run.landing is None and abs(run.xs[-1, 0]) < 0.05, run.xs[-5:]
