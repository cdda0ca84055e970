# ruff: noqa: E402  (the thread-count environment must be set before numpy is imported)
"""Dual methods on the paper's Sufficiently Accurate problems: ``./dev python -m bench.bench_dual [--quick]``.

For each problem (friction, quadrotor, paddle ball; the paper's spec, net, data size and batch; epochs as stated
per problem) and each training recipe, ``--seeds`` seeds (default 15: one dataset and one initialisation each,
all trained as ONE ensemble on the fast engine), printed as measured in this run:

* **feasible**: seeds whose constraints hold on their training data (dataset-level g_k <= 1 % of eps_k, the
  diagnosis tolerance);
* **near best**: seeds that are feasible AND within 10 % of the best feasible seed's objective (the best over
  every recipe of the problem, UA included);
* **near best, same data**: seeds that are feasible AND within 10 % of the best feasible objective any recipe
  reached on that seed's own dataset (each seed has its own data: this separates how well a recipe optimises
  from how hard a seed's data is);
* **near best, held-out**: seeds that are feasible AND whose objective on the shared held-out data (the same
  20000 fresh transitions for every seed) is within 10 % of the best feasible seed's;
* **near best, held-out, same data**: seeds that are feasible AND whose held-out objective is within 10 % of the
  best held-out objective any recipe reached with that seed's own dataset (the statistical objective, E[l] over
  the data's distribution, compared among runs that saw the same data);
* **objective**: the training objective, median [min - max] over seeds;
* **in-region error**: held-out (fresh data from the same distribution) mean loss of the constraint's loss inside
  its region, median [min - max];
* **verdicts**: the end-of-training diagnosis per seed: met / not converged / likely infeasible
  (:mod:`saml_ros.core.training.diagnosis`, against the bound the recipe aimed at);
* lambda (median) and the training wall time;
* per problem, a table of ``train``'s held-out verdicts (:mod:`saml_ros.core.training.verdict`: met / unconfirmed /
  met on training only / not met / no held-out data, read on a fresh verdict set of 10x the training size), the
  training value, the held-out estimate, the same left-hand side on ``--fresh`` (200000) other fresh transitions,
  and how many seeds reported met exceed eps there; per-seed tables of the ``--per-seed`` recipes.

Recipes: ``UA`` (no constraint: the objective's unconstrained level, the paper's learning rates), ``paper``
(Algorithm 1 as the experiments run it: Adam, constant rates, the experiment's primal / dual rates), each other
dual method with the recommended schedules and rates (``TrainConfig()`` is the recommended default), the default
without the margin (``default, no margin``: aiming at eps itself), and, on the problems of ``--restarts-on``
(default: friction, whose 4-2 net has optima far apart), the default with ``--restarts`` initialisations per seed,
the best one kept on a fresh selection set of 10x the training size, and the default with the first hidden layer's
PReLU started at slope -1 (``|h|``; ``DynamicsModel(prelu_init=-1)``), alone and with ``--abs-restarts``
initialisations per seed. Every recipe but ``UA`` and ``paper`` aims below eps as ``train`` does
(``margin="auto"``).

Threads: one (``torch.set_num_threads(1)``); subnormal floats flushed. Wall times depend on the machine's load.
"""

from __future__ import annotations

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse
import json
import logging
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from saml_ros.core.dynamics.system import System
from saml_ros.core.spec import ProblemSpec
from saml_ros.core.systems import get_system
from saml_ros.core.training import TrainConfig, Transitions, evaluate_spec
from saml_ros.core.training.diagnosis import INFEASIBLE, MET, NOT_CONVERGED, TOL
from saml_ros.core.training.heldout import MET as HELD_MET
from saml_ros.core.training.heldout import MET_ON_TRAINING_ONLY, NO_HELDOUT, NOT_MET, UNCONFIRMED
from saml_ros.core.training.verdict import read_verdicts, spec_estimates
from saml_ros.offline.pipelines import TrainedModels, evaluate_models, generate_datasets, train_models


@dataclass(frozen=True)
class Problem:
    """One Sufficiently Accurate problem: system, data size, epochs, the paper's learning rates."""

    name: str
    system: str
    n_train: int
    epochs: int
    paper_lrs: tuple[float, float]
    note: str


#: the problems (full mode). Epochs: friction the paper's 200; quadrotor 300 of the paper's 3000 (the bench's time
#: budget); paddle: the system's synthetic impacts, 2500 of them (the paper's "42 minutes" of bounces), 100 epochs.
PROBLEMS: dict[str, Problem] = {
    "friction": Problem("friction", "friction", 15000, 200, (1e-3, 1e-4), "4-2 net, 15000 samples, 200 epochs"),
    "quadrotor": Problem("quadrotor", "quadrotor", 10000, 300, (1e-3, 1e-4),
                         "16-8 net, 10000 samples, 300 epochs (paper: 3000)"),
    "paddle": Problem("paddle", "paddle_ball", 2500, 100, (1e-3, 1e-3),
                      "128-128 net, 2500 synthetic impacts, 100 epochs"),
}


#: the first hidden layer's initial PReLU slope of the "|h| start" recipes (DynamicsModel's prelu_init)
ABS_SLOPE = -1.0


#: the margin of the recipes that train as `train` does (every recipe but UA and the paper's Algorithm 1)
MARGIN = "auto"


def recipes(restarts: int, abs_restarts: int) -> dict[str, tuple[TrainConfig | None, int, float, str | None]]:
    """Recipe name -> (config with the problem's settings still to fill in, restarts, first PReLU slope at
    initialisation, margin); None: the paper's config. Every recipe but UA and ``paper`` aims below eps as
    ``train`` does (``margin="auto"``); ``default, no margin`` is the default recipe aiming at eps itself."""
    default = TrainConfig()
    out: dict[str, tuple[TrainConfig | None, int, float, str | None]] = {
        "UA": (None, 1, 0.25, None), "paper": (None, 1, 0.25, None)}
    for method in ("lagrangian", "nupi", "augmented", "resilient"):
        cfg = default if method == default.dual_method else method_config(method)
        out[method + (" (default)" if method == default.dual_method else "")] = (cfg, 1, 0.25, MARGIN)
        if method == default.dual_method:
            out["default, no margin"] = (default, 1, 0.25, None)
    if restarts > 1:
        out[f"default + {restarts} restarts"] = (default, restarts, 0.25, MARGIN)
    if abs_restarts > 0:
        out["default, |h| start"] = (default, 1, ABS_SLOPE, MARGIN)
    if abs_restarts > 1:
        out[f"default + {abs_restarts} restarts, |h| start"] = (default, abs_restarts, ABS_SLOPE, MARGIN)
    return out


def method_config(method: str) -> TrainConfig:
    """The recommended recipe with another dual method (its own recommended parameters are TrainConfig's)."""
    return replace(TrainConfig(), dual_method=method)


@dataclass
class Row:
    recipe: str
    problem: str
    feasible: np.ndarray  # (S,) bool
    objective: np.ndarray  # (S,) on the seed's training data
    held_objective: np.ndarray  # (S,) on the shared held-out data
    in_region: np.ndarray  # (S,) held-out error inside the first constraint's region
    lam: np.ndarray  # (S,)
    verdicts: list[str]
    seconds: float
    reachable: float
    reported: list[str] = field(default_factory=list)  # (S,) the held-out verdict train reports (first constraint)
    training: np.ndarray = field(default_factory=lambda: np.zeros(0))  # (S,) its left-hand side, training data
    held_mean: np.ndarray = field(default_factory=lambda: np.zeros(0))  # (S,) held-out estimate (verdict set)
    held_se: np.ndarray = field(default_factory=lambda: np.zeros(0))  # (S,) its standard error
    fresh: np.ndarray = field(default_factory=lambda: np.zeros(0))  # (S,) the left-hand side on FRESH transitions
    aim: float = float("nan")  # the bound training aimed at (first constraint)


@dataclass
class HeldOut:
    """The held-out data of a problem: ``test`` (the shared 20000 transitions of the held-out objective),
    ``verdict`` (what ``train``'s verdict is read on: 10x the training size, fresh), ``select`` (restarts select on
    it, as ``train`` does; fresh) and ``fresh`` (200000 fresh transitions: does a model reported met stay met?)."""

    test: tuple[np.ndarray, np.ndarray, np.ndarray]
    verdict: tuple[np.ndarray, np.ndarray, np.ndarray]
    select: tuple[np.ndarray, np.ndarray, np.ndarray]
    fresh: tuple[np.ndarray, np.ndarray, np.ndarray]


def run_recipe(p: Problem, sysm: System, spec: ProblemSpec, data: tuple[np.ndarray, ...], held: HeldOut,
               seeds: list[int], recipe: str, cfg: TrainConfig | None, restarts: int, epochs: int,
               hidden: tuple[int, ...] | None = None, prelu_init: float = 0.25, margin: str | None = None) -> Row:
    x, u, y = data
    plr, dlr = p.paper_lrs
    uniform = recipe == "UA"
    if cfg is None:
        cfg = TrainConfig.paper(epochs=epochs, primal_lr=plr, dual_lr=dlr)
    else:
        cfg = replace(cfg, epochs=epochs)
    use_spec = spec.uniform() if uniform else spec
    masks = spec.masks(*(torch.as_tensor(a, dtype=torch.float64) for a in held.verdict))[1:]
    held_in = [len(held.verdict[0]) if m is None else int(m.sum()) for m in masks]
    res: TrainedModels = train_models(sysm, use_spec, x, u, y, cfg, seeds, hidden, "residual", restarts=restarts,
                                      prelu_init=prelu_init, margin=None if uniform else margin,
                                      heldout_n=held_in, select=held.select if restarts > 1 else None)
    ev = evaluate_spec(res.model, spec, Transitions(res.model, spec, x, u, y))
    eps = np.array([t.eps for t in spec.constraints])
    rel = ev["constraints"] / eps
    test = held.test
    ev_test = evaluate_models(res.model, spec, *test)
    diag = res.trainer.diagnosis
    verdicts = ["-"] * len(seeds) if uniform or diag is None else [diag.constraints[0].members[i].verdict
                                                                       for i in range(len(seeds))]
    reach = float("nan") if uniform or diag is None else diag.constraints[0].reachable_eps
    lam = np.zeros(len(seeds)) if uniform else res.trainer.lam[:, 0].double().numpy()
    row = Row(recipe, p.name, (rel <= TOL).all(axis=1), ev["objective"], ev_test.objective,
              ev_test.regions[0].inside, lam, verdicts, res.train_seconds, reach)
    # train's verdict (first constraint), and the same left-hand side on 200000 fresh transitions
    res.spec = spec
    if uniform:  # UA has no constraint of its own: the verdict is read on the SA spec's bound
        res.training = np.array([[e.mean for e in c] for c in spec_estimates(
            res.model, spec, Transitions(res.model, spec, x, u, y))[1]]).T
    assert res.training is not None
    _, held_c = spec_estimates(res.model, spec, Transitions(res.model, spec, *held.verdict))
    v = read_verdicts(spec, held_c, res.training, None if uniform else res.aimed, None if uniform else diag)
    _, fresh_c = spec_estimates(res.model, spec, Transitions(res.model, spec, *held.fresh))
    c0 = v.constraints[0]
    row.reported = [m.verdict for m in c0.members]
    row.training = np.array([m.training for m in c0.members])
    row.held_mean = np.array([m.heldout.mean if m.heldout else np.nan for m in c0.members])
    row.held_se = np.array([m.heldout.se if m.heldout else np.nan for m in c0.members])
    row.fresh = np.array([e.mean for e in fresh_c[0]])
    row.aim = c0.aim
    return row


def fmt_dist(a: np.ndarray, digits: int = 4) -> str:
    a = np.asarray(a, dtype=float)
    return f"{np.median(a):.{digits}g} [{a.min():.{digits}g} - {a.max():.{digits}g}]"


def table(rows: list[Row], problems: dict[str, Problem], eps: dict[str, float], n_seeds: int,
          nets: dict[str, tuple[int, ...]]) -> str:
    lines = []
    for name, p in problems.items():
        pr = [r for r in rows if r.problem == name]
        if not pr:
            continue
        feas_obj = np.concatenate([r.objective[r.feasible] for r in pr] or [np.zeros(0)])
        best = float(feas_obj.min()) if len(feas_obj) else float("nan")
        # per seed (= per dataset): the best feasible objective any recipe reached on that seed's own data
        per_seed = np.min([np.where(r.feasible, r.objective, np.inf) for r in pr], axis=0)
        feas_held = np.concatenate([r.held_objective[r.feasible] for r in pr] or [np.zeros(0)])
        best_held = float(feas_held.min()) if len(feas_held) else float("nan")
        per_seed_held = np.min([np.where(r.feasible, r.held_objective, np.inf) for r in pr], axis=0)
        note = p.note if name not in nets else p.note.replace(p.note.split(" net")[0], "-".join(map(str, nets[name])))
        lines += [f"**{name}** ({note}; eps = {eps[name]:g}; best feasible objective {best:.4g})", "",
                  "| recipe | feasible | near best | near best, same data | near best, held-out | near best, held-out, "
                  "same data | objective | in-region error (held-out) | verdicts met / not conv. / infeasible | lambda | "
                  "train s |",
                  "|---|---|---|---|---|---|---|---|---|---|---|"]
        for r in pr:
            near = int(np.sum(r.feasible & (r.objective <= 1.1 * best))) if np.isfinite(best) else 0
            same = int(np.sum(r.feasible & (r.objective <= 1.1 * per_seed)))
            held = int(np.sum(r.feasible & (r.held_objective <= 1.1 * best_held))) if np.isfinite(best_held) else 0
            held_same = int(np.sum(r.feasible & (r.held_objective <= 1.1 * per_seed_held)))
            v = ("-" if r.recipe == "UA" else
                 f"{r.verdicts.count(MET)} / {r.verdicts.count(NOT_CONVERGED)} / {r.verdicts.count(INFEASIBLE)}")
            feas = f"{int(r.feasible.sum())}/{n_seeds}"
            nb = f"{near}/{n_seeds}"
            cell = r.recipe.replace("|", "\\|")  # a markdown cell
            lines.append(f"| {cell} | {feas} | {nb} | {same}/{n_seeds} | {held}/{n_seeds} | {held_same}/{n_seeds} | {fmt_dist(r.objective)} | {fmt_dist(r.in_region)} | {v} | "
                         f"{np.median(r.lam):.3g} | {r.seconds:.0f} |")
        lines.append("")
        lines += verdict_table(pr, eps[name], n_seeds)
    return "\n".join(lines)


#: verdicts in the order of the verdict table's columns
VERDICT_COLUMNS = (HELD_MET, UNCONFIRMED, MET_ON_TRAINING_ONLY, NOT_MET, NO_HELDOUT)


def verdict_table(pr: list[Row], eps: float, n_seeds: int) -> list[str]:
    """Per recipe: the bound it aimed at, ``train``'s held-out verdicts (first constraint), and the left-hand side
    on the fresh transitions: how many seeds reported met exceed eps there."""
    lines = ["Verdicts as `train` reports them (first constraint, read on the verdict set) and the same left-hand "
             "side on the fresh transitions:", "",
             "| recipe | aimed at | met / unconfirmed / met on training only / not met / no held-out | training | "
             "held-out (verdict set) | fresh | fresh > eps | **reported met, fresh > eps** |",
             "|---|---|---|---|---|---|---|---|"]
    for r in pr:
        if not r.reported:
            continue
        counts = " / ".join(str(r.reported.count(v)) for v in VERDICT_COLUMNS)
        met = np.array([v == HELD_MET for v in r.reported])
        over = r.fresh > eps
        cell = r.recipe.replace("|", "\\|")
        lines.append(f"| {cell} | {r.aim:.4g} | {counts} | {fmt_dist(r.training)} | {fmt_dist(r.held_mean)} | "
                     f"{fmt_dist(r.fresh)} | {int(over.sum())}/{n_seeds} | {int((met & over).sum())}/{int(met.sum())} |")
    lines.append("")
    return lines


def per_seed_table(r: Row, eps: float, n_fresh: int) -> str:
    """One recipe's seeds: the reported verdict, the training value, the held-out estimate +- its standard error,
    the value on the fresh transitions (relative to eps in parentheses)."""
    lines = [f"**{r.problem}, {r.recipe}** (eps = {eps:g}, aimed at {r.aim:.4g}; fresh: {n_fresh} transitions)", "",
             "| seed | reported | training | held-out +- se | fresh | fresh <= eps |", "|---|---|---|---|---|---|"]
    for i, v in enumerate(r.reported):
        lines.append(f"| {i} | {v} | {r.training[i]:.5f} | {r.held_mean[i]:.5f} +- {r.held_se[i]:.5f} | "
                     f"{r.fresh[i]:.5f} ({100 * (r.fresh[i] / eps - 1):+.1f} %) | {'yes' if r.fresh[i] <= eps else 'NO'} |")
    lines.append("")
    return "\n".join(lines)


def budget_sweep(p: Problem, sysm: System, spec: ProblemSpec, data: tuple[np.ndarray, ...],
                 test: HeldOut, seeds: list[int], budgets: list[int],
                 plot: Path | None = None) -> list[dict[str, Any]]:
    """The default recipe at several epoch budgets: does the seeds' spread of the objective shrink as training goes
    on (an optimum being reached) or not? Prints, per budget, the training and the held-out objective over seeds
    (median, min, max, max / min, seeds within 10 % of the best); optionally a PNG of both against the budget."""
    out = []
    n = len(seeds)
    for ep in budgets:
        row = run_recipe(p, sysm, spec, data, test, seeds, "default", TrainConfig(), 1, ep, margin=MARGIN)
        out.append({"epochs": ep, "train": row.objective, "held": row.held_objective, "feasible": row.feasible,
                    "seconds": row.seconds})
        parts = []
        for label, a in (("training", row.objective), ("held-out", row.held_objective)):
            parts.append(f"{label} {np.median(a):.5f} [{a.min():.5f} - {a.max():.5f}], max/min {a.max() / a.min():.3f}, "
                         f"within 10 % of the best {int(np.sum(a <= 1.1 * a.min()))}/{n}")
        print(f"  {p.name} default, {ep:4d} epochs ({row.seconds:.0f} s): feasible {int(row.feasible.sum())}/{n}; "
              + "; ".join(parts), flush=True)
    if plot is not None:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(figsize=(6.4, 4.2))
        eps_ = np.array(budgets, dtype=float)
        train = np.stack([np.asarray(r["train"], dtype=float) for r in out])  # (budgets, seeds)
        held = np.stack([np.asarray(r["held"], dtype=float) for r in out])
        for i in range(n):
            ax.plot(eps_, train[:, i], "-", color="tab:blue", alpha=0.5, lw=1,
                    label="training objective (one line per seed)" if i == 0 else None)
            ax.plot(eps_, held[:, i], "--", color="tab:orange", alpha=0.5, lw=1,
                    label="held-out objective (20000 fresh transitions)" if i == 0 else None)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("epochs (the cosine schedule spans the whole run)")
        ax.set_ylabel("normalised objective")
        ax.set_title(f"{p.name}: default recipe, {n} seeds" + (", one shared dataset" if data[0].ndim == 2 else ""))
        ax.legend(fontsize=8)
        fig.tight_layout()
        fig.savefig(plot, dpi=120)
        print(f"  plot: {plot}")
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="5 seeds, a fifth of the epochs, quarter of the data (a "
                                                         "smoke run: the numbers are not the claims)")
    ap.add_argument("--seeds", type=int, help="seeds per problem (default 15, --quick 5)")
    ap.add_argument("--problems", nargs="+", choices=sorted(PROBLEMS), default=list(PROBLEMS))
    ap.add_argument("--restarts", type=int, default=3, help="initialisations per seed of the restarts recipe")
    ap.add_argument("--restarts-on", nargs="*", choices=sorted(PROBLEMS), default=["friction"],
                    help="problems that also run the restarts recipes")
    ap.add_argument("--abs-restarts", type=int, default=12,
                    help="initialisations per seed of the '|h| start' restarts recipe (first PReLU slope -1; 0: "
                         "neither |h| recipe), on the problems of --restarts-on")
    ap.add_argument("--recipes", nargs="+", help="only these recipes (names as printed)")
    ap.add_argument("--friction", action="append", default=[], metavar="KEY=VALUE",
                    help="parameter of the friction system, e.g. a friction profile once the system has one")
    ap.add_argument("--hidden", action="append", default=[], metavar="PROBLEM=H1-H2",
                    help="another net for a problem, e.g. quadrotor=64-64 (does a larger net meet the bound?)")
    ap.add_argument("--epochs", action="append", default=[], metavar="PROBLEM=N",
                    help="other epochs for a problem, e.g. paddle=300 (default: the problem's, see PROBLEMS; divided by 5 "
                         "under --quick, like the defaults)")
    ap.add_argument("--shared-data", action="store_true",
                    help="every seed trains on the same dataset (that of the first seed): seeds then differ only by "
                         "initialisation and minibatch order")
    ap.add_argument("--json", type=Path, help="also write every number into this file")
    ap.add_argument("--fresh", type=int, default=200_000,
                    help="fresh transitions the reported verdicts are checked on (--quick: a quarter)")
    ap.add_argument("--per-seed", nargs="*", default=[f"{TrainConfig().dual_method} (default)", "default, no margin"],
                    help="recipes whose seeds are listed one by one (verdict, training, held-out +- se, fresh)")
    ap.add_argument("--budgets", metavar="PROBLEM=E1,E2,...",
                    help="instead of the recipe tables: the default recipe on PROBLEM at each epoch budget, the "
                         "seeds' spread of the training and held-out objectives (e.g. paddle=50,100,200,400)")
    ap.add_argument("--plot", type=Path, help="with --budgets: a PNG of both objectives against the budget")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    torch.set_flush_denormal(True)
    logging.getLogger("saml_ros.trainer").setLevel(logging.ERROR)
    n_seeds = args.seeds or (5 if args.quick else 15)
    seeds = list(range(n_seeds))
    friction_params: dict[str, Any] = {}
    for item in args.friction:
        k, _, v = item.partition("=")
        try:
            friction_params[k] = json.loads(v)
        except json.JSONDecodeError:
            friction_params[k] = v
    problems = {k: PROBLEMS[k] for k in args.problems}
    nets: dict[str, tuple[int, ...]] = {}
    for item in args.hidden:
        k, _, v = item.partition("=")
        if k not in PROBLEMS:
            ap.error(f"--hidden: unknown problem {k!r}")
        nets[k] = tuple(int(h) for h in v.split("-"))
    for item in args.epochs:
        k, _, v = item.partition("=")
        if k not in PROBLEMS or not v.isdigit() or int(v) < 1:
            ap.error(f"--epochs: expected PROBLEM=N with PROBLEM one of {sorted(PROBLEMS)}, got {item!r}")
        problems[k] = replace(problems.get(k, PROBLEMS[k]), epochs=int(v),
                              note=PROBLEMS[k].note.replace(f"{PROBLEMS[k].epochs} epochs", f"{v} epochs"))
    problems = {k: v for k, v in problems.items() if k in args.problems}
    budgets: list[int] = []
    if args.budgets:
        k, _, v = args.budgets.partition("=")
        try:
            budgets = [int(e) for e in v.split(",")]
        except ValueError:
            budgets = []
        if k not in PROBLEMS or not budgets or min(budgets) < 1:
            ap.error(f"--budgets: expected PROBLEM=E1,E2,... with PROBLEM one of {sorted(PROBLEMS)}, got {args.budgets!r}")
        problems = {k: problems.get(k, PROBLEMS[k])}
    print(("bench_dual: one dataset shared by every seed; " if args.shared_data else "bench_dual: ")
          + f"{n_seeds} seeds per problem, problems {list(problems)}, restarts {args.restarts} on "
          f"{args.restarts_on}" + (" (--quick)" if args.quick else ""), flush=True)
    print(f"default recipe: {TrainConfig()}", flush=True)
    rows: list[Row] = []
    eps: dict[str, float] = {}
    t_all = time.perf_counter()
    for name, p in problems.items():
        sysm = get_system(p.system, **(friction_params if p.system == "friction" else {}))
        spec = ProblemSpec.for_system(sysm.paper_spec(), sysm)
        eps[name] = spec.constraints[0].eps
        n = p.n_train // 4 if args.quick else p.n_train
        epochs = max(1, p.epochs // 5) if args.quick else p.epochs
        data = generate_datasets(sysm, n, seeds[:1] if args.shared_data else seeds)
        if args.shared_data:
            data = tuple(a[0] for a in data)  # (N, .): one dataset, shared by every member
        n_fresh = args.fresh // 4 if args.quick else args.fresh
        test = HeldOut(sysm.make_dataset(20000, np.random.default_rng(10_000)),
                       sysm.make_dataset(max(10_000, 10 * n), np.random.default_rng(20_000)),
                       sysm.make_dataset(max(10_000, 10 * n), np.random.default_rng(40_000)),
                       sysm.make_dataset(n_fresh, np.random.default_rng(30_000)))
        if budgets:
            budget_sweep(p, sysm, spec, data, test, seeds, budgets, args.plot)
            continue
        on = name in args.restarts_on
        for recipe, (cfg, restarts, slope, margin) in recipes(args.restarts if on else 1,
                                                              args.abs_restarts if on else 0).items():
            if args.recipes and recipe not in args.recipes:
                continue
            t0 = time.perf_counter()
            row = run_recipe(p, sysm, spec, data, test, seeds, recipe, cfg, restarts, epochs, nets.get(name), slope,
                             margin)
            rows.append(row)
            print(f"  {name:9s} {recipe:24s} feasible {int(row.feasible.sum())}/{n_seeds}, objective "
                  f"{fmt_dist(row.objective)}, in-region {fmt_dist(row.in_region)}, verdicts "
                  f"{row.verdicts}, smallest final left-hand side {row.reachable:.3g}, reported {row.reported}, "
                  f"fresh {fmt_dist(row.fresh)}, {time.perf_counter() - t0:.0f} s", flush=True)
    if rows:
        print()
        print(table(rows, problems, eps, n_seeds, nets))
        for r in rows:
            if r.recipe in args.per_seed:
                print(per_seed_table(r, eps[r.problem], args.fresh // 4 if args.quick else args.fresh))
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(f"total {time.perf_counter() - t_all:.0f} s (load average at the end {load:.1f} on {os.cpu_count()} CPUs)")
    if args.json:
        args.json.write_text(json.dumps([{**r.__dict__, **{k: np.asarray(v).tolist() for k, v in r.__dict__.items()
                                                           if isinstance(v, np.ndarray)}} for r in rows], indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
