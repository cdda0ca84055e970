"""The generic planner: a Gauss-Newton SQP over the controls of any robot's ``mpc:`` task (:class:`GenericSQP`).

Per iteration, from the controls ``U (T, m)`` and their predicted states:

1. the exact Jacobians ``A_t, B_t`` of ``f_hat + phi`` along the plan, one batched call
   (:class:`~saml_ros.core.mpc.generic.dynamics.GenericDynamics`: CasADi for f_hat, the network's own for phi);
2. condensed sensitivities ``S_t = dx_t/dU`` (``S_{t+1} = A_t S_t + [0 .. B_t .. 0]``) (with ``compile``, steps 1-2
   in one compiled call for the whole horizon, :mod:`~saml_ros.core.mpc.generic.horizon`);
3. the Gauss-Newton model of the least-squares cost (:class:`~saml_ros.core.mpc.generic.problem.GenericProblem`)
   plus a Levenberg-Marquardt term, and the linearised state constraints;
4. one QP in the step (box on the controls, the state rows in elastic mode: always feasible), solved by DAQP
   (:func:`saml_ros.core.mpc.shooting.qp.solve_qp`, the same QP code as the built-in systems' fast solver);
5. a backtracking line search on the exact l1 merit ``cost + penalty * sum max(c, 0)`` (the full step, then all
   shorter ones in one batched rollout; every rollout one CasADi call for the whole horizon); the
   Levenberg-Marquardt weight follows the ratio of actual to predicted decrease by the hand-written quadrotor SQP's
   rule (kept between solves). Each QP is one iteration.

It stops when the QP predicts a merit decrease below ``tol * (1 + merit)`` (with a heavily damped step, only after
the same check with the initial weight: ``undamped_check``), at ``max_iter`` or ``max_time``; stopped on a plan that
violates a constraint some control can move, it raises the violation's price tenfold up to ``penalty_max`` and goes
on. Each
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
from typing import TYPE_CHECKING, Any

import numpy as np

from saml_ros.core.dynamics.system import System
from saml_ros.core.mpc.contract import MPCResult
from saml_ros.core.mpc.generic.dynamics import GenericDynamics, SymbolicBase, TorchBase, make_base
from saml_ros.core.mpc.generic.problem import GenericProblem
from saml_ros.core.mpc.generic.section import MPCTask, mpc_task
from saml_ros.core.mpc.shooting.qp import DEFAULT_BACKEND, solve_box_qp, solve_qp

if TYPE_CHECKING:
    from saml_ros.core.model.network import DynamicsModel

_ALPHAS = (1.0, 0.5, 0.25, 0.125, 0.0625)
#: values of the solver option ``ensemble``: which network of an ensemble the planner predicts with
ENSEMBLE_MODES = ("member", "mean")
_NO_G, _NO_ROWS = np.zeros((0, 0)), np.zeros(0)


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
        penalty_max: the continuation of the violation price: it starts at the task's ``penalty`` and is multiplied
            by 10, up to ``penalty_max``, whenever the SQP converges to a plan that still violates a constraint
            some control can move (default: the task's ``penalty``, i.e. fixed).
        undamped_check: before stopping with a damped step (Levenberg-Marquardt weight above ``rho0``), solve the
            QP once more with ``rho0`` (True).
        compile: the whole-horizon rollouts and the plan's sensitivities (through the network too, with exact
            Jacobians: not with ``smoothing``) compiled to C through CasADi (once per machine and problem shape,
            cached; :mod:`~saml_ros.core.mpc.generic.codegen`; without a compiler CasADi's virtual machine or numpy
            computes the same numbers, and ``describe`` says why) (False).
        qp_backend: ``daqp`` or ``ipm`` (:func:`~saml_ros.core.mpc.shooting.qp.solve_qp`).
        ensemble: ``member`` (plan with ensemble member ``member``, the default) or ``mean`` (plan with the mean of
            all the members, :class:`~saml_ros.core.mpc.generic.dynamics.EnsembleMeanMLP`; a one-member model is
            planned as itself).
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
                 smoothing: float | None = None, penalty_max: float | None = None,
                 undamped_check: bool | None = None, compile: bool | None = None, ensemble: str | None = None,
                 base: Any = None,
                 true: Any = None,
                 f_hat: SymbolicBase | TorchBase | None = None) -> None:
        self.system = system
        self.task = task if task is not None else system_task(system)
        self.problem = GenericProblem(self.task, system.state.size, system.control.size, horizon)
        self.horizon = self.problem.T
        self.member = int(member)
        self.n, self.m = system.state.size, system.control.size
        opt = _options(self.task, max_iter=max_iter, tol=tol, max_time=max_time, rho0=rho0, lm_floor=lm_floor,
                       feas_tol=feas_tol, qp_backend=qp_backend, smoothing=smoothing, penalty_max=penalty_max,
                       undamped_check=undamped_check, compile=compile, ensemble=ensemble)
        self.smoothing = float(opt.get("smoothing", 0.0))
        self.max_iter, self.tol = int(opt.get("max_iter", 15)), float(opt.get("tol", 1e-4))
        self.max_time = None if opt.get("max_time") is None else float(opt["max_time"])
        self.rho0, self.lm_floor = float(opt.get("rho0", 1e-4)), float(opt.get("lm_floor", 1e-6))
        self.feas_tol = float(opt.get("feas_tol", 1e-3))
        self.qp_backend = str(opt.get("qp_backend") or DEFAULT_BACKEND)
        if self.max_iter < 1 or not self.tol > 0 or not self.feas_tol > 0:
            raise ValueError(f"{system.name} MPC: max_iter must be >= 1, tol and feas_tol > 0")
        self.penalty = float(self.task.penalty)
        self.penalty_max = max(float(opt.get("penalty_max", self.penalty)), self.penalty)
        self.undamped_check = _flag(opt.get("undamped_check", True), "undamped_check")
        self.compile = _flag(opt.get("compile", False), "compile")
        mode = str(opt.get("ensemble", "member")).strip().lower()
        if mode not in ENSEMBLE_MODES:
            raise ValueError(f"{system.name} MPC: solver option ensemble must be one of {list(ENSEMBLE_MODES)}, "
                             f"got {opt.get('ensemble')!r}")
        #: plan with the mean of the ensemble's members (solver option ``ensemble: mean``)
        self.plans_mean = mode == "mean"
        # the disagreement cost (cost.disagreement): the fields it weighs and the square roots of their weights
        wd = np.asarray(self.task.w_disagreement, dtype=np.float64)
        self._dis_idx = np.flatnonzero(wd) if wd.size == self.n else np.zeros(0, dtype=int)
        self._dis_sw = np.sqrt(wd[self._dis_idx]) if self._dis_idx.size else np.zeros(0)
        self._fixed = np.zeros(0, dtype=bool)
        pb = self.problem
        #: the bounds of U, the control residuals' Gauss-Newton Hessian and the identity, ``(T m,)``/``(T m, T m)``
        self._consts = (np.tile(pb.u_low, pb.T), np.tile(pb.u_high, pb.T), pb.ju.T @ pb.ju, np.eye(pb.T * self.m))
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
        self.dyn = GenericDynamics(self.system, self._base, model, self.member, smoothing=self.smoothing,
                                   compile=self.compile, ensemble_mean=self.plans_mean,
                                   with_members=bool(self._dis_idx.size))
        self.dyn.prepare(self.horizon)

    def set_residual_bound(self, bound: np.ndarray | None) -> None:
        """Clip phi to ``+-bound`` ``(n,)`` per field (the guard's ``bound_residual``); None = unclipped."""
        self._bound = None if bound is None else np.asarray(bound, dtype=np.float64)
        self.dyn = GenericDynamics(self.system, self._base, self.model, self.member, self._bound, self.smoothing,
                                   self.compile, self.plans_mean, bool(self._dis_idx.size))
        self.dyn.prepare(self.horizon)

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
        out = f"generic Gauss-Newton SQP (QP {self.qp_backend}), T={self.horizon}; {self.dyn.describe()}"
        if self._dis_idx.size:
            names = self.task.state_names or tuple(str(i) for i in range(self.n))
            fields = ", ".join(names[i] for i in self._dis_idx)
            out += (f"; disagreement cost on {fields}" if self.dyn.ensemble is not None else
                    "; disagreement cost off (the model is not an ensemble)")
        return out

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
            us, xs, iters, converged, msg, cons = self._optimize(x0, us, ref, u_prev, start)
            if not (np.all(np.isfinite(xs)) and np.all(np.isfinite(us))):
                return self._fallback(start, f"non-finite plan ({msg})", iters)
        except Exception as exc:  # noqa: BLE001 - any numerical breakdown: keep flying on the last good plan
            return self._fallback(start, f"solver failure: {type(exc).__name__}: {exc}")
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
        cost = self.problem.cost(xs, us, ref, u_prev) + self._disagreement_cost(xs, us)
        return MPCResult(u=us[0].copy(), plan_u=us, plan_x=xs, cost=cost,
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

    def _merit(self, xs: np.ndarray, us: np.ndarray, ref: np.ndarray, u_prev: np.ndarray | None,
               penalty: float | None = None) -> tuple[float, np.ndarray]:
        """The l1 merit of a plan and its constraint values ``(T R,)`` (kept for the next linearisation)."""
        c = self.problem.constraints(xs).reshape(-1)
        pen = self.penalty if penalty is None else penalty
        merit = self.problem.cost(xs, us, ref, u_prev) + self._disagreement_cost(xs, us)
        if c.size:
            merit += pen * float(np.maximum(c, 0.0).sum())
        return merit, c

    def _disagreement_cost(self, xs: np.ndarray, us: np.ndarray) -> float:
        """``sum_t sum_j w_j Var_e[phi_e(x_t, u_t)_j]`` over the plan's steps t = 0..T-1 (``cost.disagreement``;
        0 without it or without an ensemble)."""
        if not self._dis_idx.size:
            return 0.0
        d = self.dyn.deviations(xs[:-1], us)
        if d is None:
            return 0.0
        r = d[:, :, self._dis_idx] * self._dis_sw
        return float(np.einsum("etj,etj->", r, r)) / d.shape[0]

    def _disagreement_model(self, xs: np.ndarray, us: np.ndarray,
                            sens: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        """The disagreement cost's residuals ``sqrt(w_j / E) (phi_e(x_t, u_t) - mean_e phi_e)_j`` ``(E T k,)`` and
        their exact Jacobian in ``U`` ``(E T k, T m)`` (``x_t`` through the plan's sensitivities ``sens``, ``u_t``
        directly): the Gauss-Newton model's part of this sum of squares; None when off."""
        if not self._dis_idx.size:
            return None
        dj = self.dyn.deviations_jac(xs[:-1], us)
        if dj is None:
            return None
        d, dx, du = dj
        e_n, T, m = d.shape[0], self.horizon, self.m
        idx, sw = self._dis_idx, self._dis_sw / math.sqrt(e_n)
        sx = np.zeros_like(sens)  # d x_t / d U for t = 0..T-1 (x_0 is given)
        sx[1:] = sens[:-1]
        jac = np.matmul(dx[:, :, idx, :], sx)  # (E, T, k, T m)
        for t in range(T):
            jac[:, t, :, t * m:(t + 1) * m] += du[:, t][:, idx, :]
        jac *= sw[None, None, :, None]
        return (d[:, :, idx] * sw).reshape(-1), jac.reshape(-1, T * m)

    def _model(self, xs: np.ndarray, us: np.ndarray, ref: np.ndarray, u_prev: np.ndarray | None,
               hu: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The Gauss-Newton model at the plan: Hessian ``(T m, T m)``, gradient ``(T m,)`` and the condensed
        sensitivities ``(T, n, T m)``."""
        pb = self.problem
        T, m, k = pb.T, self.m, pb.k
        sens = self.dyn.sensitivities(xs[:-1], us)  # (T, n, T m): d x_{t+1} / d U
        if sens is None:
            _, a_mat, b_mat = self.dyn.step_jac(xs[:-1], us)
            sens = _condense(a_mat, b_mat)
        j3 = pb.sw[:, :, None] * sens[:, pb.g_idx, :]  # (T, k, T m)
        r2 = pb.state_residuals(xs, ref)  # (T, k)
        ru = pb.control_residuals(us, u_prev)
        ju = pb.ju
        if self.task.norm_cost:
            # sum_t sqrt(||r_t||^2 + eps^2): gradient J_t' r_t / n_t, exact Hessian through the linearisation
            # J_t' (I - r_t r_t' / n_t^2) J_t / n_t (generalised Gauss-Newton; positive semi-definite)
            nt = np.sqrt(np.einsum("ij,ij->i", r2, r2) + float(self.task.norm_eps) ** 2)
            jr = np.einsum("tk,tkv->tv", r2, j3)  # r_t' J_t
            jw = (j3 * (1.0 / np.sqrt(nt))[:, None, None]).reshape(T * k, T * m)
            jrw = jr * (nt ** -1.5)[:, None]
            h_gn = jw.T @ jw - jrw.T @ jrw
            grad = (jr / nt[:, None]).sum(0)
            if ju.size:
                h_gn += 2.0 * hu
                grad += 2.0 * (ju.T @ ru)
        else:
            jx = j3.reshape(T * k, T * m)
            h_gn = 2.0 * (jx.T @ jx + hu)
            grad = 2.0 * (jx.T @ r2.reshape(-1) + ju.T @ ru)
        dis = self._disagreement_model(xs, us, sens)
        if dis is not None:
            rd, jd = dis
            h_gn = h_gn + 2.0 * (jd.T @ jd)
            grad = grad + 2.0 * (jd.T @ rd)
        return h_gn, grad, sens

    def _optimize(self, x0: np.ndarray, us: np.ndarray, ref: np.ndarray, u_prev: np.ndarray | None,
                  start: float) -> tuple[np.ndarray, np.ndarray, int, bool, str, np.ndarray]:
        """The SQP iterations (module docstring): ``(U, predicted states, iterations, converged, message, the
        plan's constraint values (T R,))``."""
        pb, dyn = self.problem, self.dyn
        T, m = pb.T, self.m
        lo_t, hi_t, hu, eye = self._consts
        reach_range = hi_t - lo_t
        penalty = self.penalty
        xs = dyn.rollout(x0, us)
        merit, cons = self._merit(xs, us, ref, u_prev, penalty)
        msg, converged, it = "max_iter", False, 0
        rho = self._rho
        self._fixed = np.zeros(pb.n_cons, dtype=bool)
        relinearise, undamped_tried = True, False
        for it in range(1, self.max_iter + 1):  # noqa: B007
            # each QP is one iteration (a real-time iteration, max_iter 1, solves exactly one); the model is
            # rebuilt only when the plan or the violation price changed
            if relinearise:
                h_gn, grad, sens = self._model(xs, us, ref, u_prev, hu)
                scale = max(float(np.trace(h_gn)) / h_gn.shape[0], 1e-6)
                u_flat = us.reshape(-1)
                g_mat, c_qp = _NO_G, _NO_ROWS
                if cons.size:
                    g_all = np.matmul(pb.constraint_jac(xs), sens).reshape(-1, T * m)  # (T R, T m)
                    # rows no control can move (a bound on x_1 fixed by the current state, the rows of a terminal
                    # constraint before T) only add a constant: left out of the QP, as the hand-written SQP does
                    self._fixed = np.abs(g_all) @ reach_range < 0.01 * self.feas_tol
                    keep = ~self._fixed
                    g_mat, c_qp = g_all[keep], cons[keep]
                pen = np.full(c_qp.size, penalty)
                rows0 = penalty * float(np.maximum(c_qp, 0.0).sum())
                lo_d, hi_d = lo_t - u_flat, hi_t - u_flat
                relinearise, undamped_tried = False, False
            hess = h_gn + (rho * scale + self.lm_floor) * eye
            if c_qp.size:
                d_flat = solve_qp(hess, grad, lo_d, hi_d, g_mat, -c_qp, pen, backend=self.qp_backend).d
            else:
                d_flat = solve_box_qp(hess, grad, lo_d, hi_d).d
            if not np.all(np.isfinite(d_flat)):
                msg = "QP failed"
                break
            pred = -(grad @ d_flat + 0.5 * d_flat @ h_gn @ d_flat) + rows0
            if c_qp.size:
                pred -= penalty * float(np.maximum(c_qp + g_mat @ d_flat, 0.0).sum())
            if pred <= self.tol * (1.0 + abs(merit)):
                if self.undamped_check and rho > self.rho0 and not undamped_tried:
                    # a heavily damped step predicts little even far from a minimum (the network's kinks make
                    # the Levenberg-Marquardt weight grow): only the undamped model may stop
                    undamped_tried, rho = True, self.rho0
                    continue
                movable = cons[~self._fixed] if cons.size else cons
                if movable.size and float(movable.max()) > self.feas_tol and penalty < self.penalty_max:
                    # converged to a plan that still violates a constraint some control can move: make
                    # violations dearer and go on (the hand-written SQP's continuation)
                    penalty = min(penalty * 10.0, self.penalty_max)
                    merit = self._merit(xs, us, ref, u_prev, penalty)[0]
                    relinearise = True
                    continue
                msg, converged = "converged", True
                break
            alpha, ut, xt, mt, ct = self._line_search(x0, us, d_flat.reshape(T, m), merit, pred, ref, u_prev,
                                                      penalty)
            if alpha == 0.0:  # no step accepted: damp more and solve the same model again
                rho = max(rho, 1e-3) * 10.0
                if rho > 1e3:
                    msg = "line search failed"
                    break
                continue
            ratio = (merit - mt) / pred
            if alpha == 1.0 and ratio > 0.75:
                rho = max(rho / 4.0, 1e-9)
            elif alpha < 1.0 or ratio < 0.25:
                rho *= max(2.0, 1.0 / alpha)
            us, xs, merit, cons = ut, xt, mt, ct
            relinearise = True
            if self.max_time is not None and time.perf_counter() - start > self.max_time:
                msg = "time budget"
                break
        self._rho = rho
        return us, xs, it, converged, msg, cons

    def _line_search(self, x0: np.ndarray, us: np.ndarray, d: np.ndarray, merit: float, pred: float,
                     ref: np.ndarray, u_prev: np.ndarray | None,
                     penalty: float) -> tuple[float, np.ndarray, np.ndarray, float, np.ndarray]:
        """Backtracking on the l1 merit (Armijo on the predicted decrease): the full step first (usually taken),
        then every shorter one of :data:`_ALPHAS` in one batched rollout. ``(alpha, U, states, merit,
        constraints)``; alpha 0 when no step length is accepted."""
        lo, hi = self.problem.u_low, self.problem.u_high
        ut = np.clip(us + d, lo, hi)
        xt = self.dyn.rollout(x0, ut)
        mt, ct = self._merit(xt, ut, ref, u_prev, penalty)
        if np.isfinite(mt) and mt <= merit - 1e-4 * pred:
            return 1.0, ut, xt, mt, ct
        alphas = np.asarray(_ALPHAS[1:])
        uts = np.clip(us[None] + alphas[:, None, None] * d[None], lo, hi)
        xts = self.dyn.rollout_batch(x0, uts)
        for j, alpha in enumerate(alphas):
            mj, cj = self._merit(xts[j], uts[j], ref, u_prev, penalty)
            if np.isfinite(mj) and mj <= merit - 1e-4 * alpha * pred:
                return float(alpha), uts[j], xts[j], mj, cj
        return 0.0, us, _NO_G, math.inf, _NO_ROWS

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


def _flag(value: Any, name: str) -> bool:
    """A yes/no solver option (a bool, 0/1, or ``true``/``false`` as text); ``ValueError`` otherwise."""
    if isinstance(value, bool | int) and value in (0, 1):
        return bool(value)
    text = str(value).strip().lower()
    if text in ("true", "yes", "on", "1"):
        return True
    if text in ("false", "no", "off", "0"):
        return False
    raise ValueError(f"solver option {name} must be true or false, got {value!r}")


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
