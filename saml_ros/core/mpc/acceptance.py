"""Checkpoint acceptance: the MPC never plans with a model that is broken or poisoned (ROS-free).

A checkpoint that loads (right system, schema, consistent contents) may still hold a model no vehicle should be
commanded with. :func:`check_model` refuses it, with one of :data:`ACCEPTANCE_REASONS`:

* ``non_finite``: a weight, normalisation value or multiplier is NaN or infinite;
* ``implausible``: on the probe inputs, a prediction is NaN / Inf, or leaves the system's plausible range
  (:mod:`saml_ros.core.data.plausibility`) where the base model's prediction stays inside it;
* ``residual``: on the probe inputs, the model's prediction differs from the base model's by more than
  ``residual_factor`` times what the training data ever showed, per target field:
  ``|pred - f_hat| > residual_factor * (max |y - f_hat| + 0.01 std(y))`` (the statistics the learner or trainer
  stored in the checkpoint, :mod:`saml_ros.core.model.evidence`; the ``0.01 std(y)`` term keeps a field the base
  model predicts exactly, e.g. the quadrotor's positions, from demanding a zero residual).
* ``heldout``: the checkpoint's own record of held-out data (``meta["heldout"]``: what the online learner writes
  from the held-out stretches of its stream, :mod:`saml_ros.core.online.heldout`) says that a member's error there is
  **worse than f_hat's on the same held-out transitions**, for the objective or inside any constraint's region (each
  judged on at least :data:`MIN_HELDOUT` transitions, in the region for a conditional constraint). The message
  gives both numbers with their standard errors. A checkpoint without such a record is not judged here.

The probe inputs are the checkpoint's own probe set (a sample of its training inputs) and the states the MPC
answered recently, each with the command sent (``recent``); rows outside the plausible range are left out. A
checkpoint without stored evidence (written before it existed) is checked on the recent states for ``non_finite``
and ``implausible`` only. Every member of an ensemble is checked.

:class:`~saml_ros.core.mpc.follower.ModelWatcher` calls the check (its ``vet`` hook) on its background thread after
loading; a refusal is counted under its reason (``checkpoints_refused/<reason>`` on /diagnostics) and the current
model is kept.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from msg_schemas.telemetry import CHECKPOINT_REFUSAL_REASONS
from saml_ros.core.data.plausibility import Plausibility
from saml_ros.core.model.evidence import DataEvidence
from saml_ros.core.model.io import LoadedModel

#: the refusal reasons of this check (the last ones of :data:`msg_schemas.telemetry.CHECKPOINT_REFUSAL_REASONS`)
ACCEPTANCE_REASONS: tuple[str, ...] = CHECKPOINT_REFUSAL_REASONS[-4:]
#: held-out transitions (in the region, for a conditional constraint) a comparison with f_hat needs (as
#: :data:`saml_ros.core.training.heldout.MIN_N`)
MIN_HELDOUT = 30

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
        heldout: refuse a model whose recorded held-out error is worse than f_hat's (see the module docstring).
    """

    residual_factor: float = 4.0
    std_fraction: float = 0.01
    heldout: bool = True

    def __post_init__(self) -> None:
        if not (self.residual_factor >= 0 and self.std_fraction >= 0):
            raise ValueError(f"acceptance limits must be >= 0, got {self}")


def check_model(loaded: LoadedModel, bounds: Plausibility, recent: Probe | None = None,
                config: AcceptanceConfig | None = None) -> Refusal | None:
    """``None`` if the loaded model may be planned with, else ``(reason, message)`` (see the module docstring)."""
    import torch  # imported already: the model was loaded with it

    cfg = config or AcceptanceConfig()
    model, system = loaded.model, loaded.system
    where = f"{loaded.path.name}: " if loaded.path is not None else ""
    bad = [k for k, v in model.state_dict().items() if not bool(torch.isfinite(v).all())]
    if bad or not bool(torch.isfinite(loaded.lam).all()):
        return "non_finite", f"{where}non-finite values in {bad or ['lam']}"
    if cfg.heldout:
        worse = heldout_refusal(loaded.meta, where)
        if worse is not None:
            return worse
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


def _estimate(d: Any) -> tuple[float, float, int] | None:
    """``(mean, se, n)`` of a recorded estimate (``Estimate.to_dict``), or None when it is not one."""
    try:
        mean, se, n = float(d["mean"]), float(d["se"]), int(d["n"])
    except (KeyError, TypeError, ValueError):
        return None
    return mean, se, n


def heldout_comparison(meta: Mapping[str, Any]) -> list[tuple[str, int, tuple[float, float, int],
                                                               tuple[float, float, int]]]:
    """``(term, member, model (mean, se, n), f_hat (mean, se, n))`` for every term and member of a checkpoint's
    held-out record (``meta["heldout"]``: ``objective`` and ``constraints`` ``{name: {"model": [estimate per
    member], "base": estimate}}``); ``[]`` without one. Malformed entries are left out."""
    rec = meta.get("heldout")
    if not isinstance(rec, Mapping):
        return []
    terms = [("objective", rec.get("objective"))]
    cons = rec.get("constraints")
    if isinstance(cons, Mapping):
        terms += [(str(k), v) for k, v in cons.items()]
    out = []
    for name, t in terms:
        if not isinstance(t, Mapping) or not isinstance(t.get("model"), list):
            continue
        base = _estimate(t.get("base"))
        for i, m in enumerate(t["model"]):
            est = _estimate(m)
            if est is not None and base is not None:
                out.append((name, i, est, base))
    return out


def heldout_refusal(meta: Mapping[str, Any], where: str = "", min_n: int = MIN_HELDOUT) -> Refusal | None:
    """``("heldout", message)`` when the checkpoint's held-out record shows a member worse than f_hat on the same
    held-out transitions (objective or any constraint, each on at least ``min_n`` of them), else None."""
    rec = meta.get("heldout")
    desc = rec.get("description", "") if isinstance(rec, Mapping) else ""
    for name, member, (mean, se, n), (bmean, bse, bn) in heldout_comparison(meta):
        if n < min_n or bn < min_n or not (math.isfinite(mean) and math.isfinite(bmean)):
            continue
        if mean > bmean:
            what = "objective" if name == "objective" else f"error in constraint '{name}'s region"
            return "heldout", (f"{where}held-out {what} of member {member} is worse than f_hat's on the same held-out "
                               f"transitions: {mean:.4g} +- {se:.2g} vs f_hat {bmean:.4g} +- {bse:.2g} (n {n}"
                               + (f"; {desc}" if desc else "") + ")")
    return None


def acceptance_hook(bounds: Plausibility, recent: Callable[[], Probe | None],
                    config: AcceptanceConfig | None = None) -> Callable[[LoadedModel], Refusal | None]:
    """The ``vet`` hook of a :class:`~saml_ros.core.mpc.follower.ModelWatcher`: :func:`check_model` with the probe
    rows ``recent()`` returns at the time of the check."""

    def vet(loaded: LoadedModel) -> Refusal | None:
        return check_model(loaded, bounds, recent(), config)

    return vet
