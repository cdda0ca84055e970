"""The fast single-shooting solver (:class:`SQPShootingMPC`), per iteration:

1. exact Jacobians ``A_t, B_t`` of ``f_hat + phi`` at the current trajectory, batched over t;
2. condensed sensitivities ``S_t = dx_t/dU`` by the recursion ``S_{t+1} = A_t S_t + [0 .. B_t .. 0]``;
3. a model of the cost: for a scalar residual (friction, ``|p_t|``) the exact l1 model as elastic LP rows; for
   Euclidean norms (quadrotor) each ``||r_t||`` smoothed to ``sqrt(||r_t||^2 + eps^2)`` with its exact Hessian
   through the linearisation (generalised Gauss-Newton), plus a Levenberg-Marquardt term;
4. one QP over the step d (:mod:`~saml_ros.core.mpc.shooting.qp`): box ``u_low - U <= d <= u_high - U`` and the
   linearised state constraints in elastic mode (always feasible), solved by DAQP when installed, else by
   projected Newton when the box alone satisfies the state rows and a small interior point method otherwise;
5. a backtracking line search on the l1 merit ``cost + penalty * sum max(c_i, 0)``; the Levenberg-Marquardt
   weight follows the ratio of actual to predicted decrease; the penalty grows if the solver converges to a
   plan that still violates a constraint some control can move.

It stops when the QP predicts a merit decrease below ``tol * (1 + merit)``, at ``max_iter`` or ``max_time``.

With a Euclidean stage cost (the quadrotor) and a model the C kernel knows (f_hat, a PReLU network, both, the
guard's bounded residual), steps 1-3, the merits and the line search's rollouts run in C
(:mod:`~saml_ros.core.mpc.shooting.native`, option ``native``); the control flow and the QP stay here.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np
from scipy.linalg.blas import dtrsm as _dtrsm

from saml_ros.core.dynamics.system import System
from saml_ros.core.mpc.dynamics_np import PredictionModel
from saml_ros.core.mpc.shooting import native as _native
from saml_ros.core.mpc.shooting.controller import ShootingMPC
from saml_ros.core.mpc.shooting.qp import DEFAULT_BACKEND, L1QP, solve_box_qp, solve_qp
from saml_ros.core.mpc.shooting.tasks import ShootingTask

#: one trial point of the line search: controls (T, m), predicted states (T+1, n), merit, residuals, constraints
_Trial = tuple[np.ndarray, np.ndarray, float, np.ndarray | None, np.ndarray]
#: the line search's step lengths, tried in this order
_ALPHAS = (1.0, 0.5, 0.25, 0.125, 0.0625)


class SQPShootingMPC(ShootingMPC):
    """The fast solver (see the module docstring).

    Args (beyond :class:`ShootingMPC`'s):
        max_iter: SQP iteration cap per solve.
        tol: stop when the QP predicts a merit decrease below ``tol * (1 + merit)``.
        max_time: optional wall-clock budget per solve (s); the best plan so far is returned when it runs out.
        eps: smoothing of the Euclidean norms (cost units); the reported cost is always the exact one.
        penalty: initial price of one unit of state-constraint violation (elastic QP and merit); multiplied by
            10 (up to ``penalty_max``) when the solver converges to a plan that still violates a constraint.
        rho0: initial Levenberg-Marquardt weight relative to the mean diagonal of the Gauss-Newton Hessian;
            adapted by the ratio of actual to predicted decrease and carried over between solves.
        lm_floor: absolute Levenberg-Marquardt term (cost units per control unit squared): keeps controls that
            barely affect the cost (the last ones of the horizon) from drifting.
        radial: weight of the radial curvature term of the Euclidean norm (1 = the exact Hessian of the
            smoothed norm, 0 = iteratively reweighted least squares).
        qp_backend: "daqp" (a C active-set solver, default when installed) or "ipm" (numpy interior point
            method, the fallback); both solve the same subproblem (:func:`~saml_ros.core.mpc.shooting.qp.solve_qp`).
        undamped_check: before declaring convergence with a damped step (Levenberg-Marquardt weight above
            ``rho0``), re-solve the QP once with ``rho0``: avoids stopping early in flat valleys where damping
            makes every step predict little, at the price of more iterations (use with a small ``tol``).
        native: use the C kernel where it applies (:mod:`~saml_ros.core.mpc.shooting.native`); False, or
            ``SAML_MPC_NATIVE=0``, keeps the numpy path. :attr:`native_reason` says why it is not used.
    """

    def __init__(
        self,
        system: System,
        model: PredictionModel = None,
        horizon: int = 10,
        max_iter: int = 20,
        tol: float = 3e-4,
        max_time: float | None = None,
        eps: float = 1e-3,
        penalty: float = 10.0,
        penalty_max: float = 1e4,
        rho0: float = 1e-3,
        lm_floor: float = 1e-3,
        radial: float = 1.0,
        qp_backend: str | None = None,
        undamped_check: bool = False,
        native: bool = True,
        **kwargs: Any,
    ) -> None:
        super().__init__(system, model, horizon, **kwargs)
        self.qp_backend = qp_backend or DEFAULT_BACKEND
        if self.qp_backend not in ("daqp", "ipm"):
            raise ValueError(f"unknown qp_backend {qp_backend!r}; use 'daqp' or 'ipm'")
        self.max_iter, self.tol, self.max_time = max_iter, tol, max_time
        self.eps, self.penalty, self.penalty_max = eps, penalty, penalty_max
        self.rho0, self.lm_floor, self.radial = rho0, lm_floor, radial
        self.undamped_check = undamped_check
        self.native = bool(native)
        self._nat: _native.NativeSQP | None = None  # the kernel bound to self.dyn and the task's layout
        #: why the last solve ran the numpy path (None: it ran the C kernel)
        self.native_reason: str | None = _native.NOT_SOLVED
        if self.native and self.task.res_idx.size > 1:  # only a Euclidean stage cost can use the kernel
            _native.load_library()  # compiled (first use on this machine, ~1 s) or loaded now, not in a solve
        self.shrink = 1.0
        self._rho = rho0
        self._ipm_first = False  # the last QP had active state constraints: skip the box-only attempt
        self._fixed = np.zeros(0, dtype=bool)  # constraint rows no control can change (last linearisation)
        nu = self.horizon * self.m
        self._sens = np.zeros((self.horizon + 1, self.n, nu))
        # small state and horizon (friction: 2 x 10): the sensitivities by one triangular solve (see
        # _sensitivities); larger ones (quadrotor: 13 x 10) by the recursion, which is faster there
        self._tri: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None
        if self.horizon * self.n <= 48:
            T, n, m = self.horizon, self.n, self.m
            nt = T * n
            ia = [((t * n + np.arange(n))[:, None] * nt + ((t - 1) * n + np.arange(n))[None, :]).ravel()
                  for t in range(1, T)]
            ib = [((t * n + np.arange(n))[:, None] * (T * m) + (t * m + np.arange(m))[None, :]).ravel()
                  for t in range(T)]
            self._tri = (np.eye(nt), np.zeros((nt, T * m)), np.concatenate(ia).astype(np.intp),
                         np.concatenate(ib).astype(np.intp))  # fmt: skip
        self._eye = np.eye(nu)
        self._alphas = np.array(_ALPHAS)[:, None, None]  # (5, 1, 1): the batched line search's step lengths
        self._zeros_nu = np.zeros(nu)
        self._zeros_hess = np.zeros((nu, nu))
        self._zeros_hess.flags.writeable = False
        self._no_rows = np.zeros(0)
        self._no_g = np.zeros((0, nu))
        #: the accepted trial point's (batch size, sequence, ``dyn.fused_calls``) in the line search's fused rollout
        self._trial_src: tuple[int, int, int] | None = None
        self._l1_rows = (self._no_g, self._no_rows)  # the l1 model's stage rows (J (T, T m), r (T,)), per iteration
        self._l1_abs = 0.0  # sum |r| of those rows
        self._l1qp: L1QP | None = None  # the l1 model's DAQP buffers (scalar stage cost), made on first use
        #: the last :meth:`_merit`'s trajectory and the attitude row's gradient ``d/dq_v`` there (or None)
        self._last_dqv: tuple[np.ndarray, np.ndarray | None] | None = None
        #: per-solve counters (iterations, QPs, rollouts, ...) of the last solve, for profiling
        self.stats: dict[str, int] = {}
        #: set to a list to record (iteration, merit, predicted, actual decrease, step, |d|, rho, penalty)
        self.trace: list[tuple[Any, ...]] | None = None

    def reset(self) -> None:
        super().reset()
        self._rho = self.rho0
        self._ipm_first = False

    def _fixed_rows(self, x0: np.ndarray, plan_u: np.ndarray, task: ShootingTask) -> np.ndarray:
        # the last linearisation's (all rows, from the full sensitivities)
        if self._fixed.size == task.n_cons:
            return self._fixed
        return super()._fixed_rows(x0, plan_u, task)

    def _native_for(self, task: ShootingTask) -> _native.NativeSQP | None:
        """The C kernel bound to the current model and ``task``'s layout (made when either changed), or None with
        :attr:`native_reason` set."""
        nat = self._nat
        if nat is not None and self.native and nat.fits(self.dyn, task, self.radial) and not _native.switched_off():
            self.native_reason = None
            return nat
        self._nat = None
        if not self.native:
            self.native_reason = "switched off (solver option native: false)"
            return None
        why = _native.unsupported_reason(self.dyn, task)
        lib = _native.load_library() if why is None else None
        if why is None and lib is None:
            why = _native.reason()
        self.native_reason = why
        if why is not None or lib is None:
            return None
        self._nat = _native.NativeSQP(lib, self.dyn, task, self._u_hi - self._u_lo, self.radial)
        return self._nat

    def _merit_of(self, nat: _native.NativeSQP | None, xs: np.ndarray, task: ShootingTask,
                  penalty: float) -> tuple[float, np.ndarray | None, np.ndarray]:
        """:meth:`_merit`, by the C kernel when bound (then without the residuals, which only the numpy path uses)."""
        if nat is None:
            return self._merit(xs, task, penalty)
        merit, c = nat.merit(xs, penalty)
        return merit, None, c

    def _drop_fixed(self, g_con: np.ndarray, reach: np.ndarray, c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Leaves out the constraint rows no control can move (``reach``: each row's largest change over the control
        box), e.g. ``pz_1 = pz_0 + dt vz_0``: they only add a constant. Remembers them for :meth:`_fixed_rows`."""
        self._fixed = reach < 0.01 * self.feas_tol
        if self._fixed.any():
            keep = ~self._fixed
            return g_con[keep], c[keep]
        return g_con, c

    def _native_subproblem(self, nat: _native.NativeSQP, xs: np.ndarray, u: np.ndarray, c: np.ndarray,
                           penalty: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, float]:
        """:meth:`_subproblem` (with the Jacobians and sensitivities) by the C kernel."""
        hess, grad, g_con, reach, scale = nat.linearize(xs, u)
        if c.size:
            g_con, c = self._drop_fixed(g_con, reach, c)
            pen_c = np.full(c.size, penalty) if c.size else self._no_rows
        else:
            g_con, pen_c = self._no_g, self._no_rows
        return hess, grad, g_con, -c, pen_c, scale

    def _merit(self, xs: np.ndarray, task: ShootingTask, penalty: float) -> tuple[float, np.ndarray, np.ndarray]:
        """Merit (cost, norms smoothed + penalty * violation), residuals ``(T, k)``, constraint values."""
        r = xs[1:, task.res_idx] - task.target
        if task.n_cons:
            c, dqv = task.solver_violations(xs)
            self._last_dqv = (xs, dqv)  # _subproblem linearises at the point whose merit came last
        else:
            c = self._no_rows
        if r.shape[1] == 1:
            merit = float(np.abs(r).sum())
        else:
            merit = float(np.sqrt(np.einsum("ij,ij->i", r, r) + self.eps**2).sum())
        if c.size:
            merit += penalty * float(np.maximum(c, 0.0).sum())
        if not np.isfinite(merit):
            merit = float("inf")
        return merit, r, c

    def _sensitivities(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """``S[t] = dx_t/dU`` ``(T+1, n, T m)`` (``S[0] = 0``); columns beyond ``t m`` stay zero.

        The recursion ``S_{t+1} = A_t S_t + [0 .. B_t .. 0]`` stacked over t is ``(I - L) X = blockdiag(B_t)``
        with ``X = [S_1; ..; S_T]`` and ``-A_t`` in the block below the diagonal of row t: a unit lower
        triangular system, one BLAS ``trsm`` for small ``T n`` instead of T matrix products."""
        s, m = self._sens, self.m
        if self._tri is not None:
            mat, rhs, ia, ib = self._tri
            mat.flat[ia] = -a[1:].ravel()
            rhs.flat[ib] = b.ravel()
            s[1:] = _dtrsm(1.0, mat, rhs, lower=1, diag=1).reshape(s[1:].shape)
            return s
        for t in range(self.horizon):
            if t:
                np.matmul(a[t], s[t, :, : t * m], out=s[t + 1, :, : t * m])
            s[t + 1, :, t * m : (t + 1) * m] = b[t]
        return s

    def _subproblem(
        self, sens: np.ndarray, xs: np.ndarray, r: np.ndarray, c: np.ndarray, task: ShootingTask, penalty: float
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, float]:
        """Model of the step d: smooth part ``hess, grad``, elastic rows ``G d <= h`` priced ``pen`` and the
        curvature scale of the Levenberg-Marquardt term. For a scalar stage residual (exact l1 model) ``hess``
        is zero and ``G, h`` hold the state-constraint rows only: the stage rows are ``self._l1_rows``."""
        T, k = self.horizon, task.res_idx.size
        # (T, k, Tm); a scalar residual's (T, 1, Tm) as a view (no fancy-index copy)
        jac = sens[1:, task.res_idx[0] : task.res_idx[0] + 1, :] if k == 1 else sens[1:, task.res_idx, :]
        if task.n_cons:
            g_con = task.cons_sign[:, None] * sens[task.cons_t, task.cons_idx, :]
            if task.att_tol is not None:
                last = self._last_dqv
                dqv = last[1] if last is not None and last[0] is xs else task.solver_violations(xs)[1]
                assert dqv is not None
                g_con = np.vstack((g_con, dqv @ sens[task.horizon, list(task.att_qv), :]))
            g_con, c = self._drop_fixed(g_con, np.abs(g_con) @ (self._u_hi - self._u_lo), c)
        else:
            g_con = self._no_g
        pen_c = np.full(c.size, penalty) if c.size else self._no_rows
        if k == 1:
            # exact l1 model |r_t + J_t d| (one slack per stage in the QP), no smooth part; the damping scales
            # with the mean squared sensitivity of the residuals, the curvature a smooth model would have
            j1, r1 = jac[:, 0, :], r[:, 0]
            self._l1_rows = (j1, r1)
            self._l1_abs = float(np.abs(r1).sum())
            nu = j1.shape[1]
            scale = max(float(np.einsum("ij,ij->", j1, j1)) / nu, 1e-6)
            return self._zeros_hess, self._zeros_nu, g_con, -c, pen_c, scale
        f = np.sqrt(np.einsum("ij,ij->i", r, r) + self.eps**2)
        jf = jac.reshape(T * k, -1)
        v = np.einsum("tk,tkj->tj", r, jac)  # J_t' r_t
        grad = (v / f[:, None]).sum(0)
        # generalised Gauss-Newton: J' [(I - radial r r'/f^2) / f] J, the Hessian of the smoothed norm
        hess = (jf.T * np.repeat(1.0 / f, k)) @ jf - (v.T * (self.radial / f**3)) @ v
        scale = max(float(np.trace(hess)) / hess.shape[0], 1e-6)
        return hess, grad, g_con, -c, pen_c, scale

    def _l1_step(self, damp: float, lo: np.ndarray, hi: np.ndarray, g_mat: np.ndarray, h_vec: np.ndarray,
                 pen: np.ndarray) -> tuple[np.ndarray, float]:
        """The l1 model's step and its predicted decrease (stage rows ``self._l1_rows``, elastic rows ``G, h``,
        Hessian ``damp * I``: the Levenberg-Marquardt term alone)."""
        j1, r1 = self._l1_rows
        d: np.ndarray | None = None
        if self.qp_backend == "daqp":
            if self._l1qp is None or (self._l1qp.t, self._l1qp.k) != (r1.size, h_vec.size):
                self._l1qp = L1QP(j1.shape[1], r1.size, h_vec.size)
            self.stats["daqp_qp"] += 1
            d = self._l1qp.solve(damp, None, lo, hi, j1, r1, g_mat, h_vec, pen)
        if d is None:  # the numpy fallback (or DAQP failed): the same model as elastic rows, two per stage
            g_all = np.vstack((j1, -j1, g_mat))
            h_all = np.concatenate((-r1, r1, h_vec))
            pen_all = np.concatenate((np.ones(2 * r1.size), pen))
            self.stats["ipm_qp"] += 1
            d = solve_qp(damp * self._eye, self._zeros_nu, lo, hi, g_all, h_all, pen_all, backend="ipm").d
        pred = self._l1_abs - float(np.abs(r1 + np.dot(j1, d)).sum())
        if h_vec.size:
            pred += float(pen @ (np.maximum(-h_vec, 0.0) - np.maximum(g_mat @ d - h_vec, 0.0)))
        return d, pred

    def _l1_converged(self, damp: float, lo: np.ndarray, hi: np.ndarray, threshold: float) -> bool:
        """Whether the l1 model's step (stage rows ``self._l1_rows``, no elastic rows, Hessian ``damp * I``,
        box ``lo <= d <= hi``) provably predicts a decrease ``pred <= threshold``, without solving the QP.

        Weak duality with the multipliers ``lam = sign(r)``: for every d in the box, ``sum |r + J d| + damp/2 |d|^2
        >= lam'r + min_box(damp/2 |d|^2 + (J'lam)'d)``, so the model's optimal decrease (damping included) is
        ``D <= B = -min_box(damp/2 |d|^2 + v'd)`` with ``v = J'lam`` (separable: ``d = clip(-v / damp, lo, hi)``).
        Strong convexity gives ``damp/2 |d*|^2 <= D``, and the QP's ``pred = D + damp/2 |d*|^2 <= 2 B``. So
        ``2 B <= threshold`` means the QP would declare convergence. Cost: 7 numpy calls (a DAQP solve and its
        ``pred``: ~20). On the bench's friction problems it decides 134 of the 240 first QPs (of 176 that converge)."""
        j1, r1 = self._l1_rows
        v = np.dot(np.sign(r1), j1)
        d = np.minimum(np.maximum(v * (-1.0 / damp), lo), hi)
        bound = -(float(np.dot(d, v)) + 0.5 * damp * float(np.dot(d, d)))
        return 2.0 * bound <= threshold

    def _qp(
        self, hess: np.ndarray, grad: np.ndarray, lo: np.ndarray, hi: np.ndarray, g_mat: np.ndarray,
        h_vec: np.ndarray, pen: np.ndarray,
    ) -> np.ndarray:
        """The QP step. DAQP (when installed): the elastic QP directly (its active-set method handles the
        box-only case as fast as projected Newton). The numpy fallback: projected Newton on the box alone when
        that also satisfies the elastic rows (the state constraints are inactive), the interior point method
        otherwise."""
        if self.qp_backend == "daqp":
            self.stats["daqp_qp"] += 1
            return solve_qp(hess, grad, lo, hi, g_mat, h_vec, pen, backend="daqp").d
        if not self._ipm_first:
            box = solve_box_qp(hess, grad, lo, hi)
            self.stats["box_qp"] += 1
            if box.converged and (not h_vec.size or (g_mat @ box.d - h_vec).max() <= 1e-9):
                return box.d
        self.stats["ipm_qp"] += 1
        qp = solve_qp(hess, grad, lo, hi, g_mat, h_vec, pen, backend="ipm")
        # stay on the interior point method while a state constraint is (nearly) active
        self._ipm_first = bool((g_mat @ qp.d - h_vec).max() > -1e-6)
        return qp.d

    def _optimize(
        self, x0: np.ndarray, u0: np.ndarray, task: ShootingTask, xs0: np.ndarray | None = None
    ) -> tuple[np.ndarray, int, bool, str, np.ndarray | None]:
        start = time.perf_counter()
        self.stats = dict.fromkeys(("iterations", "box_qp", "ipm_qp", "daqp_qp", "rollouts", "jacobians", "certified"),
                                   0)
        stage_rows = task.res_idx.size == 1
        penalty = self.penalty
        u = u0.copy()
        nat = self._native_for(task)
        if nat is not None:
            nat.set_target(task.target, self.eps)
            xs = nat.rollout(x0, u) if xs0 is None else xs0
        else:
            xs = self.rollout(x0, u) if xs0 is None else xs0
        merit, r, c = self._merit_of(nat, xs, task, penalty)
        if not np.isfinite(merit):
            raise FloatingPointError("the warm start's prediction is not finite")
        rho = self._rho
        msg, converged = "max_iter", False
        it = 0
        # the Jacobians along xs: from the activation pattern of the batched rollout that predicted it when
        # that rollout was fused (src = its batch size and sequence), else by NumpyDynamics.jacobians
        fused_jac = getattr(self.dyn, "fused_jacobians", None) if getattr(self.dyn, "fused_rollout", False) else None
        src = self._start_src if xs0 is not None else None
        for it in range(1, self.max_iter + 1):  # noqa: B007
            self.stats["jacobians"] += 1
            if nat is not None:
                hess, grad, g_mat, h_vec, pen, scale = self._native_subproblem(nat, xs, u, c, penalty)
            else:
                ab = fused_jac(src[0], self.horizon, src[1], src[2]) if fused_jac is not None and src is not None \
                    else None
                a, b = ab if ab is not None else self.dyn.jacobians(xs[:-1], u)
                assert r is not None
                sens = self._sensitivities(a, b)
                hess, grad, g_mat, h_vec, pen, scale = self._subproblem(sens, xs, r, c, task, penalty)
            lo, hi = self._u_lo - u.reshape(-1), self._u_hi - u.reshape(-1)
            rows0 = float(pen @ np.maximum(-h_vec, 0.0)) if h_vec.size else 0.0
            accepted = False
            undamped_tried = False
            while True:
                if (stage_rows and it == 1 and not h_vec.size and not (self.undamped_check and rho > self.rho0)
                        and self._l1_converged(rho * scale + self.lm_floor, lo, hi, self.tol * (1.0 + abs(merit)))):
                    # the first linearisation of a solve (often the previous plan, converged already): a dual bound
                    # proves the QP would predict too little, so the QP is not solved
                    self.stats["certified"] += 1
                    converged = True
                    break
                if stage_rows:  # exact l1 model: no smooth part beyond the damping
                    d, pred = self._l1_step(rho * scale + self.lm_floor, lo, hi, g_mat, h_vec, pen)
                else:
                    d = self._qp(hess + (rho * scale + self.lm_floor) * self._eye, grad, lo, hi, g_mat, h_vec, pen)
                    pred = (-(grad @ d + 0.5 * d @ hess @ d) + rows0
                            - float(pen @ np.maximum(g_mat @ d - h_vec, 0.0)))
                if pred <= self.tol * (1.0 + abs(merit)):
                    if self.undamped_check and rho > self.rho0 and not undamped_tried:
                        undamped_tried = True
                        # a heavily damped step predicts little even far from a stationary point (flat
                        # valleys): only the (nearly) undamped model may declare convergence
                        rho = self.rho0
                        continue
                    converged = True
                    break
                alpha, accepted, trial = self._line_search(x0, u, d, merit, pred, task, penalty, nat)
                merit_new = trial[2]
                if self.trace is not None:
                    self.trace.append((it, round(merit, 5), round(pred, 6), round(merit - merit_new, 6),
                                       alpha if accepted else 0.0, round(float(np.abs(d).max()), 3), rho, penalty))
                if accepted:
                    ratio = (merit - merit_new) / pred
                    if alpha == 1.0 and ratio > 0.75:
                        rho = max(rho / 4.0, 1e-9)
                    elif alpha < 1.0 or ratio < 0.25:
                        rho *= max(2.0, self.shrink / alpha)
                    break
                rho = max(rho, 1e-3) * 10.0
                if rho > 1e3:
                    msg = "line search failed"
                    break
            if converged:
                movable = c[~self._fixed] if c.size else c
                viol = float(np.maximum(movable, 0.0).max()) if movable.size else 0.0
                if viol > self.feas_tol and penalty < self.penalty_max:
                    # converged to a point that still violates a constraint: make violations dearer, go on
                    penalty *= 10.0
                    merit, r, c = self._merit_of(nat, xs, task, penalty)
                    converged = False
                    continue
                msg = "converged"
                break
            if not accepted:
                break
            u, xs, merit, r, c = trial
            src = self._trial_src
            if self.max_time is not None and time.perf_counter() - start > self.max_time:
                msg = "time budget"
                break
        self._rho = rho
        self.stats["iterations"] = it
        return u, it, converged, msg, xs

    def _line_search(self, x0: np.ndarray, u: np.ndarray, d: np.ndarray, merit: float, pred: float,
                     task: ShootingTask, penalty: float, nat: _native.NativeSQP | None = None,
                     ) -> tuple[float, bool, _Trial]:
        """Backtracking along the QP step ``d`` (T m,) from ``u`` (T, m) on the l1 merit (Armijo on the predicted
        decrease ``pred``) over the step lengths :data:`_ALPHAS`: the last step length tried, whether it was
        accepted, and its trial point.

        With a fused batched rollout (:attr:`NumpyDynamics.fused_rollout`: a linear base model or none, and a
        network) all step lengths are rolled out in ONE batched call, which costs about as much as one
        sequence; the merits are then taken in order, so the accepted point is the sequential search's. With the C
        kernel (``nat``) the sequential search runs there."""
        T, m = self.horizon, self.m
        if nat is not None:
            self._trial_src = None
            i, (u_new, xs_new, merit_new, c_new) = nat.line_search(x0, u, d, _ALPHAS, merit, pred, penalty)
            self.stats["rollouts"] += i + 1 if i >= 0 else len(_ALPHAS)
            return _ALPHAS[i], i >= 0, (u_new, xs_new, merit_new, None, c_new)
        if getattr(self.dyn, "fused_rollout", False):
            u_all = u[None] + self._alphas * d.reshape(1, T, m)
            xs_all = self.dyn.rollout_batch(x0, u_all)
            self.stats["rollouts"] += 1
            for i, alpha in enumerate(_ALPHAS):
                u_new, xs_new = u_all[i], xs_all[i]
                merit_new, r_new, c_new = self._merit(xs_new, task, penalty)
                if merit_new <= merit - 1e-4 * alpha * pred:
                    self._trial_src = (len(_ALPHAS), i, self.dyn.fused_calls)
                    return alpha, True, (u_new, xs_new, merit_new, r_new, c_new)
            self._trial_src = None
            return alpha, False, (u_new, xs_new, merit_new, r_new, c_new)
        self._trial_src = None
        for alpha in _ALPHAS:
            u_new = u + alpha * d.reshape(T, m)
            xs_new = self.rollout(x0, u_new)
            self.stats["rollouts"] += 1
            merit_new, r_new, c_new = self._merit(xs_new, task, penalty)
            if merit_new <= merit - 1e-4 * alpha * pred:
                return alpha, True, (u_new, xs_new, merit_new, r_new, c_new)
        return alpha, False, (u_new, xs_new, merit_new, r_new, c_new)
