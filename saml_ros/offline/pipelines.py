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

from saml_ros.core.dynamics.system import System
from saml_ros.core.model.network import DynamicsModel
from saml_ros.core.spec import ProblemSpec
from saml_ros.core.training import History, PrimalDualTrainer, TrainConfig, Transitions
from saml_ros.core.training.config import parse_margin
from saml_ros.core.training.heldout import MIN_N
from saml_ros.core.training.selection import Selection, select_members, take_trainer
from saml_ros.core.training.verdict import AimReport, aim_bounds, aimed_spec, spec_estimates


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
    (:mod:`saml_ros.core.training.selection`); ``n_train`` is then the training split's size per seed. With an aim
    (``margin``), training aimed below eps (``aim``, :mod:`saml_ros.core.training.verdict`): ``trainer.diagnosis``
    is against the aim, ``trainer.spec`` is ``spec`` again (the checkpoint's). ``training`` holds the left-hand side
    of every constraint on each kept member's training data ``(E, K)``.
    """

    spec: ProblemSpec
    model: DynamicsModel
    trainer: PrimalDualTrainer
    seeds: list[int]
    train_seconds: float
    n_train: int
    selection: Selection | None = None
    aim: AimReport | None = None
    training: np.ndarray | None = None

    @property
    def history(self) -> History:
        return self.trainer.history

    @property
    def aimed(self) -> list[float]:
        """The bounds training aimed at (eps without an aim)."""
        return list(self.aim.aim) if self.aim is not None else [t.eps for t in self.spec.constraints]


#: the fraction of the epochs after which an automatic margin is measured (the cosine schedule is then at half
#: its rates and the model near its final optimum; the rest of the run trains at the aim)
AIM_AT = 0.5


def _measure_aim(trainer: PrimalDualTrainer, spec: ProblemSpec, data: Transitions, stream: bool,
                 heldout_n: Sequence[int] | None) -> tuple[list[float], list[float]]:
    """The standard errors an automatic aim is sized by, from the model being trained: per constraint the training
    estimate's (largest over members) and the held-out estimate's as predicted from the held-out set's region count
    ``heldout_n`` (the same spread of the losses over fewer or more samples; None: as many as in training)."""
    _, cons = spec_estimates(trainer.model, spec, data, stream)
    train_se, held_se = [], []
    for k, ests in enumerate(cons):
        ok = [e for e in ests if e.n >= MIN_N and math.isfinite(e.se)]
        if not ok:
            train_se.append(math.inf)
            held_se.append(math.inf)
            continue
        train_se.append(max(e.se for e in ok))
        if heldout_n is None:
            held_se.append(train_se[-1])
        elif int(heldout_n[k]) < MIN_N:  # no held-out verdict can be read: nothing to size the margin by
            held_se.append(math.inf)
        else:
            held_se.append(max(e.se * math.sqrt(e.n / int(heldout_n[k])) for e in ok))
    return train_se, held_se


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
    margin: str | float | None = None,
    heldout_n: Sequence[int] | None = None,
    stream: bool = False,
    select: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
) -> TrainedModels:
    """Train ``len(seeds)`` models at once. ``x, u, y`` are ``(N, .)`` (shared) or ``(E, N, .)`` (one per seed).

    ``restarts > 1``: each seed trains ``restarts`` members from different initialisations (restart r of seed s is
    initialised with seed ``s + 100003 r``; r = 0 is the seed's own) and keeps the best feasible one on held-out
    data (:func:`~saml_ros.core.training.selection.select_members`): on ``select`` (``(N_s, .)`` or
    ``(E, N_s, .)``) when given, else on the last ``holdout`` of each seed's data (the rest trains); all
    ``len(seeds) * restarts`` members train as one ensemble. ``prelu_init``: the first hidden layer's initial
    PReLU slope (:class:`~saml_ros.core.model.network.DynamicsModel`).

    ``margin``: what training aims at (:mod:`saml_ros.core.training.verdict`): None (eps), a fraction ``f`` of eps
    (``(1 - f) eps``) or ``"auto"``: the first :data:`AIM_AT` of the epochs train at eps, then the standard errors
    are measured on the model (training estimate; held-out estimate predicted for ``heldout_n`` samples in each
    constraint's region, the verdict's held-out set) and the rest trains at
    :func:`~saml_ros.core.training.verdict.aim_bounds`. ``stream``: the data are recordings in time order (batch-
    means standard errors, a time-ordered selection split).
    """
    seeds = list(seeds)
    if restarts < 1 or not 0 < holdout < 1:
        raise ValueError(f"restarts must be >= 1 and holdout in (0, 1), got {restarts}, {holdout}")
    margin = parse_margin(margin)
    inits = [s + 100_003 * r for s in seeds for r in range(restarts)]
    xh = uh = yh = None
    if restarts > 1:
        if select is not None:
            xh, uh, yh = (np.asarray(a) for a in select)
        else:
            n = x.shape[-2]
            n_fit = n - max(1, int(round(holdout * n)))
            if n_fit < 2:
                raise ValueError(f"{n} transitions per seed are too few to hold out {holdout:.0%} for selection")
            x, xh = x[..., :n_fit, :], x[..., n_fit:, :]
            u, uh = u[..., :n_fit, :], u[..., n_fit:, :]
            y, yh = y[..., :n_fit, :], y[..., n_fit:, :]
        if x.ndim == 3:  # one dataset per seed: the same one for each of its restarts
            x, u, y = (np.repeat(a, restarts, axis=0) for a in (x, u, y))
        if xh.ndim == 3:
            xh, uh, yh = (np.repeat(a, restarts, axis=0) for a in (xh, uh, yh))
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
    eps = [t.eps for t in spec.constraints]
    aim_report = None
    t0 = time.perf_counter()
    if margin is None or not eps:
        trainer.fit(data, progress=progress, desc=desc)
    elif margin != "auto" or cfg.epochs < 2:
        f = 0.0 if margin == "auto" else float(margin)
        bounds = [(1.0 - f) * e for e in eps]
        aim_report = AimReport(str(margin), spec.constraint_names, eps, bounds)
        trainer.spec = aimed_spec(spec, bounds)
        trainer.fit(data, progress=progress, desc=desc)
    else:
        first = max(1, int(round(AIM_AT * cfg.epochs)))
        trainer.fit(data, epochs=first, progress=progress, desc=desc, diagnose=False)
        train_se, held_se = _measure_aim(trainer, spec, data, stream, heldout_n)
        bounds = aim_bounds(eps, train_se, held_se)
        aim_report = AimReport("auto", spec.constraint_names, eps, bounds, train_se, held_se, trainer.epochs_done)
        trainer.spec = aimed_spec(spec, bounds)
        trainer.fit(data, epochs=cfg.epochs - first, progress=progress, desc=f"{desc} (aimed)")
    seconds = time.perf_counter() - t0
    aimed_at, trainer.spec = trainer.spec, spec  # the problem as given (the checkpoint's); the diagnosis stays
    if restarts == 1:                            # against the aim
        kept, sel, kept_data = trainer, None, data
    else:
        assert xh is not None and uh is not None and yh is not None
        groups = [list(range(i * restarts, (i + 1) * restarts)) for i in range(len(seeds))]
        sel = select_members(model, spec, Transitions(model, spec, xh, uh, yh), groups, stream=stream)
        kept = take_trainer(trainer, sel.chosen)
        kept_data = Transitions(kept.model, spec, *(a[sel.chosen] if a.ndim == 3 else a for a in (x, u, y)))
        kept.spec = aimed_at
        kept.diagnosis = kept.diagnose(kept_data)
        kept.spec = spec
    _, cons = spec_estimates(kept.model, spec, kept_data, stream)
    training = np.array([[e.mean for e in ests] for ests in cons]).T.reshape(kept.model.n_models, len(eps))
    return TrainedModels(spec, kept.model, kept, seeds, seconds, len(data), sel, aim_report, training)


def stretch_split(stamps: np.ndarray, source: np.ndarray, fraction: float,
                  stretches: int = 10) -> tuple[np.ndarray, np.ndarray]:
    """Hold out whole stretches of time: each source's transitions (``source`` ``(N,)``, one per bag and namespace),
    in stamp order, are cut into ``stretches`` contiguous stretches of equal count, and ``round(fraction *
    stretches)`` of them (at least 1), spread evenly over the recording, are held out. Returns ``(kept, held)``
    index arrays, each in time order within each source (sources in order). Consecutive transitions of a recording
    are nearly identical: a random split would put a twin of every held-out transition in the training data."""
    stamps, source = np.asarray(stamps), np.asarray(source)
    if not 0 < fraction < 1:
        raise ValueError(f"the held-out fraction must be in (0, 1), got {fraction}")
    h = max(1, int(round(fraction * stretches)))
    held_chunks = {int((j + 0.5) * stretches / h) for j in range(h)}
    kept: list[np.ndarray] = []
    held: list[np.ndarray] = []
    for src in np.unique(source):
        idx = np.flatnonzero(source == src)
        idx = idx[np.argsort(stamps[idx], kind="stable")]
        chunk = np.arange(len(idx)) * stretches // max(1, len(idx))
        out = np.isin(chunk, list(held_chunks))
        kept.append(idx[~out])
        held.append(idx[out])
    empty = np.zeros(0, dtype=np.int64)
    return (np.concatenate(kept) if kept else empty), (np.concatenate(held) if held else empty)


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
