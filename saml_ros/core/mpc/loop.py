"""The closed-loop runner: a controller against the TRUE system, with a per-step hook (the MPC tools' and the
experiment runners' inner loop)."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from saml_ros.core.dynamics.system import System
from saml_ros.core.mpc.contract import Controller, MPCResult
from saml_ros.core.systems.registry import find_entry


@dataclass(frozen=True)
class LoopStep:
    """What one closed-loop step did; handed to the ``on_step`` hook of :func:`closed_loop`."""

    index: int  #: step number, 0-based
    x: np.ndarray  #: (n,) true state the controller solved from
    result: MPCResult  #: the controller's answer (``result.u`` was applied)
    x_next: np.ndarray  #: (n,) true state after the step (paddle ball: the next pre-impact state)
    cpu_time: float  #: CPU seconds of the solve (``time.process_time``)


#: called after each step of :func:`closed_loop` (e.g. to check the returned plan or record the warm start)
StepHook = Callable[[LoopStep], None]


@dataclass
class ClosedLoopRun:
    """The record of one :func:`closed_loop` run of ``k <= steps`` steps (numpy arrays)."""

    xs: np.ndarray  #: (k + 1, n) true states, ``xs[0] = x0``
    us: np.ndarray  #: (k, m) applied controls
    costs: np.ndarray  #: (k,) the MPC objective of each solve (``MPCResult.cost``, predicted with the model)
    solve_times: np.ndarray  #: (k,) s, wall clock (``MPCResult.solve_time``)
    cpu_times: np.ndarray  #: (k,) s, CPU time of each solve
    iterations: np.ndarray  #: (k,) solver iterations
    success: np.ndarray  #: (k,) bool, ``MPCResult.success``
    unavoidable: np.ndarray  #: (k,) bool, ``MPCResult.unavoidable`` (a failure no control could have avoided)
    #: (k,) the task's stage cost at the true next state: ``|p - p_goal|`` (friction), ``||p - p_goal||_2``
    #: (quadrotor), ``||landing_xy - target_xy||_2`` (paddle ball, true landing point)
    stage_costs: np.ndarray
    landing: np.ndarray | None = None  #: paddle ball only: (k, 2) true landing points (m)
    dropped: bool = False  #: paddle ball only: the loop stopped because the ball did not leave the paddle upwards


def closed_loop(
    system: System,
    controller: Controller,
    x0: np.ndarray,
    steps: int,
    goal: Any | None = None,
    true_step: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None,
    on_step: StepHook | None = None,
) -> ClosedLoopRun:
    """Run ``steps`` MPC steps from ``x0``: solve, apply ``u`` to the true system, call ``on_step``, repeat.

    ``true_step(x (n,), u (m,)) -> next`` defaults to ``system.true_step_np``. The controller's warm start
    is reset first. For time-stepped systems ``next`` is the next state. For the paddle ball one step is one
    bounce: ``true_step`` gives the post-impact velocity and the ball flies ballistically back to its impact
    height, so the next pre-impact state is ``[landing_xy, pz, vx, vy, -vz]``; the loop stops early
    (``dropped`` True) when the ball does not leave the paddle upwards.
    """
    step = true_step if true_step is not None else system.true_step_np
    controller.reset()
    x = np.asarray(x0, dtype=np.float64).copy()
    entry = find_entry(system.name)
    event = entry.loop_event if entry is not None else None  # the paddle ball's bounce
    xs, results, cpus, stage, landing = [x.copy()], [], [], [], []
    dropped = False
    for k in range(steps):
        t0 = time.process_time()
        res = controller.solve(x, goal)
        cpus.append(time.process_time() - t0)
        results.append(res)
        u = np.asarray(res.u, dtype=np.float64)
        y = np.asarray(step(x, u), dtype=np.float64)
        if event is not None:
            land, x_next, cost, dropped = event(system, x, y, goal)
            landing.append(land)
            stage.append(cost)
        else:
            x_next = y
            stage.append(_stage_cost(controller, x_next, goal))
        xs.append(x_next.copy())
        if on_step is not None:
            on_step(LoopStep(k, x, res, x_next, cpus[-1]))
        x = x_next
        if dropped:
            break
    m = system.control.size
    return ClosedLoopRun(
        xs=np.array(xs), us=np.array([np.asarray(r.u, dtype=np.float64) for r in results]).reshape(len(results), m),
        costs=np.array([r.cost for r in results]), solve_times=np.array([r.solve_time for r in results]),
        cpu_times=np.array(cpus), iterations=np.array([r.iterations for r in results]),
        success=np.array([r.success for r in results], dtype=bool),
        unavoidable=np.array([r.unavoidable for r in results], dtype=bool), stage_costs=np.array(stage),
        landing=np.array(landing).reshape(len(landing), 2) if event is not None else None, dropped=dropped,
    )  # fmt: skip


def _stage_cost(controller: Controller, x: np.ndarray, goal: Any | None) -> float:
    task = getattr(controller, "task", None)
    if task is None:
        return float("nan")
    if goal is not None:
        task = task.with_target(goal)
    return float(task.stage_costs(x[None])[0])
