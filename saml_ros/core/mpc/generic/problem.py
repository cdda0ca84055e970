"""The optimal control problem of a system file's ``mpc:`` section, as numbers (:class:`GenericProblem`).

Over the controls ``U = (u_0 .. u_{T-1})`` from the current state ``x_0``, with ``x_{t+1} = f(x_t, u_t)``:

    min  sum_{t=1..T-1} ||x_t[g] - r_t||^2_{W_stage} + ||x_T[g] - r_T||^2_{W_terminal}
         + sum_t ||u_t||^2_{W_effort} + sum_t ||u_t - u_{t-1}||^2_{W_rate}        (u_{-1}: the last command sent)
    s.t. u_low <= u_t <= u_high                                                      (hard)
         c_j(x_t) <= 0,  t = 1..T                                                    (soft: + penalty * max(c, 0))

With ``cost.norm`` each step's goal term is the weighted distance instead, ``sqrt(||x_t[g] - r_t||^2_W + eps^2)``
(the paper's quadrotor cost; the SQP models it with its exact Hessian through the linearisation, generalised
Gauss-Newton). A constraint with ``at: terminal`` binds x_T only (its rows at t < T read -1: never active).
``g`` are the goal fields, ``r_t`` the goal (a setpoint, the same at every step) or the reference trajectory;
an angle field's goal is unwrapped relative to the current state (and each reference point relative to the one
before), so the plan turns the short way round. The cost is a sum of squared residuals (:meth:`residuals`), which
the SQP linearises (Gauss-Newton). Constraint rows (:meth:`constraints`): a box ``low - x[i] <= 0``,
``x[i] - high <= 0`` (m, or the field's unit), a norm ``||x[I]|| - max <= 0``, a keep-out region
``r_min (1 - ||(x[I] - c) / r||) <= 0`` (in units of the smallest radius, so a violation reads as a depth).
"""

from __future__ import annotations

import math

import numpy as np

from saml_ros.core.mpc.generic.dynamics import wrap_angle
from saml_ros.core.mpc.generic.section import MPCTask, StateConstraint


class GenericProblem:
    """The problem of ``task`` over horizon ``horizon`` (default the task's) for ``n`` states and ``m`` controls."""

    def __init__(self, task: MPCTask, n: int, m: int, horizon: int | None = None) -> None:
        self.task = task
        self.T = T = int(task.horizon if horizon is None else horizon)
        if T < 1:
            raise ValueError(f"horizon must be >= 1, got {T}")
        self.n, self.m = n, m
        self.g_idx = np.asarray(task.goal_idx, dtype=int)
        self.k = self.g_idx.size
        self.g_angle = np.asarray(task.goal_angle, dtype=bool)
        sw = np.tile(np.sqrt(task.w_stage), (T, 1))
        sw[-1] = np.sqrt(task.w_terminal)
        #: square roots of the state weights, ``(T, k)`` for x_1 .. x_T
        self.sw = sw
        self.u_low, self.u_high = task.u_low.astype(np.float64), task.u_high.astype(np.float64)
        # control residuals: effort rows sqrt(w_e) u_t, rate rows sqrt(w_r) (u_t - u_{t-1}); constant Jacobian
        se, sr = np.sqrt(task.w_effort), np.sqrt(task.w_rate)
        ie, ir = np.flatnonzero(se), np.flatnonzero(sr)
        rows: list[np.ndarray] = []
        for t in range(T):
            for i in ie:
                r = np.zeros(T * m)
                r[t * m + i] = se[i]
                rows.append(r)
        self._n_effort = len(rows)
        for t in range(T):
            for i in ir:
                r = np.zeros(T * m)
                r[t * m + i] = sr[i]
                if t > 0:
                    r[(t - 1) * m + i] = -sr[i]
                rows.append(r)
        #: the control residuals' Jacobian ``(R_u, T m)`` and the first step's rate rows (their u_{-1} term)
        self.ju = np.array(rows).reshape(len(rows), T * m)
        self._rate0 = [(self._n_effort + j, int(i), float(sr[i])) for j, i in enumerate(ir)]
        # constraint rows per step
        self.cons = task.constraints
        self.rows_per_step = sum(c.rows for c in self.cons)
        self.row_names: list[str] = []
        for c in self.cons:
            if c.kind == "box":
                for fi, lo, hi in zip(c.idx, c.low, c.high, strict=True):
                    name = task.state_names[fi] if task.state_names else str(fi)
                    if math.isfinite(lo):
                        self.row_names.append(f"{c.name} ({name} >= {lo:g})")
                    if math.isfinite(hi):
                        self.row_names.append(f"{c.name} ({name} <= {hi:g})")
            else:
                self.row_names.append(c.name)
        # the rows as arrays (constraints() and constraint_jac() are called several times per SQP iteration):
        # box rows sign * x[i] - bound, the others (norm, keep-out) computed per constraint; their columns
        box_col: list[int] = []
        box_idx: list[int] = []
        box_sign: list[float] = []
        box_bound: list[float] = []
        other: list[tuple[int, StateConstraint]] = []
        term: list[int] = []
        col = 0
        for c in self.cons:
            first = col
            if c.kind == "box":
                for fi, lo, hi in zip(c.idx, c.low, c.high, strict=True):
                    for ok, sign, bound in ((math.isfinite(lo), -1.0, -lo), (math.isfinite(hi), 1.0, hi)):
                        if ok:
                            box_col.append(col)
                            box_idx.append(int(fi))
                            box_sign.append(sign)
                            box_bound.append(bound)
                            col += 1
            else:
                other.append((col, c))
                col += 1
            if c.terminal:
                term.extend(range(first, col))
        self._box = (np.asarray(box_col, dtype=np.intp), np.asarray(box_idx, dtype=np.intp),
                     np.asarray(box_sign, dtype=np.float64), np.asarray(box_bound, dtype=np.float64))
        self._other = other
        #: rows of terminal constraints before T read -1 (never active); their Jacobian is zero there
        self._early = np.zeros((T, self.rows_per_step), dtype=bool)
        self._early[:-1, term] = True
        jac0 = np.zeros((T, self.rows_per_step, n))
        jac0[:, self._box[0], self._box[1]] = self._box[2]
        jac0[self._early] = 0.0
        self._jac0 = jac0

    @property
    def n_cons(self) -> int:
        """Constraint rows of a whole plan (``rows_per_step * T``)."""
        return self.rows_per_step * self.T

    # ------------------------------------------------------------------------------------------ goal
    def reference(self, x0: np.ndarray, goal: np.ndarray | None) -> np.ndarray:
        """The goal of x_1 .. x_T, ``(T, k)``: ``goal`` ``(k,)`` (a setpoint; None = the task's default) or
        ``(T, k)`` (a reference trajectory), with angle fields unwrapped (see the module docstring)."""
        g = self.task.goal_default if goal is None else np.asarray(goal, dtype=np.float64)
        ref = np.tile(g, (self.T, 1)) if g.ndim == 1 else np.array(g, dtype=np.float64, copy=True)
        if ref.shape != (self.T, self.k):
            raise ValueError(f"goal must have shape ({self.k},) or ({self.T}, {self.k}), got {g.shape}")
        if self.g_angle.any():
            a = ref[:, self.g_angle]
            prev = np.vstack([x0[self.g_idx[self.g_angle]][None], a[:-1]])
            ref[:, self.g_angle] = x0[self.g_idx[self.g_angle]] + np.cumsum(wrap_angle(a - prev), axis=0)
        return ref

    # ------------------------------------------------------------------------------------------ cost
    def state_residuals(self, xs: np.ndarray, ref: np.ndarray) -> np.ndarray:
        """``sqrt(W) (x_t[g] - r_t)`` for t = 1..T: ``(T, k)`` (``xs`` ``(T+1, n)``)."""
        return self.sw * (xs[1:, self.g_idx] - ref)

    def control_residuals(self, us: np.ndarray, u_prev: np.ndarray | None) -> np.ndarray:
        """The effort and rate residuals ``(R_u,)`` (``us (T, m)``; ``u_prev``: the last command, or None: no rate
        term for u_0)."""
        r = self.ju @ us.reshape(-1)
        if u_prev is not None:
            for row, i, s in self._rate0:
                r[row] -= s * u_prev[i]
        return r

    def cost(self, xs: np.ndarray, us: np.ndarray, ref: np.ndarray, u_prev: np.ndarray | None,
             exact: bool = False) -> float:
        """The objective (see the module docstring) of a plan; ``exact``: a norm cost without its smoothing."""
        rx = self.state_residuals(xs, ref)
        ru = self.control_residuals(us, u_prev)
        if self.task.norm_cost:
            eps2 = 0.0 if exact else self.task.norm_eps ** 2
            return float(np.sqrt(np.einsum("ij,ij->i", rx, rx) + eps2).sum() + ru @ ru)
        return float(np.einsum("ij,ij->", rx, rx) + ru @ ru)

    # ------------------------------------------------------------------------------------------ constraints
    def constraints(self, xs: np.ndarray) -> np.ndarray:
        """``c(x_t) (T, rows_per_step)`` for t = 1..T (> 0 = violated), ``xs`` ``(T+1, n)`` or ``(..., T+1, n)``."""
        x = xs[..., 1:, :]
        out = np.empty((*x.shape[:-1], self.rows_per_step))
        if not self.rows_per_step:
            return out
        cols, idx, sign, bound = self._box
        if cols.size:
            out[..., cols] = sign * x[..., idx] - bound
        for col, c in self._other:
            if c.kind == "norm":
                v = x[..., list(c.idx)]
                out[..., col] = np.sqrt(np.einsum("...i,...i->...", v, v)) - c.max
            else:
                rad = np.asarray(c.radius)
                z = (x[..., list(c.idx)] - np.asarray(c.center)) / rad
                out[..., col] = rad.min() * (1.0 - np.sqrt(np.einsum("...i,...i->...", z, z)))
        out[..., self._early] = -1.0
        return out

    def constraint_jac(self, xs: np.ndarray) -> np.ndarray:
        """``d c(x_t) / d x_t``: ``(T, rows_per_step, n)`` (a norm at 0 and a keep-out centre take a fixed
        direction)."""
        if not self._other:
            return self._jac0.copy()
        out = self._jac0.copy()
        for r, c in self._other:
            idx = list(c.idx)
            x = xs[-1:] if c.terminal else xs[1:]  # a terminal row's Jacobian before T is zero
            if c.kind == "norm":
                v = x[:, idx]
                nrm = np.linalg.norm(v, axis=-1, keepdims=True)
                out[-x.shape[0]:, r, idx] = np.where(nrm > 1e-12, v / np.maximum(nrm, 1e-12), 0.0)
            else:
                rad = np.asarray(c.radius)
                z = (x[:, idx] - np.asarray(c.center)) / rad
                nrm = np.linalg.norm(z, axis=-1, keepdims=True)
                unit = np.where(nrm > 1e-12, z / np.maximum(nrm, 1e-12), np.eye(len(idx))[0])
                out[-x.shape[0]:, r, idx] = -rad.min() * unit / rad
        return out

    def violation_names(self) -> list[str]:
        """A name per constraint value of a whole plan, in :meth:`constraints`' order flattened (t major)."""
        return [f"{name} at step {t}" for t in range(1, self.T + 1) for name in self.row_names]
