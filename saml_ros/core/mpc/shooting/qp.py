"""Small dense convex QP solvers for the SQP subproblems (tens of variables).

* :func:`solve_box_qp`: ``min 1/2 d'Hd + g'd  s.t.  lo <= d <= hi`` by projected Newton (Bertsekas 1982):
  a Newton step on the free variables, then a projected backtracking line search. Usually 1-4 iterations.
* :func:`solve_qp`: the same with general inequalities ``G d <= h`` in elastic mode: every general row gets a
  slack ``s >= 0`` (``G d - s <= h``) priced ``penalty * sum(s)``, so the subproblem is always feasible even
  when the linearised state constraints are not. Two backends solve the same problem:

  - ``"daqp"`` (default when the ``daqp`` package is installed): DAQP, a dual active-set solver in C
    (Arnström, Bemporad, Axehill 2022). With ``hard_first`` it first solves the QP with the rows as hard
    constraints, which is the elastic solution whenever it is feasible and no row's multiplier exceeds its
    price (exact-penalty property of the l1 penalty); otherwise it solves the elastic QP over ``[d, s]``
    (zero Hessian block on ``s``: DAQP regularises it by proximal-point iterations). 20-170 us on the
    SQP subproblems here, against 0.4-0.7 ms for the interior point method.
  - ``"ipm"``: Mehrotra's predictor-corrector interior point method on the dense normal equations (one
    Cholesky per iteration), pure numpy; the fallback without ``daqp`` and whenever DAQP reports a failure.

* :class:`L1QP`: the exact l1 model of a scalar stage cost (friction), ``min 1/2 d'Hd + g'd + sum_t |r_t + j_t d|
  + pen' max(G d - h, 0)  s.t.  lo <= d <= hi``, by DAQP with ONE slack per stage (``-s_t <= r_t + j_t d <= s_t``)
  instead of one per elastic row, in one DAQP workspace (``daqp.Model``) kept between calls and warm-started from
  the previous active set: 20 instead of 30 variables at T = 10, 7 us instead of 23-35 us per QP.

``H`` must be symmetric positive definite (the SQP adds a Levenberg-Marquardt term).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.linalg.lapack import dpotrf as _dpotrf
from scipy.linalg.lapack import dpotrs as _dpotrs

try:
    import daqp as _daqp
except ImportError:  # optional: the numpy interior point method solves the same problems, ~5-10x slower
    _daqp = None

#: the backend :func:`solve_qp` uses by default: "daqp" when installed, else "ipm"
DEFAULT_BACKEND = "daqp" if _daqp is not None else "ipm"
_INF = 1e30  # DAQP's "no bound"


@dataclass
class QPResult:
    d: np.ndarray  #: primal solution, shape (n,)
    slack: np.ndarray  #: elastic slacks of the general rows (>= 0), shape (k,); empty for box QPs
    mult: np.ndarray  #: multipliers of the general rows, shape (k,); empty for box QPs
    iterations: int
    converged: bool


def solve_box_qp(
    hess: np.ndarray, grad: np.ndarray, lo: np.ndarray, hi: np.ndarray, max_iter: int = 30, tol: float = 1e-10
) -> QPResult:
    """``min 1/2 d'Hd + g'd  s.t.  lo <= d <= hi`` (``lo <= hi``); shapes ``(n, n), (n,)``.

    Projected Newton: each iteration takes a Newton step on the variables not held at a bound by their
    gradient, then a projected Armijo backtracking; when that fails (the projected Newton step is not a
    descent direction), an exact projected-gradient (Cauchy) step instead.
    """
    d = np.clip(np.zeros_like(grad), lo, hi)
    f = 0.5 * d @ hess @ d + grad @ d
    gscale = tol * (1.0 + np.abs(grad).max())
    it = 0
    converged = False
    for it in range(1, max_iter + 1):  # noqa: B007
        gr = hess @ d + grad
        clamped = ((d <= lo) & (gr > 0.0)) | ((d >= hi) & (gr < 0.0))
        free = ~clamped
        if not free.any() or np.abs(gr[free]).max() <= gscale:
            converged = True
            break
        step = np.zeros_like(d)
        hff = hess[np.ix_(free, free)]
        chol, info = _dpotrf(hff, lower=1, clean=0)
        if info != 0:
            raise np.linalg.LinAlgError(f"box QP: Hessian not positive definite (dpotrf info={info})")
        step[free] = -_dpotrs(chol, gr[free], lower=1)[0]
        alpha = 1.0
        for _ in range(20):
            cand = np.clip(d + alpha * step, lo, hi)
            fc = 0.5 * cand @ hess @ cand + grad @ cand
            if fc <= f + 1e-4 * (gr @ (cand - d)):
                break
            alpha *= 0.5
        else:
            # Cauchy step along the projected gradient (exact minimiser of the quadratic on that ray)
            sg = np.where(free, -gr, 0.0)
            curv = float(sg @ hess @ sg)
            cand = np.clip(d + (float(sg @ sg) / curv) * sg, lo, hi)
            fc = 0.5 * cand @ hess @ cand + grad @ cand
            if fc >= f:
                break
        moved = np.abs(cand - d).max()
        d, f = cand, fc
        if moved <= 1e-14 * (1.0 + np.abs(d).max()):
            converged = True
            break
    empty = np.zeros(0)
    return QPResult(d, empty, empty, it, converged)


def solve_qp(
    hess: np.ndarray,
    grad: np.ndarray,
    lo: np.ndarray,
    hi: np.ndarray,
    g_mat: np.ndarray,
    h_vec: np.ndarray,
    penalty: float | np.ndarray,
    max_iter: int = 40,
    tol: float = 1e-8,
    backend: str | None = None,
    hard_first: bool = True,
) -> QPResult:
    """Elastic QP ``min 1/2 d'Hd + g'd + penalty's  s.t.  lo <= d <= hi, G d - s <= h, s >= 0``.

    Shapes: ``hess (n, n)``, ``grad, lo, hi (n,)`` (finite), ``g_mat (k, n)``, ``h_vec (k,)``, ``penalty``
    a positive scalar or ``(k,)``. With ``H = 0`` on a block this also solves exact l1 (LP) models:
    ``|a + b'd| = min s1 + s2  s.t.  b'd - s1 <= -a, -b'd - s2 <= a``.

    ``backend``: ``"daqp"``, ``"ipm"`` or None (:data:`DEFAULT_BACKEND`); ``max_iter`` and ``tol`` are the
    interior point method's. ``hard_first`` (DAQP only): try the rows as hard constraints first; pass False
    when they are known to be violated at the solution (l1 cost rows), which saves a doomed attempt.
    """
    if h_vec.size == 0:
        return solve_box_qp(hess, grad, lo, hi)
    if (backend or DEFAULT_BACKEND) == "daqp":
        if _daqp is None:
            raise ValueError("QP backend 'daqp' requested but the daqp package is not installed (pip install daqp)")
        res = _solve_qp_daqp(hess, grad, lo, hi, g_mat, h_vec, penalty, hard_first)
        if res is not None:
            return res
    elif backend not in (None, "ipm"):
        raise ValueError(f"unknown QP backend {backend!r}; use 'daqp' or 'ipm'")
    return _solve_qp_ipm(hess, grad, lo, hi, g_mat, h_vec, penalty, max_iter, tol)


class L1QP:
    """The l1 step model (see the module docstring) for ``n`` controls, ``t`` stage residuals and ``k`` elastic
    rows, solved by DAQP over ``z = [d (n), s (t), e (k)]``: rows ``j d - s <= -r``, ``-j d - s <= r``,
    ``G d - e <= h``; bounds ``lo <= d <= hi``, ``e >= 0`` (``s >= |r + j d|`` follows from the rows); cost
    ``1/2 d'Hd + g'd + sum(s) + pen' e``. The matrices are allocated once and refilled per call; the DAQP
    workspace is set up once and updated per call, so each solve starts from the previous active set (the
    optimum is the same: the problem is strictly convex in d, and s is fixed by d)."""

    def __init__(self, n: int, t: int, k: int) -> None:
        if _daqp is None:
            raise ValueError("L1QP needs the daqp package (pip install daqp)")
        self.n, self.t, self.k = n, t, k
        nz = n + t + k
        self._h = np.zeros((nz, nz))
        self._f = np.zeros(nz)
        self._f[n : n + t] = 1.0
        self._a = np.zeros((2 * t + k, nz))
        self._a[:t, n : n + t] = -np.eye(t)
        self._a[t : 2 * t, n : n + t] = -np.eye(t)
        self._a[2 * t :, n + t :] = -np.eye(k)
        self._bu = np.full(nz + 2 * t + k, _INF)
        self._bl = np.full(nz + 2 * t + k, -_INF)
        self._bl[n + t : nz] = 0.0
        # views refilled per call, made once (a slice costs ~0.2 us in numpy 2.4, as much as a small copy)
        h, a, bu, bl = self._h, self._a, self._bu, self._bl
        self._h_dd = h[:n, :n]
        self._h_diag = h.reshape(-1)[: n * (nz + 1) : nz + 1]  # the d block's diagonal
        self._f_d, self._f_e = self._f[:n], self._f[n + t :]
        self._a_j, self._a_mj, self._a_g = a[:t, :n], a[t : 2 * t, :n], a[2 * t :, :n]
        self._bu_d, self._bl_d = bu[:n], bl[:n]
        self._bu_mr, self._bu_r, self._bu_h = bu[nz : nz + t], bu[nz + t : nz + 2 * t], bu[nz + 2 * t :]
        self._f_zero = True  # the cost vector's d block is zero (no gradient) and the workspace has it so
        self._damp: float | None = None  # the scalar Hessian ``damp * I`` the workspace holds, if it holds one
        self._model: Any = None  # the DAQP workspace, set up on the first solve

    def solve(
        self, hess: np.ndarray | float, grad: np.ndarray | None, lo: np.ndarray, hi: np.ndarray, j: np.ndarray,
        r: np.ndarray, g_mat: np.ndarray, h_vec: np.ndarray, pen: np.ndarray,
    ) -> np.ndarray | None:
        """The step ``d`` ``(n,)`` (clipped to the box), or None if DAQP fails. Shapes: ``hess (n, n)`` or a float
        ``c`` for ``c I`` (the SQP's damping alone: the workspace's Hessian is then refreshed only when c changes),
        ``grad, lo, hi (n,)`` (``grad`` None: zero), ``j (t, n)``, ``r (t,)``, ``g_mat (k, n)``, ``h_vec, pen (k,)``."""
        assert _daqp is not None
        new_h = True
        if isinstance(hess, float):
            if hess == self._damp:
                new_h = False
            else:
                if self._damp is None:
                    self._h_dd.fill(0.0)
                self._h_diag.fill(hess)
                self._damp = hess
        else:
            self._h_dd[...] = hess
            self._damp = None
        if grad is None:
            new_f = not self._f_zero
            if new_f:
                self._f_d.fill(0.0)
            self._f_zero = True
        else:
            self._f_d[...] = grad
            self._f_zero, new_f = False, True
        np.copyto(self._a_j, j)
        np.negative(j, out=self._a_mj)
        np.copyto(self._bu_d, hi)
        np.copyto(self._bl_d, lo)
        np.negative(r, out=self._bu_mr)
        np.copyto(self._bu_r, r)
        if self.k:
            new_f = True
            self._f_e[...] = pen
            self._a_g[...] = g_mat
            self._bu_h[...] = h_vec
        if self._model is None:
            self._model = _daqp.Model()
            self._model.setup(self._h, self._f, self._a, self._bu, self._bl)
        else:
            self._model.update(H=self._h if new_h else None, f=self._f if new_f else None, A=self._a,
                               bupper=self._bu, blower=self._bl)
        x, _, flag, _ = self._model.solve()
        if flag != 1:
            self._model = None  # start the next solve from a fresh workspace
            return None
        d = np.maximum(x[: self.n], lo)
        return np.minimum(d, hi, out=d)


def _solve_qp_daqp(
    hess: np.ndarray, grad: np.ndarray, lo: np.ndarray, hi: np.ndarray, g_mat: np.ndarray, h_vec: np.ndarray,
    penalty: float | np.ndarray, hard_first: bool,
) -> QPResult | None:
    """:func:`solve_qp` by DAQP; None if DAQP fails (the caller falls back to the interior point method)."""
    assert _daqp is not None
    n, k = grad.size, h_vec.size
    # the SQP passes its prices as a float64 array of k already: np.broadcast_to's wrapper cost 10 us a call
    if isinstance(penalty, np.ndarray) and penalty.shape == (k,) and penalty.dtype == np.float64:
        pen = penalty
    else:
        pen = np.broadcast_to(np.asarray(penalty, dtype=np.float64), (k,))
    g_mat = np.ascontiguousarray(g_mat, dtype=np.float64)
    if hard_first:
        x, _, flag, info = _daqp.solve(
            np.ascontiguousarray(hess), np.ascontiguousarray(grad), g_mat,
            np.concatenate((hi, h_vec)), np.concatenate((lo, np.full(k, -_INF))),
        )  # fmt: skip
        if flag == 1:
            lam = np.asarray(info["lam"])[n:]
            if (lam <= pen * (1.0 + 1e-9)).all():  # np.clip = maximum then minimum, without its wrapper
                return QPResult(np.minimum(np.maximum(x, lo), hi), np.zeros(k), np.maximum(lam, 0.0),
                                int(info["iterations"]), True)
    # elastic: z = [d, s], rows lo <= d <= hi, 0 <= s, G d - s <= h
    h_full = np.zeros((n + k, n + k))
    h_full[:n, :n] = hess
    a_mat = np.empty((k, n + k))
    a_mat[:, :n] = g_mat
    a_mat[:, n:] = -np.eye(k)
    x, _, flag, info = _daqp.solve(
        h_full, np.concatenate((grad, pen)), a_mat,
        np.concatenate((hi, np.full(k, _INF), h_vec)), np.concatenate((lo, np.zeros(k), np.full(k, -_INF))),
    )  # fmt: skip
    if flag != 1:
        return None
    lam = np.asarray(info["lam"])[n + k :]
    return QPResult(np.clip(x[:n], lo, hi), np.maximum(x[n:], 0.0), np.maximum(lam, 0.0),
                    int(info["iterations"]), True)


def _solve_qp_ipm(
    hess: np.ndarray,
    grad: np.ndarray,
    lo: np.ndarray,
    hi: np.ndarray,
    g_mat: np.ndarray,
    h_vec: np.ndarray,
    penalty: float | np.ndarray,
    max_iter: int = 40,
    tol: float = 1e-8,
) -> QPResult:
    """:func:`solve_qp` by the interior point method."""
    n, k = grad.size, h_vec.size
    nz = n + k
    pen = np.broadcast_to(np.asarray(penalty, dtype=np.float64), (k,))
    q = np.concatenate((grad, pen))
    c_mat, c_vec = _elastic_rows(lo, hi, g_mat, h_vec)
    c_t = np.ascontiguousarray(c_mat.T)
    g_rows = c_mat[2 * n : 2 * n + k]
    m = c_vec.size
    z = np.zeros(nz)
    z[:n] = np.clip(0.0, lo, hi)
    z[n:] = np.maximum(g_mat @ z[:n] - h_vec, 0.0) + 1.0
    # slacks and multipliers in one array, so that one call finds the step to the boundary of both
    sl = np.empty(2 * m)
    s, lam = sl[:m], sl[m:]
    s[:] = np.maximum(c_vec - c_mat @ z, 1.0)
    lam[:] = 1.0
    # the elastic pair (G d - s <= h, -s <= 0) has multipliers summing to `penalty` at the solution
    lam[2 * n : 2 * n + k] = 0.5 * pen
    lam[2 * n + k :] = 0.5 * pen
    dsl = np.empty(2 * m)
    ds, dlam = dsl[:m], dsl[m:]
    kkt0 = np.zeros((nz, nz))
    kkt0[:n, :n] = hess
    diag = np.arange(nz)
    wd = np.empty(nz)
    scale = 1.0 + max(np.abs(grad).max(), np.abs(c_vec).max())  # not the penalty: it can be huge
    stop = tol * scale
    converged = False
    it = 0
    for it in range(1, max_iter + 1):  # noqa: B007
        r_d = kkt0 @ z + q + c_t @ lam
        r_p = c_mat @ z + s - c_vec
        mu = (s @ lam) / m
        if mu <= stop and np.abs(r_d).max() <= stop and np.abs(r_p).max() <= stop:
            converged = True
            break
        w = lam / s
        # C' W C without the dense product: the bound rows only touch the diagonal
        kkt = (g_rows.T * w[2 * n : 2 * n + k]) @ g_rows
        kkt += kkt0
        wd[:n] = w[:n] + w[n : 2 * n] + 1e-12
        wd[n:] = w[2 * n + k :]
        kkt[diag, diag] += wd
        chol, info = _dpotrf(kkt, lower=1, clean=0, overwrite_a=1)
        if info != 0:
            raise np.linalg.LinAlgError(f"QP: KKT matrix not positive definite (dpotrf info={info})")
        r_dw = -r_d - c_t @ (w * r_p)
        # predictor (affine scaling), then Mehrotra's corrector with the same factorisation
        dz = _dpotrs(chol, r_dw + c_t @ lam, lower=1)[0]
        dlam[:] = w * (c_mat @ dz + r_p) - lam
        ds[:] = -s - s * dlam / lam
        a_aff = _max_step(sl, dsl)
        mu_aff = ((s + a_aff * ds) @ (lam + a_aff * dlam)) / m
        sigma = (mu_aff / mu) ** 3
        r_c = s * lam + ds * dlam - sigma * mu
        r_cs = r_c / s
        dz = _dpotrs(chol, r_dw + c_t @ r_cs, lower=1)[0]
        dlam[:] = w * (c_mat @ dz + r_p) - r_cs
        ds[:] = -(r_c + s * dlam) / lam
        alpha = min(1.0, 0.99 * _max_step(sl, dsl))
        z += alpha * dz
        sl += alpha * dsl
    d = np.clip(z[:n], lo, hi)
    return QPResult(d, np.maximum(z[n:], 0.0), lam[2 * n : 2 * n + k].copy(), it, converged)


def _elastic_rows(
    lo: np.ndarray, hi: np.ndarray, g_mat: np.ndarray, h_vec: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The interior point method's rows ``C z <= c`` over ``z = [d (n), s (k)]``: ``d <= hi``, ``-d <= -lo``,
    ``G d - s <= h``, ``-s <= 0``; ``C (2n + 2k, n + k)``, ``c (2n + 2k,)``."""
    n, k = lo.size, h_vec.size
    c_mat = np.zeros((2 * n + 2 * k, n + k))
    ar_n = np.arange(n)
    ar_k = np.arange(k)
    c_mat[ar_n, ar_n] = 1.0
    c_mat[n + ar_n, ar_n] = -1.0
    c_mat[2 * n : 2 * n + k, :n] = g_mat
    c_mat[2 * n + ar_k, n + ar_k] = -1.0
    c_mat[2 * n + k + ar_k, n + ar_k] = -1.0
    return c_mat, np.concatenate((hi, -lo, h_vec, np.zeros(k)))


def _max_step(v: np.ndarray, dv: np.ndarray) -> float:
    """Largest alpha in (0, 1] with ``v + alpha dv >= 0`` (for ``v > 0``): ``1 / max(-dv / v)``."""
    worst = -float((dv / v).min())
    return 1.0 if worst <= 1.0 else 1.0 / worst
