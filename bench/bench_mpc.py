# ruff: noqa: E402  (the thread-count environment must be set before numpy is imported)
"""MPC solver speed and quality: ``./dev python -m bench.bench_mpc [--quick]``.

For each system, the fast solver and the SLSQP reference plan with the SAME learned model (a residual net of the
paper's size, trained here for a few seconds so that phi is not trivial), the same horizon and the same start
states, on one core (``torch.set_num_threads(1)``). Printed, all measured in this run:

1. **identical problems** (the solver comparison): the states the fast controller visits in closed loop on the
   true system, each solved by both solvers from the SAME warm start (the fast controller's previous plan;
   the paddle ball: cold, one-shot). Columns: mean wall-clock solve time, rate (Hz), mean CPU time, mean plan
   cost (the paper's objective under the model), solves whose plan violates a constraint ("infeasible";
   the quadrotor's avoidable violations only: ``pz_1`` is fixed by the current state), and the ratios
   fast / slsqp of the rate and of the mean cost.
2. **closed loop** (the 100 Hz target): the fast controller alone, warm-started, on the true system: mean, p95
   and max solve time, rate, and the closed-loop stage cost. The quadrotor also flies the same starts with the
   demo's guarded MPC (``quadrotor+guard``: a 5-member ensemble of the same training, ensemble disagreement 0.1,
   bounded residual, live monitor with roll back; each step's time includes the guard's checks and the monitor's
   scoring) and with the same ensemble unguarded (``quadrotor+ensemble``), start by start in turn; the ratio
   guarded / plain rate is printed.

Wall-clock times depend on what else runs on the machine; the ratios are measured back to back.
"""

from __future__ import annotations

import os

# one core: numpy's OpenBLAS would otherwise use a second thread for the larger matrix products
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from saml_ros.core.dynamics.system import System
from saml_ros.core.model.network import DynamicsModel
from saml_ros.core.mpc import LoopStep, MPCResult, closed_loop, make_controller
from saml_ros.core.mpc.shooting import ShootingMPC
from saml_ros.core.spec import ProblemSpec
from saml_ros.core.systems import get_system
from saml_ros.core.training import PrimalDualTrainer, TrainConfig, Transitions
from saml_ros.systems.paddle_ball.mpc import paddle_goal
from saml_ros.systems.quadrotor.model import Quadrotor


def train_quick(system: System, n: int, epochs: int, seed: int = 0) -> tuple[DynamicsModel, float]:
    """A residual model of the paper's size trained on the paper's spec for a few epochs; (model, seconds)."""
    rng = np.random.default_rng(seed)
    x, u, y = system.make_dataset(n, rng)
    model = DynamicsModel(system, seed=seed)
    model.fit_normalization(x, u, y)
    spec = ProblemSpec.for_system(system.paper_spec(), system)
    trainer = PrimalDualTrainer(model, spec, TrainConfig.paper(epochs=epochs, batch_size=128, primal_lr=3e-3, seed=seed))
    t0 = time.perf_counter()
    trainer.fit(Transitions(model, spec, x, u, y))
    return model, time.perf_counter() - t0


@dataclass
class Stats:
    wall: list[float] = field(default_factory=list)
    cpu: list[float] = field(default_factory=list)
    cost: list[float] = field(default_factory=list)
    feasible: list[bool] = field(default_factory=list)

    @property
    def infeasible(self) -> int:
        return len(self.feasible) - sum(self.feasible)

    def add(self, res: MPCResult, cpu: float) -> None:
        self.wall.append(res.solve_time)
        self.cpu.append(cpu)
        self.cost.append(res.cost)
        self.feasible.append(res.success or "unavoidable" in res.message)


def timed(solve: Callable[[], MPCResult]) -> tuple[MPCResult, float]:
    t0 = time.process_time()
    res = solve()
    return res, time.process_time() - t0


def shooting_problems(system: System, model: DynamicsModel, starts: list[np.ndarray], steps: int,
                      goal: Any = None) -> tuple[list[tuple[np.ndarray, Any]], dict[str, Any]]:
    """States (with the fast controller's warm start at that moment) along fast closed loops on the true
    system, and the closed-loop timing of those runs."""
    ctrl = make_controller(system, model, "fast")
    assert isinstance(ctrl, ShootingMPC)
    problems: list[tuple[np.ndarray, Any]] = []
    warm: list[Any] = [None]  # the plan the next solve starts from (the runner resets the controller first)

    def record(step: LoopStep) -> None:
        problems.append((step.x.copy(), None if step.index == 0 else warm[0]))
        warm[0] = ctrl.warm_start_plan()

    runs = [closed_loop(system, ctrl, x0, steps, goal, on_step=record) for x0 in starts]
    t = np.concatenate([r.solve_times for r in runs])
    return problems, {"mean": t.mean(), "p95": np.percentile(t, 95), "max": t.max(), "n": t.size,
                      "cpu": float(np.mean(np.concatenate([r.cpu_times for r in runs]))),
                      "stage": float(np.sum(np.concatenate([r.stage_costs for r in runs])) / len(starts))}


#: the fast solver with a tight tolerance: stops only when the undamped QP predicts less than 1e-5 (1 + merit)
PRECISE = {"tol": 1e-5, "max_iter": 40, "undamped_check": True}


def compare_shooting(system: System, model: DynamicsModel, problems: list[tuple[np.ndarray, Any]],
                     ref_every: int, goal: Any = None, precise: bool = False) -> dict[str, Stats]:
    """Every ``ref_every``-th problem solved by each solver from the same warm start. ``precise`` adds the
    fast solver with :data:`PRECISE` options as ``fast-precise``."""
    variants: dict[str, tuple[str, dict[str, Any]]] = {"fast": ("fast", {}), "slsqp": ("slsqp", {})}
    if precise:
        variants["fast-precise"] = ("fast", PRECISE)
    out = {name: Stats() for name in variants}
    ctrls = {name: make_controller(system, model, solver, **opts) for name, (solver, opts) in variants.items()}
    for i, (x, warm) in enumerate(problems):
        if i % ref_every:
            continue
        for name, ctrl in ctrls.items():
            assert isinstance(ctrl, ShootingMPC)
            ctrl.reset()
            if warm is not None:
                ctrl.set_warm_start(*warm)
            res, cpu = timed(lambda c=ctrl, x=x: c.solve(x, goal))  # type: ignore[misc]
            out[name].add(res, cpu)
    return out


def paddle_problems(n: int, seed: int) -> list[tuple[np.ndarray, Any]]:
    """The paper's evaluation distribution: targets in [-1, 1]^2, v_min ~ U[3, 4), v_max = v_min + U[1, 2]."""
    rng = np.random.default_rng(seed)
    problems = []
    for _ in range(n):
        x = np.array([rng.uniform(-1, 1), rng.uniform(-1, 1), 0.0, rng.uniform(-1, 1), rng.uniform(-1, 1),
                      rng.uniform(-6, -2)])
        vmin = rng.uniform(3.0, 4.0)
        problems.append((x, paddle_goal(target_xy=rng.uniform(-1, 1, 2), v_rel=(vmin, vmin + rng.uniform(1, 2)))))
    return problems


def compare_one_shot(system: System, model: DynamicsModel, problems: list[tuple[np.ndarray, Any]]) -> dict[str, Stats]:
    """Every (state, goal) problem solved cold by each solver."""
    out = {"fast": Stats(), "slsqp": Stats()}
    for name in out:
        ctrl = make_controller(system, model, name)
        for x, goal in problems:
            ctrl.reset()
            res, cpu = timed(lambda c=ctrl, x=x, g=goal: c.solve(x, g))  # type: ignore[misc]
            out[name].add(res, cpu)
    return out


def ratio_row(label: str, f: Stats, s: Stats) -> str:
    """fast / slsqp: rate ratios (wall, CPU), mean-cost ratios (all problems, both feasible), target met."""
    ratio_wall = np.mean(s.wall) / np.mean(f.wall)
    ratio_cpu = np.mean(s.cpu) / np.mean(f.cpu)
    cost_ratio = np.mean(f.cost) / np.mean(s.cost)
    # a plan that violates a constraint can undercut the cost: compare where both plans are feasible
    both = np.array(f.feasible) & np.array(s.feasible)
    cost_both = np.mean(np.array(f.cost)[both]) / np.mean(np.array(s.cost)[both])
    ok = "yes" if ratio_cpu >= 20 and cost_both <= 1.0 + 1e-9 else "NO"
    return f"{label:<25} {ratio_wall:>21.1f}x {ratio_cpu:>6.1f}x {cost_ratio:>26.4f} {cost_both:>14.4f}  {ok}"


def row(system: str, solver: str, s: Stats) -> str:
    wall, cpu = float(np.mean(s.wall)), float(np.mean(s.cpu))
    return (f"{system:<12} {solver:<12} {len(s.wall):>5} {1e3 * wall:>9.2f} {1 / wall:>9.1f} {1e3 * cpu:>9.2f} "
            f"{np.mean(s.cost):>10.4f} {s.infeasible:>6}")


def friction_starts(system: System, scale: float) -> list[np.ndarray]:
    """Carts at rest at positions ~ U[-2, 2] m (seed 0)."""
    rng = np.random.default_rng(0)
    return [np.array([p0, 0.0]) for p0 in rng.uniform(-2, 2, max(2, int(8 * scale)))]


def quadrotor_starts(system: System, scale: float) -> list[np.ndarray]:
    """Level hovering quadrotors at three fixed positions (m)."""
    assert isinstance(system, Quadrotor)
    starts = [system.hover_state(p0) for p0 in ((1.0, -1.0, 2.0), (-2.0, 0.5, 3.0), (0.5, 1.5, 1.0))]
    return starts[: max(1, int(3 * scale))]


@dataclass(frozen=True)
class Case:
    """How the bench measures one system: the quick model's training budget and the problems."""

    samples: int  #: training transitions of the quick model
    epochs: int  #: its epochs
    #: shooting MPC: (system, scale) -> closed-loop start states, steps per start, every how many-th visited state
    #: both solvers solve (full run, --quick), whether ``fast-precise`` joins, the rate target (Hz)
    starts: Callable[[System, float], list[np.ndarray]] | None = None
    steps: int = 0
    ref_every: tuple[int, int] = (1, 1)
    precise: bool = False
    target_hz: float | None = None
    guard: bool = False  #: also fly the starts with the demo's guarded MPC (quadrotor)
    #: one-shot MPC: (n, seed) -> (state, goal) problems
    problems: Callable[[int, int], list[tuple[np.ndarray, Any]]] | None = None


#: the bench's cases (a data table: the training budgets and start states of the measurements in docs/mpc.md)
CASES: dict[str, Case] = {
    "friction": Case(15000, 20, starts=friction_starts, steps=30),
    "quadrotor": Case(10000, 150, starts=quadrotor_starts, steps=50, ref_every=(3, 5), precise=True, target_hz=100.0,
                      guard=True),
    "paddle_ball": Case(10000, 10, problems=paddle_problems),
}
SYSTEMS = tuple(CASES)


def report(system: System, model: DynamicsModel, case: Case, results: dict[str, dict[str, Stats]],
           loops: dict[str, dict[str, Any]], starts: list[np.ndarray]) -> None:
    """Print the tables of one system's run (see the module docstring)."""
    name = system.name
    print("\n1. identical problems (same model, horizon, states and warm starts), one core")
    print(f"{'system':<12} {'solver':<12} {'n':>5} {'wall ms':>9} {'rate Hz':>9} {'cpu ms':>9} {'mean cost':>10} "
          f"{'infeas':>6}")
    for label, res in results.items():
        for solver in res:
            print(row(label, solver, res[solver]))
    print(f"\n{'system / solver':<25} {'rate fast/slsqp: wall':>22} {'cpu':>7} {'mean cost fast/slsqp: all':>26} "
          f"{'both feasible':>14}  target (cpu rate >= 20x, cost <= 1)")
    for label, res in results.items():
        for fast in (solver for solver in res if solver != "slsqp"):
            print(ratio_row(f"{label} / {fast}", res[fast], res["slsqp"]))

    if case.problems is not None:
        f, r = results[name]["fast"], results[name]["slsqp"]
        reach = np.array(r.cost) < 1e-3
        for label, sel in (("reachable", reach), ("unreachable", ~reach)):
            if sel.any():
                tf, tr = np.mean(np.array(f.wall)[sel]), np.mean(np.array(r.wall)[sel])
                print(f"{name} {label:<11} targets ({int(sel.sum())}): fast {1e3 * tf:.2f} ms, "
                      f"slsqp {1e3 * tr:.2f} ms, {tr / tf:.1f}x; mean cost fast {np.mean(np.array(f.cost)[sel]):.4f}, "
                      f"slsqp {np.mean(np.array(r.cost)[sel]):.4f}")

    if loops:
        print("\n2. fast controller in closed loop on the true system (warm-started), one core")
        print(f"{'system':<12} {'solves':>6} {'mean ms':>8} {'p95 ms':>8} {'max ms':>8} {'rate Hz':>8} {'cpu ms':>8} "
              f"{'stage cost':>11}")
    for label, loop in loops.items():
        print(f"{label:<12} {loop['n']:>6} {1e3 * loop['mean']:>8.2f} {1e3 * loop['p95']:>8.2f} "
              f"{1e3 * loop['max']:>8.2f} {1 / loop['mean']:>8.1f} {1e3 * loop['cpu']:>8.2f} {loop['stage']:>11.3f}")
    if case.target_hz is not None:
        loop_hz = 1 / loops[name]["mean"]
        print(f"{name} target >= {case.target_hz:.0f} Hz (mean solve <= {1e3 / case.target_hz:.0f} ms wall): "
              f"{'yes' if loop_hz >= case.target_hz else 'NO'} ({loop_hz:.0f} Hz wall, "
              f"{1 / loops[name]['cpu']:.0f} Hz by CPU time)")
        g, e = loops.get(f"{name}+guard"), loops.get(f"{name}+ensemble")
        if g is not None and e is not None:
            g_hz, e_hz = 1 / g["mean"], 1 / e["mean"]
            print(f"{name} with the guard on: {g_hz:.0f} Hz wall ({1 / g['cpu']:.0f} Hz by CPU time); the same "
                  f"ensemble unguarded {e_hz:.0f} Hz ({1 / e['cpu']:.0f} Hz by CPU time): guarded / plain rate "
                  f"{g_hz / e_hz:.2f} wall, {e['cpu'] / g['cpu']:.2f} CPU; target >= {case.target_hz:.0f} Hz: "
                  f"{'yes' if g_hz >= case.target_hz else 'NO'}; guard: {g['counters'].get('fallbacks', 0)} "
                  f"fallbacks, {g['counters'].get('rollbacks', 0)} roll backs in {g['n']} steps")
        out = closed_loop(system, make_controller(system, model), starts[0], case.steps)
        print(f"{name} landing from {starts[0][:3].tolist()}: final position "
              f"{np.round(out.xs[-1, :3], 3).tolist()}")


def guarded_loops(system: System, case: Case, starts: list[np.ndarray], seed: int) -> dict[str, dict[str, Any]]:
    """The starts flown (true system) with a 5-member ensemble trained like the quick model (its residual bound
    recorded as the online learner does), by the plain fast MPC (``+ensemble``) and by the demo's guarded MPC
    (``+guard``), alternating start by start so both see the same machine load; per step the wall / CPU time of
    the solve (guarded: + the monitor's scoring), and the guard's counters."""
    from saml_ros.core.mpc.guard import RESIDUAL_BOUND_KEY, GuardConfig, make_guarded_controller

    rng = np.random.default_rng(seed)
    x, u, y = system.make_dataset(case.samples, rng)
    model = DynamicsModel(system, n_models=5, seed=seed)
    model.fit_normalization(x, u, y)
    spec = ProblemSpec.for_system(system.paper_spec(), system)
    cfg = TrainConfig.paper(epochs=case.epochs, batch_size=128, primal_lr=3e-3, seed=seed)
    PrimalDualTrainer(model, spec, cfg).fit(Transitions(model, spec, x, u, y))
    bound = np.maximum(1.5 * np.abs(y - system.base_step_np(x, u)).max(0), 1e-3)
    guarded = make_guarded_controller(system, "fast", GuardConfig(max_disagreement=0.1, bound_residual=True,
                                                                  rollback=True))
    guarded.set_model(model, 1, {"learner": {RESIDUAL_BOUND_KEY: bound.tolist()}})
    plain = make_controller(system, model, "fast")
    times: dict[str, tuple[list[float], list[float]]] = {"+ensemble": ([], []), "+guard": ([], [])}
    stage = dict.fromkeys(times, 0.0)
    for x0 in starts:
        for label, ctrl in (("+ensemble", plain), ("+guard", guarded)):
            ctrl.reset()
            xk = np.array(x0, dtype=np.float64)
            wall, cpu = times[label]
            for _ in range(case.steps):
                t0, c0 = time.perf_counter(), time.process_time()
                res = ctrl.solve(xk)
                xn = system.true_step_np(xk, res.u)
                if ctrl is guarded:
                    guarded.observe(xk, res.u, xn)
                wall.append(time.perf_counter() - t0)
                cpu.append(time.process_time() - c0)
                stage[label] += float(ctrl.task.stage_costs(xn[None])[0])  # type: ignore[attr-defined]
                xk = xn
    out = {}
    for label, (wall, cpu) in times.items():
        t = np.array(wall)
        out[f"{system.name}{label}"] = {"mean": t.mean(), "p95": np.percentile(t, 95), "max": t.max(), "n": t.size,
                                        "cpu": float(np.mean(cpu)), "stage": stage[label] / len(starts)}
    out[f"{system.name}+guard"]["counters"] = dict(guarded.counters)
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="bench_mpc", description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true", help="fewer states (a smoke run, about a minute)")
    p.add_argument("--systems", nargs="+", choices=SYSTEMS, default=list(SYSTEMS), metavar="SYSTEM",
                   help=f"which systems to measure (default: all of {', '.join(SYSTEMS)})")
    p.add_argument("--model-seed", type=int, default=0, help="seed of the models the bench trains (default 0)")
    # the paddle solver's settings were chosen on seed 1 (40 problems) and two other sets: the default set is a
    # fresh one, and large, because the few out-of-reach targets (about 10 %) dominate the mean solve time
    p.add_argument("--paddle-seed", type=int, default=314159, help="seed of the paddle problem set (default 314159)")
    p.add_argument("--paddle-problems", type=int, default=None,
                   help="number of paddle problems (default 200; 40 with --quick)")
    args = p.parse_args(argv)
    if len(args.systems) > 1:
        # one process per system: measured back to back in one process, the paddle solver (plain Python floats)
        # ran about 35 % slower after the quadrotor's comparison, in CPU time too (cause not found); a robot
        # runs one system's controller per process
        rest = [a for a in (argv if argv is not None else sys.argv[1:]) if a not in args.systems and a != "--systems"]
        t0 = time.perf_counter()
        codes = [subprocess.run([sys.executable, "-m", "bench.bench_mpc", *rest, "--systems", name]).returncode
                 for name in args.systems]
        print(f"\nall systems: total {time.perf_counter() - t0:.0f} s (one process each)")
        return max(codes)
    name = args.systems[0]
    case = CASES[name]
    torch.set_num_threads(1)
    t_start = time.perf_counter()
    scale = 0.4 if args.quick else 1.0

    system = get_system(name)
    model, secs = train_quick(system, case.samples, case.epochs, seed=args.model_seed)
    print(f"trained {name} residual {list(model.hidden)} for {case.epochs} epochs in {secs:.1f} s")

    results: dict[str, dict[str, Stats]] = {}
    loops: dict[str, dict[str, Any]] = {}
    starts: list[np.ndarray] = []
    if case.starts is not None:
        starts = case.starts(system, scale)
        problems, loops[name] = shooting_problems(system, model, starts, case.steps)
        results[name] = compare_shooting(system, model, problems, ref_every=case.ref_every[args.quick],
                                         precise=case.precise)
        if case.guard:
            loops |= guarded_loops(system, case, starts, args.model_seed)
    if case.problems is not None:
        n_problems = args.paddle_problems or (40 if args.quick else 200)
        results[name] = compare_one_shot(system, model, case.problems(n_problems, args.paddle_seed))

    report(system, model, case, results, loops, starts)
    print(f"\ntotal {time.perf_counter() - t_start:.0f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
