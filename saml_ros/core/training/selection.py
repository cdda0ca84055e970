"""Restarts and selection: of the members of an ensemble trained on the same data (restarts from different
initialisations), keep the best feasible one on a held-out split (:func:`select_members`).

The rule (docs/training.md), per group of restarts, on the held-out split's dataset-level values:

1. a member is *feasible* when every constraint holds within the diagnosis tolerance, ``g_k <= TOL * eps_k``
   (:data:`saml_ros.core.training.diagnosis.TOL`);
2. if some member is feasible, keep the feasible member with the lowest held-out objective;
3. otherwise keep the member with the smallest worst relative violation ``max_k g_k / eps_k`` (the lowest
   objective among equal ones): the closest to feasible, reported as infeasible.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from saml_ros.core.models import DynamicsModel
from saml_ros.core.spec import ProblemSpec
from saml_ros.core.training.dataset import Transitions
from saml_ros.core.training.diagnosis import TOL
from saml_ros.core.training.evaluate import evaluate_spec
from saml_ros.core.training.trainer import PrimalDualTrainer


@dataclass
class Selection:
    """Which member each group kept, and why.

    Attributes:
        groups: the member indices of each group (restarts of one seed).
        chosen: the kept member of each group (an index into the ensemble).
        feasible: whether the kept member is feasible on the held-out split.
        objective: held-out objective of every member ``(E,)``.
        constraints: held-out constraint values of every member ``(E, K)``.
    """

    groups: list[list[int]]
    chosen: list[int]
    feasible: list[bool]
    objective: np.ndarray
    constraints: np.ndarray

    def describe(self) -> list[str]:
        return [
            f"restarts {g}: kept member {c} ({'feasible' if f else 'none feasible: the least violating'}, held-out "
            f"objective {self.objective[c]:.4g})"
            for g, c, f in zip(self.groups, self.chosen, self.feasible)
        ]


def choose(objective: np.ndarray, constraints: np.ndarray, eps: Sequence[float], group: Sequence[int]) -> tuple[int,
                                                                                                            bool]:
    """The member of ``group`` the rule keeps (module docstring) and whether it is feasible; ``objective`` ``(E,)``,
    ``constraints`` ``(E, K)`` are held-out values."""
    idx = list(group)
    if not idx:
        raise ValueError("an empty group of restarts")
    e = np.asarray(eps, dtype=float)
    rel = constraints[idx] / e if len(e) else np.zeros((len(idx), 0))
    worst = rel.max(axis=1) if rel.shape[1] else np.full(len(idx), -np.inf)
    feasible = worst <= TOL
    obj = objective[idx]
    if feasible.any():
        cand = np.flatnonzero(feasible)
        j = cand[int(np.argmin(obj[cand]))]
        return idx[j], True
    order = np.lexsort((obj, worst))  # smallest worst violation first, then the lowest objective
    return idx[int(order[0])], False


@torch.no_grad()
def select_members(model: DynamicsModel, spec: ProblemSpec, heldout: Transitions,
                   groups: Sequence[Sequence[int]]) -> Selection:
    """Apply the rule to every group of ``model``'s members on ``heldout`` (one dataset per member, or shared)."""
    ev = evaluate_spec(model, spec, heldout)
    eps = [t.eps for t in spec.constraints]
    chosen, feasible = [], []
    for g in groups:
        c, f = choose(ev["objective"], ev["constraints"], eps, g)
        chosen.append(c)
        feasible.append(f)
    return Selection([list(g) for g in groups], chosen, feasible, ev["objective"], ev["constraints"])


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
