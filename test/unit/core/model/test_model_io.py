"""Model checkpoints: round trip, exact resume, incompatible checkpoints refused."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

from saml_ros.core.model.checkpoint import CheckpointError, CheckpointStore, read_checkpoint, write_checkpoint
from saml_ros.core.model.io import IncompatibleCheckpoint, load_model
from saml_ros.core.model.network import DynamicsModel
from saml_ros.core.spec import ProblemSpec
from saml_ros.core.systems import get_system
from saml_ros.core.training import PrimalDualTrainer, TrainConfig, Transitions, resume_trainer, save_checkpoint


def _trained(tmp_path: Path, steps_epochs: Any = 2) -> Any:
    system = get_system("friction")
    spec = ProblemSpec.for_system(system.paper_spec(), system)
    x, u, y = system.make_dataset(512, np.random.default_rng(0))
    model = DynamicsModel(system, seed=0)
    model.fit_normalization(x, u, y)
    tr = PrimalDualTrainer(model, spec, TrainConfig(epochs=steps_epochs, batch_size=64, dual_lr=1e-2))
    data = Transitions(model, spec, x, u, y)
    tr.fit(data)
    return system, spec, tr, data


def test_round_trip_predictions_and_metadata(tmp_path: Path) -> None:
    system, spec, tr, data = _trained(tmp_path)
    store = CheckpointStore(tmp_path / "run")
    path, version = save_checkpoint(store, tr, metrics={"objective": 0.1})
    loaded = load_model(path, expect=system)
    assert loaded.version == version == 1
    x = np.random.default_rng(1).uniform(-1, 1, (50, 2))
    u = np.random.default_rng(2).uniform(-5, 5, (50, 1))
    np.testing.assert_array_equal(loaded.model.predict_np(x, u), tr.model.predict_np(x, u))
    assert loaded.spec.to_dict() == spec.to_dict()
    torch.testing.assert_close(loaded.lam.to(tr.lam.dtype), tr.lam)
    assert loaded.meta["schema_hash"] == system.schema_hash()
    assert loaded.meta["updates"] == tr.steps and loaded.meta["metrics"]["objective"] == 0.1


def test_resume_continues_exactly(tmp_path: Path) -> None:
    system, spec, tr, data = _trained(tmp_path)
    store = CheckpointStore(tmp_path / "run")
    path, _ = save_checkpoint(store, tr)
    resumed = resume_trainer(load_model(path))
    idx = torch.arange(64).unsqueeze(0)
    for t in (tr, resumed):
        for _ in range(5):
            xx, uu, yy, bb = data.take(idx)
            t.step(xx, uu, yy, bb, data.take_masks(idx))
    for a, b in zip(tr.model.parameters(), resumed.model.parameters()):
        torch.testing.assert_close(a, b, rtol=0, atol=0)
    torch.testing.assert_close(tr.lam, resumed.lam, rtol=0, atol=0)
    assert resumed.steps == tr.steps


def test_a_former_augmented_checkpoint_resumes_as_the_lagrangian(tmp_path: Path, caplog: Any) -> None:
    """A checkpoint written when ``augmented`` moved lambda with Adam along ``rho g`` (no ``dual_methods`` in its
    meta, its dual Adam moments those of ``rho g``) resumes as ``lagrangian``, the arithmetic it ran but for the
    penalty weight ``rho g``: with its moments rescaled to those of ``g``, the resumed run takes the same steps as
    the Lagrangian run it came from (Adam's step is invariant to the scale of its gradient)."""
    system, spec, _, data = _trained(tmp_path)
    model = DynamicsModel(system, seed=0)
    model.fit_normalization(data.x, data.u, data.y)
    cfg = TrainConfig(epochs=2, batch_size=64, dual_method="lagrangian", dual_optimizer="adam", dual_lr=1e-2,
                      primal_schedule="constant", dual_schedule="constant")  # steps after the fit move lambda
    lag = PrimalDualTrainer(model, spec, cfg)
    lag.fit(data)
    assert float(lag.lam.max()) > 0
    path, _ = save_checkpoint(CheckpointStore(tmp_path / "new"), lag)
    arrays, meta = read_checkpoint(path)
    assert meta["dual_methods"] == 2
    rho = 0.01 / spec.constraints[0].eps
    old_meta = {k: v for k, v in meta.items() if k != "dual_methods"}
    old_meta["train_config"] = {**meta["train_config"], "dual_method": "augmented", "penalty": 0.01}
    old_arrays = dict(arrays)
    moments = [k for k in arrays if k.startswith("dual_opt/") and k.endswith(("exp_avg", "exp_avg_sq"))]
    assert len(moments) == 2
    for k in moments:
        old_arrays[k] = arrays[k] * (rho * rho if k.endswith("exp_avg_sq") else rho)
    old = tmp_path / "former.saml"
    write_checkpoint(old, old_arrays, old_meta)
    with caplog.at_level("WARNING", logger="saml_ros.trainer"):
        resumed = resume_trainer(load_model(old))
    assert resumed.config.dual_method == "lagrangian" and type(resumed.dual.optimizer) is torch.optim.Adam
    assert any("former one" in r.message for r in caplog.records)
    idx = torch.arange(64).unsqueeze(0)
    start = lag.lam.clone()
    for t in (lag, resumed):
        for _ in range(5):
            xx, uu, yy, bb = data.take(idx)
            t.step(xx, uu, yy, bb, data.take_masks(idx))
    assert float((lag.lam - start).abs().min()) > 1e-3
    torch.testing.assert_close(lag.lam, resumed.lam, rtol=1e-6, atol=1e-9)
    for a, b in zip(lag.model.parameters(), resumed.model.parameters()):
        torch.testing.assert_close(a, b, rtol=1e-6, atol=1e-9)
    # a checkpoint of today's augmented Lagrangian method is read as such
    aug = PrimalDualTrainer(model, spec, TrainConfig(**{**cfg.__dict__, "dual_method": "augmented"}))
    path, _ = save_checkpoint(CheckpointStore(tmp_path / "aug"), aug)
    assert resume_trainer(load_model(path)).config.dual_method == "augmented"


def test_schema_mismatch_and_wrong_system_refused(tmp_path: Path) -> None:
    system, spec, tr, data = _trained(tmp_path)
    store = CheckpointStore(tmp_path / "run")
    path, _ = save_checkpoint(store, tr)
    with pytest.raises(IncompatibleCheckpoint, match="expected 'quadrotor'"):
        load_model(path, expect=get_system("quadrotor"))
    arrays, meta = read_checkpoint(path)
    meta["schema_hash"] = "0" * 16
    bad = tmp_path / "bad.saml"
    write_checkpoint(bad, arrays, meta)
    with pytest.raises(IncompatibleCheckpoint, match="schema hash"):
        load_model(bad)
    meta["kind"] = "something_else"
    write_checkpoint(bad, arrays, meta)
    with pytest.raises(IncompatibleCheckpoint, match="not a saml_ros model"):
        load_model(bad)


def test_truncated_model_checkpoint_refused(tmp_path: Path) -> None:
    system, spec, tr, data = _trained(tmp_path)
    path, _ = save_checkpoint(CheckpointStore(tmp_path / "run"), tr)
    blob = path.read_bytes()
    cut = tmp_path / "cut.saml"
    cut.write_bytes(blob[: len(blob) // 2])
    with pytest.raises(CheckpointError):
        load_model(cut)
