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
  (:mod:`saml_ros.core.training.diagnosis`);
* lambda (median) and the training wall time.

Recipes: ``UA`` (no constraint: the objective's unconstrained level, the paper's learning rates), ``paper``
(Algorithm 1 as the experiments run it: Adam, constant rates, the experiment's primal / dual rates), each other
dual method with the recommended schedules and rates (``TrainConfig()`` is the recommended default), and, on the
problems of ``--restarts-on`` (default: friction, whose 4-2 net has optima far apart), the default with
``--restarts`` initialisations per seed, the best feasible one kept on a 20 % held-out split, and the default with
the first hidden layer's PReLU started at slope -1 (``|h|``; ``DynamicsModel(prelu_init=-1)``), alone and with
``--abs-restarts`` initialisations per seed.

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
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from saml_ros.core.spec import ProblemSpec
from saml_ros.core.systems import get_system
from saml_ros.core.systems.base import System
from saml_ros.core.training import TrainConfig, Transitions, evaluate_spec
from saml_ros.core.training.diagnosis import INFEASIBLE, MET, NOT_CONVERGED, TOL
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


def recipes(restarts: int, abs_restarts: int) -> dict[str, tuple[TrainConfig | None, int, float]]:
    """Recipe name -> (config with the problem's settings still to fill in, restarts, first PReLU slope at
    initialisation); None: the paper's config."""
    default = TrainConfig()
    out: dict[str, tuple[TrainConfig | None, int, float]] = {"UA": (None, 1, 0.25), "paper": (None, 1, 0.25)}
    for method in ("lagrangian", "nupi", "augmented", "resilient"):
        cfg = default if method == default.dual_method else method_config(method)
        out[method + (" (default)" if method == default.dual_method else "")] = (cfg, 1, 0.25)
    if restarts > 1:
        out[f"default + {restarts} restarts"] = (default, restarts, 0.25)
    if abs_restarts > 0:
        out["default, |h| start"] = (default, 1, ABS_SLOPE)
    if abs_restarts > 1:
        out[f"default + {abs_restarts} restarts, |h| start"] = (default, abs_restarts, ABS_SLOPE)
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


def run_recipe(p: Problem, sysm: System, spec: ProblemSpec, data: tuple[np.ndarray, ...], test: tuple[np.ndarray, ...],
               seeds: list[int], recipe: str, cfg: TrainConfig | None, restarts: int, epochs: int,
               hidden: tuple[int, ...] | None = None, prelu_init: float = 0.25) -> Row:
    x, u, y = data
    plr, dlr = p.paper_lrs
    uniform = recipe == "UA"
    if cfg is None:
        cfg = TrainConfig.paper(epochs=epochs, primal_lr=plr, dual_lr=dlr)
    else:
        cfg = replace(cfg, epochs=epochs)
    use_spec = spec.uniform() if uniform else spec
    res: TrainedModels = train_models(sysm, use_spec, x, u, y, cfg, seeds, hidden, "residual", restarts=restarts,
                                      prelu_init=prelu_init)
    ev = evaluate_spec(res.model, spec, Transitions(res.model, spec, x, u, y))
    eps = np.array([t.eps for t in spec.constraints])
    rel = ev["constraints"] / eps
    held = evaluate_models(res.model, spec, *test)
    diag = res.trainer.diagnosis
    verdicts = ["-"] * len(seeds) if uniform or diag is None else [diag.constraints[0].members[i].verdict
                                                                       for i in range(len(seeds))]
    reach = float("nan") if uniform or diag is None else diag.constraints[0].reachable_eps
    lam = np.zeros(len(seeds)) if uniform else res.trainer.lam[:, 0].double().numpy()
    return Row(recipe, p.name, (rel <= TOL).all(axis=1), ev["objective"], held.objective, held.regions[0].inside, lam,
               verdicts, res.train_seconds, reach)


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
            name = r.recipe.replace("|", "\\|")  # a markdown cell
            lines.append(f"| {name} | {feas} | {nb} | {same}/{n_seeds} | {held}/{n_seeds} | {held_same}/{n_seeds} | {fmt_dist(r.objective)} | {fmt_dist(r.in_region)} | {v} | "
                         f"{np.median(r.lam):.3g} | {r.seconds:.0f} |")
        lines.append("")
    return "\n".join(lines)


def budget_sweep(p: Problem, sysm: System, spec: ProblemSpec, data: tuple[np.ndarray, ...],
                 test: tuple[np.ndarray, ...], seeds: list[int], budgets: list[int],
                 plot: Path | None = None) -> list[dict[str, Any]]:
    """The default recipe at several epoch budgets: does the seeds' spread of the objective shrink as training goes
    on (an optimum being reached) or not? Prints, per budget, the training and the held-out objective over seeds
    (median, min, max, max / min, seeds within 10 % of the best); optionally a PNG of both against the budget."""
    out = []
    n = len(seeds)
    for ep in budgets:
        row = run_recipe(p, sysm, spec, data, test, seeds, "default", TrainConfig(), 1, ep)
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
        test = sysm.make_dataset(20000, np.random.default_rng(10_000))
        if budgets:
            budget_sweep(p, sysm, spec, data, test, seeds, budgets, args.plot)
            continue
        on = name in args.restarts_on
        for recipe, (cfg, restarts, slope) in recipes(args.restarts if on else 1, args.abs_restarts if on else 0).items():
            if args.recipes and recipe not in args.recipes:
                continue
            t0 = time.perf_counter()
            row = run_recipe(p, sysm, spec, data, test, seeds, recipe, cfg, restarts, epochs, nets.get(name), slope)
            rows.append(row)
            print(f"  {name:9s} {recipe:24s} feasible {int(row.feasible.sum())}/{n_seeds}, objective "
                  f"{fmt_dist(row.objective)}, in-region {fmt_dist(row.in_region)}, verdicts "
                  f"{row.verdicts}, smallest final left-hand side {row.reachable:.3g}, {time.perf_counter() - t0:.0f} s",
                  flush=True)
    if rows:
        print()
        print(table(rows, problems, eps, n_seeds, nets))
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(f"total {time.perf_counter() - t_all:.0f} s (load average at the end {load:.1f} on {os.cpu_count()} CPUs)")
    if args.json:
        args.json.write_text(json.dumps([{**r.__dict__, **{k: np.asarray(v).tolist() for k, v in r.__dict__.items()
                                                           if isinstance(v, np.ndarray)}} for r in rows], indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
