"""Held-out estimates and verdicts (saml_ros.core.training.heldout)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from saml_ros.core.training import heldout as H


def test_iid_standard_error_matches_the_formula() -> None:
    rng = np.random.default_rng(0)
    v = rng.normal(1.0, 2.0, 400)
    est = H.mean_estimate(v)
    assert est.mean == pytest.approx(v.mean())
    assert est.se == pytest.approx(v.std(ddof=1) / 20.0)
    assert est.n == 400 and est.blocks == 0


def test_batch_means_see_the_correlation_the_iid_formula_misses() -> None:
    """An AR(1) stream with correlation 0.99: the iid standard error is far too small; batch means are close to
    the spread of the mean over independent streams."""
    rng = np.random.default_rng(1)
    means, iid, bm = [], [], []
    for _ in range(200):
        e = rng.normal(size=4000)
        x = np.empty(4000)
        x[0] = e[0]
        for t in range(1, 4000):
            x[t] = 0.99 * x[t - 1] + math.sqrt(1 - 0.99**2) * e[t]
        means.append(x.mean())
        iid.append(H.mean_estimate(x).se)
        bm.append(H.mean_estimate(x, blocks=H.STREAM_BLOCKS).se)
    true_se = float(np.std(means))
    assert np.median(iid) < 0.25 * true_se
    assert 0.6 * true_se < np.median(bm) < 1.4 * true_se


def test_conditional_and_unconditional_estimates() -> None:
    losses = np.array([1.0, 2.0, 3.0, 4.0])
    mask = np.array([True, False, True, False])
    cond = H.constraint_estimate(losses, mask, conditional=True)
    assert cond.mean == pytest.approx(2.0) and cond.n == 2
    unc = H.constraint_estimate(losses, mask, conditional=False)
    assert unc.mean == pytest.approx(1.0) and unc.n == 2
    with pytest.raises(ValueError, match="shape"):
        H.constraint_estimate(losses, mask[:3], conditional=True)
    empty = H.constraint_estimate(losses, np.zeros(4, bool), conditional=True)
    assert empty.n == 0 and math.isnan(empty.mean)


@pytest.mark.parametrize(("mean", "se", "train", "want"), [
    (0.8, 0.05, 0.9, H.MET),                       # upper 0.88 <= 1
    (0.95, 0.05, 0.9, H.UNCONFIRMED),              # mean below, upper above
    (1.1, 0.01, 0.9, H.MET_ON_TRAINING_ONLY),      # fits its data, not the held-out data
    (1.1, 0.01, 1.2, H.NOT_MET),
    (1.1, 0.01, None, H.NOT_MET),
])
def test_verdicts(mean: float, se: float, train: float | None, want: str) -> None:
    assert H.heldout_verdict(1.0, H.Estimate(mean, se, 500), train) == want


def test_too_few_heldout_samples_give_no_verdict() -> None:
    assert H.heldout_verdict(1.0, H.Estimate(0.1, 0.01, H.MIN_N - 1), 0.1) == H.NO_HELDOUT
    assert H.heldout_verdict(1.0, None, 0.1) == H.NO_HELDOUT
    assert H.HELDOUT_CODES[H.MET] == 0 and H.HELDOUT_CODES[H.NOT_MET] == 2


def test_a_model_that_memorises_its_data_is_not_met() -> None:
    """Training error far below eps, held-out error above: the verdict says so."""
    rng = np.random.default_rng(2)
    train = H.constraint_estimate(rng.uniform(0, 0.002, 1000), np.ones(1000, bool), True)
    held = H.constraint_estimate(rng.uniform(0, 0.02, 1000), np.ones(1000, bool), True, blocks=H.STREAM_BLOCKS)
    assert H.heldout_verdict(0.005, held, train.mean) == H.MET_ON_TRAINING_ONLY


def test_aim_leaves_a_margin_sized_by_the_error() -> None:
    assert H.aim(1.0, 0.1) == pytest.approx(1.0 - H.Z * 0.1)
    assert H.aim(1.0, 10.0) == pytest.approx(0.5)
    assert H.aim(1.0, math.inf) == 1.0 and H.aim(1.0, 0.0) == 1.0
    est = H.Estimate(0.5, 0.1, 100, 20)
    assert H.Estimate.from_dict(est.to_dict()) == est
