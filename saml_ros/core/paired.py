"""Paired comparisons of two arms on the same units (starts, trials, seeds) and the number formats of their tables:
:class:`Paired` / :func:`paired` (mean difference with its Student-t 95 % interval, paired t and Wilcoxon tests),
:class:`PairedRate` / :func:`paired_rate` (exact McNemar on binary outcomes), :func:`mean_std`, :func:`fmt`.

Used by the demo's evaluation and the experiments (both above the core), so it lives below both.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np


def mean_std(a: Any) -> tuple[float, float]:
    """Mean and sample standard deviation (ddof = 1; 0 for a single value) of the finite entries of ``a``."""
    v = np.asarray(a, dtype=float).ravel()
    v = v[np.isfinite(v)]
    if v.size == 0:
        return math.nan, math.nan
    return float(v.mean()), float(v.std(ddof=1)) if v.size > 1 else 0.0


def fmt_ms(a: Any, digits: int = 3, sci: bool = False) -> str:
    """``"mean ± std"`` of ``a`` (see :func:`mean_std`); just the value when ``a`` holds one number."""
    m, s = mean_std(a)
    if np.asarray(a).size == 1:
        return fmt(m, digits, sci)
    return f"{fmt(m, digits, sci)} ± {fmt(s, digits, sci)}"


def fmt(x: float, digits: int = 3, sci: bool = False) -> str:
    """A number for a table: fixed point with ``digits`` decimals, or scientific with ``sci``."""
    if x is None or not math.isfinite(float(x)):
        return "n/a"
    return f"{x:.{digits}e}" if sci else f"{x:.{digits}f}"


@dataclass
class Paired:
    """Paired comparison of ``b`` against ``a`` on the same units (start states, trials, seeds).

    Attributes:
        n: number of pairs (pairs with a non-finite value are dropped).
        mean_a, mean_b: means of the two samples over the kept pairs.
        diff: mean of ``b - a``.
        ci_low, ci_high: 95 % confidence interval of the mean difference (Student t, n - 1 dof).
        p_ttest: two-sided paired t-test p-value (``scipy.stats.ttest_rel``).
        p_wilcoxon: two-sided Wilcoxon signed-rank p-value (NaN when every difference is zero or n < 2).
        frac_b_better: fraction of pairs with ``b < a`` (lower is better for costs and errors).
    """

    n: int
    mean_a: float
    mean_b: float
    diff: float
    ci_low: float
    ci_high: float
    p_ttest: float
    p_wilcoxon: float
    frac_b_better: float

    def to_dict(self) -> dict[str, float]:
        return dict(self.__dict__)

    def row(self, label: str, digits: int = 3, sci: bool = False) -> str:
        """A markdown table row (see :data:`PAIRED_HEADER`)."""
        return (f"| {label} | {self.n} | {fmt(self.diff, digits, sci)} | [{fmt(self.ci_low, digits, sci)}, "
                f"{fmt(self.ci_high, digits, sci)}] | {fmt_p(self.p_ttest)} | {fmt_p(self.p_wilcoxon)} | "
                f"{100 * self.frac_b_better:.0f}% |")


PAIRED_HEADER = ("| quantity | pairs | mean diff (SA − UA) | 95% CI | paired t p | Wilcoxon p | SA lower |\n"
                 "|---|---|---|---|---|---|---|")


def fmt_p(p: float) -> str:
    if p is None or not math.isfinite(p):
        return "n/a"
    return f"{p:.2g}" if p >= 1e-4 else "<1e-4"


def paired(a: Any, b: Any) -> Paired:
    """Compare paired samples ``a`` (e.g. Uniformly Accurate) and ``b`` (Sufficiently Accurate); ``b - a``."""
    import scipy.stats

    a = np.asarray(a, dtype=float).ravel()
    b = np.asarray(b, dtype=float).ravel()
    if a.shape != b.shape:
        raise ValueError(f"paired samples must have the same length, got {a.shape} and {b.shape}")
    keep = np.isfinite(a) & np.isfinite(b)
    a, b = a[keep], b[keep]
    n = int(a.size)
    nan = math.nan
    if n == 0:
        return Paired(0, nan, nan, nan, nan, nan, nan, nan, nan)
    d = b - a
    diff = float(d.mean())
    lo = hi = p_t = p_w = nan
    if n >= 2:
        sd = float(d.std(ddof=1))
        if sd > 0:
            half = float(scipy.stats.t.ppf(0.975, n - 1)) * sd / math.sqrt(n)
            lo, hi = diff - half, diff + half
            p_t = float(scipy.stats.ttest_rel(b, a).pvalue)
        else:
            lo = hi = diff
            p_t = 1.0 if diff == 0 else 0.0
        if np.any(d != 0):
            p_w = float(scipy.stats.wilcoxon(b, a).pvalue)
    return Paired(n, float(a.mean()), float(b.mean()), diff, lo, hi, p_t, p_w, float(np.mean(b < a)))


@dataclass
class PairedRate:
    """Paired comparison of two binary outcomes (e.g. failures) on the same trials: exact McNemar test.

    Attributes:
        n: trials; rate_a, rate_b: outcome rates; only_a / only_b: discordant trials; p_mcnemar: two-sided
        exact McNemar p-value (binomial test on the discordant pairs; 1 when there are none).
    """

    n: int
    rate_a: float
    rate_b: float
    only_a: int
    only_b: int
    p_mcnemar: float

    def to_dict(self) -> dict[str, float]:
        return dict(self.__dict__)


def paired_rate(a: Any, b: Any) -> PairedRate:
    """McNemar comparison of boolean outcomes ``a`` and ``b`` over the same trials."""
    import scipy.stats

    a = np.asarray(a, dtype=bool).ravel()
    b = np.asarray(b, dtype=bool).ravel()
    only_a, only_b = int(np.sum(a & ~b)), int(np.sum(b & ~a))
    k = only_a + only_b
    p = float(scipy.stats.binomtest(only_b, k, 0.5).pvalue) if k else 1.0
    n = int(a.size)
    return PairedRate(n, float(a.mean()) if n else math.nan, float(b.mean()) if n else math.nan,
                      only_a, only_b, p)
