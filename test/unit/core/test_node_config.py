"""The nodes' ROS-free configuration (MPCConfig, LearnerConfig) and the MPC node's work (MPCService), without rclpy."""

from __future__ import annotations

import importlib
import logging
import math
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from saml_ros.core.mpc.config import PARAMS, MPCConfig
from saml_ros.core.mpc.service import MPCService
from saml_ros.core.online.config import LearnerConfig, learner_params, param_fields
from saml_ros.core.params import Param
from saml_ros.core.systems import SYSTEM_NAMES, get_entry
from saml_ros.core.training import TrainConfig

LOG = logging.getLogger("test_node_config")


def names(params: list[Param]) -> list[str]:
    return [p.name for p in params]


# ---------------------------------------------------------------------------------------------- MPCConfig
def test_mpc_parameter_table_has_goal_and_task_parameters_from_the_registry() -> None:
    table = MPCConfig.params("quadrotor")
    assert names(table)[: len(PARAMS)] == names(list(PARAMS))
    assert names(table)[len(PARAMS):] == ["goal.position", "task.min_height", "task.qw_tol", "task.tilt_max"]
    assert table[0].default == "quadrotor" and all(p.description for p in table)
    assert names(MPCConfig.params("paddle_ball"))[len(PARAMS):] == [
        "goal.target_xy", "goal.roll_min", "goal.roll_max", "goal.pitch_min", "goal.pitch_max", "goal.v_rel_min",
        "goal.v_rel_max"]


def test_mpc_config_defaults_and_controller_options() -> None:
    c = MPCConfig.from_params({"system": "quadrotor", "goal.position": [1.0, 2.0, 0.5], "rate_hz": 20})
    assert c.solver == "fast" and c.horizon == 10 and c.mode == "lockstep" and c.rate_hz == 20.0
    assert math.isinf(c.gate.max_constraint) and c.gate.min_updates == 0
    np.testing.assert_array_equal(c.goal, [1.0, 2.0, 0.5])
    assert c.controller_options() == {"min_height": 0.2, "qw_tol": 0.05, "tilt_max": math.inf, "horizon": 10}
    assert c.deadline_s(0.1) == 0.1
    assert MPCConfig.from_params({"system": "quadrotor", "mode": "realtime", "rate_hz": 50.0}).deadline_s(0.1) == 0.02
    assert MPCConfig.from_params({"system": "friction", "deadline_ms": 5.0}).deadline_s(0.1) == 0.005
    paddle = MPCConfig.from_params({"system": "paddle_ball", "horizon": 0, "solver_options": "{max_iter: 20}"})
    assert paddle.controller_options() == {"max_iter": 20}  # one-shot: no horizon
    assert paddle.deadline_s(0.0) == 0.1
    assert MPCConfig.from_params({"system": "friction", "gate.max_constraint": 0.002}).gate.max_constraint == 0.002
    # executor auto: EventsExecutor in lockstep (simulation), SingleThreadedExecutor in realtime (beside a robot)
    assert MPCConfig.from_params({"system": "friction"}).executor == "events"
    assert MPCConfig.from_params({"system": "friction", "mode": "realtime"}).executor == "single"
    assert MPCConfig.from_params({"system": "friction", "executor": "single"}).executor == "single"
    assert MPCConfig.from_params({"system": "friction", "mode": "realtime", "executor": "events"}).executor == "events"


@pytest.mark.parametrize(("values", "message"), [
    ({"mode": "fast"}, r"parameter 'mode' must be one of \('lockstep', 'realtime'\), got 'fast'"),
    ({"executor": "multi"}, r"parameter 'executor' must be auto or one of \('events', 'single'\), got 'multi'"),
    ({"solver": "ipopt"}, r"parameter 'solver' must be one of \('fast', 'slsqp'\)"),
    ({"rate_hz": 0.0}, "parameter 'rate_hz' must be > 0, got 0.0"),
    ({"rate_hz": "fast"}, "parameter 'rate_hz': expected float, got 'fast'"),
    ({"poll_period": -1.0}, "parameter 'poll_period' must be > 0"),
    ({"deadline_ms": -1.0}, "parameter 'deadline_ms' must be >= 0"),
    ({"member": -1}, "parameter 'member' must be >= 0"),
    ({"horizon": 0}, "parameter 'horizon' must be >= 1"),
    ({"horizon": 2.5}, "parameter 'horizon': expected int"),
    ({"gate.max_constraint": math.nan}, "parameter 'gate.max_constraint': expected float"),
    ({"goal.position": [1.0, 2.0]}, "goal.position must be 3 finite"),
    ({"task.qw_tol": True}, "parameter 'task.qw_tol': expected float"),
    ({"solver_options": "[1, 2]"}, "solver_options must be a mapping"),
    ({"goal.target_xy": [0.0, 0.0]}, r"unknown MPC parameter\(s\) \['goal.target_xy'\] for system 'quadrotor'"),
    ({"system": "pendulum"}, "parameter 'system': unknown system 'pendulum'; valid names are"),
])
def test_mpc_config_names_the_bad_parameter(values: dict, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        MPCConfig.from_params({"system": "quadrotor", **values})


# ---------------------------------------------------------------------------------------------- MPCService
def test_mpc_service_answers_states_rejects_duplicates_and_falls_back_to_the_safe_command() -> None:
    sent: list[tuple[np.ndarray, int]] = []
    service = MPCService(MPCConfig.from_params({"system": "quadrotor"}), lambda u, s: sent.append((u, s)), LOG)
    service.start()
    try:
        quad: Any = service.system
        answer = service.receive(quad.hover_state((0.5, 0.0, 1.0)), 1_000_000_000, time.perf_counter())
        assert answer is not None and answer[0] == 1_000_000_000 and answer[1]["success"] == 1.0
        u, stamp = sent[-1]
        assert stamp == 1_000_000_000 and np.all(u >= quad.control_low) and np.all(u <= quad.control_high)
        assert service.receive(quad.hover_state(), 1_000_000_000, time.perf_counter()) is None  # duplicate stamp
        assert service.counters["rejected/duplicate"] == 1 and len(sent) == 1
        # a state the solver cannot take: the safe command (hover thrust) goes out, counted
        answer = service.control_step(np.zeros(5), 1_100_000_000, time.perf_counter())
        np.testing.assert_array_equal(sent[-1][0], quad.safe_control())
        assert service.counters["solver_errors"] == 1 and answer[1]["success"] == 0.0
        # a stamp jump back (a reset) restarts the warm start
        service.receive(quad.hover_state((0.0, 0.5, 2.0)), 500_000_000, time.perf_counter())
        assert service.counters["warm_start_resets"] == 1 and service.counters["solves"] == 3
        values = service.diagnostic_values()
        assert values["model_version"] == 0 and values["solves"] == 3 and values["checkpoints_refused"] == 0
    finally:
        service.stop()


def test_mpc_service_realtime_answers_only_the_newest_state_per_tick() -> None:
    sent: list[tuple[np.ndarray, int]] = []
    config = MPCConfig.from_params({"system": "friction", "mode": "realtime", "rate_hz": 10.0})
    service = MPCService(config, lambda u, s: sent.append((u, s)), LOG)
    assert service.tick() is None
    for k in range(3):
        assert service.receive(np.array([1.0 - 0.1 * k, 0.0]), 100_000_000 * (k + 1), time.perf_counter()) is None
    answer = service.tick()
    assert answer is not None and answer[0] == 300_000_000 and [s for _, s in sent] == [300_000_000]
    assert service.counters["skipped_states"] == 2 and service.tick() is None


# ---------------------------------------------------------------------------------------------- LearnerConfig
def test_learner_parameter_table() -> None:
    table = learner_params()
    train = [n for n in names(table) if n.startswith("train.")]
    assert train == [f"train.{f}" for f in ("batch_size", "primal_lr", "dual_lr", "primal_optimizer",
                                            "dual_optimizer", "log_every", "seed", "dtype", "engine",
                                            "dual_method", "nupi_kp", "nupi_ema", "penalty", "relax_cost",
                                            "primal_schedule", "dual_schedule", "schedule_steps", "lr_gamma",
                                            "lr_drops", "lr_floor", "device")]
    by_name = {p.name: p for p in table}
    assert all(not by_name[n].description.startswith("TrainConfig.") for n in train)  # each has its own text
    assert by_name["train.dual_method"].default == TrainConfig().dual_method == "lagrangian"
    assert by_name["train.primal_lr"].default == TrainConfig().primal_lr
    assert by_name["namespaces"].item_type is str and by_name["model.hidden"].item_type is int
    assert all(p.description for p in table) and len(by_name) == len(table)


def test_learner_config_defaults_namespaces_system_and_spec(tmp_path: Path) -> None:
    c = LearnerConfig.from_params({"system": "quadrotor", "dt": 0.05, "train.batch_size": 64}, "/quadrotor/")
    assert c.namespaces == ["/quadrotor"] and c.min_transitions == 1000 and c.checkpoint.resume is True
    assert c.train_config().batch_size == 64
    system = c.make_system()
    assert system.name == "quadrotor" and system.dt == 0.05
    assert c.load_spec(system).to_dict()["name"] == system.paper_spec()["name"]
    two = LearnerConfig.from_params({"namespaces": ["a", " /b/ "], "model.hidden": [8.0, 4]})
    assert two.namespaces == ["/a", "/b"] and two.model.hidden == [8, 4]
    with pytest.raises(ValueError, match="parameter 'spec_file': no such file"):
        LearnerConfig.from_params({"spec_file": str(tmp_path / "none.yaml")}).load_spec(system)


def test_learner_config_parts_hold_every_parameter_once_under_its_own_name() -> None:
    """LearnerConfig is built from parts (model, buffer, pairing, checkpoint, telemetry, health, heldout, process);
    every parameter but train.* lives in exactly one field, read from the parameter of the same name, and a
    running node's change reaches that field (with_params)."""
    declared = [p.name for p in learner_params() if not p.name.startswith("train.")]
    where = param_fields()
    assert sorted(where) == sorted(declared) and len(set(where.values())) == len(where)
    assert where["checkpoint_period"] == ("checkpoint", "period") and where["health.max_weight"] == ("health",
                                                                                                   "max_weight")
    values = {"health.max_weight": 7.0, "pairing.window": 33, "telemetry_rate": 4.0, "train_threads": 3,
              "checkpoint_keep": 2, "heldout.fraction": 0.3, "model.ensemble": 2, "buffer.policy": "reservoir",
              "diagnostics_rate": 2.5, "train.batch_size": 32}
    c = LearnerConfig.from_params(values)
    for name, value in values.items():
        if name.startswith("train."):
            assert c.train[name[len("train."):]] == value
            continue
        part, field = where[name]
        assert getattr(c if part is None else getattr(c, part), field) == value, name
    assert c.health_config().max_weight == 7.0 and c.loop_config().telemetry_rate == 4.0
    live = c.with_params({"checkpoint_period": 3.0, "telemetry_rate": 9.0, "updates_per_second": 50.0,
                          "train.seed": 4})
    assert (live.checkpoint.period, live.telemetry.rate, live.updates_per_second) == (3.0, 9.0, 50.0)
    assert live.train["seed"] == 4 and live.train["batch_size"] == 32
    assert live.checkpoint.keep == 2 and live.telemetry.diagnostics_rate == 2.5 and c.checkpoint.period == 10.0


@pytest.mark.parametrize(("values", "message"), [
    ({"system": "nosuch"}, "parameter 'system': unknown system 'nosuch'; valid names are"),
    ({"namespaces": ["/a", "a/"]}, "parameter 'namespaces' must be a list without repetitions"),
    ({"namespaces": ["/a", 3]}, "parameter 'namespaces': expected a list of str"),
    ({"model.hidden": [4, 2.5]}, "parameter 'model.hidden': expected a list of int"),
    ({"telemetry_rate": 0.0}, "parameter 'telemetry_rate' must be > 0"),
    ({"checkpoint_period": -1.0}, "parameter 'checkpoint_period' must be > 0"),
    ({"updates_per_second": -1.0}, "parameter 'updates_per_second' must be >= 0"),
    ({"checkpoint_keep": 0}, "parameter 'checkpoint_keep' must be >= 1"),
    ({"pairing.window": 1}, "parameter 'pairing.window' must be >= 2"),
    ({"training_niceness": 20}, "parameter 'training_niceness' must be in 0..19"),
    ({"train_threads": -1}, "parameter 'train_threads' must be >= 0"),
    ({"dt": math.inf}, "parameter 'dt': expected float"),
    ({"resume": 1}, "parameter 'resume': expected bool"),
    ({"train.batch_size": 0}, r"parameter 'train\.batch_size': batch_size must be >= 1"),
    ({"train.epochs": 3}, r"unknown learner parameter\(s\) \['train.epochs'\]"),
    ({"train.dual_method": "lagrange"}, r"parameter 'train\.dual_method': dual_method must be one of"),
    ({"train.primal_schedule": "cosine"}, r"parameters 'train\.\*': primal_schedule 'cosine' needs schedule_steps"),
])
def test_learner_config_names_the_bad_parameter(values: dict, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        LearnerConfig.from_params(values)


def test_learner_config_refuses_a_dt_the_system_refuses() -> None:
    with pytest.raises(ValueError, match="parameter 'system' / 'dt'"):
        LearnerConfig.from_params({"system": "paddle_ball", "dt": 0.1}).make_system()


# ---------------------------------------------------------------------------------------------- bringup defaults
@pytest.mark.parametrize("name", SYSTEM_NAMES)
def test_bringup_defaults_only_set_parameters_the_nodes_declare(name: str) -> None:
    entry = get_entry(name)
    mpc = {"system": name, **entry.bringup["mpc"]}
    MPCConfig.from_params(mpc)  # every key is an MPC parameter with a valid value
    learner = {"system": name, **entry.bringup["learner"]}
    LearnerConfig.from_params(learner)
    binding = importlib.import_module(f"sim_nodes.{entry.sim_node}").BINDING
    assert set(entry.bringup["sim"]) <= {p.name for p in binding.param_table()}
