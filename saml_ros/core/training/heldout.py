"""Held-out estimates of a constraint's left-hand side, and the verdict read on them.

A constraint ``E[l | region] <= eps`` (conditional) or ``E[l I_region] <= eps`` (unconditional) is judged on data
the model did not train on. The estimate carries its standard error, and "met" means met *there, with stated
confidence*: the upper end of the one-sided interval, ``mean + z se``, is at most ``eps``. A model that meets the
bound on its training data only gets its own verdict.

Samples of a live stream are strongly correlated (consecutive transitions at 100 Hz are nearly identical), so the
standard error of a stream's mean comes from **batch means**: the samples, in time order, are cut into
``blocks`` contiguous blocks and the spread of the block means gives the error (an iid formula would understate
it by the square root of the correlation time). Offline data drawn independently may use ``blocks=None`` (iid).

Everything here is numpy only; the learner (online), ``train`` (offline), the restart selection and the metrics
files all read their verdicts through :func:`constraint_estimate` and :func:`heldout_verdict`.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

#: one-sided 95 % normal quantile: "met" when mean + Z * se <= eps
Z = 1.645
#: fewer held-out samples (in the region, for a conditional constraint) than this: no verdict can be read
MIN_N = 30
#: blocks of the batch-means standard error for a stream (at least 2 samples per block are needed)
STREAM_BLOCKS = 20

MET = "met"                              # held-out upper bound <= eps
UNCONFIRMED = "unconfirmed"              # held-out mean <= eps < its upper bound: more held-out data needed
MET_ON_TRAINING_ONLY = "met_on_training_only"  # training value <= eps, held-out mean > eps
NOT_MET = "not_met"                      # neither
NO_HELDOUT = "no_heldout_data"           # fewer than MIN_N held-out samples
#: verdict -> diagnostic_msgs level (0 OK, 1 WARN, 2 ERROR) and the number published in telemetry
HELDOUT_CODES: dict[str, int] = {MET: 0, UNCONFIRMED: 1, MET_ON_TRAINING_ONLY: 1, NO_HELDOUT: 1, NOT_MET: 2}


@dataclass(frozen=True)
class Estimate:
    """A mean with its standard error: ``mean`` in the loss's units, ``se`` the same units, ``n`` samples used
    (in the region for a conditional constraint), ``blocks`` the batch-means blocks (0 = iid formula)."""

    mean: float
    se: float
    n: int
    blocks: int = 0

    def upper(self, z: float = Z) -> float:
        """The upper end of the one-sided interval at ``z`` standard errors."""
        return self.mean + z * self.se

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Estimate:
        return cls(float(d["mean"]), float(d["se"]), int(d["n"]), int(d.get("blocks", 0)))


def mean_estimate(values: np.ndarray, blocks: int | None = None) -> Estimate:
    """The mean of ``values`` (1-d, in time order for a stream) and its standard error: iid when ``blocks`` is
    None, else batch means over ``min(blocks, n // 2)`` contiguous blocks (fewer than 2 blocks: iid). Empty input:
    mean and se NaN, n 0."""
    v = np.asarray(values, dtype=np.float64).ravel()
    n = v.size
    if n == 0:
        return Estimate(math.nan, math.nan, 0, 0)
    mean = float(v.mean())
    k = 0 if blocks is None else min(int(blocks), n // 2)
    if k >= 2:
        means = np.array([b.mean() for b in np.array_split(v, k)])
        # a block mean's variance, scaled to the mean of n samples (blocks differ by at most one sample)
        se = float(means.std(ddof=1) / math.sqrt(k))
    else:
        k = 0
        se = float(v.std(ddof=1) / math.sqrt(n)) if n > 1 else math.inf
    return Estimate(mean, se, n, k)


def constraint_estimate(losses: np.ndarray, in_region: np.ndarray, conditional: bool,
                        blocks: int | None = None) -> Estimate:
    """The held-out estimate of a constraint's left-hand side ``E[l | region]`` (``conditional``) or
    ``E[l I_region]`` from per-sample ``losses`` (N,) and the region mask ``in_region`` (N,) bool, both in time
    order for a stream. For the unconditional form ``n`` counts the samples in the region (what the estimate
    rests on), although the mean runs over all of them."""
    losses = np.asarray(losses, dtype=np.float64).ravel()
    mask = np.asarray(in_region, dtype=bool).ravel()
    if losses.shape != mask.shape:
        raise ValueError(f"losses {losses.shape} and in_region {mask.shape} differ in shape")
    if conditional:
        return mean_estimate(losses[mask], blocks)
    est = mean_estimate(np.where(mask, losses, 0.0), blocks)
    return Estimate(est.mean, est.se, int(mask.sum()), est.blocks)


def heldout_verdict(eps: float, heldout: Estimate | None, train_value: float | None = None, z: float = Z,
                    min_n: int = MIN_N) -> str:
    """The verdict on a bound ``eps`` from the ``heldout`` estimate of its left-hand side (and the training
    value, the same left-hand side on the training data, when known): :data:`MET`, :data:`UNCONFIRMED`,
    :data:`MET_ON_TRAINING_ONLY`, :data:`NOT_MET` or :data:`NO_HELDOUT`."""
    if heldout is None or heldout.n < min_n or not math.isfinite(heldout.mean):
        return NO_HELDOUT
    if math.isfinite(heldout.se) and heldout.upper(z) <= eps:
        return MET
    if heldout.mean <= eps:
        return UNCONFIRMED
    if train_value is not None and math.isfinite(train_value) and train_value <= eps:
        return MET_ON_TRAINING_ONLY
    return NOT_MET


def aim(eps: float, se: float, z: float = Z, max_fraction: float = 0.5) -> float:
    """The bound training aims at so that a model that meets it on its data stays met on fresh data: ``eps``
    less ``z`` standard errors of the held-out estimate, never below ``(1 - max_fraction) eps`` (an estimate
    with few samples must not push the target to zero). A non-finite ``se`` aims at ``eps``."""
    if not math.isfinite(se) or se <= 0.0:
        return float(eps)
    return float(max(eps - z * se, (1.0 - max_fraction) * eps))
