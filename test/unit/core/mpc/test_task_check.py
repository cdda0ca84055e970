"""The guard's task check (core.mpc.task_check, wired in core.mpc.guard), ROS-free: a model whose plans break a task
constraint that f_hat's own plan keeps has those steps flown with f_hat's plan and is rolled back after
``strikes`` of them; a model that does not make the task worse is never struck; a violation no control avoids is
no strike."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from helpers.models import QUAD, TASK, quad_model

from saml_ros.core.model.network import DynamicsModel
from saml_ros.core.mpc import closed_loop, make_controller
from saml_ros.core.mpc.config import MPCConfig
from saml_ros.core.mpc.guard import GuardConfig, make_guarded_controller
from saml_ros.core.mpc.task_check import TaskCheck, TaskCheckConfig
from saml_ros.demo.landing import episode_metrics, plant, standard_starts


def spin_model() -> DynamicsModel:
    """A residual model that predicts a yaw-rate residual of 20 rad/s everywhere: its plans end the horizon yawed
    far off level, breaking the terminal attitude bound f_hat's plans keep (the failure traced in the wind world,
    where a learned plan yawed the vehicle a full turn)."""
    model = quad_model(0)
    with torch.no_grad():
        j = QUAD.target.index("wz")
        model.net.biases[-1][0, 0, j] = 20.0 / float(model.out_std[0, 0, j])
    return model


def observer(ctrl: Any) -> Any:
    def on_step(s: Any) -> None:
        ctrl.observe(s.x, s.result.u, s.x_next)

    return on_step


def test_the_window_counts_strikes_and_says_roll_back_at_the_threshold() -> None:
    check = TaskCheck(TaskCheckConfig(enabled=True, window=4, strikes=2))
    assert not check.add(True) and check.strikes == 1
    assert not any(check.add(False) for _ in range(3)) and check.strikes == 1 and check.steps == 4
    assert not check.add(False) and check.strikes == 0 and check.steps == 4  # the first strike left the window
    assert not check.add(True) and check.add(True) and check.verdict == (2, 4)
    assert "2 of the last 4 steps" in check.describe_verdict()
    check.reset()
    assert check.steps == 0 and check.verdict == (2, 4)
    never = TaskCheck(TaskCheckConfig(enabled=True, window=3, strikes=0))
    assert not any(never.add(True) for _ in range(5))  # 0 = strikes only swap the step's plan
    for bad in ({"window": 0}, {"strikes": -1}, {"window": 3, "strikes": 4}):
        with pytest.raises(ValueError):
            TaskCheckConfig(enabled=True, **bad)


def test_a_model_that_breaks_a_constraint_f_hat_keeps_is_struck_and_rolled_back() -> None:
    """The spin model's plans break the terminal attitude bound (avoidably); f_hat planning on its own from the same
    state keeps it. Without the check the episode is flown on failing plans; with it each such step flies f_hat's
    plan, the third strike rolls the model back (never used again), and f_hat flies on. (The check alone, no
    live monitor: this model's one-step errors are large too; the recorded test below has a model the monitor
    passes.)"""
    f = plant(QUAD, TASK.landing_height)
    x0 = QUAD.hover_state((1.0, -1.0, 2.0))
    steps = 15
    base = closed_loop(QUAD, make_controller(QUAD, None, "fast", **TASK.mpc_options()), x0, steps, goal=TASK.goal,
                       true_step=f)
    runs, ctrls = {}, {}
    for name, task in (("off", TaskCheckConfig()), ("on", TaskCheckConfig(enabled=True, window=10, strikes=3)),
                       ("swap only", TaskCheckConfig(enabled=True, window=10, strikes=0))):
        ctrl = make_guarded_controller(QUAD, "fast", GuardConfig(task=task), **TASK.mpc_options())
        ctrl.set_model(spin_model(), 7, {})
        runs[name] = closed_loop(QUAD, ctrl, x0, steps, goal=TASK.goal, true_step=f, on_step=observer(ctrl))
        ctrls[name] = ctrl
    off, on, swap = runs["off"], runs["on"], runs["swap only"]
    assert not off.success[:3].any() and not off.unavoidable[:3].any()  # its plans break the bound, avoidably
    assert ctrls["off"].tag == 7
    c = ctrls["on"].counters
    assert c["task_fallbacks"] == 3 and c["task_rollbacks"] == 1 and c["rollbacks"] == 1
    assert ctrls["on"].tag == 0 and 7 in ctrls["on"].banned
    assert on.success.all()
    # from the roll back on f_hat flies: the vehicle ends as near the pad as f_hat's own flight (not spinning)
    dist = {k: float(np.linalg.norm(r.xs[-1, :3] - TASK.goal)) for k, r in (("on", on), ("base", base))}
    assert abs(dist["on"] - dist["base"]) < 0.1 and abs(on.xs[-1, 12]) < 1.0, dist
    assert ctrls["swap only"].tag == 7 and ctrls["swap only"].counters["task_fallbacks"] == steps
    assert swap.success.all()
    assert "3 of the last 3 steps" in ctrls["on"].task_check.describe_verdict()


def test_a_model_that_does_not_make_the_task_worse_is_never_struck() -> None:
    """A model near f_hat (and one with a small vertical bias, so its plans differ) flown from the demo's standard
    starts under the demo's guard (the infeasible-plan fallback on) with the check on: no strike, no roll back, the
    same landings as without the check."""
    f = plant(QUAD, TASK.landing_height)
    starts = standard_starts(QUAD, 2, 4242)
    for model in (quad_model(1), quad_model(2, bias={"vz": 0.01})):
        ends = {}
        for on in (False, True):
            guard = GuardConfig(rollback=True, infeasible=True, task=TaskCheckConfig(enabled=on))
            ctrl = make_guarded_controller(QUAD, "fast", guard, **TASK.mpc_options())
            errors = []
            for x0 in starts:
                ctrl.reset_models()
                ctrl.set_model(model, 3, {})
                run = closed_loop(QUAD, ctrl, x0, TASK.steps, goal=TASK.goal, true_step=f, on_step=observer(ctrl))
                errors.append(episode_metrics(run.xs, run.success | run.unavoidable, run.solve_times,
                                              TASK)["landing_error"])
            assert ctrl.counters["task_fallbacks"] == 0 and ctrl.counters["task_rollbacks"] == 0
            assert ctrl.tag == 3
            ends[on] = errors
        np.testing.assert_allclose(ends[True], ends[False], atol=1e-9)


def test_a_violation_no_control_avoids_is_no_strike() -> None:
    """Below the height bound and sinking, the next height is fixed by the state: the plan fails whatever the model,
    so f_hat is not asked and nothing is counted."""
    ctrl = make_guarded_controller(QUAD, "fast", GuardConfig(task=TaskCheckConfig(enabled=True, strikes=1)),
                                   **TASK.mpc_options())
    ctrl.set_model(quad_model(3), 2, {})
    low = QUAD.hover_state((0.0, 0.0, 0.21))
    low[5] = -1.0  # pz_1 = 0.11 whatever the command
    res = ctrl.solve(low, TASK.goal)
    assert not res.success and res.unavoidable
    assert ctrl.counters["task_checks"] == 0 and ctrl.tag == 2 and ctrl.task_check.steps == 1


def test_mpc_config_reads_the_task_check_parameters() -> None:
    cfg = MPCConfig.from_params({"system": "quadrotor", "guard.task_check": True, "guard.task_window": 8,
                                 "guard.task_strikes": 2})
    assert cfg.guard.task == TaskCheckConfig(enabled=True, window=8, strikes=2) and cfg.guard.needs_shooting
    assert MPCConfig.from_params({"system": "quadrotor"}).guard.task.enabled is False
    with pytest.raises(ValueError, match="task check"):
        MPCConfig.from_params({"system": "quadrotor", "guard.task_check": True, "guard.task_window": 2,
                               "guard.task_strikes": 3})
    with pytest.raises(ValueError, match="guard"):  # the one-shot paddle MPC has no plans to compare
        MPCConfig.from_params({"system": "paddle_ball", "guard.task_check": True})


#: the SA checkpoint (v9, a 5-member 16-8 ensemble) of a wind-world demo run (``./dev demo --world wind --seed 2``)
RECORDED = Path(__file__).resolve().parents[3] / "helpers" / "recorded" / "wind_demo_seed2_sa_v9.saml"


def test_the_recorded_wind_world_failure_is_caught_and_the_checkpoint_still_lands_its_standard_starts() -> None:
    """A recorded failure: the demo's SA checkpoint of a wind-world run, flown under the demo's guard from the
    aggressive start that made the demo's worst-case check fail (x, y = -1.1, 3.3 m, 0.72 m up, falling at 2.4 m/s).
    Its first plan yaws the vehicle a full turn; the f_hat fallback, warm-started from that plan, keeps the turn;
    every plan of the episode breaks the terminal attitude bound and it ends far from the pad, while the one-step
    monitor stays silent (the model predicts the flown transitions better than f_hat). With the task check, f_hat's
    own plan flies that first step and the model lands. The same checkpoint from standard starts is not rolled back."""
    from saml_ros.core.model.io import load_model
    from saml_ros.demo.cli import demo_config
    from saml_ros.demo.evaluation import evaluation_starts, run_task_and_guard

    task, guard = run_task_and_guard(demo_config(2, 180.0, "wind"))
    system = task.system()
    loaded = load_model(str(RECORDED), expect=system)
    f = plant(system, task.landing_height)
    starts = evaluation_starts(system, 2, 10, 2)
    end, counters = {}, {}
    for on in (False, True):
        g = replace(guard, task=TaskCheckConfig(enabled=on))
        ctrl = make_guarded_controller(system, "fast", g, **task.mpc_options())
        ctrl.set_model(loaded.model, loaded.version, loaded.meta)
        run = closed_loop(system, ctrl, starts["aggressive"][4], task.steps, goal=task.goal, true_step=f,
                          on_step=observer(ctrl))
        end[on] = (float(np.linalg.norm(run.xs[-1, :3] - task.reachable)), float(np.mean(~run.success)))
        counters[on] = dict(ctrl.counters)
    assert end[False][0] > 0.2 and end[False][1] > 0.8, end  # every plan failed; far from the pad
    assert counters[False].get("rollbacks", 0) == 0, counters  # the one-step monitor saw nothing wrong
    assert end[True][0] < 0.05 and counters[True]["task_fallbacks"] >= 1, (end, counters)
    ctrl = make_guarded_controller(system, "fast", replace(guard, task=TaskCheckConfig(enabled=True)),
                                   **task.mpc_options())
    for x0 in starts["standard"]:
        ctrl.reset_models()
        ctrl.set_model(loaded.model, loaded.version, loaded.meta)
        run = closed_loop(system, ctrl, x0, task.steps, goal=task.goal, true_step=f, on_step=observer(ctrl))
        assert np.linalg.norm(run.xs[-1, :3] - task.reachable) < 0.01
    assert ctrl.counters["task_rollbacks"] == 0 and ctrl.counters["rollbacks"] == 0
