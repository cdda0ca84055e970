"""Plausibility bounds (saml_ros.core.data.plausibility) and every receiver that checks them, without ROS: the learner's
pairing and paired batches, bag extraction, the MPC service's failure path, the time-stepped simulator.

The node-level checks (the learner counting ``rejected/bounds`` on /diagnostics, the MPC answering an implausible
state with the safe command) are in test_learner_node.py and test_mpc_node.py.
"""

from __future__ import annotations

import logging
import math
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from helpers.bag_publisher import rollout
from helpers.bag_test_helpers import T0, write_rollout
from helpers.models import trap_model

from saml_ros.bags.transitions import extract_transitions
from saml_ros.core.data.buffer import ReplayBuffer
from saml_ros.core.data.pairing import PairingConfig, StampPairer
from saml_ros.core.data.plausibility import Plausibility, parse_overrides
from saml_ros.core.mpc.config import MPCConfig
from saml_ros.core.mpc.service import MPCService
from saml_ros.core.online.ingest import Ingest, RecentWindow
from saml_ros.core.systems import SYSTEM_NAMES, get_system
from saml_ros.core.worlds.sim_core import APPLIED, STATE, SimConfig, build_stepped_sim

LOG = logging.getLogger("test_plausibility")
DT = 100_000_000


@pytest.mark.parametrize("name", SYSTEM_NAMES)
def test_every_system_has_physical_ranges_that_hold_its_data_and_refuse_absurd_values(name: str) -> None:
    system = get_system(name)
    bounds = Plausibility.for_system(system)
    x, u, y = system.make_dataset(5000, np.random.default_rng(0))
    assert bounds.state.inside(x).all() and bounds.control.inside(u).all() and bounds.target.inside(y).all()
    # the control box and the simulators' clip margin are inside; every field has a finite range
    assert np.all(np.array(bounds.control.low) < system.control_low)
    assert np.all(np.array(bounds.control.high) > system.control_high)
    for kind in ("state", "control", "target"):
        r = bounds.range(kind)
        assert all(math.isfinite(v) for v in (*r.low, *r.high)), (kind, r)
        for i, field in enumerate(r.names):  # one absurd value in one field is enough
            v = np.asarray(x[0] if kind == "state" else u[0] if kind == "control" else y[0]).copy()
            v[i] = 1e6
            why = bounds.outside(kind, v)
            assert why is not None and field in why
    assert bounds.outside("applied_cmd", u[0]) is None  # pairing kinds map onto the vector kinds


def test_overrides_name_fields_like_a_spec_and_are_validated() -> None:
    quad = get_system("quadrotor")
    b = Plausibility.for_system(quad, "{x.pz: [-1.0, 20000.0], u.f1: [null, .inf]}")
    i = quad.state.index("pz")
    assert b.state.high[i] == 20000.0 and b.target.high[i] == 20000.0  # the target is the next state
    assert b.control.low[0] == -math.inf and b.control.high[0] == math.inf
    paddle = get_system("paddle_ball")
    b = Plausibility.for_system(paddle, {"next.vz": [-1.0, 1.0]})
    assert b.target.high[2] == 1.0 and b.state.high[paddle.state.index("vz")] == 30.0  # separate layouts
    with pytest.raises(ValueError, match="unknown field 'x.q'.*x.p"):
        Plausibility.for_system(get_system("friction"), "{x.q: [0, 1]}")
    for bad in ("{x.p: [2, 1]}", "{x.p: 3}", "[1, 2]", "{x.p: [0, .nan]}", "{x.p: [0"):
        with pytest.raises(ValueError, match="plausible_bounds"):
            parse_overrides(bad)
    assert parse_overrides("") == {} and parse_overrides(None) == {}


def test_pairing_rejects_implausible_states_and_commands_and_loses_no_good_transition() -> None:
    system = get_system("friction")
    pairer = StampPairer(PairingConfig.for_system(system, "next"))
    rng = np.random.default_rng(1)
    x = np.array([0.3, -0.2])
    good = 0
    for k in range(40):
        t = 10**9 + k * DT
        if k == 20:  # absurd messages with the stamps of the good ones, sent first: rejected, nothing else lost
            assert pairer.add("state", t, np.array([3e6, 0.0])).rejected == "bounds"
            res = pairer.add("applied_cmd", t, np.array([-1e9]))
            assert res.rejected == "bounds" and "u = -1e+09 not in [-20, 20]" in res.detail
        u = rng.uniform(-10, 10, 1)
        good += len(pairer.add("state", t, x).transitions)
        good += len(pairer.add("applied_cmd", t, u).transitions)
        x = system.true_step_np(x, u)
    good += len(pairer.add("state", 10**9 + 40 * DT, x).transitions)
    assert good == 40 and pairer.counts["paired"] == 40
    assert pairer.counts["bounds"] == 2 and pairer.counts["duplicate"] == 0 and pairer.counts["nan"] == 0


def test_paired_batches_drop_non_finite_and_implausible_rows() -> None:
    system = get_system("quadrotor")
    x, u, y = system.make_dataset(10, np.random.default_rng(2))
    x[3, 2] = 5e4  # 50 km up
    u[5, 0] = -1e3
    y[7, 0] = np.nan
    ingest = Ingest(ReplayBuffer(100, 13, 4, 13), RecentWindow(100, 13, 4, 13), Plausibility.for_system(system))
    ingest.add_batch(x, u, y, stamp=np.arange(10) * 0.1, source=np.zeros(10, dtype=np.int64))
    rows = ingest.buffer.arrays()
    assert len(rows.x) == 7 and ingest.counts()["bounds"] == 2 and ingest.counts()["nan"] == 1
    np.testing.assert_array_equal(rows.stamp, (np.arange(10) * 0.1)[[0, 1, 2, 4, 6, 8, 9]])


def test_bag_extraction_counts_implausible_messages_like_the_learner(tmp_path: Path) -> None:
    events = rollout("friction", 40, 0, seed=3, t0_ns=T0)
    bad = [{"stamp": events[10]["stamp"], "x": np.array([0.0, 7e5])},  # before the good state of that stamp
           {"stamp": events[20]["stamp"], "x": np.array([-2e6, 0.0]), "u": np.array([1e8])}]
    write_rollout(tmp_path / "b", "friction", events[:10] + bad[:1] + events[10:20] + bad[1:] + events[20:])
    out = extract_transitions([tmp_path / "b"], "friction")
    assert len(out) == 39 and out.counts["bounds"] == 3 and out.counts["duplicate"] == 0


# ------------------------------------------------------------------------------------------ the MPC's failure path
def _service(system: str, **params: object) -> tuple[MPCService, list[tuple[np.ndarray, int]]]:
    sent: list[tuple[np.ndarray, int]] = []
    service = MPCService(MPCConfig.from_params({"system": system, **params}), lambda u, s: sent.append((u, s)), LOG)
    return service, sent


def test_mpc_answers_an_implausible_state_with_the_safe_command_and_never_plans_from_it() -> None:
    service, sent = _service("quadrotor")
    quad: Any = service.system
    stamp, values = service.control_step(quad.hover_state((0.0, 0.0, 2e4)), 10**9, time.perf_counter())
    np.testing.assert_array_equal(sent[-1][0], quad.safe_control())
    assert sent[-1][1] == stamp == 10**9 and values["safe"] == 1.0 and values["safe_commands"] == 1.0
    assert math.isnan(values["cost"]) and values["success"] == 0.0
    diag = service.diagnostic_values()
    assert diag["rejected/bounds"] == 1 and diag["safe_commands/bounds"] == 1 and diag["safe_commands"] == 1
    assert service.recent_probe() is None  # the acceptance check never probes with it
    _, values = service.control_step(quad.hover_state((0.5, 0.0, 1.0)), 11 * 10**8, time.perf_counter())
    probe = service.recent_probe()
    assert values["safe"] == 0.0 and values["success"] == 1.0 and probe is not None and probe[0].shape == (1, 13)


@pytest.mark.parametrize("system", ["quadrotor", "paddle_ball"])
def test_a_non_finite_or_absurd_solve_is_answered_with_the_safe_command(system: str) -> None:
    """Two models that are f_hat near the origin and broken beyond px = 3 m: one overflows to inf there (float64,
    weight 1e308), one predicts finite nonsense (float32, 3e38: the paddle's solver even calls that plan a
    success). Beyond 3 m the MPC answers with the safe command; near the origin it plans as usual."""
    sys_ = get_system(system)
    far = (sys_.hover_state((5.0, 0.0, 1.5)) if system == "quadrotor"  # type: ignore[attr-defined]
           else np.array([5.0, 0.0, 0.0, 0.0, 0.0, -4.0]))
    near = far.copy()
    near[0] = 0.5
    # finite nonsense: the quadrotor's SQP breaks down on it (non-finite), the paddle's solver reports success
    absurd = {"implausible"} if system == "paddle_ball" else {"non_finite", "implausible"}
    for weight, dtype, reasons in ((1e308, torch.float64, {"non_finite"}), (3e38, torch.float32, absurd)):
        service, sent = _service(system)
        service.controller.set_model(trap_model(system, "px", 3.0, weight, dtype))
        _, values = service.control_step(far, 10**9, time.perf_counter())
        np.testing.assert_array_equal(sent[-1][0], sys_.safe_control())
        counted = {r for r in ("non_finite", "implausible") if service.counters[f"safe_commands/{r}"]}
        assert values["safe"] == 1.0 and len(counted) == 1 and counted <= reasons, service.counters
        _, values = service.control_step(near, 2 * 10**9, time.perf_counter())
        assert values["safe"] == 0.0 and np.all(np.isfinite(sent[-1][0]))
        assert service.diagnostic_values()["safe_commands"] == 1


def test_safe_on_infeasible_also_answers_a_constraint_violating_plan_with_the_safe_command() -> None:
    quad = get_system("quadrotor")
    x = quad.hover_state((0.0, 0.0, 0.6))  # type: ignore[attr-defined]
    x[5] = -4.0  # falling fast: pz_2 breaks min_height even at full thrust (a row the controls move)
    for strict in (False, True):
        service, sent = _service("quadrotor", safe_on_infeasible=strict)
        _, values = service.control_step(x, 10**9, time.perf_counter())
        assert values["success"] == 0.0 and service.counters["solves_failed"] == 1
        assert values["safe"] == float(strict)
        assert np.array_equal(sent[-1][0], quad.safe_control()) == strict


def test_a_violation_no_command_can_avoid_is_sent_not_replaced_by_the_safe_command() -> None:
    """pz_1 below min_height is fixed by the state (the quadrotor resting on a pad that sits on the bound, or
    falling onto it): the safe command cannot avoid it either, and the plan brakes harder than hover thrust."""
    quad = get_system("quadrotor")
    x = quad.hover_state((0.0, 0.0, 0.21))  # type: ignore[attr-defined]
    x[5] = -1.0  # pz_1 = 0.11 whatever the command
    for strict in (False, True):
        service, sent = _service("quadrotor", safe_on_infeasible=strict)
        _, values = service.control_step(x, 10**9, time.perf_counter())
        assert values["success"] == 0.0 and values["safe"] == 0.0
        assert service.counters["solves_unavoidable"] == 1 and service.counters["solves_failed"] == 0
        assert np.all(sent[-1][0] > quad.safe_control())  # braking above hover thrust


# ------------------------------------------------------------------------------------------ the simulator
def test_a_stepped_simulator_never_publishes_an_implausible_state() -> None:
    system = get_system("friction")
    sim: Any = build_stepped_sim(system, SimConfig(mode="lockstep", initial_state=(995.0, 99.0)), publish_clock=False)
    out = sim.begin(0)
    assert out[-1][0] == STATE and out[-1][1][0] == 995.0
    out = sim.on_cmd(np.array([10.0]), sim.awaiting, 1)  # p -> 1004.9 m: beyond the plausible 1000 m
    assert sim.counters["diverged"] == 1 and [k for k, _, _ in out] == [STATE]  # a restart, no applied_cmd
    assert out[-1][1][0] == 995.0 and APPLIED not in [k for k, _, _ in out]
