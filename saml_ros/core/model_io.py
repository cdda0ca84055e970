"""Saving and loading trained dynamics models (and the trainer state to resume them) as checkpoints.

A model checkpoint's meta holds: ``kind = "saml_ros.model"``, the system name and physical parameters,
the schema hash and field names of the state/control/target layouts, the architecture, the problem spec,
the training config, lambda, the update count, metrics and the time. Arrays hold the weights and
normalisation (``model/...``), lambda (``lam``) and the optimizer states (``primal_opt/...``,
``dual_opt/...``). See ``docs/checkpoints.md``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from saml_ros.core.checkpoint import (
    CheckpointError,
    CheckpointStore,
    arrays_to_torch_state,
    read_checkpoint,
    torch_state_to_arrays,
)
from saml_ros.core.models import DynamicsModel
from saml_ros.core.spec import ProblemSpec
from saml_ros.core.systems import get_system
from saml_ros.core.systems.base import System
from saml_ros.core.trainer import PrimalDualTrainer, TrainConfig

MODEL_KIND = "saml_ros.model"


class IncompatibleCheckpoint(CheckpointError):
    """A readable checkpoint that does not fit the system it is meant for (schema or system mismatch)."""


def system_params(system: System) -> dict[str, Any]:
    params = getattr(system, "params", None)
    return dict(params()) if callable(params) else {}


def checkpoint_payload(
    trainer: PrimalDualTrainer, metrics: dict[str, Any] | None = None, extra: dict[str, Any] | None = None
) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """Arrays and meta of a checkpoint holding ``trainer``'s model, lambda and optimizer states."""
    model, system = trainer.model, trainer.model.system
    arrays: dict[str, np.ndarray] = {"lam": trainer.lam.double().numpy().copy()}
    skeletons = {}
    for prefix, state in (("model", model.state_dict()), ("primal_opt", trainer.primal_opt.state_dict()),
                          ("dual_opt", trainer.dual_opt.state_dict())):
        a, sk = torch_state_to_arrays(prefix, state)
        arrays.update(a)
        skeletons[prefix] = sk
    meta = {
        "kind": MODEL_KIND,
        "system": system.name,
        "system_params": _jsonable(system_params(system)),
        "schema_hash": system.schema_hash(),
        "layouts": {
            "state": list(system.state.names),
            "control": list(system.control.names),
            "target": list(system.target.names),
        },
        "architecture": model.architecture(),
        "spec": trainer.spec.to_dict(),
        "train_config": dict(trainer.config.__dict__),
        "lambda": trainer.lam.double().tolist(),
        "constraint_names": trainer.spec.constraint_names,
        "updates": trainer.steps,
        "epochs": trainer.epochs_done,
        "metrics": _jsonable(metrics or {}),
        "skeletons": skeletons,
    }
    if extra:
        meta.update(_jsonable(extra))
    return arrays, meta


def save_checkpoint(store: CheckpointStore, trainer: PrimalDualTrainer, metrics: dict[str, Any] | None = None,
                    extra: dict[str, Any] | None = None) -> tuple[Path, int]:
    """Write the next versioned checkpoint of ``trainer`` into ``store`` and point ``latest`` at it."""
    arrays, meta = checkpoint_payload(trainer, metrics, extra)
    return store.save(arrays, meta)


@dataclass
class LoadedModel:
    """A model rebuilt from a checkpoint, with everything needed to use or resume it."""

    model: DynamicsModel
    spec: ProblemSpec
    system: System
    lam: torch.Tensor
    meta: dict[str, Any]
    arrays: dict[str, np.ndarray]
    path: Path | None = None

    @property
    def version(self) -> int:
        return int(self.meta.get("version", 0))

    def trainer(self, config: TrainConfig | None = None) -> PrimalDualTrainer:
        """A trainer that resumes exactly where the checkpoint left off (weights, lambda, optimizer state)."""
        cfg = config or TrainConfig.from_dict(self.meta.get("train_config", {}))
        tr = PrimalDualTrainer(self.model, self.spec, cfg)
        sk = self.meta["skeletons"]
        tr.load_state({
            "model": self.model.state_dict(),
            "lam": self.lam,
            "primal_opt": arrays_to_torch_state(self.arrays, sk["primal_opt"]),
            "dual_opt": arrays_to_torch_state(self.arrays, sk["dual_opt"]),
            "steps": int(self.meta.get("updates", 0)),
            "epochs_done": float(self.meta.get("epochs", 0.0)),
        })
        return tr


def model_from_payload(
    arrays: dict[str, np.ndarray], meta: dict[str, Any], expect: System | None = None, path: Path | None = None
) -> LoadedModel:
    """Rebuild a model from checkpoint contents; raises :class:`IncompatibleCheckpoint` with the reason when
    it is not a model checkpoint, names an unknown system, or its layouts differ from ``expect``'s."""
    where = f"{path}: " if path else ""
    if meta.get("kind") != MODEL_KIND:
        raise IncompatibleCheckpoint(f"{where}not a saml_ros model checkpoint (kind={meta.get('kind')!r})")
    try:
        system = get_system(meta["system"], **meta.get("system_params", {}))
    except (KeyError, ValueError, TypeError) as exc:
        raise IncompatibleCheckpoint(f"{where}cannot rebuild its system: {exc}") from exc
    if system.schema_hash() != meta.get("schema_hash"):
        raise IncompatibleCheckpoint(
            f"{where}schema hash {meta.get('schema_hash')} does not match this saml_ros's {system.name} "
            f"layouts ({system.schema_hash()}); it was written for fields {meta.get('layouts')}"
        )
    if expect is not None:
        if expect.name != system.name or expect.schema_hash() != system.schema_hash():
            raise IncompatibleCheckpoint(
                f"{where}checkpoint is for system {system.name!r} (schema {system.schema_hash()}), "
                f"expected {expect.name!r} (schema {expect.schema_hash()})"
            )
        system = expect
    arch = meta["architecture"]
    try:
        model = DynamicsModel(system, arch["hidden"], arch["kind"], n_models=int(arch["n_models"]))
        state = arrays_to_torch_state(arrays, meta["skeletons"]["model"])
        dtype = next(iter(state.values())).dtype
        model.to(dtype)
        model.load_state_dict(state)
        spec = ProblemSpec.for_system(meta["spec"], system)
        lam = torch.as_tensor(arrays["lam"])
    except CheckpointError:
        raise
    except Exception as exc:  # shape mismatch, missing keys, bad spec: all mean "not usable"
        raise IncompatibleCheckpoint(f"{where}checkpoint contents are inconsistent: {exc}") from exc
    model.eval()
    return LoadedModel(model, spec, system, lam, meta, arrays, path)


def load_model(path: str | Path, expect: System | None = None) -> LoadedModel:
    """Read and rebuild a model checkpoint file (never executes code from it)."""
    arrays, meta = read_checkpoint(Path(path))
    return model_from_payload(arrays, meta, expect, Path(path))


def _jsonable(obj: Any) -> Any:
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, (np.floating, np.integer)):
        return obj.item()
    if isinstance(obj, torch.Tensor):
        return obj.tolist()
    return obj
