"""What the training data showed, stored in a checkpoint so its reader can tell a sane model from a poisoned one.

:class:`DataEvidence` summarises the transitions a model was trained on: how far the observed target ever was from
the base model's prediction (the residual ``y - f_hat(x, u)``, largest magnitude and RMS per target field), the
spread of the target, and a probe set (a random sample of the training inputs ``(x, u)``). The learner and the
offline trainer write it into every checkpoint (arrays ``evidence/x``, ``evidence/u``, ``meta["evidence"]``); the
MPC's acceptance check (:mod:`saml_ros.core.mpc.acceptance`) predicts on the probe set (and on recent states)
and refuses a model whose residual is far beyond anything the data showed.

Shapes: ``x (N, n_x)``, ``u (N, n_u)``, ``y (N, n_y)``; per-field statistics ``(n_y,)``. Units: those of the target
fields.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from saml_ros.core.dynamics.system import System

#: probe rows a checkpoint stores
PROBE_ROWS = 256
#: array names in a checkpoint
PROBE_X, PROBE_U = "evidence/x", "evidence/u"


@dataclass
class DataEvidence:
    """Statistics of the training data and a probe set of its inputs.

    Attributes:
        n: transitions summarised (the learner: every transition it ever accepted).
        residual_max: ``(n_y,)`` largest ``|y - f_hat(x, u)|`` per target field.
        residual_rms: ``(n_y,)`` RMS of ``y - f_hat(x, u)`` per target field.
        target_std: ``(n_y,)`` standard deviation of ``y`` per target field.
        probe_x, probe_u: ``(P, n_x)``, ``(P, n_u)`` training inputs to predict on.
    """

    n: int
    residual_max: np.ndarray
    residual_rms: np.ndarray
    target_std: np.ndarray
    probe_x: np.ndarray
    probe_u: np.ndarray

    @classmethod
    def from_data(cls, system: System, x: np.ndarray, u: np.ndarray, y: np.ndarray,
                  rng: np.random.Generator | None = None, probe_rows: int = PROBE_ROWS) -> DataEvidence | None:
        """Evidence of the transitions ``(x, u, y)`` (``None`` for no rows); the probe set is ``probe_rows`` rows
        drawn without replacement by ``rng``."""
        x, u, y = (np.asarray(a, dtype=np.float64) for a in (x, u, y))
        if len(x) == 0:
            return None
        r = y - system.base_step_np(x, u)
        rng = rng or np.random.default_rng(0)
        pick = rng.choice(len(x), size=min(probe_rows, len(x)), replace=False)
        with np.errstate(over="ignore", invalid="ignore"):  # absurd data (no bounds) overflow to inf: so be it
            return cls(n=len(x), residual_max=np.abs(r).max(0), residual_rms=np.sqrt((r * r).mean(0)),
                       target_std=y.std(0), probe_x=x[pick].copy(), probe_u=u[pick].copy())

    def merged(self, older: DataEvidence | None, n: int | None = None) -> DataEvidence:
        """This evidence (of the data at hand) combined with ``older`` (of the data before): the larger residual
        maximum, this one's RMS, spread and probe set; ``n`` transitions in all (default: this one's)."""
        res_max = self.residual_max if older is None else np.maximum(self.residual_max, older.residual_max)
        return DataEvidence(self.n if n is None else int(n), res_max, self.residual_rms, self.target_std,
                            self.probe_x, self.probe_u)

    def to_payload(self, target_fields: tuple[str, ...]) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        """Checkpoint arrays (the probe set) and ``meta["evidence"]`` (the statistics, by target field)."""
        meta = {"n": int(self.n), "fields": list(target_fields), "residual_max": self.residual_max.tolist(),
                "residual_rms": self.residual_rms.tolist(), "target_std": self.target_std.tolist()}
        return {PROBE_X: self.probe_x, PROBE_U: self.probe_u}, meta

    @classmethod
    def from_checkpoint(cls, arrays: dict[str, np.ndarray], meta: dict[str, Any],
                        system: System) -> DataEvidence | None:
        """The evidence a checkpoint holds, or ``None`` (none stored, or it does not fit ``system``'s layouts)."""
        ev = meta.get("evidence")
        if not isinstance(ev, dict) or PROBE_X not in arrays or PROBE_U not in arrays:
            return None
        n_y = system.target.size
        try:
            stats = [np.asarray(ev[k], dtype=np.float64) for k in ("residual_max", "residual_rms", "target_std")]
            px = np.asarray(arrays[PROBE_X], dtype=np.float64)
            pu = np.asarray(arrays[PROBE_U], dtype=np.float64)
        except (KeyError, TypeError, ValueError):
            return None
        if (any(s.shape != (n_y,) for s in stats) or px.ndim != 2 or px.shape[1] != system.state.size
                or pu.shape != (len(px), system.control.size)):
            return None
        return cls(int(ev.get("n", len(px))), stats[0], stats[1], stats[2], px, pu)
