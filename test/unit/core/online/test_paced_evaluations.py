"""The training loop's evaluations (held-out, model metrics) yield to the updates on a busy CPU: with ``paced`` each
runs only once the updates since its previous run used nine times its cost in CPU time, or after its longest delay
(saml_ros.core.online.learner.EVAL_SHARE); unpaced calls evaluate as before."""

from __future__ import annotations

import numpy as np

from saml_ros.core.online import OnlineConfig, OnlineLearner
from saml_ros.core.online import learner as learner_mod
from saml_ros.core.spec import ProblemSpec
from saml_ros.core.systems import get_system
from saml_ros.core.training import TrainConfig

FRICTION = get_system("friction")
SPEC = {"name": "wide", "objective": {"loss": "l2"},
        "constraints": [{"name": "wide", "loss": "l2", "eps": 0.02, "mean": "conditional",
                         "region": {"norm": {"fields": ["x.p", "x.v"], "ord": "inf", "max": 2.0}}}]}


def _learner() -> tuple[OnlineLearner, list[float]]:
    clock = [0.0]
    learner = OnlineLearner(FRICTION, ProblemSpec.for_system(SPEC, FRICTION),
                            OnlineConfig(min_transitions=200, hidden=(8, 8), train=TrainConfig(batch_size=32)),
                            clock=lambda: clock[0])
    rng = np.random.default_rng(3)
    x, u = FRICTION.sample_inputs(3000, rng)
    learner.add_batch(x, u, FRICTION.true_step_np(x, u), stamp=100.0 + 0.1 * np.arange(3000), source=0)
    learner.update(50)
    return learner, clock


def test_paced_evaluations_wait_for_update_time_or_their_longest_delay() -> None:
    learner, clock = _learner()
    first = learner.compute_model_metrics(paced=True)
    assert learner.heldout_report is not None and learner.heldout_report.updates == 50
    learner.update(1)  # far less update time than nine evaluations
    assert learner.compute_model_metrics(paced=True) == first  # the cached metrics: nothing was evaluated
    clock[0] += 1.5  # a held-out period passed, but not the update time
    learner.update(1)
    learner.compute_model_metrics(paced=True)
    assert learner.heldout_report.updates == 50
    clock[0] += learner_mod.HELDOUT_MAX_PERIODS * learner.config.heldout_period  # its longest delay
    again = learner.compute_model_metrics(paced=True)
    assert learner.heldout_report.updates == 52 and again["heldout_updates"] == 52
    # enough update CPU time since the last run: evaluated again without waiting for the longest delay
    cost = learner._paced["heldout"][0]
    clock[0] += 1.5
    while learner._update_cpu - learner._paced["heldout"][1] < cost * (1 - learner_mod.EVAL_SHARE) / \
            learner_mod.EVAL_SHARE:
        learner.update(200)
    learner.compute_model_metrics(paced=True)
    assert learner.heldout_report.updates == learner.updates > 52


def test_unpaced_calls_evaluate_every_held_out_period() -> None:
    learner, clock = _learner()
    learner.compute_model_metrics()
    learner.update(1)
    clock[0] += 1.5
    after = learner.compute_model_metrics()
    assert learner.heldout_report is not None and learner.heldout_report.updates == 51
    assert after["updates"] == 51
