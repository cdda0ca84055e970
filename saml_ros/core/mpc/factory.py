"""``make_controller``: the one entry point the MPC node and the experiment runners use."""

from __future__ import annotations

from typing import Any

from saml_ros.core.models import DynamicsModel
from saml_ros.core.mpc.contract import Controller
from saml_ros.core.mpc.paddle import GaussNewtonPaddle, SLSQPPaddle
from saml_ros.core.mpc.shooting import SLSQPShootingMPC, SQPShootingMPC
from saml_ros.core.systems.base import System
from saml_ros.core.systems.friction import FrictionDoubleIntegrator
from saml_ros.core.systems.paddle_ball import PaddleBall
from saml_ros.core.systems.quadrotor import Quadrotor

SOLVERS = ("fast", "slsqp")


def make_controller(
    system: System, model: DynamicsModel | None = None, solver: str = "fast", **options: Any
) -> Controller:
    """The paper's MPC for ``system`` (friction, quadrotor or paddle_ball) planning with ``model``.

    Args:
        system: the system to control (its ``base_step`` is f_hat; ``true_step`` is never used).
        model: a residual or full :class:`DynamicsModel` for this system (member ``member`` of an ensemble,
            default 0), or None for the base model f_hat alone. Swap later with ``set_model``.
        solver: ``"fast"`` (exact-derivative SQP / Gauss-Newton, warm-started) or ``"slsqp"`` (the paper's
            reference: scipy SLSQP with finite differences).
        options: ``horizon`` (time-stepped systems, default 10; ignored by the one-shot paddle ball),
            ``member``, ``feas_tol``; quadrotor task options ``min_height`` (0.2 m), ``qw_tol`` (0.05); solver
            options, see :class:`SQPShootingMPC`, :class:`SLSQPShootingMPC`, :class:`GaussNewtonPaddle`,
            :class:`SLSQPPaddle` (e.g. ``max_iter``, ``tol``, ``max_time``).

    Raises:
        ValueError: unknown solver or system, a model for another system; TypeError: unknown option.
    """
    if solver not in SOLVERS:
        raise ValueError(f"unknown MPC solver {solver!r}; valid: {list(SOLVERS)}")
    if isinstance(system, PaddleBall):
        options.pop("horizon", None)  # one-shot: a horizon (e.g. the MPC node's generic parameter) is ignored
        return (GaussNewtonPaddle if solver == "fast" else SLSQPPaddle)(system, model, **options)
    if isinstance(system, (FrictionDoubleIntegrator, Quadrotor)):
        return (SQPShootingMPC if solver == "fast" else SLSQPShootingMPC)(system, model, **options)
    raise ValueError(f"no MPC for system {system.name!r}")
