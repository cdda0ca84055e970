"""Feasibility diagnosis of a primal-dual run: per constraint, is it met, how low did its left-hand side get,
is lambda still rising, and a verdict (:func:`diagnose`; the rules are docs/training.md's).

Per member and constraint, over the *tail* of the history (its last quarter, at least :data:`MIN_ROWS` rows):

* ``g`` is the final constraint value: the dataset-level one when given (end of offline training), else the mean
  of the tail's minibatch estimates (online); the constraint is **met** when ``g <= TOL * eps``;
* ``lhs_min`` is the smallest left-hand side ``g + eps`` of any history row or of the final value;
* lambda is **rising** when a least-squares line through the tail's lambdas rises by more than
  ``RISE * lambda_end`` over the tail (a multiplier at a saddle point hovers);
* a violated constraint is **likely infeasible** when a resilient run relaxed it (the relaxation it pays for
  says the bound is out of reach at that price), or when it is violated by more than ``MARGIN * eps``, its
  estimate is no longer falling fast enough to reach the bound within as many updates again as the run has done
  (the tail's least-squares slope, extrapolated geometrically as a loss decays: ``ln(lhs / eps) lhs / -slope``
  updates; online, where the run goes on, within ``ONLINE_REACH`` times as many, and by the slope over the tail or
  over twice the tail: while lambda still grows the estimate's descent speeds up, and a short tail of noisy
  minibatch means can look flat), lambda is rising (the multiplier keeps pushing and the model does not follow) and lambda has grown to where the constraint weighs in the Lagrangian: ``lambda (g + eps) >= f``, the
  objective (below that a multiplier still too small to matter explains a flat estimate; the augmented
  Lagrangian's weight is ``lambda + rho g``); otherwise it is
  **not converged** (still falling, nearly met, or a multiplier that has not pushed hard enough yet: train
  longer or raise the dual step). A multiplier moved by Adam (at most about its learning rate per update) that
  used at least ``RATE_LIMITED`` of the largest movement its learning rates allowed (``sum_t lr_t``) is
  **rate-limited**: the run cannot tell how far a larger lambda would get, so such a constraint is not
  converged, with the hint to raise the dual step (the paper's friction run: lambda 1.6 of at most 2.34),
  unless lambda already dominates the Lagrangian (``lambda (g + eps) >= DOMINATES * f``) and the estimate is still
  flat: then a faster multiplier would not change the verdict.

Over the members of an ensemble: **met** when every member meets it; a constraint that some member meets is
feasible for this model and data, so the others are **not converged** (a poorer local optimum: restart and
select, :mod:`saml_ros.core.training.selection`); when no member meets it, **likely infeasible** only if every
member says so. Levels as ``diagnostic_msgs``: met OK (0), not converged WARN (1), likely infeasible ERROR (2).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from saml_ros.core.training.history import History

MET, NOT_CONVERGED, INFEASIBLE = "met", "not_converged", "infeasible"
#: verdict -> number published in telemetry (``verdict/<k>``) and diagnostic level (0 OK, 1 WARN, 2 ERROR)
VERDICT_CODES: dict[str, int] = {MET: 0, NOT_CONVERGED: 1, INFEASIBLE: 2}
#: a constraint is met when g <= TOL * eps (1 % of the bound: the iterates of a converged run hover at g ~ 0)
TOL = 0.01
#: lambda is rising when its tail trend adds more than RISE * lambda_end over the tail
RISE = 0.01
#: a violation below MARGIN * eps is never called infeasible (a run hovering just above the bound)
MARGIN = 0.05
#: a multiplier that moved at least this fraction of its optimizer's largest possible movement is rate-limited
RATE_LIMITED = 0.6
#: a rate-limited multiplier with lambda (g + eps) >= DOMINATES * f dominates the objective: a constraint still flat
#: then is likely infeasible however fast lambda could have moved
DOMINATES = 4.0
#: horizon of the reach test, in multiples of the updates done: a violated constraint whose estimate falls fast
#: enough to reach the bound within it (:func:`_updates_to_reach`) is not called infeasible. At the end of a run
#: (``final_g`` given: offline, whose schedule is spent) 1x, "as long again", on the tail's slope. Online (a run
#: that goes on at a constant rate) ONLINE_REACH x, on the tail's slope or the slope over twice the tail: friction
#: at eps 0.035 (the recommended recipe, 800 transitions) levels off near g ~ eps after 500-1000 updates while
#: lambda still grows, then meets the bound by 1300-1800 updates; a 1x horizon on the tail alone called 3 of 8 such
#: runs infeasible on the way (test_online_verdict_is_never_infeasible_on_a_feasible_bound)
ONLINE_REACH = 4.0
#: the tail: the last TAIL of the history rows, at least MIN_ROWS of them
TAIL = 0.25
MIN_ROWS = 4


@dataclass
class MemberStatus:
    """One member's state for one constraint (loss units as the spec's; lambda dimensionless per unit of g)."""

    met: bool
    g: float
    lhs_min: float
    lam: float
    lam_start: float
    lam_rising: bool
    g_slope: float  # d g / d update over the tail (NaN without a tail)
    relaxation: float
    verdict: str
    rate_limited: bool = False


@dataclass
class ConstraintDiagnosis:
    """The verdict for one constraint over all members (see the module docstring)."""

    name: str
    eps: float
    verdict: str
    members: list[MemberStatus]
    lhs_min: float  # smallest left-hand side any member reached
    lhs_min_member: int
    reachable_eps: float  # smallest final left-hand side of any member (the bound this model and data reached)
    net: str
    message: str

    @property
    def level(self) -> int:
        return VERDICT_CODES[self.verdict]

    @property
    def n_met(self) -> int:
        return sum(m.met for m in self.members)

    @property
    def lambda_rising(self) -> bool:
        return any(m.lam_rising for m in self.members)


@dataclass
class FeasibilityDiagnosis:
    """Per constraint verdicts (:class:`ConstraintDiagnosis`), after ``updates`` updates."""

    constraints: list[ConstraintDiagnosis] = field(default_factory=list)
    updates: int = 0

    @property
    def level(self) -> int:
        """The worst level (0 OK when there are no constraints)."""
        return max((c.level for c in self.constraints), default=0)

    @property
    def all_met(self) -> bool:
        return all(c.verdict == MET for c in self.constraints)

    def messages(self) -> list[str]:
        return [c.message for c in self.constraints]

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe: per constraint its verdict, numbers and per-member statuses."""
        out: dict[str, Any] = {"updates": self.updates, "level": self.level, "constraints": {}}
        for c in self.constraints:
            d = asdict(c)
            d["level"] = c.level
            d["n_met"] = c.n_met
            d["lambda_rising"] = c.lambda_rising
            out["constraints"][c.name] = d
        return out


def _slope(t: np.ndarray, v: np.ndarray) -> float:
    """Least-squares slope of ``v`` over ``t`` (0 for fewer than 2 distinct times)."""
    if len(t) < 2 or float(np.ptp(t)) == 0.0:
        return 0.0
    tc = t - t.mean()
    return float((tc * (v - v.mean())).sum() / (tc * tc).sum())


def _updates_to_reach(lhs: float, eps: float, slope: float) -> float:
    """Updates a left-hand side ``lhs > eps`` falling at ``slope`` (per update, now) needs to reach ``eps``, if it keeps
    falling geometrically (a loss decays multiplicatively, not linearly: a bound 1000x below the estimate is far
    further away than a straight line says): ``ln(lhs / eps) / (-slope / lhs)``; inf when it is not falling."""
    if not slope < 0 or lhs <= 0 or eps <= 0:
        return float("inf")
    return float(np.log(lhs / eps) * lhs / -slope)


def _member(h: dict[str, np.ndarray], m: int, k: int, eps: float, g_final: float | None, relax: float,
            updates: int, f: float, dual_limit: float | None, rho: float = 0.0) -> MemberStatus:
    rows = len(h["step"])
    n_tail = min(rows, max(MIN_ROWS, int(round(rows * TAIL))))
    has_tail = rows >= MIN_ROWS
    con = h["constraints"][:, m, k] if rows else np.zeros(0)
    lam = h["lambdas"][:, m, k] if rows else np.zeros(0)
    steps = h["step"].astype(float)
    t_tail, g_tail, lam_tail = steps[rows - n_tail:], con[rows - n_tail:], lam[rows - n_tail:]
    online = g_final is None  # a run that goes on (online), not the end of one (offline, its schedule spent)
    g = float(g_final) if g_final is not None else (float(g_tail.mean()) if rows else float("nan"))
    lhs = [g + eps] + ([float(con.min()) + eps] if rows else [])
    lam_end = float(lam[-1]) if rows else 0.0
    lam_start = float(lam_tail[0]) if rows else 0.0
    g_slope = _slope(t_tail, g_tail) if has_tail else float("nan")
    rise = _slope(t_tail, lam_tail) * float(np.ptp(t_tail)) if has_tail else 0.0
    rising = has_tail and lam_end > 0 and rise > RISE * lam_end
    met = bool(g <= TOL * eps)
    limited = bool(dual_limit is not None and dual_limit > 0 and lam_end >= RATE_LIMITED * dual_limit)
    if met:
        verdict = MET
    elif relax > TOL * eps:
        verdict = INFEASIBLE  # the resilient method pays for a relaxation: out of reach at its price
    elif not has_tail:
        verdict = NOT_CONVERGED
    else:
        slopes = [g_slope]
        if online:  # a short tail of noisy minibatch means can look flat: the slope over twice the tail too
            n_long = min(rows, 2 * n_tail)
            slopes.append(_slope(steps[rows - n_long:], con[rows - n_long:]))
        reach = ONLINE_REACH if online else 1.0
        reaches = any(_updates_to_reach(g + eps, eps, s) <= reach * max(updates, 1) for s in slopes)
        weight = lam_end + rho * max(g, 0.0)  # the augmented Lagrangian weighs g by relu(lambda + rho g)
        weighs = weight * (g + eps) >= f  # the constraint's term in the Lagrangian is as large as the objective
        # a rate-limited multiplier may just be too slow, unless it already dominates the Lagrangian
        dominates = weight * (g + eps) >= DOMINATES * f
        infeasible = g > MARGIN * eps and not reaches and rising and weighs and (dominates or not limited)
        verdict = INFEASIBLE if infeasible else NOT_CONVERGED
    return MemberStatus(met, g, min(lhs), lam_end, lam_start, bool(rising), g_slope, relax, verdict, limited)


def diagnose(history: History, eps: Sequence[float], updates: int, net: Sequence[int] | str = "",
             final_g: np.ndarray | None = None, relaxation: np.ndarray | None = None,
             objective: np.ndarray | None = None, dual_limit: float | None = None,
             rho: Sequence[float] | None = None) -> FeasibilityDiagnosis:
    """The feasibility verdict of every constraint (rules: the module docstring).

    Args:
        history: the run's training curve (rows of minibatch means; lambda ``(E, K)`` per row).
        eps: the constraint bounds ``(K,)``.
        updates: primal-dual updates done.
        net: the network's hidden sizes (reported with the reachable bound), e.g. ``(16, 8)``.
        final_g: dataset-level constraint values ``(E, K)`` at the end (None: the tail's minibatch mean).
        relaxation: the resilient method's relaxation ``u`` ``(E, K)`` (None: zeros).
        objective: the final objective ``(E,)`` (None: the last history row's).
        dual_limit: the largest movement of lambda its optimizer allowed, ``sum_t lr_t`` (Adam); None: no such
            bound (SGD, nuPI).
        rho: the augmented Lagrangian's penalty per constraint ``(K,)`` (None: 0, the other methods); the
            constraint's weight in the Lagrangian is then ``lambda + rho g``.
    """
    k_all = len(history.constraint_names)
    out = FeasibilityDiagnosis(updates=int(updates))
    if not k_all:
        return out
    h = history.as_arrays()
    n_rows = len(h["step"])
    e = (h["lambdas"].shape[1] if n_rows else (final_g.shape[0] if final_g is not None else 0))
    net_s = net if isinstance(net, str) else "-".join(str(int(v)) for v in net) or "linear"
    if objective is None:
        objective = h["objective"][-1] if n_rows else np.zeros(e)
    for k, name in enumerate(history.constraint_names):
        ek = float(eps[k])
        members = [
            _member(h, m, k, ek, None if final_g is None else float(final_g[m, k]),
                    0.0 if relaxation is None else float(relaxation[m, k]), updates, float(objective[m]),
                    dual_limit, 0.0 if rho is None else float(rho[k]))
            for m in range(e)
        ]
        if not members:
            continue
        met = [m.met for m in members]
        if all(met):
            verdict = MET
        elif any(met):
            verdict = NOT_CONVERGED
        elif all(m.verdict == INFEASIBLE for m in members):
            verdict = INFEASIBLE
        else:
            verdict = NOT_CONVERGED
        i_min = int(np.argmin([m.lhs_min for m in members]))
        reach = min(m.g for m in members) + ek
        c = ConstraintDiagnosis(name, ek, verdict, members, members[i_min].lhs_min, i_min, reach, net_s, "")
        c.message = _message(c)
        out.constraints.append(c)
    return out


def _message(c: ConstraintDiagnosis) -> str:
    ms, n = c.members, len(c.members)
    who = f"{n} member{'s' if n > 1 else ''}"
    worst = max(m.g for m in ms) / c.eps
    rising = [i for i, m in enumerate(ms) if m.lam_rising]
    lam = f"lambda {min(m.lam for m in ms) + 0.0:.3g}" + (f"-{max(m.lam for m in ms) + 0.0:.3g}" if n > 1 else "")
    lam += f", still rising for {len(rising)}/{n}" if rising else ", not rising"
    head = f"constraint '{c.name}' (eps = {c.eps:.4g})"
    if c.verdict == MET:
        return (f"{head}: met by {'all ' if n > 1 else ''}{who} (largest g = {worst * 100:+.1f}% of eps); smallest "
                f"left-hand side {c.lhs_min:.4g}; {lam}")
    if c.verdict == NOT_CONVERGED:
        limited = [m for m in ms if m.rate_limited]
        why = (f"met by {c.n_met}/{n} members, so it is feasible for this model and data: the others ended in "
               "poorer optima (restart and select the best feasible member)" if c.n_met else
               f"lambda is limited by the dual step for {len(limited)}/{n} (it moved nearly as far as its learning "
               "rate allows)" if limited else "the estimate is still falling or lambda is not pushing")
        return (f"{head}: NOT CONVERGED: violated by up to {worst * 100:+.1f}% of eps; {why}; {lam}: train longer "
                f"or raise the dual step (dual_lr); smallest left-hand side {c.lhs_min:.4g} (member "
                f"{c.lhs_min_member})")
    relaxed = [m.relaxation for m in ms if m.relaxation > TOL * c.eps]
    how = (f"the resilient method relaxed it by {min(relaxed) / c.eps * 100:.0f}-{max(relaxed) / c.eps * 100:.0f}% "
           "of eps" if relaxed else "its left-hand side levelled off above eps while lambda kept rising")
    return (f"{head}: LIKELY INFEASIBLE for this model and data: {how}; {lam}; eps = {c.reachable_eps:.4g} was "
            f"reachable with the {c.net} net (smallest left-hand side seen {c.lhs_min:.4g}): raise eps to at least "
            "that, enlarge the network, or relax it at a price (dual_method: resilient)")
