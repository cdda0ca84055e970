"""The demo's paired evaluation (ROS-free): arms (base, oracle, learned models with or without the guard) flown from
the SAME start states on the true system, per-start metrics, paired comparisons, captured headroom, worst cases.

Each arm's episodes run in worker processes (``workers``, default 2: the machine's cores); an arm is identified
by a picklable :class:`Arm` (a learned model by its checkpoint path), so a worker rebuilds its own controller.
Learned arms run the :class:`~saml_ros.core.mpc.guard.GuardedController` exactly as the MPC node does; its
roll-back state is reset before every episode (each start is judged on its own, from a model the controller
trusts).
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass, field
from multiprocessing import get_context
from pathlib import Path
from typing import Any

import numpy as np

from saml_ros.core.mpc.guard import GuardConfig
from saml_ros.demo.landing import (
    FAR,
    METRICS,
    TASK_METRIC,
    LandingTask,
    aggressive_starts,
    episode_metrics,
    plant,
    standard_starts,
    world_params,
)

#: seeds of the evaluation starts (the simulator's episodes use ``--seed``, 0 by default); ``--seed`` adds to them
EVAL_SEED = 4242
AGGRESSIVE_SEED = 999


def evaluation_starts(system: Any, n_standard: int, n_aggressive: int, seed: int = 0) -> dict[str, np.ndarray]:
    """The demo's evaluation starts of run seed ``seed``: ``{"standard": (n_standard, 13), "aggressive":
    (n_aggressive, 13)}`` (the same for every arm and every tool that re-flies a run)."""
    return {"standard": standard_starts(system, n_standard, EVAL_SEED + seed),
            "aggressive": aggressive_starts(system, n_aggressive, AGGRESSIVE_SEED + seed)}


def run_task_and_guard(config: dict[str, Any]) -> tuple[LandingTask, GuardConfig]:
    """The landing task and the MPC's guard a bringup configuration (a run's ``bringup.yaml``) flew with."""
    from saml_ros.core.mpc.config import MPCConfig

    mpc, sim = config["mpc"], config["sim"]
    task = LandingTask.from_mpc_params(mpc, int(sim["episode_steps"]), float(sim.get("landing_height", 0.1)),
                                       world_params(sim))
    return task, MPCConfig.from_params({"system": "quadrotor", **mpc}).guard


def newest_checkpoint(directory: Path) -> tuple[Path, int] | None:
    """The newest valid checkpoint in ``directory`` (path, version), or None."""
    from saml_ros.core.model.checkpoint import CheckpointStore

    if not directory.is_dir():
        return None
    found = CheckpointStore(directory).load_latest_valid()
    if found is None:
        return None
    return Path(found.path), int(found.meta.get("version", 0))


@dataclass(frozen=True)
class Arm:
    """One way of flying the task: ``model`` is ``"base"`` (f_hat), ``"oracle"`` (the true dynamics) or a
    checkpoint path (a learned model; ``guard`` its remedies, None = unguarded)."""

    name: str
    model: str
    guard: GuardConfig | None = None

    @property
    def learned(self) -> bool:
        return self.model not in ("base", "oracle")


@dataclass
class ArmResult:
    """Per-start metrics of one arm (``metrics[name]`` ``(n,)``), trajectories ``xs`` ``(n, steps + 1, 13)``, the
    guard's summed counters and the model version flown (0 for base / oracle)."""

    arm: Arm
    metrics: dict[str, np.ndarray]
    xs: np.ndarray
    guard: dict[str, float] = field(default_factory=dict)
    version: int = 0


def _episodes(arm: Arm, task: LandingTask, starts: np.ndarray, solver: str) -> dict[str, Any]:
    """Worker: fly ``starts`` with ``arm``; metrics per start, trajectories, guard counters."""
    import torch

    torch.set_num_threads(1)
    from saml_ros.core.model.io import load_model
    from saml_ros.core.mpc import closed_loop, make_controller
    from saml_ros.core.mpc.guard import make_guarded_controller

    system = task.system()
    f = plant(system, task.landing_height)
    version = 0
    if arm.learned:
        loaded = load_model(arm.model, expect=system)
        version = loaded.version
        ctrl: Any = make_guarded_controller(system, solver, arm.guard or GuardConfig(), **task.mpc_options())
    else:
        ctrl = make_controller(system, "oracle" if arm.model == "oracle" else None, solver, **task.mpc_options())
    rows, xs = [], []
    for x0 in starts:
        hook = None
        if arm.learned:
            ctrl.reset_models()
            ctrl.set_model(loaded.model, version, loaded.meta)
            hook = (lambda s: ctrl.observe(s.x, s.result.u, s.x_next))  # noqa: E731
        run = closed_loop(system, ctrl, x0, task.steps, goal=task.goal, true_step=f, on_step=hook)
        # a violation no control could avoid (the height bound at the next step, fixed by the state: the pad
        # sits on it) is not the plan's failure
        rows.append(episode_metrics(run.xs, run.success | run.unavoidable, run.solve_times, task, system.dt))
        xs.append(run.xs)
    guard = {k: float(v) for k, v in ctrl.counters.items()} if arm.learned else {}
    return {"rows": rows, "xs": np.stack(xs) if xs else np.zeros((0, task.steps + 1, 13)), "guard": guard,
            "version": version}


def evaluate_arms(arms: Sequence[Arm], task: LandingTask, starts: np.ndarray, solver: str = "fast",
                  workers: int | None = None, progress: Callable[[int], Any] | None = None) -> dict[str, ArmResult]:
    """Fly every arm from every start (paired: the same starts, the same task); ``workers`` processes (default:
    2, or 1 when ``starts`` is small); returns the results by arm name. ``progress(n)`` is called with the number
    of episodes of each finished part (e.g. a tqdm bar's ``update``)."""
    n_workers = workers if workers is not None else min(2, os.cpu_count() or 1)
    chunks = max(1, n_workers)
    jobs = [(arm, part) for arm in arms for part in np.array_split(starts, chunks) if len(part)]
    if n_workers <= 1:
        outs = []
        for arm, part in jobs:
            outs.append(_episodes(arm, task, part, solver))
            if progress is not None:
                progress(len(part))
    else:
        with ProcessPoolExecutor(n_workers, mp_context=get_context("spawn")) as pool:
            futures = [pool.submit(_episodes, arm, task, part, solver) for arm, part in jobs]
            if progress is not None:
                sizes = {f: len(part) for f, (_, part) in zip(futures, jobs, strict=True)}
                for fut in as_completed(futures):
                    progress(sizes[fut])
            outs = [f.result() for f in futures]
    results: dict[str, ArmResult] = {}
    for (arm, _), out in zip(jobs, outs):
        rows = out["rows"]
        got = results.get(arm.name)
        new = {k: np.array([r[k] for r in rows]) for k in rows[0]}
        if got is None:
            results[arm.name] = ArmResult(arm, new, out["xs"], dict(out["guard"]), out["version"])
        else:
            got.metrics = {k: np.concatenate((got.metrics[k], new[k])) for k in got.metrics}
            got.xs = np.concatenate((got.xs, out["xs"]))
            for k, v in out["guard"].items():
                got.guard[k] = got.guard.get(k, 0.0) + v
    return results


# ------------------------------------------------------------------------------------------ statistics
def paired_diff(a: np.ndarray, b: np.ndarray) -> dict[str, float]:
    """``a - b`` over the same starts (positive = ``b`` better, for lower-is-better metrics): mean, 95 % t CI,
    p (paired t), fraction of starts where ``b < a``, and the two means."""
    from saml_ros.core.paired import paired

    p = paired(b, a)  # paired(a, b) is b - a
    return {"mean_a": p.mean_b, "mean_b": p.mean_a, "diff": p.diff, "lo": p.ci_low, "hi": p.ci_high,
            "p": p.p_ttest, "frac_b_better": float(np.mean(np.asarray(b) < np.asarray(a))), "n": p.n}


def captured(base: np.ndarray, learned: np.ndarray, oracle: np.ndarray, n_boot: int = 4000,
             seed: int = 0) -> dict[str, float]:
    """The fraction of the oracle's headroom a model captures, ``mean(base - learned) / mean(base - oracle)``,
    with a paired bootstrap 95 % CI over the starts (NaN when there is no headroom)."""
    b, m, o = (np.asarray(v, dtype=np.float64) for v in (base, learned, oracle))
    keep = np.isfinite(b) & np.isfinite(m) & np.isfinite(o)
    b, m, o = b[keep], m[keep], o[keep]
    if b.size < 2 or not (b - o).mean() > 0:
        return {"capture": math.nan, "lo": math.nan, "hi": math.nan}
    rng = np.random.default_rng(seed)
    idx = rng.integers(0, b.size, size=(n_boot, b.size))
    num, den = (b[idx] - m[idx]).mean(1), (b[idx] - o[idx]).mean(1)
    boot = np.where(den > 0, num / np.where(den > 0, den, 1.0), np.nan)
    return {"capture": float((b - m).mean() / (b - o).mean()), "lo": float(np.nanpercentile(boot, 2.5)),
            "hi": float(np.nanpercentile(boot, 97.5))}


def summarize(results: dict[str, ArmResult], base: str = "base", oracle: str = "oracle",
              learned: Sequence[str] = ()) -> dict[str, Any]:
    """Headroom (base - oracle), each learned arm's gain (base - learned) with its captured fraction, per metric;
    worst cases (largest landing error; episodes ending > 1 m off)."""
    out: dict[str, Any] = {"n": int(len(results[base].metrics[TASK_METRIC])), "metrics": {}}
    for k in METRICS:
        row: dict[str, Any] = {"mean": {a: float(np.nanmean(r.metrics[k])) for a, r in results.items()}}
        if oracle in results:
            row["headroom"] = paired_diff(results[base].metrics[k], results[oracle].metrics[k])
        for name in learned:
            row[f"gain/{name}"] = paired_diff(results[base].metrics[k], results[name].metrics[k])
            if oracle in results:
                row[f"captured/{name}"] = captured(results[base].metrics[k], results[name].metrics[k],
                                                   results[oracle].metrics[k])
        out["metrics"][k] = row
    out["worst"] = {a: float(np.max(r.metrics[TASK_METRIC])) for a, r in results.items()}
    out["far"] = {a: int(np.sum(r.metrics[TASK_METRIC] > FAR)) for a, r in results.items()}
    out["guard"] = {a: r.guard for a, r in results.items() if r.guard}
    return out


def _ci(d: dict[str, float], digits: int = 3) -> str:
    return f"{d['diff']:+.{digits}f} [{d['lo']:+.{digits}f}, {d['hi']:+.{digits}f}]"


def format_table(summary: dict[str, Any], arms: Sequence[str], learned: Sequence[str] = (),
                 oracle: str = "oracle") -> str:
    """Means per arm, the oracle's headroom and each learned arm's gain (95 % CI) and captured headroom."""
    head = f"  {'metric':<42}" + "".join(f"{a:>9}" for a in arms)
    if oracle in arms:
        head += f"  {'headroom base - oracle':>28}"
    for name in learned:
        head += f"  {'gain base - ' + name:>28} {'captured':>18}"
    lines = [head]
    for k, (label, unit) in METRICS.items():
        row = summary["metrics"][k]
        digits = 2 if unit in ("s", "ms") else 3
        line = f"  {label + ' (' + unit + ')':<42}" + "".join(f"{row['mean'][a]:>9.{digits}f}" for a in arms)
        if "headroom" in row:
            line += f"  {_ci(row['headroom'], digits):>28}"
        for name in learned:
            line += f"  {_ci(row[f'gain/{name}'], digits):>28}"
            c = row.get(f"captured/{name}")
            line += (f" {100 * c['capture']:>5.0f}% [{100 * c['lo']:.0f}, {100 * c['hi']:.0f}]"
                     if c and math.isfinite(c["capture"]) else f" {'n/a':>18}")
        lines.append(line)
    return "\n".join(lines)
