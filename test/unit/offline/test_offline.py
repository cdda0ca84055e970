"""Offline pipeline: the Sufficiently Accurate trade-off on the double integrator, the train CLI."""

from __future__ import annotations

from saml_ros.core.spec import ProblemSpec
from saml_ros.core.systems import get_system
from saml_ros.core.training import TrainConfig
from saml_ros.offline.pipelines import compare


def test_sufficient_beats_uniform_inside_region_and_loses_outside() -> None:
    """A short version of the paper's double-integrator experiment (5k samples, 30 epochs, a faster dual
    step than the paper's 1e-4 so the multiplier becomes active within the budget); the full run is
    `./dev demo --offline` (docs/results.md)."""
    system = get_system("friction")
    spec = ProblemSpec.for_system(system.paper_spec(), system)
    cmp = compare(system, spec, TrainConfig.paper(epochs=30, batch_size=128, dual_lr=1e-2), seeds=[0, 1, 2],
                  n_train=5000, n_test=20000)
    sa, ua = cmp.eval_sufficient.regions[0], cmp.eval_uniform.regions[0]
    assert (sa.inside < ua.inside).all(), (sa.inside, ua.inside)     # every seed, paired
    assert sa.outside.mean() > ua.outside.mean()
    assert cmp.claim_holds()
    assert (cmp.sufficient.trainer.lam > 0).all() and cmp.uniform.trainer.lam.numel() == 0
    assert "| Sufficiently Accurate |" in cmp.table()
