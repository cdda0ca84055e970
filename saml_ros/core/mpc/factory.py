"""``make_controller``: the one entry point the MPC node and the experiment runners use."""

from __future__ import annotations

from typing import Any

from saml_ros.core.mpc.contract import Controller
from saml_ros.core.mpc.dynamics_np import PredictionModel
from saml_ros.core.systems.base import System
from saml_ros.core.systems.registry import get_entry

#: the MPC solvers; every system's registry entry has a controller for each
SOLVERS = ("fast", "slsqp")


def make_controller(
    system: System, model: PredictionModel = None, solver: str = "fast", **options: Any
) -> Controller:
    """The paper's MPC for ``system`` planning with ``model``: the controller its registry entry names.

    Args:
        system: the system to control (its ``base_step`` is f_hat; ``true_step`` is never used).
        model: a residual or full :class:`DynamicsModel` for this system (member ``member`` of an ensemble,
            default 0), None for the base model f_hat alone, or ``"oracle"`` for the TRUE dynamics (the registry
            entry's ``true_model_np``: what a perfect model would do in the same MPC). Swap later with
            ``set_model``.
        solver: ``"fast"`` (exact-derivative SQP / Gauss-Newton, warm-started) or ``"slsqp"`` (the paper's
            reference: scipy SLSQP with finite differences).
        options: ``horizon`` (default 10; ignored by a one-shot MPC such as the paddle ball's), ``member``,
            ``feas_tol``; task options (the entry's ``task_params``, e.g. the quadrotor's ``min_height`` (0.2 m)
            and ``qw_tol`` (0.05)); solver options, see :class:`SQPShootingMPC`, :class:`SLSQPShootingMPC`, :class:`GaussNewtonPaddle`,
            :class:`SLSQPPaddle` (e.g. ``max_iter``, ``tol``, ``max_time``).

    Raises:
        ValueError: unknown solver or system, a model for another system; TypeError: unknown option.
    """
    if solver not in SOLVERS:
        raise ValueError(f"unknown MPC solver {solver!r}; valid: {list(SOLVERS)}")
    entry = get_entry(system.name)
    if not entry.mpc_horizon:
        options.pop("horizon", None)  # one-shot: a horizon (e.g. the MPC node's generic parameter) is ignored
    return entry.controllers()[solver](system, model, **options)
