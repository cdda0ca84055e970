"""Closed-loop evaluation of a user's robot under the generic MPC: base model vs learned models vs the oracle, paired
by start state (docs/your_robot.md, "Evaluate it").

    from saml_ros.experiments.robot_eval import evaluate_robot
    ev = evaluate_robot(system, simulator, {"seed0": m0, "seed1": m1, "seed2": m2}, starts, steps=750,
                        oracle=true_step)
    print(ev.report())

    ./dev python -m saml_ros.experiments.robot_eval --system-file examples/diff_drive/system.yaml \\
        --simulator examples/diff_drive/dynamics.py:make_robot --starts examples/diff_drive/dynamics.py:sample_starts \\
        --n-starts 30 --runs runs/dd_seed0 runs/dd_seed1 runs/dd_seed2 \\
        --oracle examples/diff_drive/dynamics.py:true_step -o out/     # --nested: each run from its own starts

Every controller flies the same starts in the robot's own simulator (``simulator(x0)`` returns an object with
``state() -> (n,)`` and ``step(u, dt)``; the simulator knows nothing of saml_ros) with the planner of the file's
``mpc:`` section (the same horizon, weights, constraints, solver options) for ``steps`` steps of ``dt``; the task
error of an episode is the distance of its last state from the goal over the goal fields that are not angles (the
file's units), or ``error(x, goal)``. Reported, as the demo does:

* each controller's mean and worst error; the **headroom** (base minus oracle, the most a model can gain) when an
  oracle is given (``oracle(x (B, n), u (B, m), *, dt) -> (B, n)``, the true dynamics in torch or as an
  array-namespace form: planned with like f_hat);
* per learned model and pooled over them (the mean over models of each start's error), the paired difference
  learned - base with its 95 % Student-t interval over the starts, the paired t and Wilcoxon p-values and the
  fraction of starts where the learned model did better (:func:`saml_ros.experiments.common.paired`);
* whether any learned-model episode ended worse than the base model's worst over the same starts;
* a figure (``errors.png``): each start's error per controller, and the paired differences.

With independently trained models (one per training seed), :func:`evaluate_nested` (``--nested``) flies each from
its own starts and reports the difference with the **seed as the unit** (:class:`NestedEvaluation`).
"""

from __future__ import annotations

import argparse
import importlib
import json
import math
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from saml_ros.experiments.common import Paired, paired


@dataclass
class RobotEvaluation:
    """What :func:`evaluate_robot` measured (errors ``(S,)`` per controller label, in the goal fields' units)."""

    starts: np.ndarray  #: (S, n)
    errors: dict[str, np.ndarray]  #: label -> (S,)
    finals: dict[str, np.ndarray]  #: label -> (S, n) last states
    solve_ms: dict[str, float]  #: label -> mean wall ms per solve
    learned: list[str]  #: labels of the learned models
    goal: np.ndarray
    steps: int
    dt: float
    stats: dict[str, Paired] = field(default_factory=dict)  #: learned label (and "pooled") -> paired vs base
    #: learned label -> the guard's counters summed over the starts (``solves``, ``solves_base``, ``rollbacks``, ...;
    #: empty without a guard)
    guard: dict[str, dict[str, int]] = field(default_factory=dict)

    def __post_init__(self) -> None:
        base = self.errors["base"]
        for label in self.learned:
            self.stats[label] = paired(base, self.errors[label])
        if self.learned:
            self.errors["pooled"] = np.mean([self.errors[k] for k in self.learned], axis=0)
            self.stats["pooled"] = paired(base, self.errors["pooled"])

    @property
    def worse_than_base_worst(self) -> int:
        """Learned-model episodes that ended worse than the base model's worst over the same starts."""
        worst = float(np.max(self.errors["base"]))
        return int(sum(np.sum(self.errors[k] > worst) for k in self.learned))

    @property
    def headroom(self) -> float:
        """Mean base error minus mean oracle error (NaN without an oracle)."""
        if "oracle" not in self.errors:
            return math.nan
        return float(np.mean(self.errors["base"]) - np.mean(self.errors["oracle"]))

    def report(self) -> str:
        """The evaluation as markdown."""
        lines = [f"{len(self.starts)} starts, {self.steps} steps of {self.dt:g} s; error at the last state "
                 f"(goal fields' units)", "", "| controller | mean error | worst | mean solve ms |", "|---|---|---|---|"]
        for label, e in self.errors.items():
            ms = self.solve_ms.get(label, math.nan)
            lines.append(f"| {label} | {e.mean():.4f} | {e.max():.4f} | {ms:.2f} |")
        if "oracle" in self.errors:
            lines += ["", f"headroom (base - oracle): {self.headroom:.4f}"]
        for label, c in self.guard.items():
            lines += ["", f"guard ({label}): {_guard_line(c)}"]
        if self.stats:
            lines += ["", "| learned vs base | pairs | mean diff (learned - base) | 95% CI | paired t p | "
                          "Wilcoxon p | learned better |", "|---|---|---|---|---|---|---|"]
            for label, st in self.stats.items():
                lines.append(f"| {label} | {st.n} | {st.diff:.4f} | [{st.ci_low:.4f}, {st.ci_high:.4f}] | "
                             f"{st.p_ttest:.2g} | {st.p_wilcoxon:.2g} | {100 * st.frac_b_better:.0f}% |")
            pooled = self.stats.get("pooled")
            if pooled is not None:
                verdict = ("gain: the interval excludes 0" if pooled.ci_high < 0 else
                           "loss: the interval excludes 0" if pooled.ci_low > 0 else "no significant difference")
                lines += ["", f"pooled over {len(self.learned)} model(s): {verdict}; learned episodes worse than the "
                              f"base model's worst: {self.worse_than_base_worst}"]
        return "\n".join(lines)

    def to_json(self) -> dict[str, Any]:
        return {"starts": self.starts.tolist(), "errors": {k: v.tolist() for k, v in self.errors.items()},
                "solve_ms": self.solve_ms, "learned": self.learned, "goal": self.goal.tolist(), "steps": self.steps,
                "dt": self.dt, "headroom": self.headroom, "worse_than_base_worst": self.worse_than_base_worst,
                "paired": {k: v.to_dict() for k, v in self.stats.items()}, "guard": self.guard}

    def figure(self, path: str | Path) -> None:
        """``path`` (PNG): each start's error per controller, and the paired differences learned - base."""
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4))
        order = np.argsort(self.errors["base"])
        for label, e in self.errors.items():
            a.plot(e[order], "o-" if label in ("base", "oracle", "pooled") else ".", label=label, ms=4, lw=1)
        a.set_xlabel("start (sorted by the base model's error)")
        a.set_ylabel("final error")
        a.legend(fontsize=8)
        diffs = [self.errors[k] - self.errors["base"] for k in self.learned]
        if diffs:
            b.boxplot(diffs, tick_labels=self.learned)
            b.axhline(0.0, color="k", lw=0.8)
            b.set_ylabel("learned - base (per start)")
        fig.tight_layout()
        fig.savefig(path, dpi=110)
        plt.close(fig)


@dataclass
class NestedEvaluation:
    """Learned models trained with independent seeds, each flown from its own starts (starts nested in seeds):
    one :class:`RobotEvaluation` per seed (base, that seed's model and the oracle on the same starts).

    The claim "the learned model docks better than f_hat" is about learning, so the **seed is the unit**: the
    per-seed mean of learned - base over its starts, then a Student-t interval over the seeds
    (:attr:`seed_level`); each seed's paired interval over its own starts and the pooled (seed, start) pairs
    (pseudo-replication, for comparison only) are reported beside it (docs/experiments.md, "How to read it")."""

    runs: dict[str, RobotEvaluation]  #: seed label -> its evaluation (one learned model, label = seed label)

    @property
    def seed_level(self) -> Paired:
        """learned - base: per-seed means over the starts, paired over the seeds."""
        return paired([np.mean(ev.errors["base"]) for ev in self.runs.values()],
                      [np.mean(ev.errors[k]) for k, ev in self.runs.items()])

    @property
    def pooled(self) -> Paired:
        """learned - base over every (seed, start) pair (pseudo-replication: for comparison only)."""
        return paired(np.concatenate([ev.errors["base"] for ev in self.runs.values()]),
                      np.concatenate([ev.errors[k] for k, ev in self.runs.items()]))

    @property
    def worse_than_base_worst(self) -> int:
        """Learned episodes that ended worse than the base model's worst over the same starts (per seed)."""
        return int(sum(ev.worse_than_base_worst for ev in self.runs.values()))

    def headroom(self) -> tuple[float, float, float]:
        """``(base mean, oracle mean, (base - oracle) / base)`` over every start (NaN without an oracle)."""
        base = float(np.mean(np.concatenate([ev.errors["base"] for ev in self.runs.values()])))
        if not all("oracle" in ev.errors for ev in self.runs.values()):
            return base, math.nan, math.nan
        oracle = float(np.mean(np.concatenate([ev.errors["oracle"] for ev in self.runs.values()])))
        return base, oracle, (base - oracle) / base if base else math.nan

    def report(self) -> str:
        """The evaluation as markdown: per seed, then seed-level and pooled."""
        first = next(iter(self.runs.values()))
        starts = sum(len(ev.starts) for ev in self.runs.values())
        lines = [f"{len(self.runs)} training seeds x {len(first.starts)} starts each (nested: {starts} episodes per "
                 f"controller), {first.steps} steps of {first.dt:g} s; error at the last state (goal fields' units)",
                 "", "| seed | base mean | base worst | learned mean | learned worst | oracle mean | learned - base "
                     "[95 % CI over the starts] | learned better | learned worse than base's worst |",
                 "|---|---|---|---|---|---|---|---|---|"]
        for label, ev in self.runs.items():
            st, e, b = ev.stats[label], ev.errors[label], ev.errors["base"]
            o = ev.errors.get("oracle")
            lines.append(f"| {label} | {b.mean():.4f} | {b.max():.4f} | {e.mean():.4f} | {e.max():.4f} | "
                         f"{'n/a' if o is None else f'{o.mean():.4f}'} | {st.diff:+.4f} [{st.ci_low:+.4f}, "
                         f"{st.ci_high:+.4f}] | {100 * st.frac_b_better:.0f}% | {ev.worse_than_base_worst} |")
        for label, ev in self.runs.items():
            for c in ev.guard.values():
                lines.append(f"guard ({label}): {_guard_line(c)}")
        seed, pooled = self.seed_level, self.pooled
        base, oracle, rel = self.headroom()
        lines += ["", f"seed level (unit: the training seed, n = {seed.n}): learned - base {seed.diff:+.4f} "
                      f"[{seed.ci_low:+.4f}, {seed.ci_high:+.4f}] ({100 * seed.diff / base:+.0f} % of the base "
                      f"model's mean error)",
                  f"pooled (seed, start) pairs, for comparison only (pseudo-replication, n = {pooled.n}): "
                  f"{pooled.diff:+.4f} [{pooled.ci_low:+.4f}, {pooled.ci_high:+.4f}], paired t p "
                  f"{pooled.p_ttest:.2g}, Wilcoxon p {pooled.p_wilcoxon:.2g}",
                  (f"headroom: base {base:.4f}, oracle {oracle:.4f}: (base - oracle) / base = {100 * rel:.0f} %"
                   if math.isfinite(oracle) else "headroom: not measured (no oracle)"),
                  f"learned episodes worse than the base model's worst over the same starts: "
                  f"{self.worse_than_base_worst}"]
        return "\n".join(lines)

    def to_json(self) -> dict[str, Any]:
        base, oracle, rel = self.headroom()
        return {"runs": {k: ev.to_json() for k, ev in self.runs.items()}, "seed_level": self.seed_level.to_dict(),
                "pooled": self.pooled.to_dict(), "headroom": {"base": base, "oracle": oracle, "relative": rel},
                "worse_than_base_worst": self.worse_than_base_worst}


def evaluate_nested(system: Any, simulator: Callable[[np.ndarray], Any], models: Mapping[str, Any],
                    sample_starts: Callable[[int, np.random.Generator], np.ndarray], n_starts: int, steps: int, *,
                    seed: int = 0, progress: Callable[[str], None] | None = None,
                    **options: Any) -> NestedEvaluation:
    """:func:`evaluate_robot` once per learned model (label -> model, e.g. one per training seed), each from its own
    ``n_starts`` starts (``sample_starts(n, rng)``, ``rng`` seeded ``seed + i`` for the i-th model); ``options`` as
    there (``oracle``, ``task``, ``metas``, ...)."""
    runs: dict[str, RobotEvaluation] = {}
    for i, (label, model) in enumerate(models.items()):
        starts = np.asarray(sample_starts(n_starts, np.random.default_rng(seed + i)), dtype=np.float64)
        if progress is not None:
            progress(f"{label}: {n_starts} starts")
        runs[label] = evaluate_robot(system, simulator, {label: model}, starts, steps, progress=progress, **options)
    return NestedEvaluation(runs)


def _guard_line(c: Mapping[str, int]) -> str:
    solves = max(int(c.get("solves", 0)), 1)
    return (f"{c.get('solves', 0)} solves, {100 * (1 - c.get('solves_base', 0) / solves):.0f} % planned with the learned "
            f"model, {c.get('fallbacks', 0)} disagreement fallbacks, {c.get('rollbacks', 0)} roll backs "
            f"({c.get('refused_before_flight', 0)} refused before flight), {c.get('clipped', 0)} plans clipped")


def node_guard() -> Any:
    """The guard the MPC node runs with its default parameters (:class:`~saml_ros.core.mpc.config.MPCConfig`:
    the live monitor with roll back on, ensemble disagreement and residual bound off)."""
    from saml_ros.core.mpc.config import MPCConfig

    return MPCConfig.from_params({}).guard


def acceptance(system: Any, model: Any, spec: Any, x: np.ndarray, u: np.ndarray, y: np.ndarray,
               residual_factor: float = 4.0) -> tuple[str, str] | None:
    """The MPC node's checkpoint acceptance (:func:`saml_ros.core.mpc.acceptance.check_model`, its default limits)
    for ``model`` trained on ``(x, u, y)`` with ``spec``: the evidence a learner stores in a checkpoint (residual
    statistics and a probe set of the training inputs) is built from the data; ``None`` = accepted, else
    ``(reason, message)``."""
    import torch

    from saml_ros.core.data.plausibility import Plausibility
    from saml_ros.core.model.evidence import DataEvidence
    from saml_ros.core.model.io import LoadedModel
    from saml_ros.core.mpc.acceptance import AcceptanceConfig, check_model

    evidence = DataEvidence.from_data(system, x, u, y)
    arrays: dict[str, np.ndarray] = {}
    meta: dict[str, Any] = {}
    if evidence is not None:
        arrays, meta["evidence"] = evidence.to_payload(tuple(system.target.names))
    loaded = LoadedModel(model, spec, system, torch.zeros(len(spec.constraints)), meta, arrays)
    return check_model(loaded, Plausibility.for_system(system), None,
                       AcceptanceConfig(residual_factor=residual_factor))


def default_error(system: Any, task: Any) -> Callable[[np.ndarray, np.ndarray], float]:
    """Distance of a state from the goal over the goal fields that are not angles."""
    idx = [i for i, a in zip(task.goal_idx, task.goal_angle, strict=True) if not a]
    keep = [k for k, a in enumerate(task.goal_angle) if not a]

    def error(x: np.ndarray, goal: np.ndarray) -> float:
        return float(np.linalg.norm(x[idx] - goal[keep]))

    return error


def evaluate_robot(system: Any, simulator: Callable[[np.ndarray], Any], models: Mapping[str, Any],
                   starts: np.ndarray, steps: int, *, goal: np.ndarray | None = None,
                   oracle: Callable[..., Any] | None = None, error: Callable[[np.ndarray, np.ndarray], float] | None = None,
                   member: int = 0, progress: Callable[[str], None] | None = None, task: Any = None,
                   guard: Any = None, metas: Mapping[str, Mapping[str, Any]] | None = None,
                   **planner_options: Any) -> RobotEvaluation:
    """See the module docstring. ``models``: label -> a :class:`~saml_ros.core.model.network.DynamicsModel` of ``system``
    (ensemble member ``member`` plans, or with the planner option ``ensemble="mean"`` the members' mean); the base
    model f_hat (label ``base``) and, with ``oracle``, the true dynamics
    (label ``oracle``) fly the same starts. ``task``: an :class:`~saml_ros.core.mpc.generic.section.MPCTask` to plan
    and score instead of the file's (e.g. :func:`task_from_file`). ``guard``: a
    :class:`~saml_ros.core.mpc.guard.GuardConfig` (e.g. :func:`node_guard`): each learned model flies inside the
    guarded controller as the MPC node runs it (its live monitor given every transition; counters in
    :attr:`RobotEvaluation.guard`); None = the bare planner. ``metas``: label -> the model's checkpoint meta, as the
    node gives it to the guard (its ``evidence`` sets the live monitor's margin; without one the monitor scales it
    by the live transitions)."""
    from saml_ros.core.dynamics.base_forms import is_form
    from saml_ros.core.mpc.generic import GenericSQP, system_task
    from saml_ros.core.mpc.generic.dynamics import GenericDynamics, SymbolicBase, TorchBase

    task = system_task(system) if task is None else task
    planner_options["task"] = task
    goal = task.goal_default if goal is None else task.check_goal(goal)
    err = error or default_error(system, task)
    controllers: dict[str, Any] = {"base": GenericSQP(system, None, member=member, **planner_options)}
    if oracle is not None:
        ctrl = GenericSQP(system, None, member=member, **planner_options)
        if is_form(oracle):
            ctrl._base = SymbolicBase(oracle, {}, system.state.size, system.control.size, system.dt, "oracle")
        else:
            dt = system.dt

            def true_torch(x: Any, u: Any) -> Any:
                return oracle(x, u, dt=dt)

            ctrl._base = TorchBase(true_torch, "oracle (true dynamics, torch autograd)")
        ctrl.dyn = GenericDynamics(system, ctrl._base)
        controllers["oracle"] = ctrl
    guarded: dict[str, Any] = {}
    for label, model in models.items():
        if guard is None:
            controllers[label] = GenericSQP(system, model, member=member, **planner_options)
            continue
        from saml_ros.core.mpc.guard import GuardedController

        learned: Any = GenericSQP(system, None, member=member, **planner_options)  # the guard's planner protocol
        fallback: Any = GenericSQP(system, None, member=member, **planner_options)
        wrapped = GuardedController(learned, fallback, guard)
        wrapped.set_model(model, 1, dict((metas or {}).get(label, {})))
        controllers[label] = guarded[label] = wrapped
    angles = np.asarray(getattr(system, "angle_indices", ()), dtype=int)
    starts = np.asarray(starts, dtype=np.float64)
    errors = {k: np.zeros(len(starts)) for k in controllers}
    finals = {k: np.zeros_like(starts) for k in controllers}
    times: dict[str, list[float]] = {k: [] for k in controllers}
    t0 = time.perf_counter()
    for i, x0 in enumerate(starts):
        for label, ctrl in controllers.items():
            ctrl.reset()
            sim = simulator(x0)
            x_now = np.asarray(sim.state(), dtype=np.float64)
            for _ in range(steps):
                res = ctrl.solve(x_now, goal)
                times[label].append(res.solve_time)
                sim.step(res.u, system.dt)
                x_next = np.asarray(sim.state(), dtype=np.float64)
                if label in guarded:  # the live transition, its angle fields unwrapped as the learner pairs them
                    y = x_next.copy()
                    y[angles] = x_now[angles] + (y[angles] - x_now[angles] + math.pi) % (2 * math.pi) - math.pi
                    ctrl.observe(x_now, res.u, y)
                x_now = x_next
            x = np.asarray(sim.state(), dtype=np.float64)
            finals[label][i] = x
            errors[label][i] = err(x, goal)
        if progress is not None:
            progress(f"start {i + 1}/{len(starts)} ({time.perf_counter() - t0:.0f} s): "
                     + ", ".join(f"{k} {errors[k][i]:.3f}" for k in controllers))
    return RobotEvaluation(starts, errors, finals, {k: 1e3 * float(np.mean(v)) for k, v in times.items()},
                           list(models), goal, steps, system.dt,
                           guard={k: dict(c.counters) for k, c in guarded.items()})


def task_from_file(system: Any, path: str | Path) -> Any:
    """The :class:`~saml_ros.core.mpc.generic.section.MPCTask` of a YAML file holding an ``mpc:`` mapping (the
    file's section with some keys changed, e.g. another goal or horizon), checked as the system file's is."""
    import copy

    import yaml

    from saml_ros.core.mpc.generic.section import mpc_task, parse_mpc_section

    definition = copy.deepcopy(system.definition)
    raw = yaml.safe_load(Path(path).read_text())
    # checked and completed (goal bounds, penalty, ...) against the system file as its own section
    definition["mpc"] = parse_mpc_section(raw.get("mpc", raw) if isinstance(raw, dict) else raw, definition,
                                          f"{Path(path).name}: mpc")
    task = mpc_task(definition)
    if task is None:
        raise ValueError(f"{path}: no mpc: mapping")
    return task


def _load(target: str) -> Any:
    """``module:attribute`` (a module path or a ``.py`` file path before the colon)."""
    module, _, attr = target.partition(":")
    if module.endswith(".py") or "/" in module:
        path = Path(module if module.endswith(".py") else module.replace(".", "/") + ".py").resolve()
        sys.path.insert(0, str(path.parent))
        module = path.stem
    obj: Any = importlib.import_module(module)
    for part in attr.split("."):
        obj = getattr(obj, part)
    return obj


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="robot_eval", description="Closed-loop evaluation of a robot's system file "
                                                               "under the generic MPC (see the module docstring).")
    p.add_argument("--system-file", type=Path, required=True)
    p.add_argument("--simulator", required=True, help="module:factory, factory(x0) -> object with state(), step(u, dt)")
    p.add_argument("--starts", help="module:sampler, sampler(n, rng) -> (n, n_x); default: uniform in the state bounds")
    p.add_argument("--n-starts", type=int, default=30)
    p.add_argument("--steps", type=int, default=500)
    p.add_argument("--runs", nargs="*", default=[], help="run directories or checkpoints of learned models")
    p.add_argument("--oracle", help="module:function, the true dynamics (x, u, *, dt) -> next x (torch or xp form)")
    p.add_argument("--member", type=int, default=0)
    p.add_argument("--ensemble", choices=("member", "mean"), default=None,
                   help="plan an ensemble with its member --member or the mean of its members (default: the file's "
                        "mpc.solver_options, else member)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--nested", action="store_true", help="each learned model (e.g. one per training seed) flies its "
                   "own --n-starts starts (seeded --seed + i); statistics with the seed as the unit")
    p.add_argument("--task", type=Path, help="a YAML file with an mpc: mapping to plan and score instead of the "
                   "system file's")
    p.add_argument("--guard", action="store_true", help="fly each learned model inside the guard the MPC node runs "
                   "with its default parameters (live monitor with roll back)")
    p.add_argument("-o", "--out", type=Path, required=True)
    args = p.parse_args(argv)
    import torch

    torch.set_num_threads(1)
    from saml_ros.api import load_model
    from saml_ros.user_code import load_system_file

    system = load_system_file(args.system_file)
    task = task_from_file(system, args.task) if args.task else None
    loaded = {Path(r).name: load_model(r).loaded for r in args.runs}
    models = {k: v.model.double() for k, v in loaded.items()}
    metas = {k: v.meta for k, v in loaded.items()}
    planner: dict[str, Any] = {} if args.ensemble is None else {"ensemble": args.ensemble}
    if args.nested:
        if not args.starts or not models:
            p.error("--nested needs --starts and --runs")
        nested = evaluate_nested(system, _load(args.simulator), models, _load(args.starts), args.n_starts,
                                 args.steps, seed=args.seed, oracle=_load(args.oracle) if args.oracle else None,
                                 member=args.member, task=task, guard=node_guard() if args.guard else None,
                                 metas=metas, progress=lambda s: print(s, flush=True), **planner)
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "results.json").write_text(json.dumps(nested.to_json(), indent=1))
        (args.out / "results.md").write_text(nested.report() + "\n")
        print(nested.report())
        return 0
    rng = np.random.default_rng(args.seed)
    if args.starts:
        starts = np.asarray(_load(args.starts)(args.n_starts, rng), dtype=np.float64)
    else:
        starts = rng.uniform(system.state_low, system.state_high, (args.n_starts, system.state.size))
    ev = evaluate_robot(system, _load(args.simulator), models, starts, args.steps,
                        oracle=_load(args.oracle) if args.oracle else None, member=args.member, task=task,
                        guard=node_guard() if args.guard else None, metas=metas,
                        progress=lambda s: print(s, flush=True), **planner)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "results.json").write_text(json.dumps(ev.to_json(), indent=1))
    (args.out / "results.md").write_text(ev.report() + "\n")
    ev.figure(args.out / "errors.png")
    print(ev.report())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
