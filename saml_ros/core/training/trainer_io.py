"""A trainer into a model checkpoint and back: the model's part (:func:`saml_ros.core.model_io.model_payload`) plus
the trainer's (lambda, both optimizer states, training config, counters), and a trainer rebuilt from a loaded
checkpoint that resumes exactly where it left off (:func:`resume_trainer`). The file format is
``docs/checkpoints.md``'s."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from saml_ros.core.checkpoint import CheckpointStore, arrays_to_torch_state, torch_state_to_arrays
from saml_ros.core.model_io import LoadedModel, jsonable, model_payload
from saml_ros.core.training.config import TrainConfig
from saml_ros.core.training.trainer import PrimalDualTrainer


def checkpoint_payload(
    trainer: PrimalDualTrainer, metrics: dict[str, Any] | None = None, extra: dict[str, Any] | None = None
) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """Arrays and meta of a checkpoint holding ``trainer``'s model, lambda and optimizer states (``metrics`` and
    ``extra`` go into the meta as they are, made JSON-safe)."""
    dual = trainer.dual.state_dict()
    arrays: dict[str, np.ndarray] = {"lam": dual["lam"].double().numpy().copy()}
    model_arrays, meta, model_skeleton = model_payload(trainer.model, trainer.spec)
    arrays.update(model_arrays)
    skeletons = {"model": model_skeleton}
    for prefix, state in (("primal_opt", trainer.primal_opt.state_dict()), ("dual_opt", dual["optimizer"])):
        a, sk = torch_state_to_arrays(prefix, state)
        arrays.update(a)
        skeletons[prefix] = sk
    meta.update({
        "train_config": dict(trainer.config.__dict__),
        "lambda": trainer.lam.double().tolist(),
        "constraint_names": trainer.spec.constraint_names,
        "updates": trainer.steps,
        "epochs": trainer.epochs_done,
        "metrics": jsonable(metrics or {}),
        "skeletons": skeletons,
    })
    if extra:
        meta.update(jsonable(extra))
    return arrays, meta


def save_checkpoint(store: CheckpointStore, trainer: PrimalDualTrainer, metrics: dict[str, Any] | None = None,
                    extra: dict[str, Any] | None = None) -> tuple[Path, int]:
    """Write the next versioned checkpoint of ``trainer`` into ``store`` and point ``latest`` at it."""
    arrays, meta = checkpoint_payload(trainer, metrics, extra)
    return store.save(arrays, meta)


def resume_trainer(loaded: LoadedModel, config: TrainConfig | None = None) -> PrimalDualTrainer:
    """A trainer of ``loaded``'s model and spec that resumes exactly where the checkpoint left off (weights, lambda,
    optimizer states, update and epoch counts); ``config`` defaults to the checkpoint's training config."""
    cfg = config or TrainConfig.from_dict(loaded.meta.get("train_config", {}))
    tr = PrimalDualTrainer(loaded.model, loaded.spec, cfg)
    sk = loaded.meta["skeletons"]
    tr.load_state({
        "model": loaded.model.state_dict(),
        "lam": loaded.lam,
        "primal_opt": arrays_to_torch_state(loaded.arrays, sk["primal_opt"]),
        "dual_opt": arrays_to_torch_state(loaded.arrays, sk["dual_opt"]),
        "steps": int(loaded.meta.get("updates", 0)),
        "epochs_done": float(loaded.meta.get("epochs", 0.0)),
    })
    return tr
