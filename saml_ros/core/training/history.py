"""Bookkeeping of a primal-dual run, shared by every engine: the training curve (:class:`History`), the minibatch
values since its last row (:class:`TrainingLog`), the progress bar and the end-of-run feasibility check."""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from saml_ros.core.spec import SpecValues

if TYPE_CHECKING:
    import torch


@dataclass
class History:
    """Training curve: one row per log point. Arrays are ``(E,)`` or ``(E, K)`` per row."""

    constraint_names: list[str]
    step: list[int] = field(default_factory=list)
    epoch: list[float] = field(default_factory=list)
    objective: list[np.ndarray] = field(default_factory=list)
    constraints: list[np.ndarray] = field(default_factory=list)
    lambdas: list[np.ndarray] = field(default_factory=list)
    lagrangian: list[np.ndarray] = field(default_factory=list)
    wall_time: list[float] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        for k in ("objective", "constraints", "lambdas", "lagrangian"):
            d[k] = [np.asarray(v).tolist() for v in d[k]]
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> History:
        h = cls(list(d["constraint_names"]))
        h.step, h.epoch, h.wall_time = list(d["step"]), list(d["epoch"]), list(d["wall_time"])
        for k in ("objective", "constraints", "lambdas", "lagrangian"):
            setattr(h, k, [np.asarray(v) for v in d[k]])
        return h

    def as_arrays(self) -> dict[str, np.ndarray]:
        """Stacked curves: objective ``(T, E)``, constraints/lambdas ``(T, E, K)``, lagrangian ``(T, E)``."""
        return {
            "step": np.asarray(self.step),
            "epoch": np.asarray(self.epoch),
            "objective": np.stack(self.objective) if self.objective else np.zeros((0, 0)),
            "constraints": np.stack(self.constraints) if self.constraints else np.zeros((0, 0, 0)),
            "lambdas": np.stack(self.lambdas) if self.lambdas else np.zeros((0, 0, 0)),
            "lagrangian": np.stack(self.lagrangian) if self.lagrangian else np.zeros((0, 0)),
        }

    def keep_last(self, rows: int) -> None:
        """Drop all but the newest ``rows`` rows (online training never ends; its history must not grow)."""
        extra = len(self.step) - rows
        if extra > 0:
            for name in ("step", "epoch", "objective", "constraints", "lambdas", "lagrangian", "wall_time"):
                del getattr(self, name)[:extra]


class TrainingLog:
    """The :class:`History` of a run and the minibatch values since its last row.

    An engine either adds each step's values (:meth:`add`) and closes a row with :meth:`point`, or keeps its own
    values (:meth:`take_pending` hands over those added before) and appends rows with :meth:`record`.
    """

    def __init__(self, constraint_names: Sequence[str]) -> None:
        self.history = History(list(constraint_names))
        self._pending: list[SpecValues] = []
        self._t0 = time.monotonic()

    def add(self, vals: SpecValues) -> None:
        """One step's detached minibatch values (objective ``(E,)``, constraints ``(E, K)``)."""
        self._pending.append(vals)

    def take_pending(self) -> list[SpecValues]:
        """The values added since the last row, in order (the log forgets them)."""
        out, self._pending = self._pending, []
        return out

    def point(self, step: int, epoch: float, lam: torch.Tensor) -> None:
        """Append the mean of the values added since the last row (nothing when there are none)."""
        import torch

        if not self._pending:
            return
        obj = torch.stack([v.objective for v in self._pending]).mean(0)
        con = torch.stack([v.constraints for v in self._pending]).mean(0)
        self._pending.clear()
        self.record(step, epoch, obj, con, lam)

    def record(self, step: int, epoch: float, obj: torch.Tensor, con: torch.Tensor, lam: torch.Tensor) -> None:
        """Append one row: mean objective ``(E,)``, constraints ``(E, K)`` and lambda ``(E, K)`` (copied)."""
        h = self.history
        lam = lam.detach().clone()
        h.step.append(step)
        h.epoch.append(epoch)
        h.objective.append(obj.double().numpy())
        h.constraints.append(con.double().numpy())
        h.lambdas.append(lam.double().numpy())
        h.lagrangian.append((obj + (lam * con).sum(-1)).double().numpy())
        h.wall_time.append(time.monotonic() - self._t0)

    def postfix(self) -> str:
        """The last row, member means, for a progress bar: ``obj=... g[name]=... lam=...``."""
        h = self.history
        s = f"obj={float(np.mean(h.objective[-1])):.4g}"
        for k, name in enumerate(h.constraint_names):
            s += f" g[{name}]={float(np.mean(h.constraints[-1][..., k])):+.3g}"
            s += f" lam={float(np.mean(h.lambdas[-1][..., k])):.3g}"
        return s


def progress_bar(total: int, desc: str) -> Any:
    """A tqdm bar over ``total`` steps (disabled when the output is not a terminal)."""
    from tqdm import tqdm

    return tqdm(total=total, desc=desc, unit="step", mininterval=0.5, dynamic_ncols=True,
                disable=None if not math.isinf(total) else True)


@dataclass
class FeasibilityReport:
    """Constraints that stayed violated while their multiplier kept growing (likely infeasible)."""

    violated: list[tuple[int, str, float, float, float]]  # (member, name, mean g, lambda start, lambda end)

    @property
    def ok(self) -> bool:
        return not self.violated

    def messages(self) -> list[str]:
        return [
            f"member {m}: constraint '{n}' still violated at the end of training (mean g = {g:+.4g} > 0) "
            f"while lambda grew {a:.4g} -> {b:.4g}: the constraint may be infeasible for this model and data "
            f"(raise eps, enlarge the network, or train longer)"
            for m, n, g, a, b in self.violated
        ]


def check_feasibility(h: History, eps: Sequence[float], tail: float = 0.25, rel_tol: float = 0.02) -> FeasibilityReport:
    """Flag constraints whose mean g over the last ``tail`` of ``h`` exceeds ``rel_tol * eps[k]`` while lambda kept
    growing over that window (a converged saddle point hovers at g ~ 0)."""
    if len(h.step) < 4 or not h.constraint_names:
        return FeasibilityReport([])
    a = h.as_arrays()
    start = int(len(h.step) * (1 - tail))
    g = a["constraints"][start:].mean(0)  # (E, K)
    lam0, lam1 = a["lambdas"][start], a["lambdas"][-1]
    bad = []
    for m in range(g.shape[0]):
        for k, name in enumerate(h.constraint_names):
            if g[m, k] > rel_tol * eps[k] and lam1[m, k] > lam0[m, k]:
                bad.append((m, name, float(g[m, k]), float(lam0[m, k]), float(lam1[m, k])))
    return FeasibilityReport(bad)
