"""Closed-loop evaluation of an MPC on the TRUE system, recording a check of every returned plan.

The experiments do not use :func:`saml_ros.core.mpc.closed_loop` because they also check each
:class:`~saml_ros.core.mpc.contract.MPCResult` (control bounds on the whole planned sequence, the quadrotor's
height bound on the predicted states) and count unsuccessful solves.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from saml_ros.core.models import DynamicsModel
from saml_ros.core.mpc.contract import Controller, MPCResult
from saml_ros.core.systems.base import System

#: tolerance on control bounds of returned plans (solvers clip, so anything above rounding is a bug)
BOUND_TOL = 1e-9


def make_mpc(system: System, model: DynamicsModel | None, solver: str, **options: Any) -> Controller:
    """``saml_ros.core.mpc.make_controller(system, model, solver, **options)``."""
    from saml_ros.core.mpc import make_controller

    return make_controller(system, model, solver=solver, **options)


def bound_violation(plan_u: np.ndarray, low: np.ndarray, high: np.ndarray) -> float:
    """Largest amount by which any planned control leaves ``[low, high]`` (0 when inside); ``(T, m)``."""
    pu = np.asarray(plan_u, dtype=float)
    if not np.all(np.isfinite(pu)):
        return float("inf")
    return float(max(0.0, np.max(pu - high), np.max(low - pu)))


@dataclass
class PlanChecks:
    """Per-solve checks of returned plans, accumulated over a closed loop."""

    solves: int = 0
    unsuccessful: int = 0
    #: largest control-bound violation over every plan_u returned (must stay 0)
    max_u_violation: float = 0.0
    #: largest violation of the problem's state constraints among plans reported successful (must stay <= tol)
    max_state_violation_success: float = 0.0
    #: largest violation among all plans with finite predictions (unsuccessful ones included)
    max_state_violation_any: float = 0.0
    messages: dict[str, int] = field(default_factory=dict)

    def add(self, res: MPCResult, low: np.ndarray, high: np.ndarray, state_violation: float) -> None:
        self.solves += 1
        self.unsuccessful += int(not res.success)
        self.max_u_violation = max(self.max_u_violation, bound_violation(res.plan_u, low, high),
                                   bound_violation(res.u[None], low, high))
        if np.isfinite(state_violation):
            self.max_state_violation_any = max(self.max_state_violation_any, state_violation)
            if res.success:
                self.max_state_violation_success = max(self.max_state_violation_success, state_violation)
        if not res.success:
            key = re.sub(r"\d+(\.\d+)?(e[+-]?\d+)?", "#", res.message)[:80]
            self.messages[key] = self.messages.get(key, 0) + 1

    def merge(self, other: PlanChecks) -> None:
        self.solves += other.solves
        self.unsuccessful += other.unsuccessful
        self.max_u_violation = max(self.max_u_violation, other.max_u_violation)
        self.max_state_violation_success = max(self.max_state_violation_success, other.max_state_violation_success)
        self.max_state_violation_any = max(self.max_state_violation_any, other.max_state_violation_any)
        for k, v in other.messages.items():
            self.messages[k] = self.messages.get(k, 0) + v

    def to_dict(self) -> dict[str, Any]:
        return dict(self.__dict__)


@dataclass
class Rollout:
    """A closed loop on the true system: ``xs (steps + 1, n)`` (``xs[0]`` = start), ``us (steps, m)``,
    ``solve_times (steps,)`` seconds, ``plans`` the checks of every returned plan."""

    xs: np.ndarray
    us: np.ndarray
    solve_times: np.ndarray
    plans: PlanChecks


def closed_loop(
    controller: Controller,
    x0: np.ndarray,
    steps: int,
    true_step: Callable[[np.ndarray, np.ndarray], np.ndarray],
    goal: Any | None = None,
    state_violation: Callable[[MPCResult], float] | None = None,
) -> Rollout:
    """Run ``steps`` MPC steps from ``x0``: solve, apply ``res.u`` to ``true_step(x, u) -> x_next`` (the
    simulated plant, ``(n,), (m,) -> (n,)``), repeat. The controller's warm start is reset first.

    ``state_violation(res)`` returns the largest violation of the problem's state constraints on the plan
    (0 when feasible; NaN when the plan has no finite prediction).
    """
    system = controller.system
    low, high = system.control_low, system.control_high
    controller.reset()
    x = np.asarray(x0, dtype=np.float64).copy()
    xs = np.empty((steps + 1, x.size))
    us = np.empty((steps, low.size))
    times = np.empty(steps)
    checks = PlanChecks()
    xs[0] = x
    for k in range(steps):
        res = controller.solve(x, goal)
        viol = state_violation(res) if state_violation is not None else 0.0
        checks.add(res, low, high, viol)
        us[k] = res.u
        times[k] = res.solve_time
        x = np.asarray(true_step(x, res.u), dtype=np.float64)
        xs[k + 1] = x
    return Rollout(xs, us, times, checks)
