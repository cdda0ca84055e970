"""Offline pipelines: generate datasets as in the paper, train Sufficiently / Uniformly Accurate models
(many seeds at once as one ensemble), and evaluate them per region on held-out data.

ROS-free; used by the ``train`` CLI, the demo and the experiment runners.
"""

from __future__ import annotations

import copy
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from saml_ros.core.models import DynamicsModel
from saml_ros.core.spec import ProblemSpec
from saml_ros.core.systems.base import System
from saml_ros.core.training import History, PrimalDualTrainer, TrainConfig, Transitions
from saml_ros.core.training.selection import Selection, select_members, take_trainer


def generate_datasets(
    system: System, n: int, seeds: Sequence[int], noise: dict[str, float] | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One dataset of ``n`` transitions per seed, stacked: ``x (E, n, n_x)``, ``u (E, n, n_u)``, ``y (E, n, n_y)``."""
    parts = [system.make_dataset(n, np.random.default_rng(s), noise) for s in seeds]
    return tuple(np.stack([p[i] for p in parts]) for i in range(3))  # type: ignore[return-value]


@dataclass
class TrainedModels:
    """An ensemble trained with one spec; member i was trained with ``seeds[i]``.

    With restarts, ``trainer`` holds the kept member of each seed and ``selection`` says which restart it was
    (:mod:`saml_ros.core.training.selection`); ``n_train`` is then the training split's size per seed.
    """

    spec: ProblemSpec
    model: DynamicsModel
    trainer: PrimalDualTrainer
    seeds: list[int]
    train_seconds: float
    n_train: int
    selection: Selection | None = None

    @property
    def history(self) -> History:
        return self.trainer.history


def train_models(
    system: System,
    spec: ProblemSpec,
    x: np.ndarray,
    u: np.ndarray,
    y: np.ndarray,
    config: TrainConfig,
    seeds: Sequence[int],
    hidden: Sequence[int] | None = None,
    kind: str = "residual",
    progress: bool = False,
    desc: str = "training",
    restarts: int = 1,
    holdout: float = 0.2,
    prelu_init: float = 0.25,
) -> TrainedModels:
    """Train ``len(seeds)`` models at once. ``x, u, y`` are ``(N, .)`` (shared) or ``(E, N, .)`` (one per seed).

    ``restarts > 1``: each seed trains ``restarts`` members from different initialisations (restart r of seed s is
    initialised with seed ``s + 100003 r``; r = 0 is the seed's own) on the first ``1 - holdout`` of its data, and
    keeps the best feasible one on the rest (:func:`~saml_ros.core.training.selection.select_members`); all
    ``len(seeds) * restarts`` members train as one ensemble. ``prelu_init``: the first hidden layer's initial
    PReLU slope (:class:`~saml_ros.core.models.DynamicsModel`).
    """
    seeds = list(seeds)
    if restarts < 1 or not 0 < holdout < 1:
        raise ValueError(f"restarts must be >= 1 and holdout in (0, 1), got {restarts}, {holdout}")
    inits = [s + 100_003 * r for s in seeds for r in range(restarts)]
    xh = uh = yh = None
    if restarts > 1:
        n = x.shape[-2]
        n_fit = n - max(1, int(round(holdout * n)))
        if n_fit < 2:
            raise ValueError(f"{n} transitions per seed are too few to hold out {holdout:.0%} for selection")
        x, xh = x[..., :n_fit, :], x[..., n_fit:, :]
        u, uh = u[..., :n_fit, :], u[..., n_fit:, :]
        y, yh = y[..., :n_fit, :], y[..., n_fit:, :]
        if x.ndim == 3:  # one dataset per seed: the same one for each of its restarts
            x, u, y, xh, uh, yh = (np.repeat(a, restarts, axis=0) for a in (x, u, y, xh, uh, yh))
    model = DynamicsModel(system, hidden, kind, n_models=len(inits), seed=inits[0], prelu_init=prelu_init)
    if len(inits) > 1:  # distinct initialisations per seed
        with torch.no_grad():
            for i, s in enumerate(inits):
                one = DynamicsModel(system, hidden, kind, n_models=1, seed=s, prelu_init=prelu_init)
                for p_all, p_one in zip(model.net.parameters(), one.net.parameters()):
                    p_all[i].copy_(p_one[0])
    model.fit_normalization(x, u, y)
    cfg = TrainConfig(**{**config.__dict__, "seed": seeds[0]})
    trainer = PrimalDualTrainer(model, spec, cfg)
    data = Transitions(model, spec, x, u, y)
    t0 = time.perf_counter()
    trainer.fit(data, progress=progress, desc=desc)
    seconds = time.perf_counter() - t0
    if restarts == 1:
        return TrainedModels(spec, model, trainer, seeds, seconds, len(data))
    assert xh is not None and uh is not None and yh is not None
    groups = [list(range(i * restarts, (i + 1) * restarts)) for i in range(len(seeds))]
    sel = select_members(model, spec, Transitions(model, spec, xh, uh, yh), groups)
    kept = take_trainer(trainer, sel.chosen)
    kept.diagnosis = kept.diagnose(Transitions(kept.model, spec, *(a[sel.chosen] if a.ndim == 3 else a
                                                                    for a in (x, u, y))))
    return TrainedModels(spec, kept.model, kept, seeds, seconds, len(data), sel)


def finetune_models(start: TrainedModels, spec: ProblemSpec, x: np.ndarray, u: np.ndarray, y: np.ndarray,
                    config: TrainConfig, progress: bool = False, desc: str = "fine-tuning") -> TrainedModels:
    """Train a copy of ``start``'s ensemble (its weights and normalisation; fresh optimizers and multipliers) under
    ``spec`` for ``config.epochs`` passes over ``x, u, y``; ``start`` is left as it was."""
    model = copy.deepcopy(start.model)
    cfg = TrainConfig(**{**config.__dict__, "seed": start.seeds[0]})
    trainer = PrimalDualTrainer(model, spec, cfg)
    data = Transitions(model, spec, x, u, y)
    t0 = time.perf_counter()
    trainer.fit(data, progress=progress, desc=desc)
    return TrainedModels(spec, model, trainer, list(start.seeds), time.perf_counter() - t0, len(data))


@dataclass
class RegionErrors:
    """Held-out errors of each member, for one constraint region: arrays of shape ``(E,)``."""

    name: str
    inside: np.ndarray
    outside: np.ndarray
    overall: np.ndarray
    frac_inside: float


@dataclass
class Evaluation:
    objective: np.ndarray  # (E,) dataset objective
    constraints: np.ndarray  # (E, K) dataset g_k
    regions: list[RegionErrors] = field(default_factory=list)


@torch.no_grad()
def evaluate_models(model: DynamicsModel, spec: ProblemSpec, x: Any, u: Any, y: Any) -> Evaluation:
    """Objective, constraints and per-region mean errors on held-out data ``(N, .)`` shared by all members."""
    dt = model.in_mean.dtype
    xt, ut, yt = (torch.as_tensor(np.asarray(a), dtype=dt) for a in (x, u, y))
    data = Transitions(model, spec, x, u, y)
    from saml_ros.core.training import evaluate_spec

    vals = evaluate_spec(model, spec, data)
    pred = model(xt, ut, data.base)
    regions = []
    for name, r in spec.region_errors(xt, ut, yt, pred).items():
        n_in = float(r["n_in"].reshape(-1)[0])
        regions.append(RegionErrors(name, r["in"].numpy(), r["out"].numpy(), r["all"].numpy(),
                                    n_in / max(1.0, n_in + float(r["n_out"].reshape(-1)[0]))))
    return Evaluation(vals["objective"], vals["constraints"], regions)


def mean_std(a: np.ndarray) -> str:
    a = np.asarray(a, dtype=float)
    sd = float(a.std(ddof=1)) if a.size > 1 else 0.0
    return f"{float(a.mean()):.4f} ± {sd:.4f}"


@dataclass
class Comparison:
    """Sufficiently vs Uniformly Accurate, trained on the same data with the same seeds."""

    system: str
    spec: ProblemSpec
    sufficient: TrainedModels
    uniform: TrainedModels
    eval_sufficient: Evaluation
    eval_uniform: Evaluation
    n_test: int

    def table(self) -> str:
        """Markdown table: mean ± std over seeds of the held-out error in / out of each region and overall."""
        lines = []
        for rs, ru in zip(self.eval_sufficient.regions, self.eval_uniform.regions):
            lines += [
                f"Held-out error of the `{rs.name}` constraint's loss, mean ± std over "
                f"{len(self.sufficient.seeds)} seeds ({self.n_test} test transitions, "
                f"{100 * rs.frac_inside:.1f}% inside the region):",
                "",
                "| model | overall | inside region | outside region |",
                "|---|---|---|---|",
                f"| Uniformly Accurate | {mean_std(ru.overall)} | {mean_std(ru.inside)} | {mean_std(ru.outside)} |",
                f"| Sufficiently Accurate | {mean_std(rs.overall)} | {mean_std(rs.inside)} | "
                f"{mean_std(rs.outside)} |",
                "",
            ]
        return "\n".join(lines)

    def claim_holds(self) -> bool:
        """SA better inside every region and worse outside, on average over seeds."""
        return all(
            float(np.mean(rs.inside)) < float(np.mean(ru.inside))
            and float(np.mean(rs.outside)) > float(np.mean(ru.outside))
            for rs, ru in zip(self.eval_sufficient.regions, self.eval_uniform.regions)
        )

    def per_seed_wins(self) -> list[int]:
        """For each region: how many seeds have SA's in-region error below UA's (paired by seed)."""
        return [int(np.sum(rs.inside < ru.inside))
                for rs, ru in zip(self.eval_sufficient.regions, self.eval_uniform.regions)]


def compare(
    system: System,
    spec: ProblemSpec,
    config: TrainConfig,
    seeds: Sequence[int],
    n_train: int,
    n_test: int,
    hidden: Sequence[int] | None = None,
    kind: str = "residual",
    noise: dict[str, float] | None = None,
    progress: bool = False,
    test_seed: int = 10_000,
) -> Comparison:
    """Train SA and UA ensembles on per-seed datasets and evaluate both on one held-out test set."""
    x, u, y = generate_datasets(system, n_train, seeds, noise)
    sa = train_models(system, spec, x, u, y, config, seeds, hidden, kind, progress, "sufficiently accurate")
    ua = train_models(system, spec.uniform(), x, u, y, config, seeds, hidden, kind, progress, "uniformly accurate")
    xt, ut, yt = system.make_dataset(n_test, np.random.default_rng(test_seed), noise)
    return Comparison(system.name, spec, sa, ua, evaluate_models(sa.model, spec, xt, ut, yt),
                      evaluate_models(ua.model, spec, xt, ut, yt), n_test)


def finite(a: float) -> bool:
    return not (math.isnan(a) or math.isinf(a))
