"""The MPC contract: :class:`MPCResult` and the :class:`Controller` protocol every solver implements."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol, runtime_checkable

import numpy as np

from saml_ros.core.dynamics.system import System

if TYPE_CHECKING:
    from saml_ros.core.model.network import DynamicsModel


@dataclass
class MPCResult:
    """One solve.

    ``u`` always lies within the control bounds (it is clipped), even when ``success`` is False.
    ``plan_x``/``cost`` are predicted with the model in use (``f_hat + phi`` or ``f_hat`` alone).
    """

    u: np.ndarray  #: (m,) first control to apply
    plan_u: np.ndarray  #: (T, m) planned controls; (1, m) for the one-shot paddle problem
    plan_x: np.ndarray  #: (T+1, n) predicted states from x0; paddle: (1, n) = ball just after the impact
    cost: float  #: objective of the plan under the model in use (exact, unsmoothed)
    solve_time: float  #: seconds (wall clock)
    iterations: int  #: solver iterations (SQP / Gauss-Newton / SLSQP major iterations)
    success: bool  #: the plan is finite and satisfies every constraint of the problem (within feas_tol)
    message: str  #: what happened, e.g. "converged", "max_iter", "height constraint violated by 0.03 m"
    constraint_violation: float = 0.0  #: largest violation of the non-bound constraints on the plan (>= 0)
    converged: bool = False  #: the solver met its optimality tolerance (not just a feasible plan)
    #: ``success`` is False only through constraint rows the current state fixes, which no control can move
    #: (e.g. the quadrotor's ``pz_1 = pz_0 + dt vz_0`` below the height bound): reported, but no command avoids it
    unavoidable: bool = False


@runtime_checkable
class Controller(Protocol):
    """An MPC that plans with a (hot-swappable) dynamics model."""

    system: System
    horizon: int

    def set_model(self, model: DynamicsModel | None) -> None:
        """Use ``model`` (member 0 of an ensemble) from the next solve on; ``None`` = base model f_hat only.

        The weights are copied at this call: call it again after training the model further. The warm
        start is kept.
        """

    def solve(self, x0: np.ndarray, goal: Any | None = None) -> MPCResult:
        """Plan from state ``x0`` (n,). Never raises on a numerical failure (returns ``success=False``)."""

    def reset(self) -> None:
        """Drop the warm start (previous plan)."""
