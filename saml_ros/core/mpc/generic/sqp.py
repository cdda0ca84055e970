"""The generic planner: a Gauss-Newton SQP over the controls of any robot's ``mpc:`` task (:class:`GenericSQP`).

Per iteration, from the controls ``U (T, m)`` and their predicted states:

1. the exact Jacobians ``A_t, B_t`` of ``f_hat + phi`` along the plan, one batched call
   (:class:`~saml_ros.core.mpc.generic.dynamics.GenericDynamics`: CasADi for f_hat, the network's own for phi);
2. condensed sensitivities ``S_t = dx_t/dU`` (``S_{t+1} = A_t S_t + [0 .. B_t .. 0]``);
3. the Gauss-Newton model of the least-squares cost (:class:`~saml_ros.core.mpc.generic.problem.GenericProblem`)
   plus a Levenberg-Marquardt term, and the linearised state constraints;
4. one QP in the step (box on the controls, the state rows in elastic mode: always feasible), solved by DAQP
   (:func:`saml_ros.core.mpc.shooting.qp.solve_qp`, the same QP code as the built-in systems' fast solver);
5. a backtracking line search on the exact l1 merit ``cost + penalty * sum max(c, 0)`` (the full step, then all
   shorter ones in one batched rollout); the Levenberg-Marquardt
   weight follows the ratio of actual to predicted decrease (kept between solves).

It stops when the QP predicts a merit decrease below ``tol * (1 + merit)`` (with a heavily damped step, only after
the same check with the initial weight), at ``max_iter`` or ``max_time``. Each
solve warm-starts from the previous plan (shifted one step when the state moved on), else from the last command
held. A hot swap of the network (:meth:`GenericSQP.set_model`) copies its weights into the prediction model;
nothing is rebuilt or recompiled.

The controller implements the MPC contract (:class:`~saml_ros.core.mpc.contract.Controller`) and what the guard
(:class:`~saml_ros.core.mpc.guard.GuardedController`) uses: ``warm_start_plan``, ``set_warm_start``, ``dyn.step1``,
``set_residual_bound``, ``phi_clipped``.
"""

from __future__ import annotations

import math
import time
from typing import Any

import numpy as np

from saml_ros.core.dynamics.system import System
from saml_ros.core.model.network import DynamicsModel
from saml_ros.core.mpc.contract import MPCResult
from saml_ros.core.mpc.generic.dynamics import GenericDynamics, SymbolicBase, TorchBase, make_base
from saml_ros.core.mpc.generic.problem import GenericProblem
from saml_ros.core.mpc.generic.section import MPCTask, mpc_task
from saml_ros.core.mpc.shooting.qp import DEFAULT_BACKEND, solve_box_qp, solve_qp

_ALPHAS = (1.0, 0.5, 0.25, 0.125, 0.0625, 0.03125)


def system_task(system: System) -> MPCTask:
    """The :class:`MPCTask` of a robot described by a system file with an ``mpc:`` section; ``ValueError``
    otherwise."""
    definition = getattr(system, "definition", None)
    task = mpc_task(definition) if isinstance(definition, dict) else None
    if task is None:
        raise ValueError(f"system {system.name!r} has no 'mpc:' section (its control task): add one to its system "
                         "file (docs/your_robot.md, 'Control it')")
    return task


class GenericSQP:
    """See the module docstring.

    Args:
        system: a robot from a system file with an ``mpc:`` section.
        model: the learned model (member ``member``) or None (f_hat alone); swap with :meth:`set_model`.
        horizon: T (default: the section's ``horizon``).
        task: the control task (default: the system's ``mpc:`` section).
        max_iter: SQP iterations per solve (15); tol: stop when the predicted merit decrease is below
            ``tol * (1 + merit)`` (1e-4); max_time: optional wall-clock budget per solve (s).
        rho0: initial Levenberg-Marquardt weight, relative to the mean diagonal of the Gauss-Newton Hessian (1e-4);
            lm_floor: absolute term added to it (1e-6).
        feas_tol: largest constraint value (state units) of a plan still called a success (1e-3).
        qp_backend: ``daqp`` or ``ipm`` (:func:`~saml_ros.core.mpc.shooting.qp.solve_qp`).
        The solver options not given here come from the section's ``mpc.solver_options``.
        base, true: the registry's numpy twins :func:`~saml_ros.core.mpc.factory.make_controller` hands every
            controller; not used (this planner builds f_hat from the system file, :func:`make_base`).
        f_hat: the base model to plan with instead of :func:`make_base`'s (e.g. a built-in system's form:
            :func:`~saml_ros.systems.quadrotor.generic_form.quadrotor_base`, or the true dynamics for an oracle).
    """

    def __init__(self, system: System, model: DynamicsModel | None = None, horizon: int | None = None,
                 member: int = 0, *, task: MPCTask | None = None, max_iter: int | None = None,
                 tol: float | None = None, max_time: float | None = None, rho0: float | None = None,
                 lm_floor: float | None = None, feas_tol: float | None = None, qp_backend: str | None = None,
                 smoothing: float | None = None, base: Any = None, true: Any = None,
                 f_hat: SymbolicBase | TorchBase | None = None) -> None:
        self.system = system
        self.task = task if task is not None else system_task(system)
        self.problem = GenericProblem(self.task, system.state.size, system.control.size, horizon)
        self.horizon = self.problem.T
        self.member = int(member)
        self.n, self.m = system.state.size, system.control.size
        opt = _options(self.task, max_iter=max_iter, tol=tol, max_time=max_time, rho0=rho0, lm_floor=lm_floor,
                       feas_tol=feas_tol, qp_backend=qp_backend, smoothing=smoothing)
        self.smoothing = float(opt.get("smoothing", 0.0))
        self.max_iter, self.tol = int(opt.get("max_iter", 15)), float(opt.get("tol", 1e-4))
        self.max_time = None if opt.get("max_time") is None else float(opt["max_time"])
        self.rho0, self.lm_floor = float(opt.get("rho0", 1e-4)), float(opt.get("lm_floor", 1e-6))
        self.feas_tol = float(opt.get("feas_tol", 1e-3))
        self.qp_backend = str(opt.get("qp_backend") or DEFAULT_BACKEND)
        if self.max_iter < 1 or not self.tol > 0 or not self.feas_tol > 0:
            raise ValueError(f"{system.name} MPC: max_iter must be >= 1, tol and feas_tol > 0")
        self.penalty = float(self.task.penalty)
        self._base: SymbolicBase | TorchBase = make_base(system) if f_hat is None else f_hat
        self._base_params: Any = _base_params(system)
        self._bound: np.ndarray | None = None
        self.model: DynamicsModel | None = None
        self.dyn = GenericDynamics(system, self._base)
        self.set_model(model)
        self._plan_u: np.ndarray | None = None
        self._plan_x: np.ndarray | None = None
        self._u_last: np.ndarray | None = None
        self._rho = self.rho0

    # ------------------------------------------------------------------------------------------ models
    def set_model(self, model: DynamicsModel | None) -> None:
        """Plan with ``model`` (member ``member``) from the next solve on; the warm start is kept. Copies the
        network's weights (a learner may keep training the same object); f_hat is rebuilt only when the model's
        system has other base model parameters (a fitted ``linear`` f_hat)."""
        if model is not None and model.system.state.names != self.system.state.names:
            raise ValueError(f"model of system {model.system.name!r} does not fit {self.system.name!r}")
        if model is not None and _base_params(model.system) != self._base_params:
            self._base, self._base_params = make_base(model.system), _base_params(model.system)
        self.model = model
        self._bound = None
        self.dyn = GenericDynamics(self.system, self._base, model, self.member, smoothing=self.smoothing)

    def set_residual_bound(self, bound: np.ndarray | None) -> None:
        """Clip phi to ``+-bound`` ``(n,)`` per field (the guard's ``bound_residual``); None = unclipped."""
        self._bound = None if bound is None else np.asarray(bound, dtype=np.float64)
        self.dyn = GenericDynamics(self.system, self._base, self.model, self.member, self._bound, self.smoothing)

    def phi_clipped(self, res: MPCResult) -> bool:
        """Whether the residual bound clipped phi anywhere on plan ``res``."""
        if not np.all(np.isfinite(res.plan_x)):
            return False
        return self.dyn.clipped(res.plan_x[:-1], res.plan_u)

    def reset(self) -> None:
        """Drop the warm start, the last command (the rate cost of the first control) and the adapted
        Levenberg-Marquardt weight: the next solve is a cold start."""
        self._plan_u = self._plan_x = None
        self._u_last = None
        self._rho = self.rho0

    def warm_start_plan(self) -> tuple[np.ndarray, np.ndarray] | None:
        if self._plan_u is None or self._plan_x is None:
            return None
        return self._plan_u.copy(), self._plan_x.copy()

    def set_warm_start(self, plan_u: np.ndarray, plan_x: np.ndarray) -> None:
        self._plan_u = np.array(plan_u, dtype=np.float64).reshape(self.horizon, self.m)
        self._plan_x = np.array(plan_x, dtype=np.float64).reshape(self.horizon + 1, self.n)
        self._u_last = self._plan_u[0].copy()

    def describe(self) -> str:
        """The planner path, the solver and the model (for /diagnostics)."""
        return (f"generic Gauss-Newton SQP (QP {self.qp_backend}), T={self.horizon}; {self.dyn.describe()}")

    # ------------------------------------------------------------------------------------------ solve
    def solve(self, x0: np.ndarray, goal: Any | None = None) -> MPCResult:
        """Plan from ``x0 (n,)`` towards ``goal`` (``(k,)`` setpoint of the goal fields, ``(T, k)`` reference of
        x_1 .. x_T, or None: the task's default). Never raises on a numerical failure; ``ValueError`` for a wrong
        ``x0`` shape or goal shape."""
        start = time.perf_counter()
        x0 = np.asarray(x0, dtype=np.float64)
        if x0.shape != (self.n,):
            raise ValueError(f"{self.system.name} MPC: x0 must have shape ({self.n},), got {x0.shape}")
        ref = self.problem.reference(x0, goal) if np.all(np.isfinite(x0)) else None
        if ref is None or not np.all(np.isfinite(ref)):
            return self._fallback(start, "non-finite state" if ref is None else "non-finite goal")
        try:
            u_prev = self._u_last
            us = self._warm_start(x0)
            us, xs, iters, converged, msg = self._optimize(x0, us, ref, u_prev, start)
            if not (np.all(np.isfinite(xs)) and np.all(np.isfinite(us))):
                return self._fallback(start, f"non-finite plan ({msg})", iters)
        except Exception as exc:  # noqa: BLE001 - any numerical breakdown: keep flying on the last good plan
            return self._fallback(start, f"solver failure: {type(exc).__name__}: {exc}")
        cons = self.problem.constraints(xs).reshape(-1)
        worst = float(max(0.0, cons.max())) if cons.size else 0.0
        ok = worst <= self.feas_tol
        unavoidable = False
        if not ok:
            i = int(np.argmax(cons))
            msg = f"{msg}; {self.problem.violation_names()[i]} violated by {worst:.3g}"
            fixed = self._fixed_rows(x0, us)
            movable = cons[~fixed]
            unavoidable = not (movable.size and float(movable.max()) > self.feas_tol)
            if fixed[i]:
                msg += " (unavoidable: fixed by the current state)"
        self._plan_u, self._plan_x = us, xs
        self._u_last = us[0].copy()
        return MPCResult(u=us[0].copy(), plan_u=us, plan_x=xs, cost=self.problem.cost(xs, us, ref, u_prev),
                         solve_time=time.perf_counter() - start, iterations=iters, success=ok, message=msg,
                         constraint_violation=worst, converged=converged, unavoidable=unavoidable)

    def _warm_start(self, x0: np.ndarray) -> np.ndarray:
        """The previous plan, shifted one step when ``x0`` is nearer its x_1 than its x_0, its last control
        repeated; without one, the last command (else the safe command) held; clipped to the bounds."""
        T, lo, hi = self.horizon, self.problem.u_low, self.problem.u_high
        if self._plan_u is None or self._plan_x is None:
            u = self._u_last if self._u_last is not None else self.task.u_safe
            return np.tile(np.clip(u, lo, hi), (T, 1))
        d1, d0 = x0 - self._plan_x[1], x0 - self._plan_x[0]
        shift = 1 if d1 @ d1 < d0 @ d0 else 0
        us = np.empty((T, self.m))
        us[: T - shift] = self._plan_u[shift:]
        us[T - shift:] = self._plan_u[-1]
        return np.clip(us, lo, hi)

    def _merit(self, xs: np.ndarray, us: np.ndarray, ref: np.ndarray, u_prev: np.ndarray | None) -> float:
        c = self.problem.constraints(xs)
        return self.problem.cost(xs, us, ref, u_prev) + self.penalty * float(np.maximum(c, 0.0).sum())

    def _optimize(self, x0: np.ndarray, us: np.ndarray, ref: np.ndarray, u_prev: np.ndarray | None,
                  start: float) -> tuple[np.ndarray, np.ndarray, int, bool, str]:
        """The SQP iterations (module docstring): ``(U, predicted states, iterations, converged, message)``."""
        pb, dyn = self.problem, self.dyn
        T, m, k = pb.T, self.m, pb.k
        lo, hi = pb.u_low, pb.u_high
        xs = dyn.rollout(x0, us)
        merit = self._merit(xs, us, ref, u_prev)
        ju = pb.ju
        hu = ju.T @ ju
        eye = np.eye(T * m)
        msg, converged, it = "max_iter", False, 0
        undamped = False
        norm_cost, eps2 = bool(self.task.norm_cost), float(self.task.norm_eps) ** 2
        for it in range(1, self.max_iter + 1):  # noqa: B007
            _, a_mat, b_mat = dyn.step_jac(xs[:-1], us)
            sens = _condense(a_mat, b_mat)  # (T, n, T m): d x_{t+1} / d U
            jx = (pb.sw[:, :, None] * sens[:, pb.g_idx, :]).reshape(T * k, T * m)
            rx = pb.state_residuals(xs, ref).reshape(-1)
            ru = pb.control_residuals(us, u_prev)
            if norm_cost:
                # sum_t sqrt(||r_t||^2 + eps^2): gradient J_t' r_t / n_t, exact Hessian through the linearisation
                # J_t' (I - r_t r_t' / n_t^2) J_t / n_t (generalised Gauss-Newton; positive semi-definite)
                r2 = rx.reshape(T, k)
                nt = np.sqrt(np.einsum("ij,ij->i", r2, r2) + eps2)
                j3 = jx.reshape(T, k, T * m)
                jr = np.einsum("tk,tkv->tv", r2, j3)  # r_t' J_t
                h_gn = (np.einsum("tkv,tkw->vw", j3 / nt[:, None, None], j3)
                        - (jr / nt[:, None] ** 3).T @ jr + 2.0 * hu)
                grad = jr.T @ (1.0 / nt) + 2.0 * (ju.T @ ru)
            else:
                h_gn = 2.0 * (jx.T @ jx + hu)
                grad = 2.0 * (jx.T @ rx + ju.T @ ru)
            lm = self._rho * float(np.mean(np.diag(h_gn))) + self.lm_floor
            hess = h_gn + lm * eye
            u_flat = us.reshape(-1)
            cons = pb.constraints(xs).reshape(-1)
            if cons.size:
                cj = pb.constraint_jac(xs)  # (T, R, n)
                g_mat = np.einsum("trn,tnv->trv", cj, sens).reshape(-1, T * m)
                qp = solve_qp(hess, grad, np.tile(lo, T) - u_flat, np.tile(hi, T) - u_flat, g_mat, -cons,
                              self.penalty, backend=self.qp_backend)
                lin = cons + g_mat @ qp.d
                pred = -(grad @ qp.d + 0.5 * qp.d @ h_gn @ qp.d) + self.penalty * (
                    float(np.maximum(cons, 0.0).sum()) - float(np.maximum(lin, 0.0).sum()))
            else:
                qp = solve_box_qp(hess, grad, np.tile(lo, T) - u_flat, np.tile(hi, T) - u_flat)
                pred = -(grad @ qp.d + 0.5 * qp.d @ h_gn @ qp.d)
            if not np.all(np.isfinite(qp.d)):
                msg = "QP failed"
                break
            if pred <= self.tol * (1.0 + abs(merit)):
                if self._rho > 10.0 * self.rho0 and not undamped:
                    # a heavily damped step predicts little even far from a minimum (the network's kinks make
                    # the Levenberg-Marquardt weight grow): check once with the initial weight before stopping
                    self._rho, undamped = self.rho0, True
                    continue
                msg, converged = "converged", True
                break
            d = qp.d.reshape(T, m)
            # the full step first (usually taken); if refused, every shorter step in one batched rollout
            ut = np.clip(us + d, lo, hi)
            xt = dyn.rollout(x0, ut)
            mt = self._merit(xt, ut, ref, u_prev)
            accepted = bool(np.isfinite(mt) and mt <= merit - 1e-4 * pred)
            if not accepted:
                alphas = np.asarray(_ALPHAS[1:])
                uts = np.clip(us[None] + alphas[:, None, None] * d[None], lo, hi)
                xts = dyn.rollout_batch(x0, uts)
                for j, alpha in enumerate(alphas):
                    mj = self._merit(xts[j], uts[j], ref, u_prev)
                    if np.isfinite(mj) and mj <= merit - 1e-4 * alpha * pred:
                        ut, xt, mt, accepted = uts[j], xts[j], mj, True
                        break
            if not accepted:
                self._rho = min(self._rho * 10.0, 1e6)
                if self._rho >= 1e6:
                    msg = "line search failed"
                    break
                continue
            ratio = (merit - mt) / pred
            if ratio > 0.75:
                self._rho = max(self._rho / 3.0, 1e-9)
            elif ratio < 0.25:
                self._rho = min(self._rho * 4.0, 1e6)
            us, xs, merit = ut, xt, mt
            if self.max_time is not None and time.perf_counter() - start > self.max_time:
                msg = "time budget"
                break
        return us, xs, it, converged, msg

    def _fixed_rows(self, x0: np.ndarray, us: np.ndarray) -> np.ndarray:
        """Which constraint values (flattened, t major) no control can move: rows at t = 1 whose state does not
        depend on u_0 (within the control bounds)."""
        pb = self.problem
        fixed = np.zeros(pb.n_cons, dtype=bool)
        if not pb.rows_per_step:
            return fixed
        _, _, b = self.dyn.step_jac(x0[None], us[:1])
        xs1 = np.vstack([x0, self.dyn.step1(x0, us[0])])
        cj = pb.constraint_jac(np.vstack([xs1, np.repeat(xs1[-1:], pb.T - 1, axis=0)]))[0]  # (R, n) at t = 1
        reach = np.abs(cj @ b[0]) @ (pb.u_high - pb.u_low)
        fixed[: pb.rows_per_step] = reach < 0.01 * self.feas_tol
        return fixed

    def _fallback(self, start: float, why: str, iters: int = 0) -> MPCResult:
        """A safe result: the next control of the last good plan (else the safe command), clipped."""
        T = self.horizon
        if self._plan_u is not None and T > 1:
            plan_u = np.vstack((self._plan_u[1:], self._plan_u[-1:]))
        else:
            plan_u = np.tile(self.task.u_safe, (T, 1))
        plan_u = np.clip(plan_u, self.problem.u_low, self.problem.u_high)
        return MPCResult(u=plan_u[0].copy(), plan_u=plan_u, plan_x=np.full((T + 1, self.n), np.nan), cost=math.nan,
                         solve_time=time.perf_counter() - start, iterations=iters, success=False, message=why,
                         constraint_violation=math.inf, converged=False)


def _options(task: MPCTask, **given: Any) -> dict[str, Any]:
    """Solver options: those given explicitly (not None), else the section's ``mpc.solver_options``."""
    out = dict(task.solver_options)
    out.update({k: v for k, v in given.items() if v is not None})
    return out


def _condense(a_mat: np.ndarray, b_mat: np.ndarray) -> np.ndarray:
    """``S (T, n, T m)``: ``S_t = d x_{t+1} / d U`` from ``A (T, n, n)``, ``B (T, n, m)``."""
    T, n, m = b_mat.shape
    sens = np.zeros((T, n, T * m))
    sens[0, :, :m] = b_mat[0]
    for t in range(1, T):
        w = t * m
        sens[t, :, :w] = a_mat[t] @ sens[t - 1, :, :w]
        sens[t, :, w: w + m] = b_mat[t]
    return sens


def _base_params(system: System) -> Any:
    base = getattr(system, "base_model", None)
    if base is None:
        return None
    return getattr(base, "kind", None), repr(base.params()) if hasattr(base, "params") else None
