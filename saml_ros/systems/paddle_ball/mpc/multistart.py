"""The fast paddle-ball solver's multi-start strategy, on top of the per-start iterations of
:class:`~saml_ros.systems.paddle_ball.mpc.projected_newton.ProjectedNewton`.

1. **Probe** (a reachable target, most problems): from the first start, Gauss-Newton towards the nearest
   post-impact velocity that lands on the target (``"velocity"``, a few iterations), then on the landing error
   itself (``"gauss-newton"``) until it hits the target or stops closing in on it quickly (a reachable target
   converges quadratically).
2. **Newton** (the target is out of reach, or behind a fold): exact-Hessian Newton from the probe's end point and,
   if ``max_runs > 1``, from the starts, the paddle tilted most towards the target first (a few cheaper
   Gauss-Newton steps before Newton). A run is abandoned once the ball collapses onto the paddle (the landing error
   tends to ``|p_xy - target|``), once it is clearly losing to the best minimum found (by a margin shrinking with
   its iterations), or once it heads into a minimum already found; the search stops after ``patience`` runs in a
   row without improvement. The default is one run: a second start found a better minimum on about 1 % of the
   out-of-reach problems tuned on, by 0.1-0.5 %, for a quarter of their solve time.
3. **Valley hop**: the landing error is piecewise smooth (the network's kinks), and its minima near the reach
   limit lie in a row along the flattest direction of the Hessian. The points displaced along that direction are
   evaluated, a short Gauss-Newton run relaxes the better one (or each, ``valley_pick=False``), and a full Newton
   run follows from it if it beats the best minimum.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass

from saml_ros.systems.paddle_ball.mpc.landing_error import Point
from saml_ros.systems.paddle_ball.mpc.projected_newton import ProjectedNewton, RunResult


@dataclass(frozen=True)
class SearchSettings:
    """Tuning of :func:`search` (measured on the bench's problem distribution; see docs/mpc.md)."""

    tol: float = 1e-4  #: landing error (m) that counts as reaching the target: no further starts
    tol_zero: float = 1e-6  #: landing error (m) at which a run stops (the target is hit)
    velocity_iter: int = 4  #: target-velocity Gauss-Newton iterations of the probe
    probe_iter: int = 10  #: probe iterations in all
    probe_slow_after: int = 2  #: Gauss-Newton probe iterations after which a slow one ends it
    max_iter: int = 20  #: iterations of a Newton run
    rtol: float = 1e-4  #: relative decrease of ||r|| below which (3 times in a row) a Newton run has converged
    max_runs: int = 16  #: Newton runs at most (the probe's end point first, then the starts)
    patience: int = 1  #: Newton runs in a row without improvement after which the multi-start stops
    screen_iter: int = 4  #: Gauss-Newton iterations before Newton from the starts after the first
    lose: float = 1.5  #: a run is losing once its cost exceeds (1 + lose / iteration) times the best one's
    same: float = 0.02  #: distance (fraction of each box side) and ...
    same_cost: float = 2e-3  #: ... relative cost difference within which a run heads into a known minimum
    valley: tuple[float, ...] = (-0.1, 0.1)  #: displacements along the flat direction (m/s, rad)
    valley_pick: bool = False  #: relax only the displaced point with the lower landing error (else each one)
    relax_iter: int = 2  #: Gauss-Newton iterations from a displaced point


def search(solver: ProjectedNewton, starts: list[list[float]], tilt: Callable[[list[float]], float], s: SearchSettings,
           deadline: float = math.inf) -> tuple[RunResult, int, str]:
    """Best end point over ``starts`` (``tilt(theta)``: how much that start's paddle leans towards the target, the
    larger the earlier it is tried), the iterations spent and a message (``converged``, ``max_iter``,
    ``time budget``)."""
    best = solver.run(starts[0], "velocity", max_iter=s.velocity_iter, tol_zero=s.tol_zero)
    total = best.iterations
    if best.cost > s.tol_zero:
        more = solver.run(best.theta, "gauss-newton", max_iter=s.probe_iter - total, tol_zero=s.tol_zero, slow=0.5,
                          slow_after=s.probe_slow_after, start=best.point)
        total += more.iterations
        best = more if more.cost <= best.cost else best
    if best.cost > s.tol and time.perf_counter() < deadline:
        lead, used = _multistart(solver, best, starts, tilt, s, deadline)
        total += used
        if math.isfinite(lead.cost) and lead.cost > s.tol and time.perf_counter() < deadline:
            lead, used = _valley_hop(solver, lead, s)
            total += used
        best = lead if lead.cost < best.cost else best
    late = time.perf_counter() > deadline
    return best, total, "converged" if best.converged else ("time budget" if late else "max_iter")


def _multistart(solver: ProjectedNewton, probe: RunResult, starts: list[list[float]],
                tilt: Callable[[list[float]], float], s: SearchSettings, deadline: float) -> tuple[RunResult, int]:
    """Newton from the probe's end point, then from the starts (step 2 of the module docstring)."""
    offset, box = solver.error.offset, solver.feasible
    drop = math.hypot(float(offset[0]), float(offset[1]))  # ||r|| when the ball barely bounces
    scale = [max(h - lo, 1e-9) for lo, h in zip(box.lo, box.hi)]
    found: list[RunResult] = []
    lead = RunResult(probe.theta, math.inf, 0, False)

    def abandon(pt: Point, it: int) -> bool:
        cost = math.sqrt(2.0 * pt.f)
        if it >= 2 and pt.v[2] < 0.3 and cost >= 0.99 * drop:  # the ball collapsing onto the paddle
            return True
        if it >= 4 and cost > (1.0 + s.lose / it) * lead.cost:  # losing, by less the longer it runs
            return True
        return it >= 3 and any(
            abs(cost - m.cost) <= s.same_cost * m.cost
            and max(abs(pt.theta[i] - m.theta[i]) / scale[i] for i in range(5)) < s.same for m in found)

    total = misses = 0
    for k, guess in enumerate(([probe.theta] + sorted(starts, key=lambda th: -tilt(th)))[: s.max_runs]):
        known = probe.point if k == 0 else None
        if lead.cost <= s.tol or misses >= s.patience or time.perf_counter() > deadline:
            break
        if math.isfinite(lead.cost) and s.screen_iter > 0:  # a few cheaper Gauss-Newton steps first
            res = solver.run(guess, "gauss-newton", max_iter=s.screen_iter, tol_zero=s.tol_zero, abandon=abandon)
            total += res.iterations
            guess, known = res.theta, res.point
            if res.abandoned or res.cost <= s.tol or not math.isfinite(res.cost):
                misses += 1
                lead = res if res.cost < lead.cost else lead
                continue
        res = solver.run(guess, "newton", max_iter=s.max_iter, tol_zero=s.tol_zero, rtol=s.rtol, abandon=abandon,
                         start=known)
        total += res.iterations
        if not res.abandoned:
            found.append(res)
        misses = 0 if res.cost < (1.0 - 1e-4) * lead.cost else misses + 1
        lead = res if res.cost < lead.cost else lead
    return lead, total


def _valley_hop(solver: ProjectedNewton, lead: RunResult, s: SearchSettings) -> tuple[RunResult, int]:
    """Step 3 of the module docstring, once."""
    direction = solver.flat_direction(lead.theta, lead.point)
    if direction is None:
        return lead, 0
    total = 0
    hop: RunResult | None = None
    value, project = solver.error.value, solver.feasible.project
    points = [value(project([c + t * d for c, d in zip(lead.theta, direction)])) for t in s.valley]
    if s.valley_pick and points:
        points = [min(points, key=lambda p: p.f if p.up else math.inf)]
    for pt in points:
        trial = solver.run(pt.theta, "gauss-newton", max_iter=s.relax_iter, tol_zero=s.tol_zero, start=pt)
        total += trial.iterations
        if trial.cost < (1.0 - 1e-4) * lead.cost and (hop is None or trial.cost < hop.cost):
            hop = trial
    if hop is None:
        return lead, total
    res = solver.run(hop.theta, "newton", max_iter=s.max_iter, tol_zero=s.tol_zero, rtol=s.rtol, start=hop.point)
    return (res if res.cost < hop.cost else hop), total + res.iterations
