# ruff: noqa: E402  (the thread-count environment must be set before numpy is imported)
"""Our dual methods against the cooper library's on the friction problem: ``./dev bench cooper``.

The friction problem at the paper's settings (4-2 net, 15000 transitions per seed, batch 128, 200 epochs,
``eps = 0.035`` on the mean l2 error where ``||[p, v]||_inf <= 0.5``), solved with the recommended recipe's
restarts: every seed trains ``--restarts`` initialisations from the ``|h|`` start (first PReLU slope -1) on the
first 80 % of its data, and the library's selection rule (:func:`~saml_ros.core.training.selection.select_members`)
keeps one per seed on the other 20 %, exactly as ``train --restarts 12 --prelu-init -1`` does.

Every method gets the same network class (:class:`~saml_ros.core.model.network.DynamicsModel`), the same data, the same
initialisations (restart r of seed s from seed ``s + 100003 r``), the same normalisation, the same minibatch order
(drawn from one generator as the trainer draws it) and the same primal optimizer (Adam 3e-3, cosine-decayed to 0
over the run); only the multipliers' method differs:

* ours (:class:`~saml_ros.core.training.PrimalDualTrainer`, the fast engine): the default ``TrainConfig()``, the
  Lagrangian at several dual rates, the augmented Lagrangian at several penalties, the unconstrained problem (UA:
  the same recipe without the constraint);
* cooper's (its :class:`cooper.formulations.Lagrangian`, :class:`cooper.optim.nuPI` and
  :class:`cooper.formulations.AugmentedLagrangian`, plain autograd steps, one multiplier per ensemble member):
  the Lagrangian with SGD on the multiplier (``SimultaneousOptimizer``), nuPI, and the augmented Lagrangian
  method as cooper's documentation prescribes it (``AlternatingPrimalDualOptimizer``, the multiplier's SGD step
  equal to the penalty: ``lambda <- relu(lambda + rho g)``).

Printed per method and seed: the objective of the kept member on the shared held-out data (20000 fresh
transitions) and on its training split, its in-region constraint value ``g = error - eps`` on the held-out data,
feasible or not (held-out ``g <= 1 % eps``, the diagnosis tolerance), and whether it reaches the best optimum
found (feasible and held-out objective within 10 % of the best feasible held-out objective any method reached on
that seed's data); then a summary per method (seeds at the best optimum, feasible seeds, medians) and, for our
runs, the largest multiplier of the kept member during the run (the push early in training).

Threads: one (``torch.set_num_threads(1)``). Times are wall times and depend on the machine's load (printed).
"""

from __future__ import annotations

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse
import json
import logging
import math
import multiprocessing
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass, field, replace
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
import torch

from saml_ros.core.dynamics.system import System
from saml_ros.core.model.network import DynamicsModel
from saml_ros.core.spec import ProblemSpec
from saml_ros.core.systems import get_system
from saml_ros.core.training import PrimalDualTrainer, TrainConfig, Transitions, evaluate_spec
from saml_ros.core.training.config import make_optimizer
from saml_ros.core.training.diagnosis import TOL
from saml_ros.core.training.schedule import schedules_for
from saml_ros.core.training.selection import select_members
from saml_ros.offline.pipelines import evaluate_models, generate_datasets

#: restart r of seed s is initialised with seed s + RESTART_STRIDE r (as offline.pipelines.train_models)
RESTART_STRIDE = 100_003
#: the |h| start: the first hidden layer's PReLU slope at initialisation
ABS_SLOPE = -1.0
#: "reaches the best optimum": feasible and held-out objective within this factor of the seed's best
NEAR = 1.10


@dataclass
class Setup:
    """The shared problem: system, spec, per-seed data split as ``train_models(restarts=R)`` splits it."""

    system: System
    spec: ProblemSpec
    seeds: list[int]
    restarts: int
    fit: tuple[np.ndarray, np.ndarray, np.ndarray]  # (E, n_fit, .): each seed's split repeated per restart
    sel: tuple[np.ndarray, np.ndarray, np.ndarray]  # (E, n_sel, .): the selection split
    test: tuple[np.ndarray, np.ndarray, np.ndarray]  # (N, .): shared held-out data
    epochs: int
    batch: int
    dtype: str = "float32"

    @property
    def inits(self) -> list[int]:
        return [s + RESTART_STRIDE * r for s in self.seeds for r in range(self.restarts)]

    @property
    def groups(self) -> list[list[int]]:
        r = self.restarts
        return [list(range(i * r, (i + 1) * r)) for i in range(len(self.seeds))]

    @property
    def eps(self) -> float:
        return float(self.spec.constraints[0].eps)


def make_setup(seeds: list[int], restarts: int, n: int, epochs: int, batch: int = 128,
               holdout: float = 0.2) -> Setup:
    system = get_system("friction")
    spec = ProblemSpec.for_system(system.paper_spec(), system)
    x, u, y = generate_datasets(system, n, seeds)
    n_fit = n - max(1, int(round(holdout * n)))
    fit = tuple(np.repeat(a[:, :n_fit], restarts, axis=0) for a in (x, u, y))
    sel = tuple(np.repeat(a[:, n_fit:], restarts, axis=0) for a in (x, u, y))
    test = system.make_dataset(20000, np.random.default_rng(10_000))
    return Setup(system, spec, seeds, restarts, fit, sel, test, epochs, batch)  # type: ignore[arg-type]


def make_model(s: Setup) -> DynamicsModel:
    """The ensemble of every seed's restarts, initialised and normalised as ``train_models`` does."""
    inits = s.inits
    model = DynamicsModel(s.system, None, "residual", n_models=len(inits), seed=inits[0], prelu_init=ABS_SLOPE)
    with torch.no_grad():
        for i, seed in enumerate(inits):
            one = DynamicsModel(s.system, None, "residual", n_models=1, seed=seed, prelu_init=ABS_SLOPE)
            for p_all, p_one in zip(model.net.parameters(), one.net.parameters()):
                p_all[i].copy_(p_one[0])
    model.fit_normalization(*s.fit)
    return model


def base_config(s: Setup, **kw: Any) -> TrainConfig:
    """The recommended recipe's settings with this run's epochs and batch (and ``kw``)."""
    return replace(TrainConfig(), epochs=s.epochs, batch_size=s.batch, seed=s.seeds[0], dtype=s.dtype, **kw)


# ------------------------------------------------------------------------------------------------- ours
class FormerAugmentedConfig(TrainConfig):
    """The former ``augmented`` (before it became the method of multipliers), reproduced for the comparison: the
    augmented Lagrangian's primal weights ``relu(lambda + rho g)``, lambda moved by Adam at ``dual_lr`` along
    ``rho g`` (see :func:`train_ours`)."""

    @property
    def dual_lr0(self) -> float:
        return self.dual_lr


def train_ours(s: Setup, cfg: TrainConfig | None) -> tuple[DynamicsModel, np.ndarray]:
    """Train with our trainer (``cfg`` None: UA, the default recipe without the constraint). Returns the model and
    each member's multiplier at the end of every epoch ``(epochs, E)``."""
    model = make_model(s)
    uniform = cfg is None
    spec = s.spec.uniform() if uniform else s.spec
    tr = PrimalDualTrainer(model, spec, base_config(s) if cfg is None else cfg)
    if isinstance(cfg, FormerAugmentedConfig):  # Adam on rho g: the fast engines run it (the dual Adam merged)
        tr.dual.optimizer = make_optimizer("adam", [tr.dual.param], cfg.dual_lr, maximize=True)
    tr.fit(Transitions(model, spec, *s.fit))
    lam = np.zeros((s.epochs, model.n_models))
    if not uniform and tr.history.lambdas:
        lam = np.stack([np.asarray(v)[:, 0] for v in tr.history.lambdas])[: s.epochs]
    return model, lam


# ------------------------------------------------------------------------------------------------- cooper
def train_cooper(s: Setup, kind: str, dual_lr: float, kp: float = 0.0, penalty: float = 0.0,
                 dual_cosine: bool = True, dual_adam: bool = False) -> tuple[DynamicsModel, np.ndarray]:
    """Train with cooper: ``kind`` ``"lagrangian"`` (SGD on lambda at ``dual_lr``; Adam with ``dual_adam``),
    ``"nupi"`` (cooper's nuPI at ``dual_lr`` with K_P ``kp``, K_I 1) or ``"alm"`` (augmented Lagrangian method:
    penalty ``penalty`` in g's units, the multiplier's SGD step equal to it, alternating updates). The primal side
    is ours (Adam, cosine); the dual rate follows the same cosine when ``dual_cosine``. Returns the model and each
    member's multiplier at the end of every epoch ``(epochs, E)``."""
    import cooper

    model = make_model(s).to(torch.float64 if s.dtype == "float64" else torch.float32)
    spec = s.spec
    data = Transitions(model, spec, *s.fit)
    e = model.n_models
    cfg = base_config(s)
    primal_sched, _ = schedules_for(cfg, cfg.epochs * (len(data) // cfg.batch_size))

    multiplier = cooper.multipliers.DenseMultiplier(num_constraints=e, dtype=model.in_mean.dtype)

    class Friction(cooper.ConstrainedMinimizationProblem):
        def __init__(self) -> None:
            super().__init__()
            form = cooper.formulations.AugmentedLagrangian if kind == "alm" else cooper.formulations.Lagrangian
            pen = None
            if kind == "alm":
                pen = cooper.penalty_coefficients.DensePenaltyCoefficient(
                    init=torch.full((e,), penalty, dtype=model.in_mean.dtype))
            self.con = cooper.Constraint(cooper.ConstraintType.INEQUALITY, formulation_type=form,
                                         multiplier=multiplier,
                                         penalty_coefficient=pen)

        def compute_cmp_state(self, batch: tuple[Any, ...]) -> Any:
            x, u, y, base, masks = batch
            vals = spec.evaluate_with_masks(y, model(x, u, base), masks)
            self.last = vals
            return cooper.CMPState(loss=vals.objective.sum(),
                                   observed_constraints={self.con: cooper.ConstraintState(
                                       violation=vals.constraints[:, 0])})

    cmp = Friction()
    primal = torch.optim.Adam(model.net.parameters(), lr=cfg.primal_lr)
    dual: torch.optim.Optimizer
    if kind == "nupi":
        dual = cooper.optim.nuPI(cmp.dual_parameters(), lr=dual_lr, Kp=torch.tensor(kp), Ki=torch.tensor(1.0),
                                  maximize=True)
    elif dual_adam:
        dual = torch.optim.Adam(cmp.dual_parameters(), lr=dual_lr, maximize=True)
    else:
        dual = torch.optim.SGD(cmp.dual_parameters(), lr=dual_lr, maximize=True)
    opt_cls = cooper.optim.AlternatingPrimalDualOptimizer if kind == "alm" else cooper.optim.SimultaneousOptimizer
    opt = opt_cls(cmp=cmp, primal_optimizers=primal, dual_optimizers=dual)
    rng = torch.Generator().manual_seed(cfg.seed)
    n = len(data)
    bsz = cfg.batch_size
    per_epoch = n // bsz
    t = 0
    trace = []
    model.train()
    for _ in range(cfg.epochs):
        perm = torch.argsort(torch.rand(e, n, generator=rng), dim=1)  # as the trainer's engines draw it
        idx = perm[:, : per_epoch * bsz]
        xs, us, ys, bases = data.take(idx)  # the epoch's minibatches gathered at once, then sliced
        ms = data.take_masks(idx)
        for j in range(per_epoch):
            sl = slice(j * bsz, (j + 1) * bsz)
            f = primal_sched.factor(t)
            for g in primal.param_groups:
                g["lr"] = cfg.primal_lr * f
            for g in dual.param_groups:
                g["lr"] = dual_lr * (f if dual_cosine else 1.0)
            batch = (xs[:, sl], us[:, sl], ys[:, sl], bases[:, sl], [None if m is None else m[:, sl] for m in ms])
            opt.roll(compute_cmp_state_kwargs={"batch": batch})
            t += 1
        trace.append(multiplier().detach().double().numpy().copy())
    return model, np.stack(trace)


# ------------------------------------------------------------------------------------------------- results
@dataclass
class Result:
    method: str
    held_objective: np.ndarray  # (S,) kept member, shared held-out data
    train_objective: np.ndarray  # (S,) kept member, its training split
    held_g: np.ndarray  # (S,) kept member: in-region error - eps on the held-out data
    lam_trace: np.ndarray  # (epochs, S) kept member's multiplier at the end of each epoch

    @property
    def lam_max(self) -> np.ndarray:
        """(S,) the kept member's largest multiplier (at an epoch's end) during the run."""
        return self.lam_trace.max(axis=0)

    def lam_at(self, frac: float) -> float:
        """The median over seeds of the kept member's multiplier after ``frac`` of the epochs."""
        i = min(len(self.lam_trace) - 1, max(0, int(round(frac * len(self.lam_trace))) - 1))
        return float(np.median(self.lam_trace[i]))
    seconds: float
    best: np.ndarray = field(default_factory=lambda: np.zeros(0))  # filled in by mark_best


def evaluate(s: Setup, method: str, model: DynamicsModel, lam_trace: np.ndarray, seconds: float) -> Result:
    sel = select_members(model, s.spec, Transitions(model, s.spec, *s.sel), s.groups)
    kept = np.asarray(sel.chosen)
    held = evaluate_models(model, s.spec, *s.test)
    train = evaluate_spec(model, s.spec, Transitions(model, s.spec, *s.fit))
    g = held.constraints[kept, 0]
    return Result(method, held.objective[kept], train["objective"][kept], g, lam_trace[:, kept], seconds)


def is_feasible(r: Result, eps: float) -> np.ndarray:
    return r.held_g <= TOL * eps


def mark_best(results: list[Result], eps: float) -> None:
    """Per seed, the best feasible held-out objective of any method; each result's seeds within 10 % of it."""
    cand = np.stack([np.where(is_feasible(r, eps), r.held_objective, np.inf) for r in results])
    best = cand.min(axis=0)
    for r in results:
        r.best = is_feasible(r, eps) & (r.held_objective <= NEAR * best)


def report(results: list[Result], s: Setup) -> str:
    eps = s.eps
    mark_best(results, eps)
    cand = np.stack([np.where(is_feasible(r, eps), r.held_objective, np.inf) for r in results]).min(axis=0)
    lines = ["per seed: held-out objective / training objective / held-out in-region g (error - eps) / feasible / "
             "at the best optimum", "",
             "| method | " + " | ".join(f"seed {x}" for x in s.seeds) + " |",
             "|---|" + "---|" * len(s.seeds)]
    for r in results:
        cells = [f"{r.held_objective[i]:.4f} / {r.train_objective[i]:.4f} / {r.held_g[i]:+.4f} / "
                 f"{'feasible' if is_feasible(r, eps)[i] else 'INFEASIBLE'} / {'BEST' if r.best[i] else 'no'}"
                 for i in range(len(s.seeds))]
        lines.append(f"| {r.method} | " + " | ".join(cells) + " |")
    lines += ["", "best feasible held-out objective per seed: " + ", ".join(f"{b:.4f}" for b in cand), "",
              "| method | at the best optimum | feasible (held-out) | held-out objective, median [min - max] | "
              "in-region g held-out, median [min - max] | lambda after 5 / 25 / 50 / 100 % of the epochs, median | "
              "largest lambda, median | train s |",
              "|---|---|---|---|---|---|---|---|"]
    n = len(s.seeds)
    for r in results:
        lines.append(f"| {r.method} | {int(r.best.sum())}/{n} | {int(is_feasible(r, eps).sum())}/{n} | "
                     f"{_dist(r.held_objective)} | {_dist(r.held_g, '+.4f')} | "
                     f"{' / '.join(f'{r.lam_at(q):.3g}' for q in (0.05, 0.25, 0.5, 1.0))} | {np.median(r.lam_max):.3g} | "
                     f"{r.seconds:.0f} |")
    return "\n".join(lines)


def _dist(a: np.ndarray, fmt: str = ".4f") -> str:
    return f"{np.median(a):{fmt}} [{a.min():{fmt}} - {a.max():{fmt}}]"


# ------------------------------------------------------------------------------------------------- methods
def methods(s: Setup) -> dict[str, Callable[[], tuple[DynamicsModel, np.ndarray]]]:
    """Method name -> a function training it on ``s``."""
    eps = s.eps
    ours: dict[str, TrainConfig | None] = {
        "ours: default TrainConfig() (lagrangian, Adam 0.01)": base_config(s),
        "ours: UA (no constraint)": None,
    }
    for lr in (1e-3, 1e-4):  # slower multipliers
        ours[f"ours: lagrangian, Adam {lr:g}"] = base_config(s, dual_method="lagrangian", dual_lr=lr,
                                                          dual_optimizer="adam")
    ours["ours: former augmented (Adam 0.01 on rho g, c 0.01)"] = FormerAugmentedConfig(**base_config(
        s, dual_method="augmented", dual_optimizer="adam", dual_lr=1e-2, penalty=0.01).__dict__)
    for c in (0.01, 0.1, 1.0):
        ours[f"ours: augmented (method of multipliers), c {c:g}"] = base_config(s, dual_method="augmented",
                                                                               penalty=c)
    for m in ("nupi", "resilient"):
        ours[f"ours: {m}"] = base_config(s, dual_method=m)
    out: dict[str, Callable[[], tuple[DynamicsModel, np.ndarray]]] = {
        k: partial(train_ours, s, c) for k, c in ours.items()}
    # cooper: the multiplier's rates in g's units (g ~ 0.01-0.05 here); nuPI with our nupi's gains (our nupi
    # steps on g / eps at 1e-2 with K_P 10: the same controller on g has step 1e-2 / eps)
    for lr in (1.0, 0.1):
        out[f"cooper: Lagrangian, SGD {lr:g}"] = partial(train_cooper, s, "lagrangian", lr)
    out["cooper: nuPI, step 1e-2/eps, K_P 10"] = partial(train_cooper, s, "nupi", 1e-2 / eps, kp=10.0)
    for c in (0.01, 0.1, 1.0):
        rho = c / eps
        out[f"cooper: AugmentedLagrangian, rho {rho:.3g} (c {c:g})"] = partial(
            train_cooper, s, "alm", rho, penalty=rho, dual_cosine=False)
    return out


_SETUPS: dict[tuple[int, ...], Setup] = {}


def _run_method(key: tuple[int, int, int, int], name: str, s: Setup | None = None) -> Result:
    """Train and evaluate method ``name`` on the setup ``key`` = (seeds, restarts, n, epochs) (built here in a
    worker process: threads, logging and the setup are per process)."""
    torch.set_num_threads(1)
    torch.set_flush_denormal(True)
    logging.getLogger("saml_ros.trainer").setLevel(logging.ERROR)
    if s is None:
        s = _SETUPS.get(key) or _SETUPS.setdefault(key, make_setup(list(range(key[0])), key[1], key[2], key[3]))
    t0 = time.perf_counter()
    model, lam = methods(s)[name]()
    return evaluate(s, name, model, lam, time.perf_counter() - t0)


def _print_result(r: Result, s: Setup) -> None:
    feas = is_feasible(r, s.eps)
    print(f"  {r.method:58s} held-out objective {_dist(r.held_objective)}, feasible {int(feas.sum())}/{len(feas)}, "
          f"g {_dist(r.held_g, '+.4f')}, lambda max {np.median(r.lam_max):.3g}, {r.seconds:.0f} s "
          f"(load {os.getloadavg()[0]:.1f})", flush=True)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=5, help="seeds (datasets), default 5")
    ap.add_argument("--restarts", type=int, default=12, help="initialisations per seed (default 12)")
    ap.add_argument("--epochs", type=int, default=200, help="epochs (default: the paper's 200)")
    ap.add_argument("--n", type=int, default=15000, help="transitions per seed (default: the paper's 15000)")
    ap.add_argument("--quick", action="store_true", help="2 seeds, 3 restarts, 20 epochs, 3000 transitions, a few "
                                                         "methods (a smoke run: the numbers are not the claims)")
    ap.add_argument("--methods", nargs="+", metavar="SUBSTRING",
                    help="only the methods whose name contains one of these (e.g. cooper default UA)")
    ap.add_argument("--list", action="store_true", help="print the methods and exit")
    ap.add_argument("--workers", type=int, default=1, help="methods trained in this many processes at once")
    ap.add_argument("--json", type=Path, help="also write every number into this file")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    torch.set_flush_denormal(True)
    logging.getLogger("saml_ros.trainer").setLevel(logging.ERROR)
    if args.quick:
        args.seeds, args.restarts, args.epochs, args.n = 2, 3, 20, 3000
        args.methods = args.methods or ["default", "UA", "cooper: Lagrangian, SGD 1", "cooper: nuPI",
                                        "cooper: AugmentedLagrangian, rho 2.86"]
    t_all = time.perf_counter()
    s = make_setup(list(range(args.seeds)), args.restarts, args.n, args.epochs)
    todo = methods(s)
    if args.list:
        print("\n".join(todo))
        return 0
    if args.methods:
        todo = {k: v for k, v in todo.items() if any(m in k for m in args.methods)}
    print(f"bench_cooper: friction, {args.seeds} seeds x {args.restarts} restarts from the |h| start, {args.epochs} "
          f"epochs, {args.n} transitions per seed (80 % fit / 20 % selection), eps = {s.eps:g}; "
          f"{len(todo)} methods; load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs", flush=True)
    print(f"default recipe: {TrainConfig()}", flush=True)
    key = (args.seeds, args.restarts, args.n, args.epochs)
    results: dict[str, Result] = {}
    if args.workers > 1:  # methods in parallel processes (each rebuilds the same setup: the data are seeded)
        ctx = multiprocessing.get_context("spawn")
        with ProcessPoolExecutor(args.workers, mp_context=ctx) as pool:
            # the slow ones (cooper's autograd loop) first
            order = sorted(todo, key=lambda k: not k.startswith("cooper"))
            futures = {pool.submit(_run_method, key, name): name for name in order}
            for fut in as_completed(futures):
                r = fut.result()
                results[r.method] = r
                _print_result(r, s)
    else:
        for name in todo:
            r = _run_method(key, name, s)
            results[name] = r
            _print_result(r, s)
    ordered = [results[name] for name in todo]
    print()
    print(report(ordered, s))
    print(f"\ntotal {time.perf_counter() - t_all:.0f} s (load average at the end {os.getloadavg()[0]:.1f} on "
          f"{os.cpu_count()} CPUs)")
    if args.json:
        args.json.write_text(json.dumps([{k: (np.asarray(v).tolist() if isinstance(v, np.ndarray) else v)
                                          for k, v in r.__dict__.items()} for r in ordered], indent=1))
    return 0 if all(math.isfinite(float(np.sum(r.held_objective))) for r in ordered) else 1


if __name__ == "__main__":
    raise SystemExit(main())
