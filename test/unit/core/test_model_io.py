"""Model checkpoints: round trip, exact resume, incompatible checkpoints refused."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

from saml_ros.core.checkpoint import CheckpointError, CheckpointStore, read_checkpoint, write_checkpoint
from saml_ros.core.model_io import IncompatibleCheckpoint, load_model
from saml_ros.core.models import DynamicsModel
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
