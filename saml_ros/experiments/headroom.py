"""How much a model can matter on a task, and the statistics of a claim about a training method.

* **Headroom**: the base model f_hat alone and the oracle (the TRUE dynamics inside the same MPC,
  ``make_controller(system, "oracle")``) run from the same starts; headroom = (base - oracle) / base, with a 95 %
  confidence interval over the starts (:func:`ratio_ci`). A task with less than :data:`MIN_HEADROOM` cannot show
  a model effect: even a perfect model would change the cost by less than that.
* **Share captured**: for each learned arm, (base - arm) / (base - oracle), one value per training seed.
* **Seed-level test** (:func:`seed_test`): the claim "SA beats UA" is about a training method, so the unit of
  replication is the independently trained model (one per seed); starts and trials are nested inside seeds and are
  averaged per seed first. Pooling the (seed, start) pairs as if independent is pseudo-replication: it shrinks the
  interval by about sqrt(starts) although the variation between trained models is what the claim is about.
* **Verdict** (:func:`verdict`): ``holds`` / ``does not hold`` / ``cannot show``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from saml_ros.experiments.common import Paired, fmt, fmt_p, paired

#: headroom below which a task is marked as unable to show a model effect
MIN_HEADROOM = 0.10


def _t(n: int) -> float:
    import scipy.stats

    return float(scipy.stats.t.ppf(0.975, n - 1)) if n > 1 else math.nan


@dataclass
class Estimate:
    """A value with its 95 % confidence interval over ``n`` units."""

    value: float
    ci_low: float
    ci_high: float
    n: int

    def to_dict(self) -> dict[str, float]:
        return dict(self.__dict__)

    def pct(self, digits: int = 1) -> str:
        """``"17.5 % [16.9, 18.1]"`` (``n/a`` for an undefined interval, e.g. one seed)."""
        def one(v: float) -> str:
            return f"{100 * v:.{digits}f}" if math.isfinite(v) else "n/a"

        return f"{one(self.value)} % [{one(self.ci_low)}, {one(self.ci_high)}]"

    def text(self, digits: int = 3, sci: bool = False) -> str:
        return f"{fmt(self.value, digits, sci)} [{fmt(self.ci_low, digits, sci)}, {fmt(self.ci_high, digits, sci)}]"


def mean_ci(a: Any) -> Estimate:
    """Mean of the finite entries of ``a`` with a Student-t 95 % interval."""
    v = np.asarray(a, dtype=float).ravel()
    v = v[np.isfinite(v)]
    n = int(v.size)
    if n == 0:
        return Estimate(math.nan, math.nan, math.nan, 0)
    m = float(v.mean())
    if n < 2:
        return Estimate(m, math.nan, math.nan, n)
    half = _t(n) * float(v.std(ddof=1)) / math.sqrt(n)
    return Estimate(m, m - half, m + half, n)


def ratio_ci(num: Any, den: Any) -> Estimate:
    """``mean(num) / mean(den)`` over paired units with a delta-method Student-t 95 % interval
    (the interval of a ratio of means: ``se = sd(num - R den) / (sqrt(n) mean(den))``)."""
    a = np.asarray(num, dtype=float).ravel()
    b = np.asarray(den, dtype=float).ravel()
    keep = np.isfinite(a) & np.isfinite(b)
    a, b = a[keep], b[keep]
    n = int(a.size)
    if n == 0 or float(b.mean()) == 0.0:
        return Estimate(math.nan, math.nan, math.nan, n)
    r = float(a.mean() / b.mean())
    if n < 2:
        return Estimate(r, math.nan, math.nan, n)
    se = float(np.std(a - r * b, ddof=1)) / (math.sqrt(n) * abs(float(b.mean())))
    return Estimate(r, r - _t(n) * se, r + _t(n) * se, n)


@dataclass
class Headroom:
    """Base model vs oracle on the same units, and the share of the gap each learned arm closes.

    Attributes:
        base, oracle: mean cost (or failure rate) of the base model and of the oracle.
        headroom: (base - oracle) / base over the units (:func:`ratio_ci`).
        shares: arm -> share of (base - oracle) the arm captures: mean over seeds of the per-seed share
            (base - arm_seed) / (base - oracle), with a t interval over seeds (the base and oracle means are held
            fixed: they do not depend on a training seed).
        per_seed_shares: arm -> the per-seed shares.
    """

    base: float
    oracle: float
    headroom: Estimate
    shares: dict[str, Estimate] = field(default_factory=dict)
    per_seed_shares: dict[str, list[float]] = field(default_factory=dict)

    @property
    def enough(self) -> bool:
        """Whether the task can show a model effect (headroom >= :data:`MIN_HEADROOM`)."""
        return bool(np.isfinite(self.headroom.value) and self.headroom.value >= MIN_HEADROOM)

    def to_dict(self) -> dict[str, Any]:
        return {"base": self.base, "oracle": self.oracle, "headroom": self.headroom.to_dict(),
                "enough": self.enough, "shares": {k: v.to_dict() for k, v in self.shares.items()},
                "per_seed_shares": self.per_seed_shares}

    def line(self) -> str:
        """One sentence for a results table."""
        mark = "" if self.enough else f" — **cannot show a model effect** (headroom < {100 * MIN_HEADROOM:.0f} %)"
        if np.isfinite(self.headroom.value) and self.headroom.value < 0:
            mark += ": the oracle does worse than the base model here"
        shares = "; ".join(f"{k} captures {v.pct(0)} of it" for k, v in self.shares.items())
        return (f"headroom (base − oracle) / base = {self.headroom.pct()} (base {fmt(self.base)}, oracle "
                f"{fmt(self.oracle)}){mark}" + (f"; {shares}" if shares else ""))


def headroom(base: Any, oracle: Any, arms: dict[str, Any] | None = None) -> Headroom:
    """:class:`Headroom` from per-unit costs ``base`` ``(S,)``, ``oracle`` ``(S,)`` and, per learned arm, costs
    ``(n_seeds, S)`` on the same units (lower = better)."""
    b = np.asarray(base, dtype=float).ravel()
    o = np.asarray(oracle, dtype=float).ravel()
    out = Headroom(float(np.nanmean(b)), float(np.nanmean(o)), ratio_ci(b - o, b))
    gap = out.base - out.oracle
    for name, costs in (arms or {}).items():
        c = np.atleast_2d(np.asarray(costs, dtype=float))
        shares = [(out.base - float(np.nanmean(row))) / gap if gap != 0 else math.nan for row in c]
        out.per_seed_shares[name] = shares
        out.shares[name] = mean_ci(shares)
    return out


@dataclass
class SeedTest:
    """SA vs UA with the training seed as the unit (see the module docstring).

    Attributes:
        by_seed: paired comparison of the per-seed means (SA - UA), one pair per seed: the primary test.
        per_seed_a, per_seed_b: per-seed mean and 95 % interval over the starts / trials of that seed.
        pooled: the (seed, start) pairs pooled (reported for comparison only: pseudo-replication).
        relative: (SA - UA) / UA of the means.
    """

    by_seed: Paired
    per_seed_a: list[Estimate]
    per_seed_b: list[Estimate]
    pooled: Paired
    relative: float

    def to_dict(self) -> dict[str, Any]:
        return {"by_seed": self.by_seed.to_dict(), "per_seed_a": [e.to_dict() for e in self.per_seed_a],
                "per_seed_b": [e.to_dict() for e in self.per_seed_b], "pooled": self.pooled.to_dict(),
                "relative": self.relative}

    def line(self, digits: int = 3) -> str:
        p = self.by_seed
        return (f"SA − UA by seed {fmt(p.diff, digits)} [{fmt(p.ci_low, digits)}, {fmt(p.ci_high, digits)}] "
                f"({100 * self.relative:+.1f} %, n = {p.n} seeds, t p = {fmt_p(p.p_ttest)}, SA lower for "
                f"{round(p.frac_b_better * p.n)}/{p.n} seeds); pooled over (seed, start) pairs (pseudo-replication): "
                f"{fmt(self.pooled.diff, digits)} [{fmt(self.pooled.ci_low, digits)}, {fmt(self.pooled.ci_high, digits)}]"
                f", n = {self.pooled.n}")


def seed_test(a: Any, b: Any) -> SeedTest:
    """``a`` (UA) and ``b`` (SA) of shape ``(n_seeds, S)``: row i = the seed-i model on the same S units."""
    a2 = np.atleast_2d(np.asarray(a, dtype=float))
    b2 = np.atleast_2d(np.asarray(b, dtype=float))
    if a2.shape != b2.shape:
        raise ValueError(f"seed_test: shapes differ, {a2.shape} vs {b2.shape}")
    ma, mb = np.nanmean(a2, axis=1), np.nanmean(b2, axis=1)
    rel = float((np.mean(mb) - np.mean(ma)) / np.mean(ma)) if np.mean(ma) != 0 else math.nan
    return SeedTest(paired(ma, mb), [mean_ci(r) for r in a2], [mean_ci(r) for r in b2], paired(a2, b2), rel)


@dataclass
class Power:
    """How many seeds a seed-level paired t test needs to resolve an effect (:func:`power`).

    Attributes:
        sd: standard deviation of the per-seed differences SA - UA (from ``n_measured`` seeds).
        effect: the effect to resolve (same units; e.g. the paper's difference).
        seeds_narrow: the fewest seeds whose 95 % interval half-width ``t sd / sqrt(n)`` is below ``effect``
            (an interval narrower than the effect on either side of its mean).
        seeds_80: the fewest seeds for 80 % power of the two-sided 5 % test against ``effect`` (noncentral t).
    """

    sd: float
    effect: float
    n_measured: int
    seeds_narrow: int
    seeds_80: int

    def to_dict(self) -> dict[str, float]:
        return dict(self.__dict__)

    def line(self, unit: str = "", digits: int = 3) -> str:
        return (f"per-seed SD of SA − UA {fmt(self.sd, digits)}{unit} (from {self.n_measured} seeds): an interval "
                f"narrower than ±{fmt(self.effect, digits)}{unit} needs {self.seeds_narrow} seeds, 80 % power against "
                f"that effect {self.seeds_80} seeds")


def power(diffs: Any, effect: float, max_seeds: int = 10_000) -> Power:
    """Seeds needed (:class:`Power`) for the per-seed differences ``diffs`` (their SD is the spread) to resolve
    ``effect`` (> 0); ``max_seeds`` when even that many do not."""
    import scipy.stats

    d = np.asarray(diffs, dtype=float).ravel()
    d = d[np.isfinite(d)]
    sd = float(d.std(ddof=1)) if d.size > 1 else math.nan
    eff = abs(float(effect))
    if not (math.isfinite(sd) and eff > 0):
        return Power(sd, eff, int(d.size), max_seeds, max_seeds)
    narrow = eighty = max_seeds
    for n in range(2, max_seeds + 1):
        tq = float(scipy.stats.t.ppf(0.975, n - 1))
        if narrow == max_seeds and tq * sd / math.sqrt(n) < eff:
            narrow = n
        if eighty == max_seeds:
            nc = eff / (sd / math.sqrt(n)) if sd > 0 else math.inf
            p = 1.0 if not math.isfinite(nc) else float(
                scipy.stats.nct.sf(tq, n - 1, nc) + scipy.stats.nct.cdf(-tq, n - 1, nc))
            if p >= 0.8:
                eighty = n
        if narrow < max_seeds and eighty < max_seeds:
            break
    return Power(sd, eff, int(d.size), narrow, eighty)


def verdict(enough: bool, test: Paired, expect_lower: bool = True) -> str:
    """``"cannot show"`` without headroom; else ``"holds"`` when the seed-level 95 % interval of SA - UA lies on
    the claimed side of 0 (below it when ``expect_lower``), ``"does not hold"`` otherwise (no significant
    difference, or one in the other direction)."""
    if not enough:
        return "cannot show"
    if not (np.isfinite(test.ci_low) and np.isfinite(test.ci_high)):
        return "does not hold"
    ok = test.ci_high < 0 if expect_lower else test.ci_low > 0
    return "holds" if ok else "does not hold"


@dataclass
class Claim:
    """One line of the claims table: what the paper says, what we measured, the headroom, the verdict."""

    experiment: str
    claim: str
    paper: str
    ours: str
    headroom: str
    verdict: str
    note: str = ""

    def to_dict(self) -> dict[str, str]:
        return dict(self.__dict__)


CLAIMS_HEADER = ("| experiment | claim | paper | ours (95 % CI) | headroom | verdict |\n"
                 "|---|---|---|---|---|---|")


def claims_table(claims: list[Claim]) -> str:
    """The claims as a markdown table (:data:`CLAIMS_HEADER`), notes as footnotes below it."""
    def cell(text: str) -> str:
        return text.replace("|", "\\|")

    rows = [f"| {cell(c.experiment)} | {cell(c.claim)} | {cell(c.paper)} | {cell(c.ours)} | {cell(c.headroom)} | "
            f"**{c.verdict}** |" for c in claims]
    notes = [f"* {c.experiment}, {c.claim}: {c.note}" for c in claims if c.note]
    return "\n".join([CLAIMS_HEADER, *rows, *([""] + notes if notes else [])])
