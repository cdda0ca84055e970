"""Held-out stretches of a live stream, and the model's errors read on them (ROS-free).

Consecutive transitions of a stream are nearly identical (a robot at 100 Hz), so a random split would test the model
on the twins of its training samples. The learner instead keeps **whole stretches of time** aside: with
``period`` P and ``fraction`` f, a transition whose state is stamped t belongs to the held-out stretch when
``t mod P >= (1 - f) P`` (by default the last 2 s of every 10 s of the stream's own clock), and is **never** put in the
replay buffer: it goes to a FIFO :class:`HeldoutSet` of the newest held-out transitions instead
(:func:`heldout_mask`). Transitions without stamps (all 0) all go to training.

:func:`evaluate` reads, for every term of the spec (the objective, then each constraint), the left-hand side on the
held-out set with its standard error (batch means, one block per held-out stretch up to
:data:`~saml_ros.core.training.heldout.STREAM_BLOCKS`: :func:`~saml_ros.core.training.heldout.constraint_estimate`),
the same for f_hat on the same transitions, the value on (a sample of) the training buffer, and the verdict
(:func:`~saml_ros.core.training.heldout.heldout_verdict`: met / unconfirmed / met on training data only / not met /
no held-out data). The learner reports it on ``learner/model_error`` and ``/diagnostics`` and writes it into every
checkpoint (``meta["heldout"]``, :meth:`HeldoutReport.to_meta`), where the MPC reads it
(:mod:`saml_ros.core.mpc.acceptance`).

Shapes: ``x (N, n_x)``, ``u (N, n_u)``, ``y (N, n_y)``, ``stamp (N,)`` in seconds; E ensemble members.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from saml_ros.core.data.buffer import ReplayBuffer, Transitions
from saml_ros.core.training.heldout import (
    NO_HELDOUT,
    STREAM_BLOCKS,
    Estimate,
    Z,
    constraint_estimate,
    heldout_verdict,
)

if TYPE_CHECKING:  # torch is imported where the model is evaluated: the learner node imports this module
    from saml_ros.core.model.network import DynamicsModel
    from saml_ros.core.spec import ProblemSpec, Term

#: the ``meta`` key of a checkpoint's held-out record (read by :mod:`saml_ros.core.mpc.acceptance`)
META_KEY = "heldout"
#: rows evaluated per forward pass (bounds the memory of an evaluation)
CHUNK = 8192


@dataclass(frozen=True)
class HeldoutConfig:
    """Which stretches of the stream are held out, and how many held-out transitions are kept.

    Attributes:
        period: s of stream time per cycle (P).
        fraction: the share of each cycle held out, at its end, in [0, 0.5]; 0 = no held-out data.
        capacity: held-out transitions kept (the newest; FIFO).
        train_sample: training-buffer rows the training value of each term is read on (a uniform sample).
    """

    period: float = 10.0
    fraction: float = 0.2
    capacity: int = 25_000
    train_sample: int = 20_000

    def __post_init__(self) -> None:
        if not (math.isfinite(self.period) and self.period > 0):
            raise ValueError(f"heldout.period must be > 0 s, got {self.period}")
        if not 0.0 <= self.fraction <= 0.5:
            raise ValueError(f"heldout.fraction must be in [0, 0.5], got {self.fraction}")
        if self.capacity < 1 or self.train_sample < 1:
            raise ValueError(f"heldout.capacity and the training sample must be >= 1, got {self.capacity}, "
                             f"{self.train_sample}")

    def describe(self) -> str:
        """One line: which stretches are held out."""
        if self.fraction == 0:
            return "no held-out data"
        return (f"the last {self.fraction * self.period:g} s of every {self.period:g} s of the stream "
                f"(newest {self.capacity} transitions)")


def heldout_mask(stamps_s: Any, config: HeldoutConfig) -> np.ndarray:
    """``(N,)`` bool: which transitions (state stamps in s) fall into a held-out stretch (see the module
    docstring). Stamps that are all exactly 0 (unstamped rows) are training data."""
    t = np.asarray(stamps_s, dtype=np.float64).reshape(-1)
    if config.fraction == 0:
        return np.zeros(t.shape, dtype=bool)
    phase = np.mod(t, config.period) / config.period
    return (phase >= 1.0 - config.fraction) & (t != 0.0)


def stretch_ids(stamps_s: Any, config: HeldoutConfig) -> np.ndarray:
    """``(N,)`` int64: the index of the cycle (of ``period`` s) each stamp falls into."""
    return np.floor(np.asarray(stamps_s, dtype=np.float64) / config.period).astype(np.int64)


class HeldoutSet:
    """The newest ``config.capacity`` held-out transitions (FIFO, thread-safe: a :class:`ReplayBuffer`)."""

    def __init__(self, config: HeldoutConfig, n_x: int, n_u: int, n_y: int) -> None:
        self.config = config
        self.buffer = ReplayBuffer(config.capacity, n_x, n_u, n_y, "fifo")

    def __len__(self) -> int:
        return len(self.buffer)

    @property
    def total_added(self) -> int:
        return self.buffer.total_added

    def add_batch(self, x: np.ndarray, u: np.ndarray, y: np.ndarray, stamp: Any, source: Any) -> None:
        self.buffer.add_batch(x, u, y, stamp=stamp, source=source)

    def arrays(self) -> Transitions:
        """Copies of the held-out rows, oldest first (time order within each source)."""
        return self.buffer.arrays()


# ------------------------------------------------------------------------------------------------ evaluation
@dataclass
class TermReport:
    """One spec term on the held-out set, per ensemble member.

    Attributes:
        name: ``"objective"`` or the constraint's name.
        eps: the constraint's bound (None for the objective).
        conditional: the left-hand side is ``E[l | region]`` (else ``E[l I_region]``, or ``E[l]`` without region).
        model: per member, the held-out estimate of the left-hand side.
        base: f_hat's estimate on the same transitions (one, shared by the members).
        training: per member, the left-hand side on (a sample of) the training buffer (NaN: none yet).
        verdicts: per member, the verdict (constraints only; ``[]`` for the objective).
    """

    name: str
    eps: float | None
    conditional: bool
    model: list[Estimate]
    base: Estimate
    training: list[float]
    verdicts: list[str] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        return {"eps": self.eps, "conditional": self.conditional, "model": [e.to_dict() for e in self.model],
                "base": self.base.to_dict(), "training": list(self.training), "verdicts": list(self.verdicts)}


@dataclass
class HeldoutReport:
    """Every term on the held-out set (:func:`evaluate`): ``terms[0]`` is the objective, then each constraint.

    Attributes:
        terms: see :class:`TermReport`.
        n: held-out transitions evaluated.
        stretches: held-out stretches they come from.
        description: which stretches are held out (:meth:`HeldoutConfig.describe`).
        updates: the model's update count when evaluated.
        published: which weights were evaluated: ``"latest"`` (the trainer's) or ``"average"`` (their exponential
            average, :class:`~saml_ros.core.online.learner.OnlineLearner`).
    """

    terms: list[TermReport]
    n: int
    stretches: int
    description: str
    updates: int = 0
    published: str = "latest"

    @property
    def objective(self) -> TermReport:
        return self.terms[0]

    @property
    def constraints(self) -> list[TermReport]:
        return self.terms[1:]

    def to_meta(self) -> dict[str, Any]:
        """The checkpoint's ``meta["heldout"]``: the model's and f_hat's held-out estimates of every term, the
        training values and the verdicts (JSON)."""
        return {"source": "stream", "description": self.description, "n": self.n, "stretches": self.stretches,
                "updates": self.updates, "published": self.published, "z": Z, "objective": self.objective.to_dict(),
                "constraints": {t.name: t.to_dict() for t in self.constraints}}

    def metrics(self, member: int = 0) -> dict[str, float]:
        """The telemetry values of member ``member`` (:data:`saml_ros.core.online.telemetry.HELDOUT_METRICS`)."""
        from saml_ros.core.online.telemetry import VERDICT_NUMBERS

        ob = self.objective
        out = {"heldout_size": float(self.n), "heldout_objective": ob.model[member].mean,
               "heldout_objective_base": ob.base.mean, "heldout_updates": float(self.updates),
               "heldout_average": 1.0 if self.published == "average" else 0.0}
        for t in self.constraints:
            est = t.model[member]
            out[f"heldout/{t.name}"] = est.mean
            out[f"heldout_se/{t.name}"] = est.se
            out[f"heldout_upper/{t.name}"] = est.upper()
            out[f"heldout_n/{t.name}"] = float(est.n)
            out[f"heldout_base/{t.name}"] = t.base.mean
            out[f"training_lhs/{t.name}"] = t.training[member]
            out[f"heldout_verdict/{t.name}"] = float(VERDICT_NUMBERS[t.verdicts[member]])
        return out


def _is_conditional(term: Term) -> bool:
    return term.region is not None and term.mean == "conditional"


def term_losses(model: DynamicsModel, spec: ProblemSpec, x: np.ndarray, u: np.ndarray, y: np.ndarray,
                base: bool = False) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per-sample losses of every spec term (objective first) and their region masks, ``(losses (E, N), in_region
    (N,))`` each, of ``model``'s prediction (every member), or with ``base`` of f_hat's (``(1, N)``: the system's
    base model, also for a full model)."""
    import torch

    terms = [spec.objective, *spec.constraints]
    n = len(x)
    e = 1 if base else model.n_models
    losses = [np.empty((e, n)) for _ in terms]
    masks = [np.ones(n, dtype=bool) for _ in terms]
    with torch.no_grad():
        for s in range(0, n, CHUNK):
            xs, us, ys = (torch.from_numpy(np.ascontiguousarray(a[s:s + CHUNK], dtype=np.float64)) for a in (x, u, y))
            if base:
                pred = model.system.base_step(xs, us).double()[None]
            else:
                dt = model.in_mean.dtype
                pred = model(xs.to(dt), us.to(dt)).double()
            for j, (t, m) in enumerate(zip(terms, spec.masks(xs, us, ys), strict=True)):
                losses[j][:, s:s + len(xs)] = t.per_sample(pred, ys).numpy()
                if m is not None:
                    masks[j][s:s + len(xs)] = m.numpy()
    return list(zip(losses, masks, strict=True))


def _estimates(spec: ProblemSpec, losses: list[tuple[np.ndarray, np.ndarray]], blocks: int | None,
               groups: np.ndarray | None) -> list[list[Estimate]]:
    """Per term, per member: the estimate of the left-hand side (batch means over ``blocks`` blocks)."""
    out = []
    for t, (loss, mask) in zip([spec.objective, *spec.constraints], losses, strict=True):
        k = blocks
        if k is not None and groups is not None:  # at most one block per held-out stretch in the region
            k = max(1, min(k, len(np.unique(groups[mask]))))
        out.append([constraint_estimate(loss[m], mask, _is_conditional(t), k) for m in range(loss.shape[0])])
    return out


def evaluate(model: DynamicsModel, spec: ProblemSpec, heldout: Transitions, training: Transitions | None,
             config: HeldoutConfig, base_losses: list[tuple[np.ndarray, np.ndarray]] | None = None,
             updates: int = 0) -> HeldoutReport:
    """The held-out report of ``model`` (every member) on ``heldout`` (in time order), with f_hat's estimates on
    the same rows (``base_losses``: :func:`term_losses` of them with ``base``, when already at hand) and the training
    values on ``training`` (a sample of the training buffer; None: NaN)."""
    ids = stretch_ids(heldout.stamp, config)
    n_stretches = int(len(np.unique(ids))) if len(ids) else 0
    model_l = term_losses(model, spec, heldout.x, heldout.u, heldout.y)
    base_l = base_losses if base_losses is not None else term_losses(model, spec, heldout.x, heldout.u, heldout.y,
                                                                      base=True)
    held = _estimates(spec, model_l, STREAM_BLOCKS, ids)
    base = _estimates(spec, base_l, STREAM_BLOCKS, ids)
    e = model.n_models
    if training is not None and len(training.x):
        tl = term_losses(model, spec, training.x, training.u, training.y)
        train = [[e_.mean for e_ in per] for per in _estimates(spec, tl, None, None)]
    else:
        train = [[math.nan] * e for _ in held]
    terms = []
    for j, t in enumerate([spec.objective, *spec.constraints]):
        is_con = j > 0
        verdicts = [heldout_verdict(t.eps, held[j][m], train[j][m]) if held[j][m].n else NO_HELDOUT
                    for m in range(e)] if is_con else []
        terms.append(TermReport(t.name, t.eps if is_con else None, _is_conditional(t), held[j], base[j][0],
                                train[j], verdicts))
    return HeldoutReport(terms, len(heldout.x), n_stretches, config.describe(), updates)
