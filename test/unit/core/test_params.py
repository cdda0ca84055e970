"""The parameter checks without ROS (saml_ros.core.params and the nodes' configuration classes): every bad parameter
reported at once, sizes bounded by memory, unknown names and exclusive pairs, and the review of a change on a
running node (which value, when it applies). The same functions run inside the nodes: test_param_changes.py."""

from __future__ import annotations

import importlib
import math
from typing import Any

import pytest

from saml_ros.core.mpc.config import MPCConfig
from saml_ros.core.online.config import LearnerConfig, learner_params
from saml_ros.core.params import (
    CONFIGURE,
    LIVE,
    START,
    Param,
    ParamErrors,
    Problems,
    change_note,
    exclusive_problems,
    format_bytes,
    memory_problems,
    read_params,
    review_change,
    unknown_problems,
)
from saml_ros.core.runtime.lifecycle import AUTOSTART, MANAGER_PARAMS, check_manager_params
from saml_ros.viewers.foxglove_server import PARAMS as FOXGLOVE_PARAMS
from saml_ros.viewers.foxglove_server import check_params as check_foxglove
from sim_nodes.binding import read_sim_params

TABLE = (
    Param("rate", 1.0, "a live rate (Hz)", when=LIVE),
    Param("size", 10, "read at configure"),
    Param("mode", "a", "a choice"),
    Param("items", [1.0], "a list"),
    Param("name", "x", "read at start-up", when=START),
)


def validate(values: dict[str, Any]) -> None:
    problems = Problems()
    p = read_params(TABLE, values, problems)
    problems.check(p["rate"] > 0, "rate", "> 0", p["rate"])
    problems.check(p["size"] >= 1, "size", ">= 1", p["size"])
    problems.check(p["mode"] in ("a", "b"), "mode", "one of ('a', 'b')", p["mode"])
    problems.check(len(p["items"]) == 1, "items", "one number", p["items"])
    problems.raise_if_any()


CURRENT = {p.name: p.default for p in TABLE}


def review(changes: dict[str, Any], configured: bool = True, managed: bool = True, **kw: Any) -> Any:
    return review_change(TABLE, CURRENT, changes, validate, configured=configured, managed=managed, node="/n",
                         **kw)


# ---------------------------------------------------------------------------------------------- collecting
def test_read_params_reports_every_wrong_type_and_problems_collect_without_repeats() -> None:
    with pytest.raises(ParamErrors) as err:
        read_params(TABLE, {"rate": "fast", "size": 2.5, "mode": 3, "items": ["a"], "name": "ok"})
    assert err.value.problems == [
        "parameter 'rate': expected float, got 'fast'", "parameter 'size': expected int, got 2.5",
        "parameter 'mode': expected str, got 3", "parameter 'items': expected a list of float, got ['a']"]
    problems = Problems()
    got = read_params(TABLE, {"rate": math.nan, "size": 3}, problems)
    assert got["rate"] == 1.0 and got["size"] == 3 and problems.has("rate") and not problems.has("size")
    problems.add(problems.messages[0], "rate")
    with problems.capture("x", prefix="p: "):
        raise ParamErrors(["a", "b"])
    assert problems.messages == ["parameter 'rate': expected float, got nan", "p: a", "p: b"]
    assert isinstance(ParamErrors(["a"]), ValueError) and str(ParamErrors(["a", "b"])) == "a; b"


def test_learner_configuration_reports_every_bad_parameter_at_once() -> None:
    with pytest.raises(ParamErrors) as err:
        LearnerConfig.validated({"checkpoint_period": -5.0, "buffer.policy": "lifo", "train.primal_lr": "fast",
                                 "system": "bogus", "train.dual_method": "lagrange", "model.kind": "deep",
                                 "health.max_weight": 0.0, "health.error_after": 0, "spec_file": "/nonexistent.yaml"})
    text = str(err.value)
    for expected in ("parameter 'checkpoint_period' must be > 0, got -5.0",
                     "parameter 'buffer.policy' must be one of ['fifo', 'reservoir'], got 'lifo'",
                     "parameter 'train.primal_lr': expected float, got 'fast'",
                     "parameter 'system': unknown system 'bogus'",
                     "parameter 'train.dual_method': dual_method must be one of",
                     "parameter 'model.kind' must be one of ['residual', 'full'], got 'deep'",
                     "parameter 'health.max_weight' must be > 0", "parameter 'health.error_after' must be >= 1"):
        assert expected in text, (expected, text)
    assert len(err.value.problems) == 8  # no system: spec_file cannot be read against one
    with pytest.raises(ParamErrors) as err:
        LearnerConfig.validated({"spec_file": "/nonexistent.yaml", "buffer.capacity": 10, "min_transitions": 1,
                                 "telemetry_window": 0})
    assert err.value.problems == [
        "parameter 'min_transitions' must be >= 2 (the normalisation needs a spread), got 1",
        "parameter 'telemetry_window' must be >= 1, got 0",
        "parameter 'spec_file': no such file '/nonexistent.yaml'"]
    with pytest.raises(ParamErrors, match=r"parameter 'buffer.capacity' must be >= min_transitions \(1000\), got 10"):
        LearnerConfig.from_params({"buffer.capacity": 10})
    config, system, spec = LearnerConfig.validated({"system": "quadrotor", "checkpoint_period": 2})
    assert config.checkpoint.period == 2.0 and system.name == "quadrotor" and spec.n_constraints >= 1
    assert config.loop_config().checkpoint_period == 2.0


def test_mpc_configuration_reports_every_bad_parameter_at_once() -> None:
    with pytest.raises(ParamErrors) as err:
        MPCConfig.from_params({"system": "quadrotor", "mode": "fast", "rate_hz": "abc", "horizon": 0,
                               "solver": "ipopt", "goal.position": [1.0], "plausible_bounds": "[1]",
                               "diagnostics_rate": 0.0, "goal.target_xy": [0.0, 0.0]})
    assert len(err.value.problems) == 8, err.value.problems
    assert err.value.problems[0] == "unknown MPC parameter(s) ['goal.target_xy'] for system 'quadrotor'"
    assert "parameter 'diagnostics_rate' must be > 0, got 0.0" in err.value.problems


def test_simulator_foxglove_and_lifecycle_manager_parameters_report_every_bad_one() -> None:
    binding = importlib.import_module("sim_nodes.friction_sim").BINDING
    with pytest.raises(ParamErrors) as err:
        read_sim_params(binding, {"mode": "x", "rate_hz": "abc", "seed": 1.5, "max_speed": -1.0, "executor": "multi",
                                  "episode_steps": -2, "plausible_bounds": "[1]"})
    assert len(err.value.problems) == 7, err.value.problems
    assert read_sim_params(binding, {"rate_hz": 20})["rate_hz"] == 20.0
    with pytest.raises(ParamErrors) as err:
        check_foxglove({"system": "nosuch", "port": 70000})
    assert err.value.problems[1] == "parameter 'port' must be in 0..65535, got 70000"
    assert check_foxglove({"port": 0})["system"] == "friction" and all(p.when == CONFIGURE for p in FOXGLOVE_PARAMS)
    with pytest.raises(ParamErrors) as err:
        check_manager_params({"transitions": ["configure", "fly"], "timeout": -1.0})
    assert len(err.value.problems) == 2 and "unknown transition 'fly'" in err.value.problems[0]
    assert check_manager_params({}) == ["configure", "activate"] and len(MANAGER_PARAMS) == 3


# ---------------------------------------------------------------------------------------------- sizes
def test_sizes_the_machine_cannot_hold_are_refused_with_their_size() -> None:
    assert format_bytes(8 * 10**12) == "7.28 TiB" and format_bytes(512) == "512 B"
    needs = [("buffer.capacity", "a buffer", 6 * 2**30), ("train.batch_size", "minibatches", 1 * 2**30)]
    assert memory_problems(needs, available=8 * 2**30) == []
    assert memory_problems(needs, available=4 * 2**30) == [
        "parameter 'buffer.capacity': a buffer would take 6.00 GiB, more than the 4.00 GiB of memory available"]
    assert memory_problems(needs, available=int(6.5 * 2**30)) == [
        "parameters 'buffer.capacity', 'train.batch_size': together they would take 7.00 GiB, more than the 6.50 GiB "
        "of memory available"]
    with pytest.raises(ParamErrors, match=r"parameter 'train.batch_size': minibatches of 1000000000000 transitions x 1 "
                                          r"ensemble member\(s\) would take 1\d\d\.\d\d TiB, more than the"):
        LearnerConfig.validated({"train.batch_size": 10**12})
    with pytest.raises(ParamErrors, match=r"parameter 'buffer.capacity': a replay buffer of 1000000000000 transitions"):
        LearnerConfig.validated({"buffer.capacity": 10**12})
    with pytest.raises(ParamErrors, match=r"parameter 'horizon': the plan's dense matrices for a horizon of 1000000"):
        MPCConfig.from_params({"system": "friction", "horizon": 10**6})
    config, system, _ = LearnerConfig.validated({"model.ensemble": 5, "train.batch_size": 256})
    (_, _, buffer), (_, _, batch), *_ = config.memory_needs(system)
    assert buffer == 100_000 * (2 + 1 + 2 + 3) * 8 and 0 < batch < 2**20  # the defaults: small


# ---------------------------------------------------------------------------------------------- names
def test_unknown_names_with_suggestions_and_exclusive_pairs() -> None:
    declared = [p.name for p in learner_params()]
    assert unknown_problems(["checkpont_period", "bogus", "system"], declared, "/friction/learner") == [
        "parameter 'bogus' is not a parameter of /friction/learner",
        "parameter 'checkpont_period' is not a parameter of /friction/learner (did you mean 'checkpoint_period' or "
        "'checkpoint_keep'?)"]
    pair = [("system", "system_file")]
    assert exclusive_problems({"system": "friction", "system_file": "r.yaml"}, {"system", "system_file"}, pair) == [
        "parameters 'system' and 'system_file' were both given (system='friction', system_file='r.yaml'): give one "
        "of them"]
    assert exclusive_problems({"system": "friction", "system_file": "r.yaml"}, {"system_file"}, pair) == []
    assert exclusive_problems({"system": "friction", "system_file": ""}, {"system", "system_file"}, pair) == []


# ---------------------------------------------------------------------------------------------- changes
def test_a_change_is_refused_for_its_type_its_value_or_when_it_applies() -> None:
    assert review({"rate": "fast"}).reason == "parameter 'rate': expected float, got 'fast'"
    assert review({"rate": -1}).reason == "parameter 'rate' must be > 0, got -1.0"
    assert review({"rate": -1, "mode": "c"}).reason == (
        "parameter 'rate' must be > 0, got -1.0; parameter 'mode' must be one of ('a', 'b'), got 'c'; parameter "
        "'mode' is read at configure and /n is configured: deactivate it and clean it up (lifecycle transitions "
        "deactivate, cleanup), set 'mode', then configure (and activate) again")
    assert review({"name": "y"}).reason == "parameter 'name' is read only at start-up: restart /n to change it"
    assert review({"name": "y"}, configured=False).reason.startswith("parameter 'name' is read only at start-up")
    assert review({"size": 5}, managed=False).reason == ("parameter 'size' is read only at start-up: restart /n to "
                                                         "change it")
    assert not review({"items": [1.0, 2.0]}, configured=False).accepted


def test_a_good_change_applies_live_or_at_the_next_configure() -> None:
    r = review({"rate": 2})
    assert r.accepted and r.live == {"rate": 2.0} and r.stored == {}
    r = review({"size": 5, "mode": "b"}, configured=False)
    assert r.accepted and r.live == {} and r.stored == {"size": 5, "mode": "b"}
    r = review({"size": 10, "name": "x", "items": [1]})  # the current values: nothing changes, nothing refused
    assert r.accepted and r.live == {} and r.stored == {}


def test_a_problem_already_in_the_current_values_does_not_block_fixing_another() -> None:
    current = dict(CURRENT, rate=-1.0, size=0)  # an unconfigured node started with two bad values
    r = review_change(TABLE, current, {"size": 3}, validate, configured=False, managed=True)
    assert r.accepted and r.stored == {"size": 3}
    r = review_change(TABLE, current, {"mode": "z"}, validate, configured=False, managed=True)
    assert r.reason == "parameter 'mode' must be one of ('a', 'b'), got 'z'"


def test_exclusive_parameters_given_in_a_change() -> None:
    table = (Param("system", "friction", "s"), Param("system_file", "", "f"))
    current = {"system": "friction", "system_file": "robot.yaml"}
    r = review_change(table, current, {"system": "quadrotor"}, configured=False, managed=True,
                      given={"system_file"}, exclusive=[("system", "system_file")])
    assert r.reason.startswith("parameters 'system' and 'system_file' were both given")
    r = review_change(table, current, {"system_file": ""}, configured=False, managed=True,
                      given={"system_file", "system"}, exclusive=[("system", "system_file")])
    assert r.accepted


def test_every_node_table_says_when_a_change_applies() -> None:
    assert change_note(Param("a", 1.0, "", when=LIVE), managed=True) == "Changes apply at once."
    assert change_note(Param("a", 1.0, ""), managed=True) == ("Read at configure: change it while the node is "
                                                              "unconfigured.")
    assert change_note(Param("a", 1.0, ""), managed=False) == "Read at start-up: restart the node to change it."
    assert AUTOSTART.when == START
    live = {p.name for p in learner_params() if p.when == LIVE}
    assert live == {"updates_per_second", "checkpoint_period", "telemetry_rate", "diagnostics_rate"}
    mpc = {p.name: p.when for p in MPCConfig.params("quadrotor")}
    assert {n for n, w in mpc.items() if w == LIVE} == {"deadline_ms", "poll_period", "diagnostics_rate",
                                                          "safe_on_infeasible", "goal.position"}
    assert mpc["system"] == mpc["executor"] == START
    binding = importlib.import_module("sim_nodes.paddle_ball_sim").BINDING
    assert {p.name for p in binding.param_table() if p.when == LIVE} == {"episode_steps", "max_speed",
                                                                        "diagnostics_period"}
