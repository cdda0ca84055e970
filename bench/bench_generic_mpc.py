# ruff: noqa: E402  (the thread-count environment must be set before numpy is imported)
"""The generic MPC of a robot's system file: speed and how its derivatives are taken. ``./dev bench generic_mpc``
(``--quick``: fewer starts and steps).

The example differential-drive robot (examples/diff_drive: its ``mpc:`` section, horizon 20) with a 5-member
ensemble of 32-32 residual networks trained here on transitions of the robot's own simulator
(examples/diff_drive/dynamics.py: wheel lag, slip on the wet patch), on one core. Printed, all measured in this run:

1. **derivatives** (why the planner takes them as it does): CPU time per call, for the 20 steps of a plan, of f_hat's
   Jacobians from its CasADi form against torch autograd of the same f_hat; of phi's Jacobians from the network's
   own reverse pass (numpy) against CasADi (the network written symbolically, weights a parameter) and torch
   autograd; and of a rollout by one CasADi call for the horizon (the planner's) against numpy arrays step by step;
2. **closed loop** on the robot's simulator from the same starts: the guarded planner (ensemble disagreement, bounded
   residual, live monitor with roll back; each step's time includes the guard's checks and the monitor's scoring)
   with the file's solver options (up to 15 SQP iterations per step), with 2, and as a real-time iteration (one
   SQP step per control step from the shifted previous plan: ``solver_options: {max_iter: 1}``), and so
   planning the members' mean (``ensemble: mean``) instead of member 0; the planner
   unguarded (full and RTI), and f_hat alone: mean / p95 CPU time per step and SQP iterations, the rate by CPU
   time (the target: 100 Hz or more with the guard on), the guard's counters (the share of steps the learned model
   planned), and the distance to the dock at the end (15 s);
3. **identical problems**: states the unguarded ensemble planner visited, each solved from the warm start it had
   there (the previous plan) by the SQP with f_hat's CasADi form, the SQP with torch autograd for f_hat, and the
   IPOPT path (the whole NLP in CasADi): CPU time per solve and the plans' mean cost ratio.

4. **quadrotor parity**: the quadrotor demo's landing task (horizon 10, unsquared distance cost, height and tilt
   bounds, final attitude bound) planned with f_hat by the hand-written SQP with its C kernel and by the generic
   SQP (the task as a generic ``MPCTask``: ``cost.norm``, the attitude bound ``at: terminal``, the hand-written
   SQP's solver options; f_hat's array-namespace form, :mod:`saml_ros.systems.quadrotor.generic_form`), the generic
   one with its whole-horizon functions compiled (the task's ``compile: true``) and in CasADi's virtual machine (what
   runs without a compiler), then both with f_hat + the same learned 16-8 residual (trained as ``bench_mpc`` trains
   it); each flying the true dynamics (ground effect) from the same three starts for 50 steps: CPU time per solve,
   SQP iterations and the landing error (distance from (0, 0, min_height) at the end), their ratios (goal: within
   2x); where the generic SQP's time goes (rollouts, sensitivities, QP, cost and constraint rows, the rest); then
   identical problems (states the hand-written loop visited, each from the warm start it had there) solved by both
   to a tight tolerance: the largest differences of the whole plan, the first control and the predicted positions
   (goal 1e-3) and the exact cost ratio.

CPU time (``time.process_time``) is reported beside wall time: on a shared machine wall time also counts the other
processes' turns. The load average is printed.
"""

from __future__ import annotations

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse
import math
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]
EXAMPLE = REPO / "examples" / "diff_drive"


def _robot() -> Any:
    sys.path.insert(0, str(EXAMPLE))
    try:
        import dynamics  # type: ignore[import-not-found]
    finally:
        sys.path.remove(str(EXAMPLE))
    return dynamics


def transitions(n: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``n`` transitions of the robot's simulator at dt = 0.02 s: random starts (half of them in the dock approach,
    x in [0.7, 1.9], |y| <= 0.5), 2-10 commands held 0.1-1 s each, a fifth of them stops."""
    dyn = _robot()
    rng = np.random.default_rng(seed)
    xs: list[np.ndarray] = []
    us: list[np.ndarray] = []
    ys: list[np.ndarray] = []
    while len(xs) < n:
        if rng.random() < 0.5:
            start = (rng.uniform(0.7, 1.9), rng.uniform(-0.5, 0.5))
        else:
            start = (rng.uniform(-2.0, 2.0), rng.uniform(-2.0, 2.0))
        r = dyn.DiffDrive(*start, rng.uniform(-math.pi, math.pi))
        for _ in range(int(rng.integers(2, 10))):
            # a fifth of the commands stop the robot: a robot's log has it standing still too (at its dock)
            u = np.zeros(2) if rng.random() < 0.2 else rng.uniform([-0.5, -1.5], [0.5, 1.5])
            for _ in range(int(rng.integers(5, 50))):
                x = r.state()
                r.step(u, 0.02)
                y = r.state()
                y[2] = x[2] + (y[2] - x[2] + math.pi) % (2 * math.pi) - math.pi  # the target unwrapped (learner)
                xs.append(x)
                us.append(u)
                ys.append(y)
    return np.array(xs[:n]), np.array(us[:n]), np.array(ys[:n])


def train(system: Any, n: int, epochs: int, seed: int = 0) -> tuple[Any, float, np.ndarray]:
    """A 5-member ensemble of 32-32 residual networks on the file's spec; (model, seconds, residual bound)."""
    from saml_ros.core.model.network import DynamicsModel
    from saml_ros.core.spec import ProblemSpec
    from saml_ros.core.training import PrimalDualTrainer, TrainConfig, Transitions

    x, u, y = transitions(n, seed)
    model = DynamicsModel(system, (32, 32), "residual", n_models=5, seed=seed)
    model.fit_normalization(x, u, y)
    spec = ProblemSpec.for_system(system.paper_spec(), system)
    trainer = PrimalDualTrainer(model, spec, TrainConfig.paper(epochs=epochs, batch_size=256, primal_lr=3e-3,
                                                               seed=seed))
    t0 = time.perf_counter()
    trainer.fit(Transitions(model, spec, x, u, y))
    bound = 1.5 * np.abs(y - system.base_step_np(x, u)).max(0)
    secs = time.perf_counter() - t0
    model = model.double()
    xh, uh, yh = transitions(5000, seed + 1000)  # held out: other starts and commands
    dock = (xh[:, 0] >= 0.7) & (xh[:, 0] <= 1.9) & (np.abs(xh[:, 1]) <= 0.5)
    with torch.no_grad():
        pred = model(torch.from_numpy(xh), torch.from_numpy(uh)).numpy()  # (E, N, n)
    e_base = np.linalg.norm(system.base_step_np(xh, uh) - yh, axis=1)
    e_model = np.linalg.norm(pred - yh[None], axis=2)
    print(f"held-out one-step error (l2, {len(xh)} transitions, {int(dock.sum())} in the dock approach): f_hat "
          f"{e_base[dock].mean():.4f} in the dock approach / {e_base[~dock].mean():.4f} elsewhere; learned (mean over "
          f"members) {e_model[:, dock].mean():.4f} / {e_model[:, ~dock].mean():.4f}")
    return model, secs, bound


def cpu_per_call(fn: Any, reps: int) -> float:
    fn()
    t0 = time.process_time()
    for _ in range(reps):
        fn()
    return (time.process_time() - t0) / reps


def derivatives(system: Any, model: Any, quick: bool) -> None:
    import casadi as ca

    from saml_ros.core.mpc.generic.casadi_model import casadi_dynamics, mlp_theta
    from saml_ros.core.mpc.generic.dynamics import GenericDynamics, TorchBase, make_base
    from saml_ros.core.mpc.mlp_np import NumpyMLP

    reps = 200 if quick else 1000
    x, u = system.sample_inputs(20, np.random.default_rng(1))
    sym, tb = make_base(system), TorchBase(system.base_step, "torch")
    mlp = NumpyMLP(model, 0)
    f = casadi_dynamics(system, "residual", model.hidden, wrap=False)
    xs_, us_ = ca.SX.sym("x", 5), ca.SX.sym("u", 2)
    theta, bound = mlp_theta(model, 0), np.full(5, np.inf)
    y = f(xs_, us_, theta, bound)
    fj = ca.Function("fj", [xs_, us_], [y, ca.jacobian(y, xs_), ca.jacobian(y, us_)]).map(20)
    mt = model.member(0)

    def torch_jac() -> Any:
        from torch.autograd.functional import jacobian

        xt, ut = torch.from_numpy(x), torch.from_numpy(u)
        return jacobian(lambda a, b: mt(a, b)[0].sum(0), (xt, ut), vectorize=True)

    rows = [
        ("f_hat Jacobians, CasADi form (the planner's)", cpu_per_call(lambda: sym.step_jac(x, u), reps)),
        ("f_hat Jacobians, torch autograd", cpu_per_call(lambda: tb.step_jac(x, u), reps)),
        ("phi Jacobians, numpy reverse pass (the planner's)", cpu_per_call(lambda: mlp.forward_jac(x, u), reps)),
        ("f_hat + phi Jacobians, CasADi (weights a parameter)", cpu_per_call(lambda: fj(x.T, u.T), reps)),
        ("f_hat + phi Jacobians, torch autograd", cpu_per_call(torch_jac, max(20, reps // 10))),
    ]
    dyn = GenericDynamics(system, sym, model, 0)
    rows += [("rollout T=20, one CasADi call (the planner's)", cpu_per_call(lambda: dyn.rollout(x[0], u), reps)),
             ("rollout T=20, numpy arrays", cpu_per_call(lambda: _numpy_rollout(dyn, x[0], u), reps))]
    print("\n1. derivatives and rollouts for one plan (T = 20, batch of 20 steps), CPU time per call, one core")
    for name, sec in rows:
        print(f"  {name:55s} {1e6 * sec:9.1f} us")


def _numpy_rollout(dyn: Any, x0: np.ndarray, us: np.ndarray) -> np.ndarray:
    xs = [x0]
    for u in us:
        xs.append(dyn.step(xs[-1][None], u[None])[0])
    return np.array(xs)


def starts(k: int, seed: int) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(k):
        out.append(np.array([rng.uniform(-1.5, 0.5), rng.uniform(-1.2, 1.2), rng.uniform(-math.pi, math.pi), 0, 0]))
    return out


Visit = tuple[np.ndarray, np.ndarray, np.ndarray]  # a state and the previous plan (plan_u, plan_x) it warm-starts from


def closed_loops(system: Any, model: Any, bound: np.ndarray, k: int, steps: int) -> list[Visit]:
    """Part 2; returns the states the unguarded ensemble planner visited with the plan each solve warm-started from
    (part 3 re-solves them)."""
    from saml_ros.core.mpc.generic import GenericSQP
    from saml_ros.core.mpc.guard import RESIDUAL_BOUND_KEY, GuardConfig, make_guarded_controller
    from saml_ros.core.mpc.monitor import MonitorConfig

    dyn = _robot()
    cfg = GuardConfig(max_disagreement=0.02, bound_residual=True, rollback=True, monitor=MonitorConfig())
    meta = {"learner": {RESIDUAL_BOUND_KEY: bound.tolist()}}
    guarded_runs: dict[str, Any] = {}
    for name, opts in (("guarded", {}), ("guarded, 2 SQP steps", {"max_iter": 2}),
                       ("guarded, RTI (1 step)", {"max_iter": 1}),
                       ("guarded, RTI, mean", {"max_iter": 1, "ensemble": "mean"})):  # the members' mean planned
        guarded_runs[name] = make_guarded_controller(system, "fast", cfg, horizon=20, **opts)
        guarded_runs[name].set_model(model, 1, meta)
    plain, base = GenericSQP(system, model), GenericSQP(system)
    rti = GenericSQP(system, model, max_iter=1)
    planners: list[tuple[str, Any]] = [*guarded_runs.items(), ("ensemble, unguarded", plain),
                                       ("unguarded, RTI (1 step)", rti), ("f_hat alone", base)]
    runs: dict[str, dict[str, list[float]]] = {n: {"cpu": [], "wall": [], "err": [], "its": []} for n, _ in planners}
    visited: list[Visit] = []
    for x0 in starts(k, 7):
        ctrl: Any
        for name, ctrl in planners:
            ctrl.reset()
            robot = dyn.DiffDrive(*x0[:3])
            prev: tuple[np.ndarray, np.ndarray] | None = None
            for _ in range(steps):
                x = robot.state()
                warm = ctrl.warm_start_plan() if ctrl is plain else None
                t0, c0 = time.perf_counter(), time.process_time()
                if name in guarded_runs and prev is not None:
                    ctrl.observe(prev[0], prev[1], x)
                res = ctrl.solve(x)
                runs[name]["cpu"].append(time.process_time() - c0)
                runs[name]["wall"].append(time.perf_counter() - t0)
                runs[name]["its"].append(res.iterations)
                if warm is not None:
                    visited.append((x, *warm))
                prev = (x, res.u)
                robot.step(res.u, system.dt)
            s = robot.state()
            runs[name]["err"].append(math.hypot(s[0] - 1.5, s[1]))
    print(f"\n2. closed loop on the robot's simulator: {k} starts x {steps} steps ({steps * system.dt:g} s), one core")
    print(f"  {'planner':22s} {'cpu ms':>7s} {'p95':>7s} {'wall ms':>8s} {'iters':>6s} {'Hz (cpu)':>9s} "
          f"{'dock error m':>13s}")
    for name, r in runs.items():
        cpu, wall = np.array(r["cpu"]), np.array(r["wall"])
        print(f"  {name:22s} {1e3 * cpu.mean():7.2f} {1e3 * np.percentile(cpu, 95):7.2f} {1e3 * wall.mean():8.2f} "
              f"{np.mean(r['its']):6.2f} {1 / cpu.mean():9.0f} {np.mean(r['err']):8.3f} (max {np.max(r['err']):.3f})")
    for name, ctrl in guarded_runs.items():
        g = ctrl.counters
        print(f"  guard ({name}): {g['solves']} solves, {100 * (1 - g['solves_base'] / max(g['solves'], 1)):.0f} % planned "
              f"with the learned model, {g['fallbacks']} fallbacks to f_hat, {g['rollbacks']} roll backs, "
              f"{g['clipped']} plans clipped by the residual bound")
    for name in guarded_runs:
        hz = 1 / np.mean(runs[name]["cpu"])
        print(f"  target (guarded ensemble, >= 100 Hz by CPU time), {name}: {'yes' if hz >= 100 else 'NO'} ({hz:.0f} Hz; "
              f"{np.mean(runs['guarded']['cpu']) / np.mean(runs[name]['cpu']):.2f}x the full SQP's rate)")
    return visited


def identical(system: Any, model: Any, visited: list[Visit], n: int) -> None:
    from saml_ros.core.mpc.generic import GenericSQP
    from saml_ros.core.mpc.generic.dynamics import GenericDynamics, TorchBase
    from saml_ros.core.mpc.generic.nlp import CasadiNLP

    casadi_sqp, torch_sqp, ipopt = GenericSQP(system, model), GenericSQP(system, model), CasadiNLP(system, model)
    torch_sqp._base = TorchBase(system.base_step, "torch")  # the same planner, f_hat differentiated by autograd
    torch_sqp.dyn = GenericDynamics(system, torch_sqp._base, model, 0)
    rng = np.random.default_rng(3)
    picks = [visited[i] for i in rng.choice(len(visited), size=min(n, len(visited)), replace=False)]
    rows: dict[str, tuple[list[float], list[float]]] = {k: ([], []) for k in (
        "SQP, CasADi f_hat", "SQP, torch f_hat", "IPOPT (CasADi NLP)")}
    for x, warm_u, warm_x in picks:
        for name, ctrl in (("SQP, CasADi f_hat", casadi_sqp), ("SQP, torch f_hat", torch_sqp),
                           ("IPOPT (CasADi NLP)", ipopt)):
            ctrl.reset()
            ctrl.set_warm_start(warm_u, warm_x)  # the previous plan, as in the closed loop
            c0 = time.process_time()
            res = ctrl.solve(x)
            rows[name][0].append(time.process_time() - c0)
            # every plan's cost under the exact model (IPOPT plans on rounded kinks)
            rows[name][1].append(casadi_sqp.problem.cost(casadi_sqp.dyn.rollout(x, res.plan_u), res.plan_u,
                                                         casadi_sqp.problem.reference(x, None), warm_u[0]))
    ref = np.array(rows["SQP, CasADi f_hat"][1])
    print(f"\n3. identical problems: {len(picks)} states of part 2, each from the warm start it had there, one core")
    print(f"  {'path':22s} {'cpu ms':>8s} {'Hz (cpu)':>9s} {'cost / SQP-CasADi':>18s}")
    for name, (cpu, cost) in rows.items():
        print(f"  {name:22s} {1e3 * np.mean(cpu):8.2f} {1 / np.mean(cpu):9.0f} {np.mean(np.array(cost) / ref):18.4f}")


class _Timed:
    """Wraps callables to sum their CPU time per category (where a solve's time goes)."""

    def __init__(self) -> None:
        self.sec: dict[str, float] = {}

    def wrap(self, fn: Any, cat: str) -> Any:
        def timed(*a: Any, **k: Any) -> Any:
            c0 = time.process_time()
            try:
                return fn(*a, **k)
            finally:
                self.sec[cat] = self.sec.get(cat, 0.0) + time.process_time() - c0
        return timed


def _time_split(gen: Any, run: Any) -> dict[str, float]:
    """CPU seconds of ``run()`` spent in the generic SQP's rollouts, sensitivities, QPs, cost and constraint rows,
    and the rest (the SQP's own Python), by wrapping those calls (about 1 us each)."""
    import saml_ros.core.mpc.generic.sqp as gsqp

    timed = _Timed()
    dyn, pb = gen.dyn, gen.problem
    saved = [(dyn, n, getattr(dyn, n)) for n in ("rollout", "rollout_batch", "sensitivities", "step_jac")]
    saved += [(pb, n, getattr(pb, n)) for n in ("constraints", "constraint_jac", "cost")]
    saved += [(gsqp, n, getattr(gsqp, n)) for n in ("solve_qp", "solve_box_qp", "_condense")]
    cats = {"rollout": "rollouts", "rollout_batch": "rollouts", "sensitivities": "sensitivities",
            "step_jac": "sensitivities", "_condense": "sensitivities", "constraints": "cost and constraints",
            "constraint_jac": "cost and constraints", "cost": "cost and constraints", "solve_qp": "QP (DAQP)",
            "solve_box_qp": "QP (DAQP)"}
    for obj, name, fn in saved:
        setattr(obj, name, timed.wrap(fn, cats[name]))
    try:
        c0 = time.process_time()
        run()
        total = time.process_time() - c0
    finally:
        for obj, name, fn in saved:
            if obj is gsqp:
                setattr(obj, name, fn)
            elif name in vars(obj):
                delattr(obj, name)  # the instance's wrapper: the class's method shows again
    out = dict(timed.sec)
    out["the SQP's own Python (model assembly, loop)"] = total - sum(out.values())
    out["total"] = total
    return out


def quadrotor_parity(quick: bool) -> None:
    from saml_ros.core.mpc.factory import make_controller
    from saml_ros.core.mpc.generic import GenericSQP, codegen
    from saml_ros.systems.quadrotor.generic_form import quadrotor_base, quadrotor_generic_task
    from saml_ros.systems.quadrotor.model import Quadrotor

    system = Quadrotor()
    task = quadrotor_generic_task(system)
    hand: Any = make_controller(system, None, "fast", horizon=10, tilt_max=0.2)
    c0 = time.perf_counter()
    gen = GenericSQP(system, None, task=task, f_hat=quadrotor_base(system))  # the task's options: compiled
    built = time.perf_counter() - c0
    vm = GenericSQP(system, None, task=task, f_hat=quadrotor_base(system), compile=False)
    # a learned residual as bench_mpc trains it (16-8, the paper's spec): both planners plan with f_hat + phi
    from bench.bench_mpc import train_quick

    model, secs = train_quick(system, 3000 if quick else 10000, 20 if quick else 150)
    hand_l: Any = make_controller(system, model, "fast", horizon=10, tilt_max=0.2)
    gen_l = GenericSQP(system, model, task=task, f_hat=quadrotor_base(system))
    starts = [system.hover_state(p) for p in ((1.0, -1.0, 2.0), (-2.0, 0.5, 3.0), (0.5, 1.5, 1.0))]
    steps = 20 if quick else 50
    goal = np.array([0.0, 0.0, 0.2])
    names = ("hand-written", "generic", "generic, VM", "hand-written + phi", "generic + phi")
    ctrls = (hand, gen, vm, hand_l, gen_l)
    rows: dict[str, dict[str, list[float]]] = {k: {"cpu": [], "err": [], "its": []} for k in names}
    visited: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
    for x0 in starts:
        for name, ctrl in zip(names, ctrls, strict=True):
            ctrl.reset()
            x = x0.copy()
            for _ in range(steps):
                warm = ctrl.warm_start_plan() if ctrl is hand else None
                c0 = time.process_time()
                res = ctrl.solve(x, np.zeros(3))
                rows[name]["cpu"].append(time.process_time() - c0)
                rows[name]["its"].append(res.iterations)
                if warm is not None:
                    visited.append((x.copy(), *warm))
                x = system.true_step(torch.from_numpy(x[None]), torch.from_numpy(res.u[None]))[0].numpy()
            rows[name]["err"].append(float(np.linalg.norm(x[:3] - goal)))
    print(f"\n4. quadrotor parity: the demo's landing task (T = 10, tilt 0.2), f_hat, true plant; {len(starts)} starts x "
          f"{steps} steps, one core")
    print(f"  generic planner: {gen.describe()} (built in {built:.2f} s"
          f"{f', compiling {sum(codegen.COMPILE_SECONDS):.1f} s' if codegen.COMPILE_SECONDS else ', loaded'})")
    print(f"  + phi: a {list(model.hidden)} residual trained for {secs:.1f} s (bench_mpc's); generic: {gen_l.dyn.describe()}")
    print(f"  {'planner':18s} {'cpu ms':>7s} {'iters':>6s} {'landing error m (per start)':>30s}")
    for name, r in rows.items():
        print(f"  {name:18s} {1e3 * np.mean(r['cpu']):7.2f} {np.mean(r['its']):6.1f}   "
              f"{np.mean(r['err']):.4f} ({', '.join(f'{e:.4f}' for e in r['err'])})")
    for name, against in (("generic", "hand-written"), ("generic, VM", "hand-written"),
                          ("generic + phi", "hand-written + phi")):
        t_ratio = np.mean(rows[name]["cpu"]) / np.mean(rows[against]["cpu"])
        e_ratio = np.mean(rows[name]["err"]) / np.mean(rows[against]["err"])
        print(f"  ratios {name} / {against}: solve time {t_ratio:.2f}x, landing error {e_ratio:.2f}x "
              f"(goal: both within 2x: {'yes' if t_ratio <= 2 and e_ratio <= 2 else 'NO'})")

    def one_start() -> None:
        gen.reset()
        x = starts[0].copy()
        for _ in range(steps):
            res = gen.solve(x, np.zeros(3))
            x = system.base_step_np(x[None], res.u[None])[0]

    split = _time_split(gen, one_start)
    total = split.pop("total")
    print(f"  where the generic SQP's time goes (start 1, {steps} solves on f_hat, {1e3 * total / steps:.2f} ms CPU a "
          "solve): " + ", ".join(f"{k} {100 * v / total:.0f} %" for k, v in sorted(split.items(), key=lambda kv: -kv[1])))
    tight_hand: Any = make_controller(system, None, "fast", horizon=10, tilt_max=0.2, tol=1e-10, max_iter=200)
    tight_gen = GenericSQP(system, None, task=task, f_hat=quadrotor_base(system), max_iter=200, tol=1e-10, compile=False)
    rng = np.random.default_rng(4)
    picks = [visited[i] for i in rng.choice(len(visited), size=min(10 if quick else 30, len(visited)), replace=False)]
    diffs, first, pos, costs = [], [], [], []
    for x, wu, wx in picks:
        plans = []
        for ctrl in (tight_hand, tight_gen):
            ctrl.reset()
            ctrl.set_warm_start(wu, wx)
            plans.append(ctrl.solve(x, np.zeros(3)))
        diffs.append(float(np.abs(plans[0].plan_u - plans[1].plan_u).max()))
        first.append(float(np.abs(plans[0].u - plans[1].u).max()))
        pos.append(float(np.abs(plans[0].plan_x[:, :3] - plans[1].plan_x[:, :3]).max()))
        pb = tight_gen.problem
        ref = pb.reference(x, np.zeros(3))
        c = [pb.cost(tight_gen.dyn.rollout(x, r.plan_u), r.plan_u, ref, None, exact=True) for r in plans]
        costs.append(c[1] / c[0])
    print(f"  identical problems ({len(picks)} visited states, tol 1e-10): exact cost generic / hand-written mean "
          f"{np.mean(costs):.5f} (min {np.min(costs):.5f}, max {np.max(costs):.5f})")
    for label, d, unit in (("whole plan U", diffs, "N"), ("first control u_0 (flown)", first, "N"),
                           ("predicted positions", pos, "m")):
        a = np.array(d)
        print(f"    largest difference, {label:26s}: median {np.median(a):.2e} {unit}, max {a.max():.2e} {unit} "
              f"({int((a <= 1e-3).sum())} of {len(a)} within 1e-3)")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="bench_generic_mpc", description=__doc__.split("\n")[0])
    p.add_argument("--quick", action="store_true", help="fewer starts, steps and training epochs")
    p.add_argument("--only", choices=("quadrotor",), help="run one part alone")
    p.add_argument("--starts", type=int, help="closed-loop starts of part 2 (default 6, --quick 2)")
    p.add_argument("--steps", type=int, help="steps per start in part 2 (default 750, --quick 150)")
    p.add_argument("--problems", type=int, help="identical problems of part 3 (default 40, --quick 10; 0 skips it)")
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    from saml_ros.user_code import load_system_file

    t_all = time.perf_counter()
    print(f"load average {os.getloadavg()[0]:.1f} (2 cores)")
    if args.only == "quadrotor":
        quadrotor_parity(args.quick)
        print(f"\nload average {os.getloadavg()[0]:.1f}; total {time.perf_counter() - t_all:.0f} s")
        return 0
    system = load_system_file(EXAMPLE / "system.yaml")
    model, secs, bound = train(system, 8000 if args.quick else 30000, 5 if args.quick else 100)
    print(f"trained a 5-member 32-32 residual ensemble for {secs:.0f} s")
    derivatives(system, model, args.quick)
    visited = closed_loops(system, model, bound, args.starts or (2 if args.quick else 6),
                           args.steps or (150 if args.quick else 750))
    problems = (10 if args.quick else 40) if args.problems is None else args.problems
    if problems:
        identical(system, model, visited, problems)
    quadrotor_parity(args.quick)
    print(f"\nload average {os.getloadavg()[0]:.1f}; total {time.perf_counter() - t_all:.0f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
