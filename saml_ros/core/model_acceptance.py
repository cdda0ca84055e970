"""Checkpoint acceptance: the MPC never plans with a model that is broken or poisoned (ROS-free).

A checkpoint that loads (right system, schema, consistent contents) may still hold a model no vehicle should be
commanded with. :func:`check_model` refuses it, with one of :data:`ACCEPTANCE_REASONS`:

* ``non_finite``: a weight, normalisation value or multiplier is NaN or infinite;
* ``implausible``: on the probe inputs, a prediction is NaN / Inf, or leaves the system's plausible range
  (:mod:`saml_ros.core.plausibility`) where the base model's prediction stays inside it;
* ``residual``: on the probe inputs, the model's prediction differs from the base model's by more than
  ``residual_factor`` times what the training data ever showed, per target field:
  ``|pred - f_hat| > residual_factor * (max |y - f_hat| + 0.01 std(y))`` (the statistics the learner or trainer
  stored in the checkpoint, :mod:`saml_ros.core.model_evidence`; the ``0.01 std(y)`` term keeps a field the base
  model predicts exactly, e.g. the quadrotor's positions, from demanding a zero residual).

The probe inputs are the checkpoint's own probe set (a sample of its training inputs) and the states the MPC
answered recently, each with the command sent (``recent``); rows outside the plausible range are left out. A
checkpoint without stored evidence (written before it existed) is checked on the recent states for ``non_finite``
and ``implausible`` only. Every member of an ensemble is checked.

:class:`~saml_ros.core.model_watch.ModelWatcher` calls the check (its ``vet`` hook) on its background thread after
loading; a refusal is counted under its reason (``checkpoints_refused/<reason>`` on /diagnostics) and the current
model is kept.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch

from msg_schemas.telemetry import CHECKPOINT_REFUSAL_REASONS
from saml_ros.core.model_evidence import DataEvidence
from saml_ros.core.model_io import LoadedModel
from saml_ros.core.plausibility import Plausibility

#: the refusal reasons of this check (the last ones of :data:`msg_schemas.telemetry.CHECKPOINT_REFUSAL_REASONS`)
ACCEPTANCE_REASONS: tuple[str, ...] = CHECKPOINT_REFUSAL_REASONS[-3:]

#: a refusal: ``(reason, message)``
Refusal = tuple[str, str]
#: the recent states and the commands sent for them, ``(x (R, n_x), u (R, n_u))``
Probe = tuple[np.ndarray, np.ndarray]


@dataclass(frozen=True)
class AcceptanceConfig:
    """Limits of :func:`check_model`.

    Attributes:
        residual_factor: allowed multiple of the training data's largest residual (0 = no residual check).
        std_fraction: share of the target's spread added to the largest residual (see the module docstring).
    """

    residual_factor: float = 4.0
    std_fraction: float = 0.01

    def __post_init__(self) -> None:
        if not (self.residual_factor >= 0 and self.std_fraction >= 0):
            raise ValueError(f"acceptance limits must be >= 0, got {self}")


def check_model(loaded: LoadedModel, bounds: Plausibility, recent: Probe | None = None,
                config: AcceptanceConfig | None = None) -> Refusal | None:
    """``None`` if the loaded model may be planned with, else ``(reason, message)`` (see the module docstring)."""
    cfg = config or AcceptanceConfig()
    model, system = loaded.model, loaded.system
    where = f"{loaded.path.name}: " if loaded.path is not None else ""
    bad = [k for k, v in model.state_dict().items() if not bool(torch.isfinite(v).all())]
    if bad or not bool(torch.isfinite(loaded.lam).all()):
        return "non_finite", f"{where}non-finite values in {bad or ['lam']}"
    evidence = DataEvidence.from_checkpoint(loaded.arrays, loaded.meta, system)
    parts = [p for p in ((evidence.probe_x, evidence.probe_u) if evidence else None, recent) if p is not None]
    if not parts:
        return None
    x = np.concatenate([np.asarray(p[0], np.float64).reshape(-1, system.state.size) for p in parts])
    u = np.concatenate([np.asarray(p[1], np.float64).reshape(-1, system.control.size) for p in parts])
    keep = bounds.state.inside(x) & bounds.control.inside(u)
    x, u = x[keep], u[keep]
    if len(x) == 0:
        return None
    dtype = model.in_mean.dtype
    with torch.no_grad():
        pred = model(torch.as_tensor(x, dtype=dtype), torch.as_tensor(u, dtype=dtype)).double().numpy()  # (E, B, n_y)
    base = system.base_step_np(x, u)
    names = system.target.names
    if not np.isfinite(pred).all():
        e, b, j = np.argwhere(~np.isfinite(pred))[0]
        return "implausible", f"{where}non-finite prediction of {names[j]} (member {e}) at x = {x[b].tolist()}"
    out = ~bounds.target.inside(pred) & bounds.target.inside(base)[None]
    if out.any():
        e, b = np.argwhere(out)[0]
        return "implausible", (f"{where}prediction outside the plausible range (member {e}): "
                               f"{bounds.target.outside(pred[e, b])} at x = {np.round(x[b], 4).tolist()}")
    if evidence is None or cfg.residual_factor == 0:
        return None
    limit = cfg.residual_factor * (evidence.residual_max + cfg.std_fraction * evidence.target_std) + 1e-9
    excess = np.abs(pred - base[None]) / limit  # (E, B, n_y)
    if excess.max() > 1.0:
        e, b, j = np.unravel_index(int(np.argmax(excess)), excess.shape)
        return "residual", (f"{where}member {e} predicts {names[j]} {pred[e, b, j] - base[b, j]:+.4g} away from the "
                            f"base model; the training data never showed more than {evidence.residual_max[j]:.4g} "
                            f"(limit {limit[j]:.4g} = accept.residual_factor {cfg.residual_factor:g} x (max + "
                            f"{cfg.std_fraction:g} std))")
    return None


def acceptance_hook(bounds: Plausibility, recent: Callable[[], Probe | None],
                    config: AcceptanceConfig | None = None) -> Callable[[LoadedModel], Refusal | None]:
    """The ``vet`` hook of a :class:`~saml_ros.core.model_watch.ModelWatcher`: :func:`check_model` with the probe
    rows ``recent()`` returns at the time of the check."""

    def vet(loaded: LoadedModel) -> Refusal | None:
        return check_model(loaded, bounds, recent(), config)

    return vet
