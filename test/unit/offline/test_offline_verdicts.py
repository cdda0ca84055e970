"""Offline verdicts on held-out data (saml_ros.core.training.verdict), the aim below eps, the restart selection on
held-out estimates, whole stretches of time held out of recordings, and what `train` prints, stores and exits with."""

from __future__ import annotations

import math

import numpy as np
import pytest
from helpers.offline import WIDE

from saml_ros.core.spec import ProblemSpec
from saml_ros.core.systems import get_system
from saml_ros.core.training import TrainConfig, Transitions
from saml_ros.core.training import heldout as H
from saml_ros.core.training.selection import MET_STATUS, UNCONFIRMED_STATUS, VIOLATED_STATUS, choose
from saml_ros.core.training.verdict import aim_bounds, aimed_spec, read_verdicts, spec_estimates
from saml_ros.offline.pipelines import parse_margin, stretch_split, train_models

FRICTION = get_system("friction")


def test_aim_bounds_and_margins() -> None:
    assert aim_bounds([1.0], [0.03], [0.04]) == [pytest.approx(1.0 - H.Z * 0.05)]
    assert aim_bounds([1.0], [math.inf], [0.01]) == [1.0]  # nothing measured: eps
    assert aim_bounds([1.0], [0.5], [0.5]) == [0.5]  # never below half of eps
    assert parse_margin("auto") == "auto" and parse_margin("none") is None and parse_margin("0") is None
    assert parse_margin(0.1) == 0.1
    with pytest.raises(ValueError, match="margin"):
        parse_margin("0.6")
    spec = ProblemSpec.for_system(FRICTION.paper_spec(), FRICTION)
    aimed = aimed_spec(spec, [0.03])
    assert aimed.constraints[0].eps == 0.03 and spec.constraints[0].eps == 0.035
    assert aimed.constraints[0].region is not None and aimed.describe().endswith("<= 0.03")


def test_fixed_margin_trains_at_the_lower_bound_and_reports_against_eps() -> None:
    """``margin=0.2``: the whole run aims at 0.8 eps; the diagnosis is against the aim, the verdict against eps."""
    spec = ProblemSpec.for_system(WIDE, FRICTION)
    x, u, y = FRICTION.make_dataset(2000, np.random.default_rng(0))
    res = train_models(FRICTION, spec, x, u, y, TrainConfig(epochs=20), [0], margin=0.2)
    assert res.aimed == [pytest.approx(0.096)] and res.trainer.spec is spec
    assert res.trainer.diagnosis is not None and res.trainer.diagnosis.constraints[0].eps == pytest.approx(0.096)
    assert res.training is not None and res.training[0, 0] <= 0.096 * 1.01
    test = FRICTION.make_dataset(20000, np.random.default_rng(1))
    _, held = spec_estimates(res.model, spec, Transitions(res.model, spec, *test))
    v = read_verdicts(spec, held, res.training, res.aimed, res.trainer.diagnosis)
    assert v.constraints[0].eps == 0.12 and v.constraints[0].verdict == H.MET and v.level == 0


def test_verdicts_over_members_and_without_held_out_data() -> None:
    spec = ProblemSpec.for_system(FRICTION.paper_spec(), FRICTION)
    est = [[H.Estimate(0.030, 0.001, 500), H.Estimate(0.0345, 0.001, 500), H.Estimate(0.040, 0.001, 500)]]
    v = read_verdicts(spec, est, np.array([[0.031], [0.034], [0.034]]))
    c = v.constraints[0]
    assert [m.verdict for m in c.members] == [H.MET, H.UNCONFIRMED, H.MET_ON_TRAINING_ONLY]
    assert c.verdict == H.MET_ON_TRAINING_ONLY and c.n_met == 1 and v.level == 1 and not v.all_met
    assert "member 1 unconfirmed" in c.message and "member 2 met on training data only" in c.message
    none = read_verdicts(spec, None, np.array([[0.03]]))
    assert none.constraints[0].verdict == H.NO_HELDOUT and "no held-out sample" in none.constraints[0].message


def test_selection_reads_held_out_estimates_with_their_standard_errors() -> None:
    """Rule: met with confidence first, then held-out mean within the bound, then the least violating; the lowest
    objective within a tier. A 1 % tolerance on the mean alone would keep member 1 (lower objective, mean just below
    eps, but its upper bound above)."""
    e = [0.035]
    obj = [H.Estimate(0.030, 0.0005, 3000), H.Estimate(0.022, 0.0005, 3000), H.Estimate(0.020, 0.0005, 3000)]
    cons = [[H.Estimate(0.031, 0.0008, 600)], [H.Estimate(0.0345, 0.003, 150)], [H.Estimate(0.050, 0.002, 150)]]
    assert choose(obj, cons, e, [0, 1, 2]) == (0, MET_STATUS)
    assert choose(obj, cons, e, [1, 2]) == (1, UNCONFIRMED_STATUS)
    assert choose(obj, cons, e, [2]) == (2, VIOLATED_STATUS)
    few = [[H.Estimate(0.02, 0.01, 5)], [H.Estimate(0.05, 0.001, 5)]]  # too few region samples to tell
    assert choose(obj[:2], few, e, [0, 1]) == (0, UNCONFIRMED_STATUS)


def test_recordings_are_split_in_whole_stretches_of_time() -> None:
    """Two sources (bags or namespaces) interleaved in the array, stamps not sorted: a fifth of each source is held
    out in two contiguous stretches spread over its recording; nothing is lost or duplicated; time order kept."""
    rng = np.random.default_rng(0)
    source = np.repeat([0, 1], [1000, 500])
    stamps = np.concatenate([np.arange(1000) * 10, np.arange(500) * 10 + 5])
    perm = rng.permutation(len(source))
    source, stamps = source[perm], stamps[perm]
    kept, held = stretch_split(stamps, source, 0.2)
    assert sorted(np.concatenate([kept, held]).tolist()) == list(range(1500))
    for src, n in ((0, 1000), (1, 500)):
        h = held[source[held] == src]
        assert len(h) == n // 5
        rank = np.argsort(np.argsort(stamps[source == src]))  # each transition's place in its recording
        order = {int(i): int(r) for i, r in zip(np.flatnonzero(source == src), rank)}
        places = np.array([order[int(i)] for i in h])
        assert (np.diff(places) >= 1).all()  # in time order
        runs = np.split(places, np.flatnonzero(np.diff(places) > 1) + 1)
        assert len(runs) == 2 and all(len(r) == n // 10 for r in runs)  # two whole stretches
        assert runs[0][0] > 0 and runs[1][-1] < n - 1 and runs[1][0] - runs[0][-1] > n // 3  # spread out
        k = kept[source[kept] == src]
        assert (np.diff(stamps[k]) > 0).all()
    with pytest.raises(ValueError, match="fraction"):
        stretch_split(stamps, source, 1.0)
