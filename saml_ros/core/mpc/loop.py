"""Closed-loop simulation of a controller against the TRUE system (the experiment runners' inner loop)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from saml_ros.core.mpc.contract import Controller
from saml_ros.core.systems.base import System
from saml_ros.core.systems.paddle_ball import PaddleBall


def closed_loop(
    system: System,
    controller: Controller,
    x0: np.ndarray,
    steps: int,
    goal: Any | None = None,
    true_step: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None,
) -> dict[str, Any]:
    """Run ``steps`` MPC steps from ``x0``: solve, apply ``u`` to the true system, repeat.

    ``true_step(x (n,), u (m,)) -> next`` defaults to ``system.true_step_np``. The controller's warm start
    is reset first. For time-stepped systems ``next`` is the next state. For the paddle ball one step is one
    bounce: ``true_step`` gives the post-impact velocity and the ball flies ballistically back to its impact
    height, so the next pre-impact state is ``[landing_xy, pz, vx, vy, -vz]``; the loop stops early (key
    ``dropped`` True) when the ball does not leave the paddle upwards.

    Returns a dict of numpy arrays:

    * ``xs`` ``(k + 1, n)`` true states (``xs[0] = x0``), ``us`` ``(k, m)`` applied controls (k <= steps);
    * ``costs`` ``(k,)`` the MPC objective of each solve (``MPCResult.cost``, predicted with the model);
    * ``solve_times`` ``(k,)`` s, ``iterations`` ``(k,)``, ``success`` ``(k,)`` bool;
    * ``stage_costs`` ``(k,)`` the task's stage cost at the true next state: ``|p - p_goal|`` (friction),
      ``||p - p_goal||_2`` (quadrotor), ``||landing_xy - target_xy||_2`` (paddle ball, true landing point);
    * paddle ball only: ``landing`` ``(k, 2)`` true landing points and ``dropped`` (bool).
    """
    step = true_step if true_step is not None else system.true_step_np
    controller.reset()
    x = np.asarray(x0, dtype=np.float64).copy()
    paddle = isinstance(system, PaddleBall)
    xs, us, costs, times, iters, ok, stage, landing = [x.copy()], [], [], [], [], [], [], []
    dropped = False
    for _ in range(steps):
        res = controller.solve(x, goal)
        u = np.asarray(res.u, dtype=np.float64)
        us.append(u)
        costs.append(res.cost)
        times.append(res.solve_time)
        iters.append(res.iterations)
        ok.append(res.success)
        y = np.asarray(step(x, u), dtype=np.float64)
        if paddle:
            assert isinstance(system, PaddleBall)
            target = _paddle_target(controller, goal)
            vz = float(y[2])
            flight = 2.0 * max(vz, 0.0) / system.g
            land = x[0:2] + y[0:2] * flight
            landing.append(land)
            stage.append(float(np.linalg.norm(land - target)))
            x = np.array([land[0], land[1], x[2], y[0], y[1], -max(vz, 0.0)])
            xs.append(x.copy())
            if vz <= 0.0:
                dropped = True
                break
        else:
            x = y
            xs.append(x.copy())
            stage.append(_stage_cost(controller, x, goal))
    out: dict[str, Any] = {
        "xs": np.array(xs),
        "us": np.array(us).reshape(len(us), system.control.size),
        "costs": np.array(costs),
        "solve_times": np.array(times),
        "iterations": np.array(iters),
        "success": np.array(ok, dtype=bool),
        "stage_costs": np.array(stage),
    }
    if paddle:
        out["landing"] = np.array(landing).reshape(len(landing), 2)
        out["dropped"] = dropped
    return out


def _stage_cost(controller: Controller, x: np.ndarray, goal: Any | None) -> float:
    task = getattr(controller, "task", None)
    if task is None:
        return float("nan")
    if goal is not None:
        task = task.with_target(goal)
    return float(task.stage_costs(x[None])[0])


def _paddle_target(controller: Controller, goal: Any | None) -> np.ndarray:
    from saml_ros.core.mpc.paddle import paddle_goal

    return paddle_goal(goal).target_xy
