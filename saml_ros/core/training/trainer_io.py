"""A trainer into a model checkpoint and back: the model's part (:func:`saml_ros.core.model.io.model_payload`) plus
the trainer's (lambda, both optimizer states, training config, counters), and a trainer rebuilt from a loaded
checkpoint that resumes exactly where it left off (:func:`resume_trainer`). The file format is
``docs/checkpoints.md``'s."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np
import torch

from saml_ros.core.model.checkpoint import CheckpointStore, arrays_to_torch_state, torch_state_to_arrays
from saml_ros.core.model.evidence import DataEvidence
from saml_ros.core.model.io import LoadedModel, UnhealthyModel, jsonable, model_payload
from saml_ros.core.training.config import TrainConfig
from saml_ros.core.training.schedule import schedules_for
from saml_ros.core.training.trainer import PrimalDualTrainer
from saml_ros.core.training.verdict import aimed_spec, recorded_aim

log = logging.getLogger("saml_ros.trainer")

#: what the dual-method names of a checkpoint's ``train_config`` mean (meta ``dual_methods``). 2: ``"augmented"``
#: is the augmented Lagrangian method (:class:`~saml_ros.core.training.dual.AugmentedDual`). 1 (no such key):
#: ``"augmented"`` moved lambda with ``dual_optimizer`` (Adam) along ``rho g``, which Adam's scale invariance makes
#: the Lagrangian's step; such a checkpoint is read as ``"lagrangian"`` (:func:`saved_config`).
DUAL_METHODS_VERSION = 2


def checkpoint_payload(
    trainer: PrimalDualTrainer, metrics: dict[str, Any] | None = None, extra: dict[str, Any] | None = None,
    evidence: DataEvidence | None = None,
) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """Arrays and meta of a checkpoint holding ``trainer``'s model, lambda and optimizer states (``metrics`` and
    ``extra`` go into the meta as they are, made JSON-safe), its health (``meta["health"]``,
    :meth:`~saml_ros.core.training.health.TrainingHealth.summary`) and the training data's ``evidence`` (probe set
    and residual statistics, :mod:`saml_ros.core.model.evidence`).

    Raises:
        saml_ros.core.model.io.UnhealthyModel: a weight, multiplier or optimizer value is NaN or infinite.
    """
    health = trainer.health.summary(trainer)
    if not health["finite"]:
        raise UnhealthyModel(f"non-finite weights or multipliers (last problem: {health['last_problem'] or '-'}): "
                             "not written")
    dual = trainer.dual.state_dict()
    arrays: dict[str, np.ndarray] = {"lam": dual["lam"].double().numpy().copy()}
    spec = trainer.given_spec or trainer.spec  # the problem as given, never the bounds trained at
    model_arrays, meta, model_skeleton = model_payload(trainer.model, spec)
    arrays.update(model_arrays)
    skeletons = {"model": model_skeleton}
    for prefix, state in (("primal_opt", trainer.primal_opt.state_dict()), ("dual_opt", dual["optimizer"])):
        a, sk = torch_state_to_arrays(prefix, state)
        arrays.update(a)
        skeletons[prefix] = sk
    meta.update({
        "train_config": dict(trainer.config.__dict__),
        "dual_methods": DUAL_METHODS_VERSION,
        "lambda": trainer.lam.double().tolist(),
        "constraint_names": spec.constraint_names,
        "updates": trainer.steps,
        "epochs": trainer.epochs_done,
        # the learning-rate schedules' horizon T in updates (fit() sets it from the data; 0: none)
        "schedule_horizon": trainer.schedules[0].horizon if trainer.schedules is not None else 0,
        "metrics": jsonable(metrics or {}),
        "skeletons": skeletons,
        "health": jsonable(health),
    })
    if trainer.aim is not None:  # the aim it trains at (a resumed one: its checkpoint's, resume_trainer)
        meta["aim"] = jsonable(trainer.aim)
    if evidence is not None:
        ev_arrays, ev_meta = evidence.to_payload(trainer.model.system.target.names)
        arrays.update(ev_arrays)
        meta["evidence"] = ev_meta
    if extra:
        meta.update(jsonable(extra))
    return arrays, meta


def save_checkpoint(store: CheckpointStore, trainer: PrimalDualTrainer, metrics: dict[str, Any] | None = None,
                    extra: dict[str, Any] | None = None, evidence: DataEvidence | None = None) -> tuple[Path, int]:
    """Write the next versioned checkpoint of ``trainer`` into ``store`` and point ``latest`` at it (see
    :func:`checkpoint_payload`; nothing is written for an unhealthy model)."""
    arrays, meta = checkpoint_payload(trainer, metrics, extra, evidence)
    return store.save(arrays, meta)


def legacy_augmented(meta: dict[str, Any]) -> bool:
    """True for a checkpoint whose ``"augmented"`` is the former one (``dual_methods`` < 2, see
    :data:`DUAL_METHODS_VERSION`): lambda moved by ``dual_optimizer`` along ``rho g``."""
    d = meta.get("train_config", {})
    return d.get("dual_method") == "augmented" and int(meta.get("dual_methods", 1)) < DUAL_METHODS_VERSION


def saved_config(meta: dict[str, Any]) -> TrainConfig:
    """The training config a checkpoint's meta records, in today's names: one written before dual methods existed
    ran the paper's method with constant learning rates; one whose ``"augmented"`` is the former
    (:func:`legacy_augmented`) ran the Lagrangian with Adam multipliers, ``"lagrangian"`` now (the same rates and
    schedules; its primal weights ``relu(lambda + rho g)`` differed from lambda by ``rho g``, a few thousandths at
    the former default)."""
    d = dict(meta.get("train_config", {}))
    if "dual_method" not in d:
        d.update(dual_method="paper", primal_schedule="constant", dual_schedule="constant")
    elif legacy_augmented(meta):
        d["dual_method"] = "lagrangian"
    return TrainConfig.from_dict(d)


def _lagrangian_moments(state: dict[str, Any], rho: np.ndarray) -> dict[str, Any]:
    """A former ``"augmented"`` checkpoint's dual Adam state (moments of ``rho g``) as the Lagrangian's (moments of
    ``g``): Adam's step ``m / sqrt(v)`` is unchanged, and the following steps on ``g`` continue it exactly."""
    out = {"param_groups": state["param_groups"], "state": {}}
    for key, st in state.get("state", {}).items():
        st = dict(st)
        if "exp_avg" in st:
            r = torch.as_tensor(rho, dtype=st["exp_avg"].dtype)
            st["exp_avg"] = st["exp_avg"] / r
            st["exp_avg_sq"] = st["exp_avg_sq"] / (r * r)
        out["state"][key] = st
    return out


def resume_trainer(loaded: LoadedModel, config: TrainConfig | None = None) -> PrimalDualTrainer:
    """A trainer of ``loaded``'s model and spec that resumes exactly where the checkpoint left off (weights, lambda,
    optimizer states, update and epoch counts, the bounds training aimed at, and, without ``config``, the
    learning-rate schedules' horizon); ``config`` defaults to the checkpoint's training config.

    A checkpoint whose training aimed below eps (``meta["aim"]``, written by ``train``: the margin sized by the
    held-out uncertainty, :mod:`~saml_ros.core.training.verdict`) resumes aiming there: the trainer's ``spec`` is
    the aimed problem, ``given_spec`` ``loaded.spec`` (what its checkpoints record) and ``aim`` the record
    (:func:`~saml_ros.core.training.verdict.recorded_aim`: only when ``loaded.spec`` has the record's constraints
    and eps; else it trains at eps, logged).

    With a ``config`` of another dual method or dual optimizer than the checkpoint's, lambda is kept and the dual
    optimizer starts afresh (its state belongs to the other method; logged)."""
    saved = saved_config(loaded.meta)
    cfg = config or saved
    tr = PrimalDualTrainer(loaded.model, loaded.spec, cfg)
    sk = loaded.meta["skeletons"]
    same_dual = (saved.dual_method, saved.dual_optimizer_used) == (cfg.dual_method, cfg.dual_optimizer_used)
    legacy = legacy_augmented(loaded.meta)
    if legacy:
        log.warning("resume: the checkpoint's dual method 'augmented' is the former one (Adam on the multipliers: "
                    "in effect the Lagrangian), read as 'lagrangian'; 'augmented' is now the augmented Lagrangian "
                    "method (docs/training.md)")
    if not same_dual:
        log.warning("resume: the checkpoint was trained with dual method %r (%s), this run uses %r (%s): lambda is "
                    "kept, the dual optimizer starts afresh", saved.dual_method, saved.dual_optimizer_used,
                    cfg.dual_method, cfg.dual_optimizer_used)
    dual_opt = arrays_to_torch_state(loaded.arrays, sk["dual_opt"]) if same_dual else None
    if dual_opt is not None and legacy:
        eps = np.array([t.eps for t in loaded.spec.constraints], dtype=float)
        dual_opt = _lagrangian_moments(dual_opt, float(loaded.meta["train_config"].get("penalty", 1.0)) / eps)
    tr.load_state({
        "model": loaded.model.state_dict(),
        "lam": loaded.lam,
        "primal_opt": arrays_to_torch_state(loaded.arrays, sk["primal_opt"]),
        "dual_opt": dual_opt,
        "steps": int(loaded.meta.get("updates", 0)),
        "epochs_done": float(loaded.meta.get("epochs", 0.0)),
    })
    horizon = int(loaded.meta.get("schedule_horizon", 0))
    if horizon > 0 and config is None:  # the same schedules as the run that wrote it
        tr.schedules = schedules_for(cfg, horizon)
    _reapply_aim(tr, loaded)
    return tr


def _reapply_aim(tr: PrimalDualTrainer, loaded: LoadedModel) -> None:
    """Train at the bounds ``loaded``'s training aimed at (its ``meta["aim"]``), when they belong to its spec."""
    record = loaded.meta.get("aim")
    if not isinstance(record, dict) or record.get("margin", "none") == "none":
        return
    bounds = recorded_aim(record, loaded.spec)
    if bounds is None:
        log.warning("resume: the checkpoint's training aimed below eps (%s), but not for this spec's constraints "
                    "and bounds %s: training aims at eps", record.get("constraints"),
                    {t.name: t.eps for t in loaded.spec.constraints})
        return
    if all(b == t.eps for b, t in zip(bounds, loaded.spec.constraints)):
        return  # aimed at eps (nothing measured to size a margin by)
    tr.given_spec, tr.aim = loaded.spec, record
    tr.spec = aimed_spec(loaded.spec, bounds)
    log.info("resume: training aims at %s (the checkpoint's aim, eps %s)",
             {t.name: round(b, 6) for t, b in zip(loaded.spec.constraints, bounds)},
             {t.name: t.eps for t in loaded.spec.constraints})
