"""Resuming an online learner from the newest *valid* checkpoint of its run directory (weights, normalisation,
lambda, optimizer states, update count), refusing one that contradicts the configuration (:class:`ResumeError`)
and skipping (with the reason) newer ones that are unreadable, inconsistent or hold non-finite weights."""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from saml_ros.core.dynamics.system import System
from saml_ros.core.errors import SamlError
from saml_ros.core.model.checkpoint import CheckpointError, CheckpointStore, read_checkpoint
from saml_ros.core.model.evidence import DataEvidence
from saml_ros.core.spec import ProblemSpec

if TYPE_CHECKING:  # the learner node imports this module for ResumeError; the training process does the rest
    from saml_ros.core.model.io import LoadedModel
    from saml_ros.core.training import PrimalDualTrainer, TrainConfig

log = logging.getLogger("saml_ros.online")


class ResumeError(SamlError, RuntimeError):
    """The run directory holds checkpoints that contradict the configuration (another system, another
    architecture, other constraints): resuming would silently mix two runs."""


@dataclass
class ResumeInfo:
    """What an online learner resumed from.

    Attributes:
        path, version: the checkpoint loaded.
        updates: its update count.
        lam: its lambda, ``(K,)``.
        skipped: ``(path, reason)`` of newer checkpoints that were unreadable or inconsistent.
    """

    path: Path
    version: int
    updates: int
    lam: list[float]
    skipped: list[tuple[Path, str]]


@dataclass
class Resumed:
    """A trainer rebuilt from checkpoint ``path`` (``version``), the newer checkpoints skipped on the way, and the
    evidence of the training data the checkpoint holds (if any)."""

    trainer: PrimalDualTrainer
    path: Path
    version: int
    skipped: list[tuple[Path, str]]
    evidence: DataEvidence | None = None


def resume_newest(
    store: CheckpointStore, system: System, spec: ProblemSpec, architecture: dict[str, Any], config: TrainConfig
) -> tuple[Resumed | None, int]:
    """The newest checkpoint of ``store`` that fits, as a trainer with ``spec`` and ``config`` (the configured
    learning rates win over the saved ones), and the number of checkpoint files passed over.

    Returns ``(None, n)`` when there is none (or none usable: logged as an error, from scratch).

    Raises:
        ResumeError: a checkpoint is of another system, architecture (``kind``, ``hidden``, ``n_models``,
            ``inputs`` of ``architecture``) or constraint set.
    """
    skipped: list[tuple[Path, str]] = []
    try:
        first = store.load_latest_valid()
    except CheckpointError as exc:  # files exist, none readable
        log.error("resume: no readable checkpoint in %s, starting from scratch (%s)", store.run_dir, exc)
        return None, len(store.versions())
    if first is None:
        log.info("resume: no checkpoint in %s yet, starting from scratch", store.run_dir)
        return None, 0
    skipped.extend(first.skipped)
    candidates: list[tuple[Path, int, dict[str, np.ndarray] | None, dict[str, Any] | None]] = [
        (first.path, first.version, first.arrays, first.meta)
    ]
    candidates += [(store.path_for(v), v, None, None) for v in reversed(store.versions()) if v < first.version]
    for path, version, arrays, meta in candidates:
        if arrays is None or meta is None:
            try:
                arrays, meta = read_checkpoint(path)
            except CheckpointError as exc:
                skipped.append((path, str(exc)))
                continue
        try:
            loaded = _check_and_rebuild(arrays, meta, path, system, spec, architecture)
            trainer = _make_trainer(loaded, spec, config)
        except ResumeError:
            raise
        except Exception as exc:  # noqa: BLE001 - CheckpointError, or torch refusing inconsistent states
            skipped.append((path, str(exc) if isinstance(exc, CheckpointError) else f"{path}: {exc}"))
            continue
        return Resumed(trainer, path, version, skipped, DataEvidence.from_checkpoint(arrays, meta, system)), len(skipped)
    log.error("resume: no usable checkpoint in %s, starting from scratch: %s", store.run_dir,
              "; ".join(r for _, r in skipped))
    return None, len(skipped)


def _check_and_rebuild(arrays: dict[str, np.ndarray], meta: dict[str, Any], path: Path, system: System,
                       spec: ProblemSpec, want: dict[str, Any]) -> LoadedModel:
    import torch

    from saml_ros.core.model.io import MODEL_KIND, model_from_payload

    sysname = meta.get("system")
    if meta.get("kind") == MODEL_KIND and (sysname != system.name or meta.get("schema_hash") != system.schema_hash()):
        raise ResumeError(
            f"{path} is a checkpoint of system {sysname!r} (schema {meta.get('schema_hash')}), but this learner "
            f"trains {system.name!r} (schema {system.schema_hash()}): use another run_dir or resume:=false"
        )
    loaded = model_from_payload(arrays, meta, expect=system, path=path)
    bad = [k for k, v in loaded.model.state_dict().items() if not bool(torch.isfinite(v).all())]
    if bad or not bool(torch.isfinite(loaded.lam).all()):
        raise CheckpointError(f"{path}: non-finite weights or multipliers ({bad or ['lam']}): not resumed from")
    arch = loaded.model.architecture()
    diffs = [f"{k}: checkpoint {arch[k]!r}, configured {want[k]!r}" for k in ("kind", "hidden", "n_models", "inputs")
             if arch.get(k) != want.get(k)]
    if loaded.spec.constraint_names != spec.constraint_names:
        diffs.append(f"constraints: checkpoint {loaded.spec.constraint_names}, configured {spec.constraint_names}")
    if diffs:
        raise ResumeError(
            f"{path} does not match the configured learner ({'; '.join(diffs)}): use another run_dir, "
            "resume:=false, or the checkpoint's settings"
        )
    if loaded.spec.to_dict() != spec.to_dict():
        log.warning("resume: %s was trained with another spec (same constraints %s); continuing with the "
                    "configured spec and the checkpoint's lambda", path, spec.constraint_names)
    return loaded


def _make_trainer(loaded: LoadedModel, spec: ProblemSpec, cfg: TrainConfig) -> PrimalDualTrainer:
    from saml_ros.core.training import resume_trainer

    trainer = resume_trainer(dataclasses.replace(loaded, spec=spec), cfg)
    # torch optimizers restore the learning rate saved with their state: the configured one wins
    for group in trainer.primal_opt.param_groups:
        group["lr"] = cfg.primal_lr
    trainer.dual.set_lr(cfg.dual_lr0)
    return trainer
