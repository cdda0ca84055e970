"""Checkpoints the model watcher and MPC node tests share: a random residual model of any system, a truncated
copy as the next version."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from saml_ros.core.model.checkpoint import CheckpointStore, atomic_write
from saml_ros.core.model.network import DynamicsModel
from saml_ros.core.spec import ProblemSpec
from saml_ros.core.systems import get_system
from saml_ros.core.training import PrimalDualTrainer, TrainConfig, save_checkpoint


def save_model(store: CheckpointStore, system_name: str, seed: int = 0,
               metrics: dict[str, float] | None = None) -> tuple[Path, int]:
    """Write a checkpoint of a (random, non-zero) residual model of ``system_name`` into ``store``."""
    system = get_system(system_name)
    model = DynamicsModel(system, seed=seed)
    x, u, y = system.make_dataset(64, np.random.default_rng(seed))
    model.fit_normalization(x, u, y)
    with torch.no_grad():
        model.net.weights[-1].normal_(0.0, 1e-3, generator=torch.Generator().manual_seed(seed))
    trainer = PrimalDualTrainer(model, ProblemSpec.for_system(system.paper_spec(), system), TrainConfig())
    return save_checkpoint(store, trainer, metrics=metrics)


def write_corrupt(store: CheckpointStore, good: Path) -> Path:
    """A truncated copy of ``good`` as the next version, with ``latest`` pointing at it."""
    version = max(store.versions()) + 1
    bad = store.path_for(version)
    bad.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    atomic_write(store.latest_path, lambda f: f.write(f"{bad.name} {version}\n".encode()))
    return bad
