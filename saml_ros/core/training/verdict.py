"""Offline verdicts read on held-out data (:func:`read_verdicts`), the estimates they rest on
(:func:`spec_estimates`), and the bound training aims at (:func:`aimed_spec`, :func:`aim_bounds`).

A constraint ``LHS_k <= eps_k`` is **met** when it is met on data the model did not train on, with stated
confidence: the held-out estimate's one-sided upper bound ``mean + Z se`` (:data:`~.heldout.Z` = 1.645, 95 %) is at
most ``eps_k`` (:func:`~.heldout.heldout_verdict`). The other verdicts say what is missing: ``unconfirmed`` (held-out
mean below eps, its upper bound above: more held-out data would decide), ``met_on_training_only`` (the training value
meets the bound, the held-out mean does not), ``not_met`` and ``no_heldout_data`` (fewer than
:data:`~.heldout.MIN_N` held-out samples in the region). The end-of-training convergence diagnosis
(:mod:`~saml_ros.core.training.diagnosis`: met / not converged / likely infeasible on the training data, against the
bound training aimed at) stays beside it and says *why* a constraint is not met. Over the members of an ensemble
(one per seed) a constraint's verdict is the worst member's.

Estimates: per member, the per-sample losses of a term on a dataset, in the data's order; the standard error is the
iid formula for independently drawn data and batch means (:data:`~.heldout.STREAM_BLOCKS` blocks) for a recording,
whose consecutive transitions are correlated (:func:`~.heldout.constraint_estimate`).

The aim: a model that ends training exactly on ``eps`` on its training data exceeds ``eps`` on fresh data about half
the time. Training aims at ``aim_k = eps_k - Z sqrt(se_t^2 + se_h^2)`` (:func:`aim_bounds`): ``se_t`` is the standard
error of the training estimate (how far the model's true value may lie from what training sees), ``se_h`` that of
the held-out estimate the verdict will read, so the root of their squares is the standard error of the difference
between the training value and the held-out estimate; both are measured on the model being trained
(:func:`~saml_ros.offline.pipelines.train_models` measures them part-way through the run). A model that ends at its
aim then has a held-out estimate below eps with about 95 % probability and is reported met (upper bound below eps)
with probability ``Phi(Z (1 - se_h / sqrt(se_t^2 + se_h^2)))`` (about 87 % with a held-out set 10 times the training
set's size); a model reported met exceeds eps on fresh data with at most about 5 % probability (the verdict's own
confidence), margin or not. docs/training.md has the measurements.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from saml_ros.core.model.network import DynamicsModel
from saml_ros.core.spec import ProblemSpec, Term
from saml_ros.core.training.dataset import Transitions
from saml_ros.core.training.diagnosis import FeasibilityDiagnosis
from saml_ros.core.training.heldout import (
    HELDOUT_CODES,
    MET,
    MET_ON_TRAINING_ONLY,
    MIN_N,
    NO_HELDOUT,
    NOT_MET,
    STREAM_BLOCKS,
    UNCONFIRMED,
    Estimate,
    Z,
    aim,
    constraint_estimate,
    heldout_verdict,
)

#: verdicts from best to worst: an ensemble's verdict on a constraint is its worst member's
ORDER = (MET, UNCONFIRMED, NO_HELDOUT, MET_ON_TRAINING_ONLY, NOT_MET)
#: the words printed for each verdict
WORDS = {MET: "met", UNCONFIRMED: "UNCONFIRMED", NO_HELDOUT: "NO HELD-OUT VERDICT",
         MET_ON_TRAINING_ONLY: "MET ON TRAINING DATA ONLY", NOT_MET: "NOT MET"}


# ------------------------------------------------------------------------------------------------ estimates
def _conditional(t: Term) -> bool:
    return t.region is not None and t.mean == "conditional"


@torch.no_grad()
def term_losses(model: DynamicsModel, spec: ProblemSpec, data: Transitions,
                chunk: int = 65536) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per-sample losses of every member on ``data``: one ``(losses (E, N) float64, in_region (E, N) bool)`` per
    term, the objective first, then each constraint (a term without a region: every sample is in it)."""
    e, n = model.n_models, len(data)
    terms = [spec.objective, *spec.constraints]
    losses = [np.empty((e, n)) for _ in terms]
    masks = [np.ones((e, n), dtype=bool) for _ in terms]
    for s in range(0, n, chunk):
        idx = torch.arange(s, min(n, s + chunk)).unsqueeze(0).expand(e, -1)
        x, u, y, base = data.take(idx)
        pred = model(x, u, base)
        for j, (t, m) in enumerate(zip(terms, data.take_masks(idx))):
            losses[j][:, s:s + idx.shape[1]] = t.per_sample(pred, y).double().numpy()
            if m is not None:
                masks[j][:, s:s + idx.shape[1]] = m.expand(e, -1).numpy()
    return list(zip(losses, masks))


def spec_estimates(model: DynamicsModel, spec: ProblemSpec, data: Transitions,
                   stream: bool = False) -> tuple[list[Estimate], list[list[Estimate]]]:
    """Held-out (or training) estimates of the objective's and each constraint's left-hand side on ``data``, per
    member: ``(objective [E], constraints [K][E])``. ``stream``: ``data`` is a recording in time order (batch-means
    standard errors), else independent draws (iid)."""
    blocks = STREAM_BLOCKS if stream else None
    terms = [spec.objective, *spec.constraints]
    out = [[constraint_estimate(loss[m], mask[m], _conditional(t), blocks) for m in range(model.n_models)]
           for t, (loss, mask) in zip(terms, term_losses(model, spec, data))]
    return out[0], out[1:]


# ------------------------------------------------------------------------------------------------ the aim
def aimed_spec(spec: ProblemSpec, bounds: Sequence[float]) -> ProblemSpec:
    """``spec`` with constraint k's bound replaced by ``bounds[k]`` (what training aims at); everything else equal."""
    if len(bounds) != spec.n_constraints:
        raise ValueError(f"{len(bounds)} bounds for {spec.n_constraints} constraints")
    raw = spec.to_dict()
    for c, b in zip(raw.get("constraints") or [], bounds):
        c["eps"] = float(b)
    return ProblemSpec.from_dict(raw, spec.state, spec.control, spec.target)


def aim_bounds(eps: Sequence[float], train_se: Sequence[float], heldout_se: Sequence[float],
               z: float = Z) -> list[float]:
    """The bound training aims at per constraint: ``eps - z sqrt(se_t^2 + se_h^2)`` through :func:`~.heldout.aim`
    (never below half of eps; a non-finite standard error aims at eps)."""
    out = []
    for e, st, sh in zip(eps, train_se, heldout_se):
        se = math.hypot(st, sh) if math.isfinite(st) and math.isfinite(sh) else math.inf
        out.append(aim(float(e), se, z))
    return out


def recorded_aim(record: Any, spec: ProblemSpec) -> list[float] | None:
    """The bounds a checkpoint's aim record (``meta["aim"]``, :meth:`AimReport.to_dict`) says training aimed at,
    per constraint of ``spec`` (eps itself where no margin was applied); None when there is no such record or it
    does not belong to ``spec`` (other constraint names, or an ``eps`` other than the record's: the margin was
    sized for that bound). Raises nothing: a malformed record is none."""
    if not isinstance(record, dict) or not isinstance(record.get("constraints"), dict) or not spec.constraints:
        return None
    cons = record["constraints"]
    out = []
    for t in spec.constraints:
        c = cons.get(t.name)
        if not isinstance(c, dict):
            return None
        try:
            eps, bound = float(c["eps"]), float(c["aim"])
        except (KeyError, TypeError, ValueError):
            return None
        if not (math.isfinite(bound) and 0.0 < bound <= t.eps) or not math.isclose(eps, t.eps, rel_tol=1e-9):
            return None
        out.append(bound)
    return out


@dataclass
class AimReport:
    """How the aim was chosen: per constraint its ``eps``, the ``aim`` trained at, the standard errors it was sized
    by (``train_se``: the training estimate's, largest over members; ``heldout_se``: the held-out estimate's as
    predicted from the held-out set's size), the ``epoch`` at which they were measured; ``margin``: the option
    (``"auto"``, a fraction of eps, or ``"none"``)."""

    margin: str
    names: list[str]
    eps: list[float]
    aim: list[float]
    train_se: list[float] = field(default_factory=list)
    heldout_se: list[float] = field(default_factory=list)
    epoch: float = 0.0

    def to_dict(self) -> dict[str, Any]:
        d: dict[str, Any] = {"margin": self.margin, "measured_at_epoch": self.epoch, "z": Z, "constraints": {}}
        for i, n in enumerate(self.names):
            d["constraints"][n] = {
                "eps": self.eps[i], "aim": self.aim[i], "margin_fraction": 1.0 - self.aim[i] / self.eps[i],
                "train_se": self.train_se[i] if self.train_se else None,
                "heldout_se": self.heldout_se[i] if self.heldout_se else None,
            }
        return d

    def describe(self) -> str:
        parts = [f"'{n}' at {a:.4g} = eps {e:g} - {100 * (1 - a / e):.1f} %" for n, e, a in
                 zip(self.names, self.eps, self.aim)]
        for i in range(len(self.names)):
            if self.train_se and not (math.isfinite(self.train_se[i]) and math.isfinite(self.heldout_se[i])):
                parts[i] += f" (no margin: fewer than {MIN_N} training or held-out samples in the region)"
        how = (f" (sized by the standard errors measured at epoch {self.epoch:g}: training "
               + ", ".join(f"{s:.2g}" for s in self.train_se) + ", held-out "
               + ", ".join(f"{s:.2g}" for s in self.heldout_se) + ")") if self.train_se else ""
        return "aimed " + "; ".join(parts) + how


# ------------------------------------------------------------------------------------------------ verdicts
@dataclass
class MemberVerdict:
    """One member's verdict on one constraint: ``heldout`` estimate (None: no held-out data), ``training`` value
    of the left-hand side on its training data."""

    verdict: str
    heldout: Estimate | None
    training: float

    def to_dict(self, z: float = Z) -> dict[str, Any]:
        h = self.heldout
        return {"verdict": self.verdict, "level": HELDOUT_CODES[self.verdict], "training": self.training,
                "heldout": None if h is None else h.to_dict(),
                "upper": None if h is None else h.upper(z)}


@dataclass
class ConstraintVerdict:
    """The verdict on one constraint over all members (the worst member's), with the training's convergence
    diagnosis (``convergence``: met / not_converged / infeasible against ``aim``, None without one)."""

    name: str
    eps: float
    aim: float
    verdict: str
    members: list[MemberVerdict]
    convergence: str | None
    convergence_message: str
    message: str = ""

    @property
    def level(self) -> int:
        return HELDOUT_CODES[self.verdict]

    @property
    def n_met(self) -> int:
        return sum(m.verdict == MET for m in self.members)

    def to_dict(self, z: float = Z) -> dict[str, Any]:
        return {"verdict": self.verdict, "level": self.level, "eps": self.eps, "aim": self.aim,
                "n_met": self.n_met, "members": [m.to_dict(z) for m in self.members],
                "convergence": self.convergence, "convergence_message": self.convergence_message,
                "message": self.message}


@dataclass
class Verdicts:
    """Every constraint's verdict; ``heldout`` says what the held-out data was."""

    constraints: list[ConstraintVerdict]
    heldout: str
    z: float = Z

    @property
    def level(self) -> int:
        """The worst level (0 OK, 1 WARN, 2 ERROR; 0 without constraints)."""
        return max((c.level for c in self.constraints), default=0)

    @property
    def all_met(self) -> bool:
        return all(c.verdict == MET for c in self.constraints)

    def to_dict(self) -> dict[str, Any]:
        return {"level": self.level, "all_met": self.all_met, "heldout": self.heldout, "z": self.z,
                "confidence": "one-sided 95 %: met when mean + z se <= eps on the held-out data",
                "constraints": {c.name: c.to_dict(self.z) for c in self.constraints}}

    def messages(self) -> list[str]:
        return [c.message for c in self.constraints]


def _rng(v: Sequence[float], fmt: str = ".4g") -> str:
    lo, hi = min(v), max(v)
    return f"{lo:{fmt}}" if f"{lo:{fmt}}" == f"{hi:{fmt}}" else f"{lo:{fmt}}-{hi:{fmt}}"


def _why(verdict: str) -> str:
    return {
        UNCONFIRMED: "the held-out mean is below eps but its 95 % upper bound is not: more held-out data "
                     "(--test-samples) or a larger margin would decide",
        NO_HELDOUT: f"fewer than {MIN_N} held-out samples in the region: no verdict can be read",
        MET_ON_TRAINING_ONLY: "the training value meets the bound, the held-out value does not: the model fits its "
                              "training data better than the distribution (more data, a smaller net, or a margin)",
        NOT_MET: "violated on the held-out data",
    }.get(verdict, "")


def _message(c: ConstraintVerdict, z: float) -> str:
    n = len(c.members)
    hs = [m.heldout for m in c.members if m.heldout is not None and m.heldout.n > 0]
    aimed = f"; aimed at {c.aim:.4g}" if c.aim != c.eps else ""
    train = f"training {_rng([m.training for m in c.members])}"
    if hs:
        mean = _rng([h.mean for h in hs])
        se = _rng([h.se for h in hs], ".2g")
        upper = max(h.upper(z) for h in hs)
        rel = "<=" if upper <= c.eps else ">"
        held = f"held-out {mean} +- {se} (upper bound {upper:.4g} {rel} eps {c.eps:g}, n in region {_rng([h.n for h in hs], 'd')})"
    else:
        held = "no held-out sample in the region"
    who = "" if n == 1 else (f" by {c.n_met}/{n} members" if c.verdict == MET or c.n_met else f" ({n} members)")
    head = f"constraint '{c.name}': {WORDS[c.verdict]}{who} ({held}; {train}{aimed})"
    if c.verdict != MET:
        head += f": {_why(c.verdict)}"
        bad = [f"member {i} {WORDS[m.verdict].lower()}" for i, m in enumerate(c.members) if m.verdict != MET]
        if n > 1:
            head += f" [{', '.join(bad)}]"
    if c.convergence is not None:
        conv = "converged to its aim" if c.convergence == MET else c.convergence.replace("_", " ")
        head += f"; training {conv}"
    return head


def read_verdicts(spec: ProblemSpec, heldout: list[list[Estimate]] | None, training: np.ndarray,
                  aimed: Sequence[float] | None = None, diagnosis: FeasibilityDiagnosis | None = None,
                  description: str = "", z: float = Z) -> Verdicts:
    """The verdict on each of ``spec``'s constraints.

    Args:
        spec: the problem (its ``eps`` are the bounds judged).
        heldout: per constraint, per member, the held-out estimate of the left-hand side (:func:`spec_estimates`);
            None: no held-out data.
        training: the left-hand side on each member's training data ``(E, K)``.
        aimed: the bounds training aimed at ``(K,)`` (None: eps).
        diagnosis: the training's convergence diagnosis (against ``aim``).
        description: what the held-out data was (stored with the verdicts).
    """
    eps = [t.eps for t in spec.constraints]
    aims = list(eps) if aimed is None else [float(a) for a in aimed]
    training = np.asarray(training, dtype=float).reshape(-1, len(eps)) if eps else np.zeros((0, 0))
    out = []
    for k, name in enumerate(spec.constraint_names):
        members = []
        for m in range(training.shape[0]):
            est = None if heldout is None else heldout[k][m]
            t = float(training[m, k])
            members.append(MemberVerdict(heldout_verdict(eps[k], est, t, z), est, t))
        verdict = max((m.verdict for m in members), key=ORDER.index, default=NO_HELDOUT)
        conv = diagnosis.constraints[k] if diagnosis is not None and k < len(diagnosis.constraints) else None
        c = ConstraintVerdict(name, eps[k], aims[k], verdict, members, None if conv is None else conv.verdict,
                              "" if conv is None else conv.message)
        c.message = _message(c, z)
        out.append(c)
    return Verdicts(out, description, z)
