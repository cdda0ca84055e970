"""``make_controller``: the one entry point the MPC node and the experiment runners use.

This is the MPC's only module that looks a system up in the registry: it resolves the system's MPC problem
(:func:`make_task`) and the numpy twins of its base model (:func:`base_model_np`) and of its true dynamics (the
oracle, :func:`true_model_np`) and hands them to the controller, so the solvers, tasks and dynamics below it never
dispatch on the system.
"""

from __future__ import annotations

import inspect
from typing import Any

from saml_ros.core.dynamics.system import System
from saml_ros.core.mpc.contract import Controller
from saml_ros.core.mpc.dynamics_np import BaseModelNP, PredictionModel, TorchBaseNP, TorchTrueNP
from saml_ros.core.mpc.shooting.tasks import ShootingTask
from saml_ros.core.systems.registry import find_entry, get_entry

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
    ctor = entry.controllers()[solver]
    parts: dict[str, Any] = {"base": base_model_np(system), "true": true_model_np(system)}
    if entry.mpc_task is not None:
        names = {p.name for p in entry.task_params}
        task_options = {k: options.pop(k) for k in list(options) if k in names}
        parts["task"] = make_task(system, int(options.get("horizon", 10)), **task_options)
    unknown = sorted(set(options) - _accepted(ctor))
    if unknown:
        valid = sorted((_accepted(ctor) | {p.name for p in entry.task_params}) - {"system", "model", *parts})
        raise TypeError(f"{system.name} MPC ({solver}) has no option(s) {unknown}; valid: {', '.join(valid)}")
    return ctor(system, model, **parts, **options)


def make_task(system: System, horizon: int = 10, **options: Any) -> ShootingTask:
    """The paper's MPC problem for a time-stepped ``system``: its registry entry's ``mpc_task`` with the task
    ``options`` (the entry's ``task_params``, e.g. the quadrotor's ``min_height`` and ``qw_tol``).

    Raises:
        ValueError: ``horizon < 1``, or the system has no shooting task; TypeError: an unknown option.
    """
    if horizon < 1:
        raise ValueError(f"horizon must be >= 1, got {horizon}")
    entry = get_entry(system.name)
    if entry.mpc_task is None:
        raise ValueError(f"no shooting MPC task for system {system.name!r}")
    valid = [p.name for p in entry.task_params]
    unknown = sorted(set(options) - set(valid))
    if unknown:
        raise TypeError(f"{system.name} MPC has no option(s) {unknown}; valid: {', '.join(valid) or 'none'}")
    return entry.mpc_task(system, horizon, **options)


def base_model_np(system: System) -> BaseModelNP:
    """The numpy twin of ``system.base_step`` its registry entry names (autograd fallback for systems without
    one, or not registered)."""
    entry = find_entry(system.name)
    if entry is None or entry.base_model_np is None or not isinstance(system, entry.system_class()):
        return TorchBaseNP(system)
    return entry.base_model_np(system)


def true_model_np(system: System) -> BaseModelNP:
    """The numpy twin of ``system.true_step`` (the oracle) its registry entry names (autograd fallback for
    systems without one, or not registered)."""
    entry = find_entry(system.name)
    if entry is None or entry.true_model_np is None or not isinstance(system, entry.system_class()):
        return TorchTrueNP(system)
    return entry.true_model_np(system)


def _accepted(ctor: Any) -> set[str]:
    """Keyword names the controller class ``ctor`` (or a base class it forwards ``**kwargs`` to) accepts."""
    names: set[str] = set()
    for cls in getattr(ctor, "__mro__", (ctor,)):
        init = cls.__dict__.get("__init__") if isinstance(cls, type) else cls
        if init is None or init is object.__init__:
            continue
        for p in list(inspect.signature(init).parameters.values())[1:]:
            if p.kind not in (p.VAR_KEYWORD, p.VAR_POSITIONAL):
                names.add(p.name)
    return names
