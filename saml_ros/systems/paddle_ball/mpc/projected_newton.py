"""The per-start iterations of the fast paddle-ball solver, in plain Python floats: projected Gauss-Newton / Newton
on ``F = 1/2 ||r(theta)||^2`` (``r`` the landing error, m, :mod:`~saml_ros.systems.paddle_ball.mpc.landing_error`) within
the feasible set (:mod:`~saml_ros.systems.paddle_ball.mpc.feasible_set`). Per iteration:

1. **active set** (Bertsekas' projected Newton): the bounds touched by ``theta`` (within ``eps``) are held:
   coordinates moved exactly onto their box bound, the step kept tangent to an active speed bound (``P``: the
   orthogonal projector onto the remaining free directions). The Gauss-Newton modes keep those the gradient pushes
   against (least-squares KKT multipliers); Newton keeps all, then releases the one with the most negative
   multiplier of its own step, and re-solves (at a corner of box and speed bound the gradient's multipliers
   flip-flop, and the iterates zig-zag);
2. **step**, one of three models (``mode``):

   * ``"velocity"``: Gauss-Newton towards a *target post-impact velocity* ``v*``, the velocity nearest the
     predicted one that lands exactly on the target (``v*_xy v*_z = g/2 (target - p)``, a 1-D minimisation);
     ``d = -P Dv^T (Dv P Dv^T + lam I)^-1 (v - v*)`` (3 x 3). ``v(theta)`` is far more linear than the landing
     point (a product ``v_xy v_z``), so a reachable target is met in fewer iterations;
   * ``"gauss-newton"``: ``d = -P J^T (J P J^T + lam I)^-1 r`` (2 x 2), the minimum-norm step of the
     underdetermined landing equations;
   * ``"newton"``: ``(P (J^T J + C) P + lam I) d = -P g`` with the exact residual curvature ``C``, by Cholesky,
     or when that matrix is not positive definite from its eigen-decomposition with ``|eigenvalue|`` (no ascent
     along negative curvature). Needed when the target cannot be reached: the optimum is then a fold of the
     landing map on the constraint boundary, where ``J^T J`` is singular. Its length is capped by a trust radius;

3. the trial point, projected back onto the feasible set, is evaluated and accepted if ``F`` decreases and the
   ball still leaves upwards; the Levenberg-Marquardt damping ``lam`` (relative to the model's scale) and the trust
   radius follow the ratio of actual to predicted decrease.

One iteration costs one model evaluation (:meth:`LandingError.value`) plus, when the step is accepted, its
derivatives (:meth:`LandingError.derivatives`, computed when the next iteration needs them, so a run's last step
costs none, and cached on the point for a run starting there; skipped while a Gauss-Newton run converges fast:
the previous Jacobian is kept); the rest is a few hundred float operations.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from saml_ros.systems.paddle_ball.mpc.feasible_set import FeasibleSet
from saml_ros.systems.paddle_ball.mpc.landing_error import LandingError, Point

MODES = ("velocity", "gauss-newton", "newton")
_ZERO = [0.0] * 5


@dataclass
class RunResult:
    """End point of one run (from one start)."""

    theta: list[float]  #: feasible end point
    cost: float  #: ||r|| (m), inf when the ball would not leave upwards
    iterations: int  #: model evaluations after the first
    converged: bool  #: met a stopping tolerance (not max_iter / failed damping / slow / abandoned)
    slow: bool = False  #: stopped because an accepted step reduced ||r|| by less than the ``slow`` factor
    abandoned: bool = False  #: stopped by the caller's ``abandon`` test
    point: Point | None = None  #: the model's evaluation at ``theta``


class ProjectedNewton:
    """Projected Gauss-Newton / Newton runs for one problem: the landing error ``error`` (model, state, target)
    within ``feasible`` (box and speed bounds around the ball's velocity ``error.x[3:6]``)."""

    def __init__(self, error: LandingError, feasible: FeasibleSet) -> None:
        self.error = error
        self.feasible = feasible
        # landing on the target means v_xy v_z = c (m^2/s^2)
        self.c = (-float(error.offset[0]) / error.k, -float(error.offset[1]) / error.k)
        self.mu0 = 1e-2  # initial damping, relative to the model's scale
        self.radius0 = 1.0  # initial trust radius of the Newton steps (m/s, rad)
        self.shrink = 0.25  # trust radius after a rejected Newton step, relative to that step's length

    # ------------------------------------------------------------------------------------------ iterations
    def run(self, theta0: list[float], mode: str, max_iter: int, tol_zero: float = 1e-7, rtol: float = 1e-6,
            slow: float = 1.0, slow_after: int = 8, abandon: Callable[[Point, int], bool] | None = None,
            start: Point | None = None) -> RunResult:
        """Iterate from ``theta0`` (projected first) with the step model ``mode`` (module docstring).

        Stops at ``||r|| <= tol_zero`` (m); when ``F`` has not improved by a relative ``2 rtol`` in 3 iterations (in
        the Gauss-Newton modes a rejected step whose model promised a real decrease does not count; Newton near a
        kink alternates tiny gains with rejected steps, which do count); when the damping fails; after
        ``max_iter`` iterations; ``slow < 1``: once an accepted step after iteration ``slow_after`` reduced
        ``||r||`` by less than this factor (a reachable target converges quadratically: this one is probably
        out of reach); or when ``abandon(point, iteration)`` returns True after an accepted step (the caller's
        test that this start is not worth finishing). ``start``: the model's evaluation at ``theta0`` if known (a
        previous run's end point), used when ``theta0`` is feasible.
        """
        if mode not in MODES:
            raise ValueError(f"unknown mode {mode!r}; valid: {MODES}")
        ev, project = self.error, self.feasible.project
        newton = mode == "newton"
        th0 = project(theta0)
        pt = start if start is not None and start.theta == th0 else ev.value(th0)
        if not pt.up:  # the ball would not leave upwards: no gradient to follow
            return RunResult(pt.theta, math.inf, 0, False, point=pt)
        jac, hess = ev.derivatives(pt, newton)
        dv_old = pt.dv
        stale = False  # derivatives at pt still to compute (lazily: a run often ends right after a step)
        f = pt.f
        mu = self.mu0
        radius = self.radius0 if newton else math.inf  # cap on the step length (m/s, rad)
        f_ref, stall = f, 0
        it = 0
        while it < max_iter:
            it += 1
            if stale:
                jac, hess = ev.derivatives(pt, newton)
                dv_old, stale = pt.dv, False
            th = pt.theta
            j0, j1 = jac
            r0, r1 = pt.r
            g = [j0[0] * r0 + j1[0] * r1, j0[1] * r0 + j1[1] * r1, j0[2] * r0 + j1[2] * r1, j0[3] * r0 + j1[3] * r1,
                 j0[4] * r0 + j1[4] * r1]
            step, free = self._step(mode, pt, jac, hess, g, mu, radius)
            keep = None if len(free) == 5 else [i not in free for i in range(5)]
            cand = project([th[0] + step[0], th[1] + step[1], th[2] + step[2], th[3] + step[3], th[4] + step[4]], keep)
            dd = [cand[0] - th[0], cand[1] - th[1], cand[2] - th[2], cand[3] - th[3], cand[4] - th[4]]
            pred = _predicted_decrease(g, dd, jac, hess)
            moved = math.sqrt(dd[0] * dd[0] + dd[1] * dd[1] + dd[2] * dd[2] + dd[3] * dd[3] + dd[4] * dd[4])
            cpt = ev.value(cand)
            ok = cpt.up and cpt.f < f - 1e-4 * max(pred, 0.0)  # (a non-finite value is rejected too)
            if ok:
                ratio = (f - cpt.f) / pred if pred > 0.0 else 0.0
                mu = max(mu * 0.1 if ratio > 0.75 else (mu * 2.0 if ratio < 0.25 else mu), 1e-15)
                if ratio > 0.75:
                    radius = max(radius, 2.0 * moved)
                f_old = f
                pt, f = cpt, cpt.f
                if f <= 0.5 * tol_zero * tol_zero:
                    return RunResult(pt.theta, math.sqrt(2.0 * f), it, True, point=pt)
                if slow < 1.0 and it > slow_after and f > slow * slow * f_old:
                    return RunResult(pt.theta, math.sqrt(2.0 * f), it, False, slow=True, point=pt)
                if abandon is not None and abandon(pt, it):
                    return RunResult(pt.theta, math.sqrt(2.0 * f), it, False, abandoned=True, point=pt)
                if not newton and f < 1e-4 * f_old and f_old < 1e-4:  # converging fast: keep the Jacobian (chord)
                    cpt.dv = dv_old
                else:
                    stale = True
            else:
                mu *= 20.0
                if newton:
                    radius = self.shrink * moved
                if mu > 1e8 or radius < 1e-12:
                    return RunResult(th, math.sqrt(2.0 * f), it, False, point=pt)
            if f < (1.0 - 2.0 * rtol) * f_ref:
                f_ref, stall = f, 0
            elif ok or newton or moved <= 1e-12 or 0.0 <= pred <= 2.0 * rtol * f:
                stall += 1
                if stall >= 3:
                    return RunResult(pt.theta, math.sqrt(2.0 * f), it, True, point=pt)
        return RunResult(pt.theta, math.sqrt(2.0 * f), it, False, point=pt)

    def _step(self, mode: str, pt: Point, jac: list[list[float]], hess: list[list[float]] | None, g: list[float],
              mu: float, radius: float) -> tuple[list[float], list[int]]:
        """The step (5 floats) of ``mode`` from ``pt`` (gradient ``g``, damping ``mu``, Newton's trust radius) and the
        free coordinates after the active set (steps 1 and 2 of the module docstring)."""
        th = pt.theta
        feasible = self.feasible
        free, unit, close = feasible.active_set(th, g, by_gradient=mode != "newton")
        if mode == "newton":
            assert hess is not None
            drop: set[int] = set()
            for _ in range(4):  # release the bounds the Newton step would leave (negative multiplier)
                cl = _ZERO if close is None else close
                step = self._newton_step(hess, g, free, unit, cl, mu)
                if len(free) == 5 and unit is None:
                    break
                worst = feasible.most_negative(th, g, hess, step, free, unit)
                if worst is None:
                    break
                drop.add(worst)
                free, unit, close = feasible.active_set(th, g, drop, by_gradient=False)
            size = math.sqrt(sum([(step[i] - cl[i]) ** 2 for i in range(5)]))
            if size > radius:  # (the move onto the active bounds is not capped)
                step = [cl[i] + (step[i] - cl[i]) * (radius / size) for i in range(5)]
        elif mode == "velocity":
            step = self._velocity_step(pt, free, unit, close, mu)
        else:
            step = self._gauss_newton_step(jac, pt.r, free, unit, _ZERO if close is None else close, mu)
        return step, free

    @staticmethod
    def _project_rows(rows: list[list[float]], free: list[int], unit: list[float] | None) -> list[list[float]]:
        """``rows`` (k x 5) restricted to the free coordinates and projected off the speed-bound normal."""
        out = [[row[i] for i in free] for row in rows]
        if unit is not None:
            ut = [unit[i] for i in free]
            for row in out:
                p = sum(row[k] * ut[k] for k in range(len(free)))
                for k in range(len(free)):
                    row[k] -= p * ut[k]
        return out

    def _gauss_newton_step(self, jac: list[list[float]], r: tuple[float, float], free: list[int],
                           unit: list[float] | None, close: list[float], mu: float) -> list[float]:
        """``close - P J^T (J P J^T + lam I)^-1 (r + J close)``, 5 floats."""
        step = list(close)
        if not free:
            return step
        ja, jb = self._project_rows(jac, free, unit)
        m = len(free)
        aa = sum(c * c for c in ja)
        ab = sum(ja[k] * jb[k] for k in range(m))
        bb = sum(c * c for c in jb)
        lam = mu * 0.5 * (aa + bb) + 1e-300
        ra = r[0] + sum(jac[0][i] * close[i] for i in range(5))
        rb = r[1] + sum(jac[1][i] * close[i] for i in range(5))
        aa += lam
        bb += lam
        det = aa * bb - ab * ab
        if not det > 0.0:  # no free direction moves the landing point (J P J^T underflows): only the move onto bounds
            return step
        ya, yb = (bb * ra - ab * rb) / det, (aa * rb - ab * ra) / det
        for k, i in enumerate(free):
            step[i] -= ja[k] * ya + jb[k] * yb
        return step

    def target_velocity(self, v: tuple[float, float, float]) -> tuple[float, float, float]:
        """The post-impact velocity nearest ``v`` that lands exactly on the target: ``(c / z, z)`` with
        ``c = g/2 (target - p)`` and ``z > 0`` minimising ``|c / z - v_xy|^2 + (z - v_z)^2`` (Newton in 1-D)."""
        cx, cy = self.c
        cc, cv = cx * cx + cy * cy, cx * v[0] + cy * v[1]
        vz = v[2]
        z = max(vz, 0.3)
        for _ in range(12):
            z2 = z * z
            d1 = -cc / (z2 * z) + cv / z2 + (z - vz)  # (half the derivative)
            d2 = 3.0 * cc / (z2 * z2) - 2.0 * cv / (z2 * z) + 1.0
            z_new = max(z - d1 / (d2 if d2 > 0.0 else 1.0), 0.5 * z)
            if abs(z_new - z) <= 1e-12 * z:
                break
            z = z_new
        return cx / z, cy / z, z

    def _velocity_step(self, pt: Point, free: list[int], unit: list[float] | None, close: list[float] | None,
                       mu: float) -> list[float]:
        """``close - P Dv^T (Dv P Dv^T + lam I)^-1 (v + Dv close - v*)``, 5 floats (module docstring)."""
        dv = pt.dv
        if not free or dv is None:
            return [0.0] * 5 if close is None else list(close)
        vs = self.target_velocity(pt.v)
        e0, e1, e2 = pt.v[0] - vs[0], pt.v[1] - vs[1], pt.v[2] - vs[2]
        if close is None:  # nothing active (the usual case): plain rows
            a, b, c = dv
        else:
            e0 += sum(dv[0][i] * close[i] for i in range(5))
            e1 += sum(dv[1][i] * close[i] for i in range(5))
            e2 += sum(dv[2][i] * close[i] for i in range(5))
            a, b, c = self._project_rows(dv, free, unit)
        m00 = sum([x * x for x in a])
        m11 = sum([x * x for x in b])
        m22 = sum([x * x for x in c])
        m01 = sum([x * y for x, y in zip(a, b)])
        m02 = sum([x * y for x, y in zip(a, c)])
        m12 = sum([x * y for x, y in zip(b, c)])
        lam = mu * (m00 + m11 + m22) / 3.0 + 1e-300
        m00, m11, m22 = m00 + lam, m11 + lam, m22 + lam
        # symmetric 3 x 3 solve by the adjugate
        c00, c01, c02 = m11 * m22 - m12 * m12, m02 * m12 - m01 * m22, m01 * m12 - m02 * m11
        c11, c12, c22 = m00 * m22 - m02 * m02, m01 * m02 - m00 * m12, m00 * m11 - m01 * m01
        det = m00 * c00 + m01 * c01 + m02 * c02
        if not det > 0.0:  # no free direction moves v (Dv P Dv^T underflows): only the move onto the bounds
            return [0.0] * 5 if close is None else list(close)
        y0 = (c00 * e0 + c01 * e1 + c02 * e2) / det
        y1 = (c01 * e0 + c11 * e1 + c12 * e2) / det
        y2 = (c02 * e0 + c12 * e1 + c22 * e2) / det
        if close is None:
            return [-(a[i] * y0 + b[i] * y1 + c[i] * y2) for i in range(5)]
        step = list(close)
        for k, i in enumerate(free):
            step[i] -= a[k] * y0 + b[k] * y1 + c[k] * y2
        return step

    @staticmethod
    def _newton_step(hess: list[list[float]], g: list[float], free: list[int], unit: list[float] | None,
                     close: list[float], mu: float) -> list[float]:
        """``close + d``, ``(P H P + lam I) d = -P (g + H close)`` on the free coordinates, ``lam = mu`` times the
        largest diagonal entry; by Cholesky when that matrix is positive definite, otherwise from the
        eigen-decomposition with ``|eigenvalues|`` (no ascent along negative curvature); 5 floats."""
        step = list(close)
        if not free:
            return step
        m = len(free)
        hm = [[hess[i][j] for j in free] for i in free]
        if any(close):
            rhs = [-(g[i] + sum([hess[i][j] * close[j] for j in range(5)])) for i in free]
        else:
            rhs = [-g[i] for i in free]
        if unit is not None:  # P = I - u u^T on the free coordinates
            ut = [unit[i] for i in free]
            hu = [sum([row[q] * ut[q] for q in range(m)]) for row in hm]
            uhu = sum([ut[k] * hu[k] for k in range(m)])
            hm = [[hm[k][q] - hu[k] * ut[q] - ut[k] * hu[q] + uhu * ut[k] * ut[q] for q in range(m)] for k in range(m)]
            ur = sum([ut[k] * rhs[k] for k in range(m)])
            rhs = [rhs[k] - ur * ut[k] for k in range(m)]
        scale = max(max(abs(hm[k][k]) for k in range(m)), 1e-300)
        d = _cholesky_solve(hm, rhs, max(mu, 1e-10) * scale)
        if d is None:
            evals, evecs = np.linalg.eigh(np.array(hm))
            mag = np.abs(evals)
            d = (evecs @ ((np.array(rhs) @ evecs) / (mag + (mu * float(mag.max()) + 1e-300)))).tolist()
        for k, i in enumerate(free):
            step[i] += d[k]
        return step

    def flat_direction(self, theta: list[float], start: Point | None = None) -> list[float] | None:
        """The direction (unit, 5 floats) of least curvature of ``F`` at ``theta`` within the active constraints:
        the eigenvector of ``P H P`` with the smallest ``|eigenvalue|`` outside ``P``'s null space (the valley
        along which distinct local minima of the piecewise-smooth landing error lie). None if nothing is free.
        ``start``: the model's evaluation at ``theta``, if known."""
        pt = start if start is not None and start.theta == theta else self.error.value(theta)
        if not pt.up:
            return None
        jac, hess = self.error.derivatives(pt, True)
        assert hess is not None
        g = [jac[0][j] * pt.r[0] + jac[1][j] * pt.r[1] for j in range(5)]
        free, unit, _ = self.feasible.active_set(theta, g)
        m = len(free) - (unit is not None)
        if m <= 0:
            return None
        hm = np.array([[hess[i][j] for j in free] for i in free])
        proj = np.eye(len(free))
        if unit is not None:
            u = np.array([unit[i] for i in free])
            proj -= np.outer(u, u)
            hm = proj @ hm @ proj
        evals, evecs = np.linalg.eigh(hm)
        inside = np.einsum("ij,ij->j", proj @ evecs, evecs) > 0.5  # eigenvectors within the free directions
        k = int(np.argmin(np.where(inside, np.abs(evals), np.inf)))
        out = [0.0] * 5
        for q, i in enumerate(free):
            out[i] = float(evecs[q, k])
        return out


def _predicted_decrease(g: list[float], dd: list[float], jac: list[list[float]],
                        hess: list[list[float]] | None) -> float:
    """``-(g . dd + 1/2 dd' M dd)`` of the step ``dd`` (5 floats) under the model ``M = J^T J`` (``hess`` None) or
    ``M = hess``."""
    if hess is None:
        j0, j1 = jac
        ja = j0[0] * dd[0] + j0[1] * dd[1] + j0[2] * dd[2] + j0[3] * dd[3] + j0[4] * dd[4]
        jb = j1[0] * dd[0] + j1[1] * dd[1] + j1[2] * dd[2] + j1[3] * dd[3] + j1[4] * dd[4]
        quad = ja * ja + jb * jb
    else:
        d0, d1, d2, d3, d4 = dd
        quad = sum([d * (h[0] * d0 + h[1] * d1 + h[2] * d2 + h[3] * d3 + h[4] * d4) for d, h in zip(dd, hess)])
    return -(g[0] * dd[0] + g[1] * dd[1] + g[2] * dd[2] + g[3] * dd[3] + g[4] * dd[4] + 0.5 * quad)


def _cholesky_solve(a: list[list[float]], b: list[float], shift: float) -> list[float] | None:
    """``(a + shift I)^-1 b`` for a small symmetric ``a`` (lists) by Cholesky; None if not positive definite.
    (Plain loops: about twice as fast as ``sum`` over list comprehensions at m <= 5, same rounding.)"""
    m = len(b)
    low: list[list[float]] = []
    for i in range(m):
        row = a[i]
        li = [0.0] * m
        _forward(low, row, li, i)  # row i of L from L[:i, :i] li[:i] = a[i][:i]
        acc = 0.0
        for k in range(i):
            acc += li[k] * li[k]
        acc = row[i] + shift - acc
        if not acc > 0.0:
            return None
        li[i] = math.sqrt(acc)
        low.append(li)
    y = [0.0] * m
    _forward(low, b, y, m)
    x = [0.0] * m
    for i in range(m - 1, -1, -1):
        acc = 0.0
        for k in range(i + 1, m):
            acc += low[k][i] * x[k]
        x[i] = (y[i] - acc) / low[i][i]
    return x


def _forward(low: list[list[float]], rhs: list[float], out: list[float], n: int) -> None:
    """Forward substitution: ``out[:n]`` solving ``L[:n, :n] out[:n] = rhs[:n]`` for the lower-triangular rows
    ``low``."""
    for j in range(n):
        lj = low[j]
        acc = 0.0
        for k in range(j):
            acc += out[k] * lj[k]
        out[j] = (rhs[j] - acc) / lj[j]
