"""The paddle-ball controller's feasible set and its active constraints, in plain Python floats (used by
:mod:`~saml_ros.systems.paddle_ball.mpc.projected_newton`).

``theta = [pv (3) m/s, roll, pitch (rad)]`` lies in a box, and the relative speed ``s = |v_ball - pv|`` in
``[v_min, v_max]``: a spherical shell around ``v_ball`` in the paddle-velocity space. :meth:`FeasibleSet.project`
maps a trial point back onto that set; :meth:`FeasibleSet.active_set` says which bounds a step must respect
(Bertsekas' projected Newton: the bounds within ``eps`` that the gradient, or the Newton step, pushes against),
with the move that puts ``theta`` exactly on them.
"""

from __future__ import annotations

import math

_ALL = [0, 1, 2, 3, 4]  # every coordinate free (shared, never modified)


class FeasibleSet:
    """Box ``lo <= theta <= hi`` (5 floats each) and speed bounds ``v_rel = (v_min, v_max)`` m/s around the
    ball's pre-impact velocity ``v_ball`` (3 floats)."""

    def __init__(self, lo: list[float], hi: list[float], v_ball: list[float], v_rel: tuple[float, float]) -> None:
        self.lo, self.hi = [float(c) for c in lo], [float(c) for c in hi]
        self.vb = [float(c) for c in v_ball]
        self.vmin, self.vmax = float(v_rel[0]), float(v_rel[1])
        self.eps = 1e-3  # distance (m/s, rad) within which a bound counts as touched

    def project(self, theta: list[float], keep: list[bool] | None = None) -> list[float]:
        """The feasible point nearest ``theta``: the box clip, then, when the speed is out of bounds, the paddle
        velocity ``pv = clip(v_ball + t (q - v_ball))`` with ``t`` such that the speed is on the violated bound
        (:meth:`_ray`; for the upper bound this is the exact projection onto the convex box-and-ball, for the
        lower one a feasible point on the same ray, or failing that the paddle moving up faster). Coordinates
        flagged in ``keep`` (active bounds) are held, so that a point put on a corner stays there."""
        lo, hi = self.lo, self.hi
        out = [min(max(theta[i], lo[i]), hi[i]) for i in range(5)]
        vb = self.vb
        w0, w1, w2 = out[0] - vb[0], out[1] - vb[1], out[2] - vb[2]
        s2 = w0 * w0 + w1 * w1 + w2 * w2
        if self.vmin * self.vmin <= s2 <= self.vmax * self.vmax:
            return out
        radius = self.vmax if s2 > self.vmax * self.vmax else self.vmin
        fixed = [False, False, False] if keep is None else list(keep[0:3])
        delta = [0.0 if fixed[i] else theta[i] - vb[i] for i in range(3)]
        if delta[0] * delta[0] + delta[1] * delta[1] + delta[2] * delta[2] < 1e-24:
            delta, fixed = [0.0, 0.0, 1.0], [False, False, False]  # no free direction: the paddle moving up
        t = self._ray(delta, [out[i] - vb[i] if fixed[i] else None for i in range(3)], radius)
        for i in range(3):
            if not fixed[i]:
                out[i] = min(max(vb[i] + t * delta[i], lo[i]), hi[i])
        if radius == self.vmin and not fixed[2]:  # the ray may leave the box before reaching the lower bound
            wx, wy = vb[0] - out[0], vb[1] - out[1]
            wz2 = self.vmin * self.vmin - wx * wx - wy * wy
            if wz2 > (vb[2] - out[2]) ** 2:  # still too slow: the paddle moves up faster, into the ball
                out[2] = min(max(vb[2] + math.sqrt(wz2), lo[2]), hi[2])
        return out

    def _ray(self, delta: list[float], held: list[float | None], radius: float) -> float:
        """``t >= 0`` with ``|clip(v_ball + t delta) - v_ball| = radius`` (held coordinates at the given offset),
        in closed form: the distance grows with ``t`` and is a quadratic in ``t`` between the breakpoints where
        coordinates enter or leave the box. The largest breakpoint if the radius cannot be reached."""
        vb, lo, hi = self.vb, self.lo, self.hi
        cuts = [0.0]
        for i in range(3):
            if held[i] is None and delta[i] != 0.0:
                cuts += [t for t in ((lo[i] - vb[i]) / delta[i], (hi[i] - vb[i]) / delta[i]) if t > 0.0]
        cuts.sort()
        target = radius * radius
        for k, t0 in enumerate(cuts):
            t1 = cuts[k + 1] if k + 1 < len(cuts) else math.inf
            tm = t0 + 1.0 if t1 == math.inf else 0.5 * (t0 + t1)  # which coordinates are clipped on (t0, t1)
            const = quad = 0.0
            for i in range(3):
                h = held[i]
                if h is not None:
                    const += h * h
                    continue
                p = vb[i] + tm * delta[i]
                if p < lo[i] or p > hi[i]:
                    const += (min(max(p, lo[i]), hi[i]) - vb[i]) ** 2
                else:
                    quad += delta[i] * delta[i]
            if const + quad * t1 * t1 >= target:  # crossed on this piece
                return t0 if quad <= 0.0 else max(math.sqrt(max(target - const, 0.0) / quad), t0)
        return cuts[-1]

    def active_set(self, theta: list[float], grad: list[float], drop: set[int] | None = None,
                   by_gradient: bool = True) -> tuple[list[int], list[float] | None, list[float] | None]:
        """Free coordinates, the unit speed-bound normal within them (None when the speed bound is not active)
        and the move putting ``theta`` exactly on the active bounds (to first order for the speed bound; None
        when no bound is active). The bounds within ``eps``, except those in ``drop`` (box coordinate ``i``, or 5
        for the speed bound) and, if ``by_gradient``, those whose least-squares KKT multiplier of the gradient
        is negative."""
        lo, hi, eps = self.lo, self.hi, self.eps
        vb = self.vb
        w = [vb[0] - theta[0], vb[1] - theta[1], vb[2] - theta[2]]
        s = math.sqrt(w[0] * w[0] + w[1] * w[1] + w[2] * w[2])
        side = 1.0 if s >= self.vmax - eps else (-1.0 if s <= self.vmin + eps else 0.0)
        near = [(-1.0 if theta[i] <= lo[i] + eps else (1.0 if theta[i] >= hi[i] - eps else 0.0)) for i in range(5)]
        if side == 0.0 and not any(near):
            return _ALL, None, None
        if drop:
            near = [0.0 if i in drop else c for i, c in enumerate(near)]
            side = 0.0 if 5 in drop else side
        # outward normal of the speed bound: d s / d pv = -w / s (upper bound), w / s (lower bound)
        nrm = [-side * c / max(s, 1e-300) for c in w]
        if by_gradient:
            box, sphere = self._kkt(grad, near, nrm, side != 0.0)
        else:
            box, sphere = [c != 0.0 for c in near], side != 0.0
        if not sphere and not any(box):
            return _ALL, None, None
        free = [i for i in range(5) if not box[i]]
        close = [((lo[i] if near[i] < 0.0 else hi[i]) - theta[i]) if box[i] else 0.0 for i in range(5)]
        unit = None
        if sphere:
            nf = [nrm[i] if (i < 3 and not box[i]) else 0.0 for i in range(5)]
            nn = math.sqrt(sum(c * c for c in nf))
            if nn > 1e-12:
                unit = [c / nn for c in nf]
                gap = (s - self.vmax) if side > 0.0 else (self.vmin - s)  # <= 0: how far inside the bound
                for i in range(3):
                    close[i] -= unit[i] * gap / nn
        return free, unit, close

    @staticmethod
    def _kkt(grad: list[float], near: list[float], nrm: list[float], sphere: bool) -> tuple[list[bool], bool]:
        """Which of the touched bounds to keep: least-squares KKT multipliers of ``grad + sum_j lam_j a_j = 0``
        (box bound ``a_i = near_i e_i``, speed bound ``a = nrm``), dropping the negative ones (two passes)."""
        box = [c != 0.0 for c in near]
        lam_s = 0.0
        for _ in range(2):
            lam_s = 0.0
            if sphere:
                nf2 = sum(nrm[i] * nrm[i] for i in range(3) if not box[i])
                if nf2 > 1e-24:
                    lam_s = -sum(nrm[i] * grad[i] for i in range(3) if not box[i]) / nf2
                sphere = lam_s > 0.0
                if not sphere:
                    lam_s = 0.0
            for i in range(5):
                if box[i]:
                    extra = lam_s * nrm[i] if i < 3 else 0.0
                    box[i] = -(grad[i] + extra) * near[i] > 0.0
        return box, sphere

    def most_negative(self, theta: list[float], grad: list[float], hess: list[list[float]], step: list[float],
                       free: list[int], unit: list[float] | None) -> int | None:
        """The active constraint (box coordinate, or 5: the speed bound) with the most negative multiplier of
        the equality-constrained Newton step ``step`` (``grad + H step + sum_j lam_j a_j = 0``), or None: a bound
        the gradient pushes against may still be one the step would leave."""
        d0, d1, d2, d3, d4 = step
        res = [g + h[0] * d0 + h[1] * d1 + h[2] * d2 + h[3] * d3 + h[4] * d4 for g, h in zip(grad, hess)]
        worst, low = None, -1e-12 * (1.0 + math.sqrt(sum([c * c for c in grad])))
        lam_s = 0.0
        if unit is not None:  # the unit normal within the free coordinates: least squares over those
            lam_s = -sum([unit[i] * res[i] for i in free])
            if lam_s < low:
                worst, low = 5, lam_s
        if len(free) == 5:
            return worst
        w = [self.vb[0] - theta[0], self.vb[1] - theta[1], self.vb[2] - theta[2]]
        if unit is not None:  # the speed bound's outward normal (length |w_free|/s) also has components on fixed ones
            s = math.sqrt(w[0] * w[0] + w[1] * w[1] + w[2] * w[2])
            side = 1.0 if s >= self.vmax - self.eps else -1.0
            per = -side * lam_s / max(math.sqrt(sum([w[k] * w[k] for k in free if k < 3])), 1e-300)
        for i in range(5):
            if i in free:
                continue
            extra = per * w[i] if unit is not None and i < 3 else 0.0
            lam = (res[i] + extra) if theta[i] <= self.lo[i] + self.eps else -(res[i] + extra)
            if lam < low:
                worst, low = i, lam
        return worst
