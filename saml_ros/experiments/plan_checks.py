"""Checks of every plan an MPC returns in the experiments: control bounds on the whole planned sequence, the
problem's state constraints on the predicted states (e.g. the quadrotor's height bound), unsuccessful solves.

:meth:`PlanChecks.hook` is an ``on_step`` hook of the closed-loop runner :func:`saml_ros.core.mpc.closed_loop`.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from saml_ros.core.dynamics.system import System
from saml_ros.core.mpc.contract import MPCResult
from saml_ros.core.mpc.loop import LoopStep, StepHook


def bound_violation(plan_u: np.ndarray, low: np.ndarray, high: np.ndarray) -> float:
    """Largest amount by which any planned control leaves ``[low, high]`` (0 when inside); ``(T, m)``."""
    pu = np.asarray(plan_u, dtype=float)
    if not np.all(np.isfinite(pu)):
        return float("inf")
    return float(max(0.0, np.max(pu - high), np.max(low - pu)))


@dataclass
class PlanChecks:
    """Per-solve checks of returned plans, accumulated over closed loops."""

    solves: int = 0
    unsuccessful: int = 0
    #: unsuccessful solves whose violation no control could avoid (fixed by the current state, e.g. a quadrotor
    #: already below the height bound): the state's fault, not the plan's
    unavoidable: int = 0
    #: largest control-bound violation over every plan_u returned (must stay 0)
    max_u_violation: float = 0.0
    #: largest violation of the problem's state constraints among plans reported successful (must stay <= tol)
    max_state_violation_success: float = 0.0
    #: largest violation among all plans with finite predictions (unsuccessful ones included)
    max_state_violation_any: float = 0.0
    messages: dict[str, int] = field(default_factory=dict)

    def add(self, res: MPCResult, low: np.ndarray, high: np.ndarray, state_violation: float) -> None:
        """Check one result against the control bounds ``[low, high]`` (m,); ``state_violation``: the largest
        violation of the problem's state constraints on its plan (NaN when the plan has no finite prediction)."""
        self.solves += 1
        self.unsuccessful += int(not res.success)
        self.unavoidable += int(not res.success and bool(getattr(res, "unavoidable", False)))
        self.max_u_violation = max(self.max_u_violation, bound_violation(res.plan_u, low, high),
                                   bound_violation(res.u[None], low, high))
        if np.isfinite(state_violation):
            self.max_state_violation_any = max(self.max_state_violation_any, state_violation)
            if res.success:
                self.max_state_violation_success = max(self.max_state_violation_success, state_violation)
        if not res.success:
            key = re.sub(r"\d+(\.\d+)?(e[+-]?\d+)?", "#", res.message)[:80]
            self.messages[key] = self.messages.get(key, 0) + 1

    def hook(self, system: System, state_violation: Callable[[MPCResult], float] | None = None) -> StepHook:
        """A :func:`~saml_ros.core.mpc.closed_loop` ``on_step`` hook adding every returned plan to these checks
        (against ``system``'s control bounds; ``state_violation(res)``: see :meth:`add`, default 0)."""
        low, high = system.control_low, system.control_high

        def check(step: LoopStep) -> None:
            res = step.result
            self.add(res, low, high, state_violation(res) if state_violation is not None else 0.0)

        return check

    def merge(self, other: PlanChecks) -> None:
        self.solves += other.solves
        self.unsuccessful += other.unsuccessful
        self.unavoidable += other.unavoidable
        self.max_u_violation = max(self.max_u_violation, other.max_u_violation)
        self.max_state_violation_success = max(self.max_state_violation_success, other.max_state_violation_success)
        self.max_state_violation_any = max(self.max_state_violation_any, other.max_state_violation_any)
        for k, v in other.messages.items():
            self.messages[k] = self.messages.get(k, 0) + v

    def to_dict(self) -> dict[str, Any]:
        return dict(self.__dict__)
