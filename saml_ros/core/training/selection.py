"""Restarts and selection: of the members of an ensemble trained on the same data (restarts from different
initialisations), keep the best feasible one on held-out data (:func:`select_members`).

The rule (docs/training.md), per group of restarts, on held-out estimates with their standard errors
(:func:`~saml_ros.core.training.verdict.spec_estimates`; batch means for a recording):

1. a member is **met** when every constraint is met there with confidence: the upper end of the one-sided 95 %
   interval, ``mean + Z se``, is at most ``eps_k`` (:func:`~saml_ros.core.training.heldout.heldout_verdict`);
   **unconfirmed** when every constraint's held-out mean is at most ``eps_k`` (or too few held-out samples fall in
   its region to tell) but not every one is confirmed;
2. keep the met member with the lowest held-out objective; if none is met, the unconfirmed member with the lowest
   held-out objective;
3. otherwise keep the member with the smallest worst relative held-out value ``max_k mean_k / eps_k`` (the lowest
   objective among equal ones): the closest to feasible, reported as violated.

A 1 % tolerance on a held-out mean of about 150 region samples (standard error about 9 % of eps, friction's 20 %
split) cannot tell a member at eps from one 10 % above; the standard errors put that uncertainty in the rule, and
``train`` sizes the selection set (docs/training.md).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from saml_ros.core.model.network import DynamicsModel
from saml_ros.core.spec import ProblemSpec
from saml_ros.core.training.dataset import Transitions
from saml_ros.core.training.heldout import MET, NO_HELDOUT, UNCONFIRMED, Estimate, Z, heldout_verdict
from saml_ros.core.training.trainer import PrimalDualTrainer
from saml_ros.core.training.verdict import spec_estimates

#: the status of a kept member: met with confidence, held-out mean within the bound, neither (the least violating)
MET_STATUS, UNCONFIRMED_STATUS, VIOLATED_STATUS = "met", "unconfirmed", "violated"


@dataclass
class Selection:
    """Which member each group kept, and why.

    Attributes:
        groups: the member indices of each group (restarts of one seed).
        chosen: the kept member of each group (an index into the ensemble).
        status: per group, the kept member's status: ``"met"``, ``"unconfirmed"`` or ``"violated"`` (module
            docstring).
        feasible: per group, whether the kept member's held-out means are within every bound (status not
            ``"violated"``).
        objective: held-out objective of every member ``(E,)``; ``objective_se`` its standard error.
        constraints: held-out ``g_k = mean_k - eps_k`` of every member ``(E, K)``; ``constraint_se`` their standard
            errors, ``n_in`` the held-out samples in each region ``(E, K)``.
    """

    groups: list[list[int]]
    chosen: list[int]
    status: list[str]
    objective: np.ndarray
    constraints: np.ndarray
    objective_se: np.ndarray
    constraint_se: np.ndarray
    n_in: np.ndarray

    @property
    def feasible(self) -> list[bool]:
        return [s != VIOLATED_STATUS for s in self.status]

    def describe(self) -> list[str]:
        out = []
        for g, c, st in zip(self.groups, self.chosen, self.status):
            why = {MET_STATUS: "met on the held-out selection data with 95 % confidence",
                   UNCONFIRMED_STATUS: "none met with confidence: the lowest objective among those whose held-out "
                                       "mean is within the bound",
                   VIOLATED_STATUS: "none within the bound: the least violating"}[st]
            others = [i for i in g if i != c]
            runner = min(others, key=lambda i: self.objective[i]) if others else None
            second = (f"; next lowest objective {self.objective[runner]:.4g} (member {runner})"
                      if runner is not None else "")
            out.append(f"restarts {g}: kept member {c} ({why}; held-out objective {self.objective[c]:.4g} +- "
                       f"{self.objective_se[c]:.2g}{second})")
        return out

    def to_dict(self) -> dict[str, Any]:
        return {"chosen": self.chosen, "status": self.status, "feasible": self.feasible,
                "heldout_objective": self.objective.tolist(), "heldout_objective_se": self.objective_se.tolist(),
                "heldout_constraints": self.constraints.tolist(), "heldout_constraint_se": self.constraint_se.tolist(),
                "heldout_n_in": self.n_in.tolist()}


def member_status(constraints: Sequence[Estimate], eps: Sequence[float], z: float = Z) -> str:
    """A member's status from its held-out constraint estimates (module docstring, rule 1)."""
    verdicts = [heldout_verdict(float(e), est, None, z) for e, est in zip(eps, constraints)]
    if all(v == MET for v in verdicts):
        return MET_STATUS
    within = [v in (MET, UNCONFIRMED) or (v == NO_HELDOUT and not est.mean > e)
              for v, est, e in zip(verdicts, constraints, eps)]
    return UNCONFIRMED_STATUS if all(within) else VIOLATED_STATUS


def choose(objective: Sequence[Estimate], constraints: Sequence[Sequence[Estimate]], eps: Sequence[float],
           group: Sequence[int], z: float = Z) -> tuple[int, str]:
    """The member of ``group`` the rule keeps (module docstring) and its status; ``objective`` ``[E]`` and
    ``constraints`` ``[E][K]`` are held-out estimates of the left-hand sides."""
    idx = list(group)
    if not idx:
        raise ValueError("an empty group of restarts")
    status = {i: member_status(constraints[i], eps, z) for i in idx}
    for want in (MET_STATUS, UNCONFIRMED_STATUS):
        cand = [i for i in idx if status[i] == want]
        if cand:
            return min(cand, key=lambda i: objective[i].mean), want

    def worst(i: int) -> float:
        rel = [est.mean / float(e) for est, e in zip(constraints[i], eps) if math.isfinite(est.mean)]
        return max(rel, default=-math.inf)

    return min(idx, key=lambda i: (worst(i), objective[i].mean)), VIOLATED_STATUS


@torch.no_grad()
def select_members(model: DynamicsModel, spec: ProblemSpec, heldout: Transitions,
                   groups: Sequence[Sequence[int]], stream: bool = False) -> Selection:
    """Apply the rule to every group of ``model``'s members on ``heldout`` (one dataset per member, or shared;
    ``stream``: a recording in time order, batch-means standard errors)."""
    obj, cons = spec_estimates(model, spec, heldout, stream)
    eps = [t.eps for t in spec.constraints]
    e, k = model.n_models, len(eps)
    per_member = [[cons[j][i] for j in range(k)] for i in range(e)]
    chosen, status = [], []
    for g in groups:
        c, st = choose(obj, per_member, eps, g)
        chosen.append(c)
        status.append(st)
    g_val = np.array([[est.mean - eps[j] for j, est in enumerate(row)] for row in per_member]).reshape(e, k)
    g_se = np.array([[est.se for est in row] for row in per_member]).reshape(e, k)
    n_in = np.array([[est.n for est in row] for row in per_member], dtype=int).reshape(e, k)
    return Selection([list(g) for g in groups], chosen, status, np.array([o.mean for o in obj]),
                     g_val, np.array([o.se for o in obj]), g_se, n_in)


@torch.no_grad()
def take_members(model: DynamicsModel, members: Sequence[int]) -> DynamicsModel:
    """A new ensemble of ``model``'s ``members`` (in that order), weights and normalisation copied."""
    idx = torch.as_tensor(list(members), dtype=torch.long)
    out = DynamicsModel(model.system, model.hidden, model.kind, n_models=len(idx), inputs=model.inputs)
    out.load_state_dict({k: v.index_select(0, idx).clone() for k, v in model.state_dict().items()})
    return out.to(model.in_mean.dtype)


def _take_state(state: dict[str, Any], idx: torch.Tensor, n: int) -> dict[str, Any]:
    """An optimizer state_dict with every per-member tensor (leading dimension ``n``) reduced to rows ``idx``."""
    out: dict[str, Any] = {"param_groups": state["param_groups"], "state": {}}
    for key, st in state["state"].items():
        out["state"][key] = {
            name: (v.index_select(0, idx).clone() if isinstance(v, torch.Tensor) and v.dim() and v.shape[0] == n
                   else v)
            for name, v in st.items()
        }
    return out


def take_trainer(trainer: PrimalDualTrainer, members: Sequence[int]) -> PrimalDualTrainer:
    """A trainer of ``trainer``'s ``members`` only: their weights, lambda rows, optimizer states and history
    columns, the same counters, config and generator state (it resumes as those members would have)."""
    idx = torch.as_tensor(list(members), dtype=torch.long)
    n = trainer.model.n_models
    out = PrimalDualTrainer(take_members(trainer.model, members), trainer.spec, trainer.config)
    dual = trainer.dual.state_dict()
    out.load_state({
        "model": out.model.state_dict(),
        "lam": dual["lam"].index_select(0, idx),
        "primal_opt": _take_state(trainer.primal_opt.state_dict(), idx, n),
        "dual_opt": _take_state(dual["optimizer"], idx, n),
        "steps": trainer.steps,
        "epochs_done": trainer.epochs_done,
        "rng": trainer.rng.get_state(),
    })
    h, k = trainer.history, idx.numpy()
    oh = out.history
    oh.step, oh.epoch, oh.wall_time = list(h.step), list(h.epoch), list(h.wall_time)
    for name in ("objective", "constraints", "lambdas", "lagrangian"):
        setattr(oh, name, [np.asarray(v)[k] for v in getattr(h, name)])
    out.schedules, out.engine_used = trainer.schedules, trainer.engine_used
    return out
