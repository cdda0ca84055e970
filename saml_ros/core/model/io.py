"""The model part of a checkpoint: writing a dynamics model's part (:func:`model_payload`) and loading a model
(:func:`load_model`, :func:`model_from_payload`) without the trainer.

A model checkpoint's meta holds: ``kind = "saml_ros.model"``, the system name and physical parameters,
the schema hash and field names of the state/control/target layouts, the architecture, the problem spec,
the training config, lambda, the update count, metrics and the time. Arrays hold the weights and
normalisation (``model/...``), lambda (``lam``) and the optimizer states (``primal_opt/...``,
``dual_opt/...``). The trainer's part (lambda, optimizer states, counters) is written and read back into a
trainer by :mod:`saml_ros.core.training.trainer_io`. See ``docs/checkpoints.md``.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from saml_ros.core.dynamics.system import System
from saml_ros.core.errors import SamlError
from saml_ros.core.model.checkpoint import (
    CheckpointError,
    arrays_to_torch_state,
    read_checkpoint,
    torch_state_to_arrays,
)
from saml_ros.core.model.inputs import input_names
from saml_ros.core.spec import ProblemSpec
from saml_ros.core.systems import get_system

if TYPE_CHECKING:  # torch and the network are imported where a model is built or written
    import torch

    from saml_ros.core.model.network import DynamicsModel

MODEL_KIND = "saml_ros.model"


class IncompatibleCheckpoint(CheckpointError):
    """A readable checkpoint that does not fit the system it is meant for (schema or system mismatch)."""


class UnhealthyModel(SamlError, ValueError):
    """A model with a non-finite weight or normalisation value: it is never written into a checkpoint."""


def system_params(system: System) -> dict[str, Any]:
    params = getattr(system, "params", None)
    return dict(params()) if callable(params) else {}


def model_payload(model: DynamicsModel, spec: ProblemSpec) -> tuple[dict[str, np.ndarray], dict[str, Any], Any]:
    """The model's part of a checkpoint: arrays ``model/...`` (weights and normalisation), meta (``kind``,
    system, its parameters, schema hash, layouts, architecture, spec) and the model state's skeleton (for
    ``meta["skeletons"]["model"]``). Raises :class:`UnhealthyModel` if a weight or normalisation value is NaN or
    infinite (no checkpoint with non-finite weights is ever written)."""
    import torch

    system = model.system
    state = model.state_dict()
    bad = [k for k, v in state.items() if not bool(torch.isfinite(v).all())]
    if bad:
        raise UnhealthyModel(f"the model has non-finite values in {bad}: not written")
    arrays, skeleton = torch_state_to_arrays("model", state)
    meta = {
        "kind": MODEL_KIND,
        "system": system.name,
        "system_params": jsonable(system_params(system)),
        "schema_hash": system.schema_hash(),
        "layouts": {
            "state": list(system.state.names),
            "control": list(system.control.names),
            "target": list(system.target.names),
        },
        "architecture": model.architecture(),
        "spec": spec.to_dict(),
    }
    return arrays, meta, skeleton


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


def model_from_payload(
    arrays: dict[str, np.ndarray], meta: dict[str, Any], expect: System | None = None, path: Path | None = None
) -> LoadedModel:
    """Rebuild a model from checkpoint contents; raises :class:`IncompatibleCheckpoint` with the reason when
    it is not a model checkpoint, names an unknown system, or its layouts differ from ``expect``'s."""
    import torch

    from saml_ros.core.model.network import DynamicsModel

    where = f"{path}: " if path else ""
    if meta.get("kind") != MODEL_KIND:
        raise IncompatibleCheckpoint(f"{where}not a saml_ros model checkpoint (kind={meta.get('kind')!r})")
    params = meta.get("system_params", {})
    try:
        system = get_system(meta["system"], **params)
    except (KeyError, ValueError, TypeError) as exc:
        # a robot whose base model is user code: only the caller (which imported it) can build it
        if expect is None or "definition" not in params or expect.name != meta.get("system"):
            raise IncompatibleCheckpoint(f"{where}cannot rebuild its system: {exc}") from exc
        system = expect
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
        if "definition" not in params:  # a robot's own stored definition carries its fitted base model: keep it
            system = expect
    arch = meta["architecture"]
    try:
        # the fields the network sees (checkpoints from before input selection: all of them)
        inputs = arch.get("inputs") or list(input_names(system))
        model = DynamicsModel(system, arch["hidden"], arch["kind"], n_models=int(arch["n_models"]), inputs=inputs)
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


def jsonable(obj: Any) -> Any:
    """``obj`` with numpy / torch values turned into JSON types (dict keys into strings), for a checkpoint's meta."""
    if isinstance(obj, dict):
        return {str(k): jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, (np.floating, np.integer)):
        return obj.item()
    torch = sys.modules.get("torch")  # a tensor exists only where torch was imported
    if torch is not None and isinstance(obj, torch.Tensor):
        return obj.tolist()
    return obj
