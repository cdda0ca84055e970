"""One demo run's final SA checkpoint flown with each guard setting (``./dev demo --guards RUN_DIR``).

From the demo's evaluation starts of that run (its ``--seed``: the standard and the aggressive ones), the base
model and the learned model with every remedy off, each remedy alone, the run's own guard (``guard.*`` of its
``bringup.yaml``) and it without roll back / with or without the constraint watch / with or without the task check
/ without the infeasible-plan fallback (or with it, for runs recorded before it existed): per setting the mean and
worst landing error, the steps planned with f_hat and the roll backs.
It answers "what does each remedy cost or buy on this model" without a new live run (ROS-free, about 30 s for
the 10 aggressive starts here). Printed as a table; ``--json`` writes it too.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from saml_ros.core.mpc.guard import GuardConfig
from saml_ros.core.mpc.task_check import TaskCheckConfig
from saml_ros.demo.landing import TASK_METRIC


def guard_settings(guard: GuardConfig) -> dict[str, GuardConfig | None]:
    """The settings flown: unguarded, each of the run's remedies alone, and the run's guard."""
    off = GuardConfig()
    out: dict[str, GuardConfig | None] = {"unguarded": None}
    if math.isfinite(guard.max_disagreement):
        out[f"disagreement {guard.max_disagreement:g} only"] = dataclasses.replace(
            off, max_disagreement=guard.max_disagreement)
    if guard.bound_residual:
        out["bound only"] = dataclasses.replace(off, bound_residual=True)
    if guard.rollback:
        out["roll back only"] = dataclasses.replace(off, rollback=True, monitor=guard.monitor)
        out["run's guard without roll back"] = dataclasses.replace(guard, rollback=False)
        if guard.monitor.constraint_strikes:
            out["run's guard without constraint watch"] = dataclasses.replace(
                guard, monitor=dataclasses.replace(guard.monitor, constraint_strikes=0))
        else:  # off by default: the watch as the capacity sweep flew it (2 strikes, 5 mm)
            out["run's guard + constraint watch"] = dataclasses.replace(
                guard, monitor=dataclasses.replace(guard.monitor, constraint_strikes=2, constraint_tol=0.005))
    if guard.task.enabled:
        out["run's guard without task check"] = dataclasses.replace(guard, task=TaskCheckConfig())
    else:  # the task check as the demo flies it in the wind world (docs/demo.md, "The task check")
        out["run's guard + task check"] = dataclasses.replace(guard, task=TaskCheckConfig(enabled=True))
    if guard.infeasible:
        out["infeasible fallback only"] = dataclasses.replace(off, infeasible=True)
        out["run's guard without infeasible fallback"] = dataclasses.replace(guard, infeasible=False)
    out["run's guard"] = guard
    if not guard.infeasible:
        out["run's guard + infeasible fallback"] = dataclasses.replace(guard, infeasible=True)
    return out


def compare(run_dir: Path, seed: int, n_standard: int, n_aggressive: int, workers: int | None = None,
            solver: str | None = None) -> dict[str, Any]:
    """Fly the run's newest valid SA checkpoint with :func:`guard_settings` and the base model from the run's
    evaluation starts; per start set and setting: per-start landing errors (m) and the guard's counters."""
    from saml_ros.bringup.config import CHECKPOINTS
    from saml_ros.demo.evaluation import Arm, evaluate_arms, evaluation_starts, newest_checkpoint, run_task_and_guard

    config = yaml.safe_load((run_dir / "bringup.yaml").read_text())
    sa = newest_checkpoint(run_dir / CHECKPOINTS)
    if sa is None:
        raise FileNotFoundError(f"no valid checkpoint in {run_dir / CHECKPOINTS}")
    task, guard = run_task_and_guard(config)
    system = task.system()
    arms = [Arm("base", "base")] + [Arm(name, str(sa[0]), g) for name, g in guard_settings(guard).items()]
    sets = evaluation_starts(system, n_standard, n_aggressive, seed)
    out: dict[str, Any] = {"run_dir": str(run_dir), "checkpoint": [str(sa[0]), sa[1]], "seed": seed, "sets": {}}
    for name, starts in sets.items():
        if not len(starts):
            continue
        res = evaluate_arms(arms, task, starts, solver or str(config["mpc"].get("solver", "fast")), workers)
        out["sets"][name] = {a: {"landing_error": r.metrics[TASK_METRIC].tolist(), "guard": r.guard}
                             for a, r in res.items()}
    return out


def format_comparison(out: dict[str, Any]) -> str:
    """The table of :func:`compare`'s result."""
    lines = [f"guard settings on {out['checkpoint'][0]} (v{out['checkpoint'][1]}), the demo's evaluation starts of "
             f"seed {out['seed']}; landing error |p_T - pad| in m"]
    for name, arms in out["sets"].items():
        base_worst = max(arms["base"]["landing_error"])
        lines.append(f"\n{name} starts ({len(arms['base']['landing_error'])}):")
        lines.append(f"  {'setting':<38} {'mean':>8} {'worst':>8}  {'no worse':>8}  steps on f_hat  roll backs")
        for a, r in arms.items():
            e = np.asarray(r["landing_error"])
            g = r["guard"]
            on_base = f"{g.get('solves_base', 0):.0f} / {g.get('solves', 0):.0f}" if a != "base" else "all"
            verdict = "" if a == "base" else ("yes" if e.max() <= base_worst else "NO")
            lines.append(f"  {a:<38} {e.mean():>8.4f} {e.max():>8.4f}  {verdict:>8}  {on_base:>14}  "
                         f"{g.get('rollbacks', 0):>10.0f}")
    return "\n".join(lines)


def spread(run_dir: Path, seed: int, start: str, copies: int, sigma: float = 1e-3,
           workers: int | None = None) -> dict[str, Any]:
    """The base model and the run's SA checkpoint under the run's guard, flown from one of the run's evaluation
    starts (``start`` = ``"aggressive:4"``: set and index) and ``copies - 1`` copies of it with the position moved by
    N(0, ``sigma``) m per axis: the landing errors (m) per arm, the start's own first. How much of a worst case is
    the start, how much the draw."""
    from saml_ros.bringup.config import CHECKPOINTS
    from saml_ros.demo.evaluation import Arm, evaluate_arms, evaluation_starts, newest_checkpoint, run_task_and_guard

    config = yaml.safe_load((run_dir / "bringup.yaml").read_text())
    sa = newest_checkpoint(run_dir / CHECKPOINTS)
    if sa is None:
        raise FileNotFoundError(f"no valid checkpoint in {run_dir / CHECKPOINTS}")
    task, guard = run_task_and_guard(config)
    name, _, index = start.partition(":")
    sets = evaluation_starts(task.system(), 30, 10, seed)
    if name not in sets or not index.isdigit() or int(index) >= len(sets[name]):
        raise ValueError(f"start {start!r}: want standard:I (I < 30) or aggressive:I (I < 10)")
    x0 = sets[name][int(index)]
    rng = np.random.default_rng(seed)
    starts = np.repeat(x0[None], copies, axis=0)
    starts[1:, 0:3] += rng.normal(0.0, sigma, (copies - 1, 3))
    arms = [Arm("base", "base"), Arm("SA, run's guard", str(sa[0]), guard)]
    res = evaluate_arms(arms, task, starts, str(config["mpc"].get("solver", "fast")), workers)
    return {"run_dir": str(run_dir), "seed": seed, "start": start, "sigma": sigma,
            "landing_error": {a: r.metrics[TASK_METRIC].tolist() for a, r in res.items()}}


def spread_main(argv: list[str]) -> int:
    """``demo --spread RUN_DIR --start SET:I [--seed S] [--copies N]``."""
    p = argparse.ArgumentParser(prog="demo --spread", description=(spread.__doc__ or "").split("\n\n")[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("run_dir", type=Path, help="a demo run directory (bringup.yaml, checkpoints/)")
    p.add_argument("--start", required=True, help="which evaluation start: standard:I or aggressive:I")
    p.add_argument("--seed", type=int, default=0, help="the run's --seed (picks its evaluation starts)")
    p.add_argument("--copies", type=int, default=12, help="flights per arm: the start and copies-1 moved ones")
    p.add_argument("--sigma", type=float, default=1e-3, help="SD of the position moves (m)")
    p.add_argument("--workers", type=int, help="evaluation processes (default: 2)")
    args = p.parse_args(argv)
    if not (args.run_dir / "bringup.yaml").is_file() or args.copies < 1:
        print(f"demo --spread: {args.run_dir} is not a demo run directory (no bringup.yaml), or --copies < 1")
        return 2
    try:
        out = spread(args.run_dir, args.seed, args.start, args.copies, args.sigma, args.workers)
    except (FileNotFoundError, ValueError) as exc:
        print(f"demo --spread: {exc}")
        return 2
    print(f"landing error (m) from {args.start} of seed {args.seed} (first) and {args.copies - 1} copies moved by "
          f"N(0, {args.sigma:g} m) per axis:")
    for arm, e in out["landing_error"].items():
        print(f"  {arm:<18} " + " ".join(f"{v:.3f}" for v in e) + f"   (max {max(e):.3f})")
    return 0


def guards_main(argv: list[str]) -> int:
    """``demo --guards RUN_DIR [--seed S]``."""
    p = argparse.ArgumentParser(prog="demo --guards", description=(__doc__ or "").split("\n\n")[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("run_dir", type=Path, help="a demo run directory (bringup.yaml, checkpoints/)")
    p.add_argument("--seed", type=int, default=0, help="the run's --seed (picks its evaluation starts)")
    p.add_argument("--eval-starts", type=int, default=0, help="standard starts (the demo flies 30)")
    p.add_argument("--aggressive-starts", type=int, default=10, help="far and fast starts")
    p.add_argument("--workers", type=int, help="evaluation processes (default: 2)")
    p.add_argument("--json", type=Path, help="also write the result here")
    args = p.parse_args(argv)
    if not (args.run_dir / "bringup.yaml").is_file():
        print(f"demo --guards: {args.run_dir} is not a demo run directory (no bringup.yaml)")
        return 2
    try:
        out = compare(args.run_dir, args.seed, args.eval_starts, args.aggressive_starts, args.workers)
    except FileNotFoundError as exc:
        print(f"demo --guards: {exc}")
        return 2
    print(format_comparison(out))
    if args.json is not None:
        args.json.write_text(json.dumps(out, indent=1, default=float))
    return 0
