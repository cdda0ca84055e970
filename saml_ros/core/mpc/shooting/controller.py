"""The shared machinery of the single-shooting MPC for the time-stepped systems (:class:`ShootingMPC`).

Both solvers (:mod:`~saml_ros.core.mpc.shooting.sqp`, the fast one, and :mod:`~saml_ros.core.mpc.shooting.slsqp`,
the reference) optimise the controls ``U (T, m)`` of a :class:`~saml_ros.core.mpc.shooting.tasks.ShootingTask`
through the same numpy prediction model (:class:`~saml_ros.core.mpc.dynamics_np.NumpyDynamics`), warm-start from
the previous plan (or the task's candidate sequences) the same way, and finish identically (clip to the bounds,
roll out, exact cost, constraint check), so their plans and costs are directly comparable.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from saml_ros.core.dynamics.system import System
from saml_ros.core.mpc.contract import MPCResult
from saml_ros.core.mpc.dynamics_np import BaseModelNP, NumpyDynamics, PredictionModel, rollout_steps
from saml_ros.core.mpc.shooting.tasks import ShootingTask

#: the start rules of :class:`ShootingMPC` (option ``start``)
START_MODES = ("robust", "plain")


class ShootingMPC:
    """Shared machinery: model handling, warm start, rollout, result assembly and failure handling.

    Args:
        system: a time-stepped system (friction or quadrotor).
        model: residual/full model (member ``member`` is used) or None for f_hat alone.
        horizon: T, number of controls planned.
        feas_tol: tolerance on the state constraints for ``success`` (state units).
        start: how each solve is started: ``"robust"`` (default: the cheapest of the shifted previous plan and the
            task's candidate sequences, :meth:`_warm_start`) or ``"plain"`` (the paper's: a cold start at the
            task's ``u_default`` (zero for the friction task), then the shifted previous plan, no candidates).
        task: the MPC problem (:func:`saml_ros.core.mpc.factory.make_task` builds the system's own, with its task
            options such as the quadrotor's ``min_height``); its horizon must be ``horizon``.
        base: numpy twin of the base model (see :class:`~saml_ros.core.mpc.dynamics_np.NumpyDynamics`).
        true: numpy twin of the true dynamics, used when the model is ``"oracle"``.
    """

    def __init__(
        self,
        system: System,
        model: PredictionModel = None,
        horizon: int = 10,
        member: int = 0,
        feas_tol: float = 1e-4,
        start: str = "robust",
        *,
        task: ShootingTask,
        base: BaseModelNP | None = None,
        true: BaseModelNP | None = None,
    ) -> None:
        if start not in START_MODES:
            raise ValueError(f"unknown start {start!r}; valid: {list(START_MODES)}")
        self.start = start
        self.system = system
        self.horizon = int(horizon)
        if task.horizon != self.horizon:
            raise ValueError(f"task horizon {task.horizon} != controller horizon {self.horizon}")
        self.member = member
        self.feas_tol = feas_tol
        self.task = task
        self.n, self.m = system.state.size, system.control.size
        self.base_np, self.true_np = base, true
        self.dyn = NumpyDynamics(system, model, member, base, true)
        self._u_lo = np.tile(self.task.u_low, self.horizon)
        self._u_hi = np.tile(self.task.u_high, self.horizon)
        self._plan_u: np.ndarray | None = None
        self._plan_x: np.ndarray | None = None
        #: how the shifted warm start fills its last step: "repeat" the previous last control or "default"
        self.tail = "repeat"
        self._starts_key: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None  # _clipped_starts' cache
        self._starts = np.zeros((0, self.horizon, self.m))
        self._cands: np.ndarray | None = None
        #: where the last start's predicted states came from: (batch size, sequence, ``dyn.fused_calls`` after it)
        #: of the batched rollout that scored the candidates (the fast solver reads that sequence's Jacobians from
        #: it, :meth:`NumpyDynamics.fused_jacobians`), or None
        self._start_src: tuple[int, int, int] | None = None

    # ------------------------------------------------------------------------------ Controller API
    def set_model(self, model: PredictionModel) -> None:
        self.dyn = NumpyDynamics(self.system, model, self.member, self.base_np, self.true_np)

    def reset(self) -> None:
        self._plan_u = None
        self._plan_x = None

    def warm_start_plan(self) -> tuple[np.ndarray, np.ndarray] | None:
        """Copies of the previous plan ``(plan_u, plan_x)`` the next solve warm-starts from, or None."""
        if self._plan_u is None or self._plan_x is None:
            return None
        return self._plan_u.copy(), self._plan_x.copy()

    def set_warm_start(self, plan_u: np.ndarray, plan_x: np.ndarray) -> None:
        """Use ``plan_u`` ``(T, m)`` / ``plan_x`` ``(T+1, n)`` as the previous plan (e.g. another solver's)."""
        self._plan_u = np.array(plan_u, dtype=np.float64).reshape(self.horizon, self.m)
        self._plan_x = np.array(plan_x, dtype=np.float64).reshape(self.horizon + 1, self.n)

    def solve(self, x0: np.ndarray, goal: Any | None = None) -> MPCResult:
        start = time.perf_counter()
        x0 = np.asarray(x0, dtype=np.float64)
        if x0.shape != (self.n,):
            raise ValueError(f"{self.system.name} MPC: x0 must have shape ({self.n},), got {x0.shape}")
        task = self.task if goal is None else self.task.with_target(goal)
        if not np.isfinite(x0).all():
            return self._fallback(start, "non-finite state")
        u0, xs0 = self._warm_start(x0, task)
        try:
            plan_u, iters, converged, msg, xs = self._optimize(x0, u0, task, xs0)
            clipped = np.minimum(np.maximum(plan_u, task.u_low), task.u_high)
            # the optimiser's own prediction is the plan's unless clipping moved a control
            plan_x = xs if xs is not None and np.array_equal(clipped, plan_u) else self.rollout(x0, clipped)
            plan_u = clipped
            if not (np.isfinite(plan_x).all() and np.isfinite(plan_u).all()):
                return self._fallback(start, f"non-finite plan ({msg})", iters)
        except Exception as exc:  # any numerical breakdown: keep flying on the last good plan
            return self._fallback(start, f"solver failure: {type(exc).__name__}: {exc}")
        viol = task.violations(plan_x)
        worst = float(max(0.0, viol.max())) if viol.size else 0.0
        ok = worst <= self.feas_tol
        unavoidable = False
        if not ok:
            i = int(np.argmax(viol))
            msg = f"{msg}; {task.names[i]} violated by {worst:.3g}"
            fixed = self._fixed_rows(x0, plan_u, task)
            if fixed[i]:
                msg += " (unavoidable: fixed by the current state)"
            movable = viol[~fixed]
            unavoidable = not (movable.size and float(movable.max()) > self.feas_tol)
        self._plan_u, self._plan_x = plan_u, plan_x
        return MPCResult(
            u=plan_u[0].copy(),
            plan_u=plan_u,
            plan_x=plan_x,
            cost=task.cost(plan_x),
            solve_time=time.perf_counter() - start,
            iterations=iters,
            success=ok,
            message=msg,
            constraint_violation=worst,
            converged=converged,
            unavoidable=unavoidable,
        )

    # ------------------------------------------------------------------------------ helpers
    def rollout(self, x0: np.ndarray, plan_u: np.ndarray) -> np.ndarray:
        """Predicted states ``(T+1, n)`` from ``x0`` under ``plan_u`` ``(T, m)`` with the model in use."""
        roll = getattr(self.dyn, "rollout", None)
        if roll is not None:
            return np.asarray(roll(x0, plan_u))
        return rollout_steps(self.dyn.step1, x0, plan_u)

    def _warm_start(self, x0: np.ndarray, task: ShootingTask) -> tuple[np.ndarray, np.ndarray | None]:
        """The initial guess ``(T, m)`` and, when candidates were scored, its predicted states ``(T+1, n)``
        (else None): the cheapest by :meth:`ShootingTask.start_scores` (cost + 100 x
        violation) of the previous plan and the task's candidate sequences ``task.u_starts``.

        The previous plan is shifted by one step when x0 is nearer its x_1 than its x_0 (closed loop), kept
        unshifted when x0 is nearer x_0 (a re-solve from the same state); its last step is filled per
        ``self.tail``. It competes with the candidates only if ``task.starts_every_solve`` (otherwise it is
        used as is); ties go to the previous plan, then to the earlier candidate."""
        self._start_src = None
        starts = self._clipped_starts(task)
        if self.start == "plain":
            starts = starts[:0]
        if self._plan_u is None or self._plan_x is None:
            if starts.shape[0] == 0:
                return np.tile(task.u_default, (self.horizon, 1)), None
            if starts.shape[0] == 1:
                return starts[0].copy(), None
            return self._cheapest(x0, starts, task)
        prev_u, prev_x = self._plan_u, self._plan_x
        d1, d0 = x0 - prev_x[1], x0 - prev_x[0]
        shift = 1 if d1 @ d1 < d0 @ d0 else 0
        compete = task.starts_every_solve and starts.shape[0] > 0
        # with candidates: the shifted plan is written into row 0 of a buffer whose other rows hold the starts
        cands = self._cands if compete else None
        u = cands[0] if cands is not None else np.empty((self.horizon, self.m))
        keep = min(self.horizon, prev_u.shape[0] - shift)
        u[:keep] = prev_u[shift : shift + keep]
        u[keep:] = prev_u[-1] if self.tail == "repeat" else task.u_default
        np.minimum(np.maximum(u, task.u_low, out=u), task.u_high, out=u)  # np.clip, without its overhead
        if cands is None:
            return u, None
        return self._cheapest(x0, cands, task)

    def _clipped_starts(self, task: ShootingTask) -> np.ndarray:
        """``task.u_starts`` clipped to the control bounds, computed once per task (``with_target`` keeps the
        starts and bounds); also keeps ``self._cands`` ``(1 + G, T, m)``: row 0 for the shifted plan, then the
        clipped starts."""
        key = (task.u_starts, task.u_low, task.u_high)  # held, so no new array can reuse their ids
        if self._starts_key is None or any(a is not b for a, b in zip(key, self._starts_key)):
            starts = np.clip(task.u_starts, task.u_low, task.u_high) if task.u_starts.size else task.u_starts
            self._starts = starts
            self._cands = np.concatenate((np.zeros((1, self.horizon, self.m)), starts)) if starts.size else None
            self._starts_key = key
        return self._starts

    def _cheapest(self, x0: np.ndarray, cands: np.ndarray, task: ShootingTask) -> tuple[np.ndarray, np.ndarray]:
        """The candidate ``(T, m)`` of ``cands`` ``(K, T, m)`` with the lowest start score (the first among
        ties) and its predicted states ``(T+1, n)``."""
        xs = self._rollout_batch(x0, cands)
        i = int(np.argmin(task.start_scores(xs)))
        self._start_src = (cands.shape[0], i, getattr(self.dyn, "fused_calls", -1))
        return cands[i].copy(), np.ascontiguousarray(xs[i])

    def _rollout_batch(self, x0: np.ndarray, cands: np.ndarray) -> np.ndarray:
        """Predicted states ``(K, T+1, n)`` of control sequences ``cands`` ``(K, T, m)`` from ``x0`` ``(n,)``:
        ONE batched rollout (:meth:`NumpyDynamics.rollout_batch`)."""
        return self.dyn.rollout_batch(x0, cands)

    def _fixed_rows(self, x0: np.ndarray, plan_u: np.ndarray, task: ShootingTask) -> np.ndarray:
        """Which of ``task.violations``' rows ``(n_cons,)`` no control can move: the linear rows at t = 1 whose
        state does not depend on u_0 (e.g. ``pz_1 = pz_0 + dt vz_0``); later rows and the attitude row are
        taken as movable."""
        fixed = np.zeros(task.n_cons, dtype=bool)
        first = np.flatnonzero(task.cons_t == 1)
        if first.size:
            _, _, b = self.dyn.step_jac(x0[None], plan_u[:1])
            reach = np.abs(b[0, task.cons_idx[first]]) @ (task.u_high - task.u_low)
            fixed[first] = reach < 0.01 * self.feas_tol
        return fixed

    def _fallback(self, start: float, why: str, iters: int = 0) -> MPCResult:
        """A safe result: the next control of the last good plan (or ``u_default``), clipped."""
        task = self.task
        if self._plan_u is not None and self._plan_u.shape[0] > 1:
            plan_u = np.vstack((self._plan_u[1:], task.u_default[None]))
        else:
            plan_u = np.tile(task.u_default, (self.horizon, 1))
        plan_u = np.clip(plan_u, task.u_low, task.u_high)
        plan_x = np.full((self.horizon + 1, self.n), np.nan)
        return MPCResult(
            u=plan_u[0].copy(), plan_u=plan_u, plan_x=plan_x, cost=float("nan"),
            solve_time=time.perf_counter() - start, iterations=iters, success=False, message=why,
            constraint_violation=float("inf"), converged=False,
        )  # fmt: skip

    def _optimize(
        self, x0: np.ndarray, u0: np.ndarray, task: ShootingTask, xs0: np.ndarray | None = None
    ) -> tuple[np.ndarray, int, bool, str, np.ndarray | None]:
        """From the initial guess ``u0`` (with its predicted states ``xs0`` when known): optimised controls ``(T, m)``, iterations, converged, message, and the predicted states ``(T+1, n)``
        of exactly those controls when the optimiser has them (else None: the caller rolls out)."""
        raise NotImplementedError
