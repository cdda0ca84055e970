"""Training health (saml_ros.core.training.health): non-finite or exploding losses, gradients and weights never reach
the model, in the plain step, the fast engine and online learning; no checkpoint with a non-finite weight is ever
written, and none is resumed from. The learner node's side (/diagnostics) is in test_learner_node.py."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from saml_ros.core.data.pairing import Transition
from saml_ros.core.model.checkpoint import CheckpointStore
from saml_ros.core.model.io import UnhealthyModel, load_model
from saml_ros.core.model.network import DynamicsModel
from saml_ros.core.online import OnlineConfig, OnlineLearner
from saml_ros.core.spec import ProblemSpec
from saml_ros.core.systems import get_system
from saml_ros.core.training import PrimalDualTrainer, TrainConfig, Transitions, checkpoint_payload
from saml_ros.core.training.health import HealthConfig

SYSTEM = get_system("friction")
SPEC = ProblemSpec.for_system(SYSTEM.paper_spec(), SYSTEM)
#: no plausibility bounds: the training guard is the only line of defence here
OPEN = "{x.p: [-.inf, .inf], x.v: [-.inf, .inf], u.u: [-.inf, .inf]}"


def _data(n: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    return SYSTEM.make_dataset(n, np.random.default_rng(seed))


def _trainer(health: HealthConfig | None = None, **cfg: object) -> PrimalDualTrainer:
    x, u, y = _data(2000, 0)
    model = DynamicsModel(SYSTEM, seed=0)
    model.fit_normalization(x, u, y)
    config = TrainConfig(**{"batch_size": 128, "primal_lr": 3e-3, "dual_lr": 1e-2, **cfg})  # type: ignore[arg-type]
    return PrimalDualTrainer(model, SPEC, config, health)


def _state(tr: PrimalDualTrainer) -> list[torch.Tensor]:
    return [p.detach().clone() for p in tr.model.net.parameters()] + [tr.lam.clone()]


def _batch(seed: int, scale: float = 1.0) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    x, u, y = _data(128, seed)
    return (torch.as_tensor(x, dtype=torch.float32), torch.as_tensor(u, dtype=torch.float32),
            torch.as_tensor(y * scale, dtype=torch.float32))


def test_a_non_finite_minibatch_is_skipped_and_changes_nothing() -> None:
    tr = _trainer()
    for k in range(30):
        tr.step(*_batch(k))
    tr.log.take_pending()
    before = _state(tr)
    x, u, y = _batch(99)
    y[5, 1] = float("nan")
    tr.step(x, u, y)
    x, u, y = _batch(98)
    x[0, 0] = float("inf")
    tr.step(x, u, y)
    assert all(torch.equal(a, b) for a, b in zip(before, _state(tr)))  # nothing reached the model or lambda
    h = tr.health
    assert h.skipped["loss"] == 2 and h.streak == 2 and tr.steps == 32 and "non-finite" in h.last_problem
    tr.step(*_batch(100))
    assert h.streak == 0 and h.healthy_steps == 31
    assert len(tr.log.take_pending()) == 1  # only the healthy step's values went into the training log
    assert all(torch.isfinite(t).all() for t in _state(tr))


def test_an_exploding_minibatch_is_skipped_but_a_lasting_change_of_scale_is_learned() -> None:
    tr = _trainer(HealthConfig(explode_ratio=1e3, rebase_after=20))
    for k in range(40):
        tr.step(*_batch(k))
    before = _state(tr)
    tr.step(*_batch(50, scale=1e5))  # finite, absurd: the objective jumps by ~1e5
    assert tr.health.skipped["loss"] == 1 and "exploding" in tr.health.last_problem
    assert all(torch.equal(a, b) for a, b in zip(before, _state(tr)))
    for k in range(60):  # the new scale persists: after rebase_after skips it is learned from
        tr.step(*_batch(60 + k, scale=1e5))
    assert tr.health.skipped["loss"] == 20 and tr.health.streak == 0
    assert all(torch.isfinite(t).all() for t in _state(tr))


def test_exploding_weights_restore_the_last_healthy_state() -> None:
    tr = _trainer(HealthConfig(max_weight=3.0, snapshot_every=1), primal_optimizer="sgd", primal_lr=1e-3)
    for k in range(10):
        tr.step(*_batch(k))
    healthy = _state(tr)
    tr.primal_opt.param_groups[0]["lr"] = 1e6  # one update throws the weights far beyond max_weight
    tr.step(*_batch(20))
    h = tr.health
    assert h.skipped["weights"] == 1 and h.restores == 1 and "exploding weights" in h.last_problem
    assert all(torch.equal(a, b) for a, b in zip(healthy, _state(tr)))


@pytest.mark.parametrize("engine", ["fast", "plain"])
def test_fit_on_data_with_a_poisoned_row_skips_its_minibatches_and_still_learns(engine: str) -> None:
    x, u, y = _data(3000, 1)
    y[123] = [np.nan, 1e30]
    model = DynamicsModel(SYSTEM, seed=0)
    model.fit_normalization(x[:122], u[:122], y[:122])
    tr = PrimalDualTrainer(model, SPEC, TrainConfig(batch_size=128, primal_lr=3e-3, dual_lr=1e-2, epochs=6,
                                                     engine=engine, log_every=10, dual_method="paper"))
    clean = Transitions(model, SPEC, *_data(2000, 2))
    before = float(tr.evaluate(clean)["objective"][0])
    tr.fit(Transitions(model, SPEC, x, u, y))
    assert tr.engine_used == engine
    h = tr.health
    assert h.skipped["loss"] >= 6  # every epoch's minibatch holding row 123 (the fast engine: its whole block)
    assert h.healthy_steps > 0.5 * tr.steps
    assert all(torch.isfinite(t).all() for t in _state(tr))
    assert float(tr.evaluate(clean)["objective"][0]) < 0.7 * before  # it kept learning
    assert np.isfinite(np.array(tr.history.objective)).all()  # skipped steps stay out of the history


def test_no_checkpoint_with_non_finite_weights_is_ever_written(tmp_path: Path) -> None:
    tr = _trainer()
    tr.step(*_batch(0))
    arrays, meta = checkpoint_payload(tr)
    assert meta["health"]["healthy"] and meta["health"]["finite"] and meta["health"]["max_abs_weight"] > 0
    with torch.no_grad():
        tr.model.net.weights[0][0, 0, 0] = float("nan")  # e.g. a bug elsewhere
    with pytest.raises(UnhealthyModel, match="non-finite"):
        checkpoint_payload(tr)
    store = CheckpointStore(tmp_path / "run")
    from saml_ros.core.training import save_checkpoint

    with pytest.raises(UnhealthyModel):
        save_checkpoint(store, tr)
    assert store.versions() == [] and not store.latest_path.exists()


def test_online_learning_with_absurd_transitions_stays_healthy_keeps_learning_and_writes_finite_checkpoints(
    tmp_path: Path,
) -> None:
    """No plausibility bounds: absurd but finite transitions reach the replay buffer. The minibatches holding them
    are skipped, the rest train the model, and every checkpoint is finite and records its health."""
    store = CheckpointStore(tmp_path / "run", keep=100)
    cfg = OnlineConfig(min_transitions=200, train=TrainConfig(batch_size=64, primal_lr=3e-3, dual_lr=1e-2),
                       buffer_capacity=5000, plausible_bounds=OPEN)
    learner = OnlineLearner(SYSTEM, SPEC, cfg, store=store)
    x, u, y = _data(1500, 3)
    learner.add_batch(x, u, y)
    learner.update(50)
    cx, cu, cy = _data(1000, 9)

    def clean_error() -> float:
        return float(np.linalg.norm(learner.model.predict_np(cx, cu) - cy, axis=1).mean())

    before = clean_error()
    bad_x, bad_u, bad_y = _data(4, 4)
    bad_y[:, 1] = [1e200, -1e200, 1e180, 3e38]
    for i in range(4):  # absurd finite values, as a faulty robot would send them
        learner.add(Transition(bad_x[i], bad_u[i], bad_y[i], 10**9 + i, 0))
    for _ in range(6):
        learner.update(100)
        assert learner.save_checkpoint() is not None
    status = learner.status()
    assert status["train_health/skipped/loss"] > 20 and status["train_health/unhealthy_streak"] < 10
    assert status["train_health/healthy_steps"] > 350 and status["checkpoints_unhealthy"] == 0
    assert clean_error() < 0.8 * before  # it kept learning
    assert all(torch.isfinite(t).all() for t in _state(learner.trainer))  # type: ignore[arg-type]
    for v in store.versions():
        loaded = load_model(store.path_for(v))
        assert all(torch.isfinite(t).all() for t in loaded.model.state_dict().values())
        assert loaded.meta["health"]["healthy"] and loaded.meta["health"]["skipped"]["loss"] >= 0
        ev = loaded.meta["evidence"]
        assert ev["n"] >= 1500 and ev["residual_max"][1] > 1e100  # the evidence says what the data held


def test_resume_passes_over_a_checkpoint_with_non_finite_weights(tmp_path: Path) -> None:
    store = CheckpointStore(tmp_path / "run")
    cfg = OnlineConfig(min_transitions=200, train=TrainConfig(batch_size=64), buffer_capacity=5000)
    learner = OnlineLearner(SYSTEM, SPEC, cfg, store=store)
    learner.add_batch(*_data(300, 5))
    learner.update(20)
    good = learner.save_checkpoint()
    assert good is not None
    arrays, meta = checkpoint_payload(learner.trainer)  # type: ignore[arg-type]
    key = next(k for k in arrays if k.startswith("model/") and "weights" in k)
    arrays[key] = np.full_like(arrays[key], np.nan)  # a foreign writer's poisoned file becomes `latest`
    store.save(arrays, meta)
    resumed = OnlineLearner(SYSTEM, SPEC, cfg, store=store)
    assert resumed.resumed is not None and resumed.resumed.version == good[1]
    assert resumed.checkpoints_skipped == 1 and "non-finite" in resumed.resumed.skipped[0][1]
