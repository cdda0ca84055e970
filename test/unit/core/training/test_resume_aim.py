"""A resumed trainer keeps training at the bounds its checkpoint's training aimed at (``meta["aim"]``: the margin
below eps sized by the held-out uncertainty), offline (``resume_trainer``) and in the online learner's resume;
its checkpoints still record the problem as given (eps) with the aim beside it."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from saml_ros.core.model.checkpoint import CheckpointStore
from saml_ros.core.model.io import load_model
from saml_ros.core.model.network import DynamicsModel
from saml_ros.core.online import OnlineConfig, OnlineLearner
from saml_ros.core.spec import ProblemSpec
from saml_ros.core.systems import get_system
from saml_ros.core.training import PrimalDualTrainer, TrainConfig, Transitions, resume_trainer, save_checkpoint
from saml_ros.core.training.verdict import AimReport, aimed_spec, recorded_aim


def _aimed_checkpoint(run: Path) -> tuple[Any, ProblemSpec, float, Path]:
    """A friction checkpoint as ``train --margin auto`` writes it: the spec at eps, trained at 0.9 eps (the aim
    record beside it)."""
    system = get_system("friction")
    spec = ProblemSpec.for_system(system.paper_spec(), system)
    eps = spec.constraints[0].eps
    x, u, y = system.make_dataset(256, np.random.default_rng(0))
    model = DynamicsModel(system, seed=0)
    model.fit_normalization(x, u, y)
    tr = PrimalDualTrainer(model, spec, TrainConfig(epochs=1, batch_size=64, engine="plain"))
    report = AimReport("auto", spec.constraint_names, [eps], [0.9 * eps], [0.001], [0.0005], 1.0)
    tr.spec = aimed_spec(spec, report.aim)
    tr.fit(Transitions(model, tr.spec, x, u, y), diagnose=False)
    tr.spec = spec  # as train_models leaves it: the problem as given; the aim goes into the meta
    path, _ = save_checkpoint(CheckpointStore(run), tr, extra={"aim": report.to_dict()})
    return system, spec, eps, path


def test_resume_trainer_aims_where_the_checkpoint_aimed_and_records_eps(tmp_path: Path) -> None:
    system, spec, eps, path = _aimed_checkpoint(tmp_path / "run")
    resumed = resume_trainer(load_model(path, expect=system))
    assert resumed.spec.constraints[0].eps == pytest.approx(0.9 * eps)  # trains at the aim, not at eps
    assert resumed.given_spec is not None and resumed.given_spec.constraints[0].eps == eps
    # its own checkpoint records the problem as given and the aim; resumed again, the aim is not applied twice
    again, _ = save_checkpoint(CheckpointStore(tmp_path / "run2"), resumed)
    loaded = load_model(again, expect=system)
    assert loaded.spec.constraints[0].eps == eps and loaded.meta["aim"]["constraints"]["near_origin"]["aim"] == \
        pytest.approx(0.9 * eps)
    assert resume_trainer(loaded).spec.constraints[0].eps == pytest.approx(0.9 * eps)


def test_the_online_learner_resumes_at_the_aim_and_judges_against_eps(tmp_path: Path) -> None:
    system, spec, eps, _ = _aimed_checkpoint(tmp_path / "run")
    learner = OnlineLearner(system, spec, OnlineConfig(), store=CheckpointStore(tmp_path / "run"))
    assert learner.trainer is not None and learner.resumed is not None
    assert learner.trainer.spec.constraints[0].eps == pytest.approx(0.9 * eps)
    assert learner.spec.constraints[0].eps == eps  # the verdicts read against eps


def test_an_aim_for_another_bound_is_not_applied(tmp_path: Path) -> None:
    system, spec, eps, _ = _aimed_checkpoint(tmp_path / "run")
    record = AimReport("auto", spec.constraint_names, [eps], [0.9 * eps]).to_dict()
    assert recorded_aim(record, spec) == [pytest.approx(0.9 * eps)]
    other = ProblemSpec.from_dict({**spec.to_dict(), "constraints": [{**spec.to_dict()["constraints"][0],
                                                                        "eps": 2 * eps}]},
                                  spec.state, spec.control, spec.target)
    assert recorded_aim(record, other) is None and recorded_aim({"margin": "none"}, spec) is None
    learner = OnlineLearner(system, other, OnlineConfig(), store=CheckpointStore(tmp_path / "run"))
    assert learner.trainer is not None and learner.trainer.spec.constraints[0].eps == 2 * eps
