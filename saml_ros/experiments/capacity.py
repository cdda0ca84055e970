"""The capacity sweep (``./dev experiment capacity``): how large a learned model must be for the demo's landing, and
whether Sufficiently Accurate learning buys a smaller, faster one than Uniformly Accurate learning.

The paper's argument is finite capacity: a model that cannot be accurate everywhere should be accurate where the
task needs it. A real-time MPC has little capacity to give: every solve evaluates the network and its Jacobians
many times, so the net that runs at the control rate is small. This sweep measures it in the demo's world (the
quadrotor with ground effect and a wind field above the pad's shelter, :attr:`CapacitySettings.world`)
and on the demo's task, closed loop:

* **Data** (offline, one recording per seed): the demo's live loop replayed without ROS
  (:func:`record_flight`): ``data_time`` simulated seconds of 5 s landing episodes from the simulator's start
  sampler (seed = the training seed), flown by the demo's MPC on f_hat (what the live loop flies until its first
  checkpoint), on the simulator's true dynamics with its ground contact; transitions changed by ground contact are
  left out, as the simulator leaves out their ``applied_cmd``. Why offline: one online demo run trains one SA and one
  UA ensemble of one size in 3 minutes of this 2-core machine; the sweep trains ``2 x sizes x seeds`` ensembles.
  Why a recording per seed: the claim is about a training method, so each seed is an independent replication
  (its own data and initialisations).
* **Models**: for every net size, SA (the demo learner's spec: squared one-step error <= ``eps`` where
  pz <= 1.5 m) and UA (the same without the constraint), trained with the learner's recipe (``TrainConfig()``,
  batch 128) for ``epochs`` passes (about the updates of a demo run's learner) as ensembles of ``ensemble``
  members per seed; the **single net** of a seed is its ensemble's member 0 (trained alone, it would be the
  same net: members share nothing but the data). The checkpoint records the residual bound the guard clips to
  (1.5 x the largest residual in the seed's data, as the online learner records it).
* **Closed loop**: every model flies the demo's evaluation starts (``eval_starts`` from the simulator's sampler,
  the demo's seeds) with the demo's guard (ensembles: disagreement, bound, roll back, infeasible-plan fallback;
  single nets: the same without the disagreement check, which needs members; the MPC plans with member 0 in both,
  as the demo's, so an ensemble costs the solve nothing and differs from its single net only by the check), beside the base model f_hat and the
  oracle (the true dynamics in the same MPC) on the same starts. Reported per size, method and kind: the landing
  error (mean over the starts per seed, then a t interval over the seeds: starts are nested in seeds), the share of
  the oracle's headroom captured ((base - model) / (base - oracle) per seed, t interval over seeds), SA - UA with
  its seed-level interval and the verdict (:func:`saml_ros.experiments.headroom.verdict`), and the held-out
  one-step error inside and outside the region on a separate recording (seed ``heldout_seed``).
* **Speed**: the guarded MPC's CPU time per solve with the C kernel for every size and kind
  (:func:`time_solves`, all sizes interleaved in one pass, so the machine's load affects them alike).

Writes ``results.json``, ``results.md``, ``capacity.png`` (landing error against solve time) and the models.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from saml_ros.demo.landing import WORLDS
from saml_ros.experiments.common import (
    Timer,
    fmt,
    machine_info,
    md_table,
    progress_bar,
    quiet_trainer_warnings,
    single_threaded,
    write_results,
)
from saml_ros.experiments.headroom import Estimate, headroom, mean_ci, seed_test, verdict

#: the methods, as the demo names its learners
METHODS = ("SA", "UA")
#: the share of the oracle's headroom a model must capture to count as "enough" (the demo's default net follows it)
ENOUGH = 0.9


@dataclass
class CapacitySettings:
    """Sweep settings (defaults: the full sweep; :meth:`quick` for the test suite)."""

    sizes: tuple[tuple[int, ...], ...] = ((4, 4), (8, 8), (16, 8), (32, 32), (64, 64))
    #: training seeds: each its own recording and initialisations
    seeds: tuple[int, ...] = (0, 1, 2, 3, 4)
    #: members of each seed's ensemble (the demo learner's ``model.ensemble``); member 0 is the single net
    ensemble: int = 5
    #: what is flown: ``"single"`` (member 0, guarded without the disagreement check) and ``"ens"`` (the ensemble
    #: as the demo flies it: the MPC plans with member 0, the other members feed the guard's disagreement check)
    kinds: tuple[str, ...] = ("single", "ens")
    #: simulated seconds of recorded flight per seed (the demo's live loop: 180 s, 36 episodes)
    data_time: float = 180.0
    #: passes over a seed's recording (500 x about 14 minibatches of 128: about the updates of a demo learner)
    epochs: int = 500
    #: SA's bound on E[squared one-step error | pz <= 1.5 m] (the demo learner's, the paper's)
    eps: float = 0.001
    #: the demo's evaluation starts (standard: the simulator's sampler) and its run seed (0: ``./dev demo``'s)
    eval_starts: int = 30
    eval_seed: int = 0
    #: the held-out recording's seed and length (s), for the one-step errors
    heldout_seed: int = 1000
    heldout_time: float = 60.0
    #: starts of the timing pass (per size and kind, interleaved), each ``steps`` solves
    timing_starts: int = 3
    #: evaluation worker processes
    workers: int = 2
    #: world parameters over the demo's (``Quadrotor`` constructor overrides): a wind field of 3 m/s^2, wavelength
    #: 8 m, above the pad's shelter, beside the demo's ground effect (``{"wind": 0.0}``: the demo's world itself)
    world: dict[str, float] = field(default_factory=lambda: dict(WORLDS["wind"]))
    #: control steps per episode, recorded and evaluated (0: the demo's, 50 = 5 s)
    steps: int = 0
    #: the guard's constraint watch (:class:`saml_ros.core.mpc.monitor.MonitorConfig`: strikes, tolerance in m) over
    #: the demo's guard, where the watch is off; (2, 0.005) is what the sweep of docs/experiments.md flew with
    constraint_watch: tuple[int, float] = (2, 0.005)
    #: the guard's task check (:mod:`saml_ros.core.mpc.task_check`), on in the demo's guard: off here, as the sweep
    #: of docs/experiments.md flew (it predates the check)
    task_check: bool = False

    @classmethod
    def quick(cls, seeds: tuple[int, ...] = (0, 1)) -> CapacitySettings:
        """A pipeline check (about a minute): two sizes, 2 seeds of 2-member ensembles, 6 s of data in episodes of
        15 steps, 2 evaluation starts."""
        return cls(sizes=((4, 4), (8, 8)), seeds=seeds, ensemble=2, data_time=6.0, epochs=5, eval_starts=2,
                   heldout_time=3.0, timing_starts=1, workers=1, steps=15)


@dataclass
class Flight:
    """Recorded transitions ``x (N, 13)``, ``u (N, 4)``, ``y (N, 13)`` and how many steps ground contact changed."""

    x: np.ndarray
    u: np.ndarray
    y: np.ndarray
    contacts: int = 0
    episodes: int = 0
    #: row of each episode's first transition
    starts: list[int] = field(default_factory=list)


def demo_task_and_guard() -> tuple[Any, Any, float]:
    """The demo's landing task (in its world), its MPC guard and its episode length in s (from the bringup
    defaults the demo runs with)."""
    from saml_ros.demo.cli import demo_config
    from saml_ros.demo.evaluation import run_task_and_guard

    config = demo_config(0, 0.0)
    task, guard = run_task_and_guard(config)
    return task, guard, task.steps * task.system().dt


def record_flight(task: Any, seed: int, sim_time: float, progress: Any = None) -> Flight:
    """The demo's live loop without ROS (see the module docstring): episodes of ``task.steps`` steps from the
    simulator's start sampler (``seed``), the MPC on f_hat, the true dynamics with ground contact; ``sim_time`` s."""
    from saml_ros.core.mpc import make_controller
    from saml_ros.core.worlds.sim_core import FastStep
    from saml_ros.systems.quadrotor.world import ground_contact, quadrotor_start

    system = task.system()
    ctrl = make_controller(system, None, "fast", **task.mpc_options())
    step = FastStep(system)
    rng = np.random.default_rng(seed)
    n_steps = int(round(sim_time / system.dt))
    xs: list[np.ndarray] = []
    us: list[np.ndarray] = []
    ys: list[np.ndarray] = []
    contacts = episodes = 0
    first: list[int] = []
    k = 0
    while k < n_steps:
        x = quadrotor_start(system, rng)
        episodes += 1
        first.append(len(xs))
        ctrl.reset()
        for _ in range(task.steps):
            if k >= n_steps:
                break
            u = np.asarray(ctrl.solve(x, task.goal).u, dtype=np.float64)
            y = step(x, u)
            x_next, touched = ground_contact(y, task.landing_height)
            if touched:
                contacts += 1
            else:
                xs.append(x)
                us.append(u)
                ys.append(y)
            x = x_next
            k += 1
            if progress is not None:
                progress.update(1)
    return Flight(np.array(xs), np.array(us), np.array(ys), contacts, episodes, first)


def residual_bound(system: Any, flight: Flight) -> np.ndarray:
    """The per-field residual bound the online learner records for the guard (1.5 x the largest residual of the
    data, at least 1e-3), :meth:`saml_ros.core.online.learner.OnlineLearner.residual_bound`."""
    from saml_ros.core.online.learner import RESIDUAL_FLOOR, RESIDUAL_MARGIN

    resid = np.abs(flight.y - system.base_step_np(flight.x, flight.u))
    return np.maximum(RESIDUAL_MARGIN * resid.max(0), RESIDUAL_FLOOR)


def size_name(hidden: tuple[int, ...]) -> str:
    return "-".join(str(h) for h in hidden)


def arm_name(method: str, hidden: tuple[int, ...], kind: str, seed: int) -> str:
    """``"SA 16-8 ens s0"``: method, size, ``single`` or ``ens``, seed."""
    return f"{method} {size_name(hidden)} {kind} s{seed}"


def train_size(system: Any, spec: Any, flights: dict[int, Flight], hidden: tuple[int, ...], s: CapacitySettings,
               out: Path, method: str) -> dict[str, Any]:
    """Train one method's ensembles of one size for every seed as ONE ensemble (``seeds x ensemble`` members, a
    seed's members on its recording); save per seed the ensemble and its member 0 (the single net) as checkpoints
    under ``out/models/<method>_<size>/``. Returns ``{"paths": {(kind, seed): path}, "seconds": ...}``."""
    from saml_ros.core.model.checkpoint import CheckpointStore
    from saml_ros.core.training import TrainConfig, save_checkpoint
    from saml_ros.core.training.selection import take_trainer
    from saml_ros.offline.pipelines import train_models

    seeds = list(s.seeds)
    n = min(len(f.x) for f in flights.values())
    members = s.ensemble
    x = np.stack([flights[sd].x[:n] for sd in seeds for _ in range(members)])
    u = np.stack([flights[sd].u[:n] for sd in seeds for _ in range(members)])
    y = np.stack([flights[sd].y[:n] for sd in seeds for _ in range(members)])
    inits = [1000 * sd + m for sd in seeds for m in range(members)]
    config = TrainConfig(epochs=s.epochs, batch_size=128)
    with quiet_trainer_warnings():
        tm = train_models(system, spec, x, u, y, config, inits, hidden=hidden)
    paths: dict[tuple[str, int], str] = {}
    base = out / "models" / f"{method}_{size_name(hidden)}"
    for i, sd in enumerate(seeds):
        extra = {"learner": {"residual_bound": residual_bound(system, flights[sd]).tolist()}, "seed": sd,
                 "members": inits[i * members:(i + 1) * members]}
        for kind, idx in (("ens", list(range(i * members, (i + 1) * members))), ("single", [i * members])):
            if kind not in s.kinds:
                continue
            path, _ = save_checkpoint(CheckpointStore(base / f"{kind}_s{sd}"), take_trainer(tm.trainer, idx),
                                      extra=extra)
            paths[(kind, sd)] = str(path)
    return {"paths": paths, "seconds": tm.train_seconds, "transitions": n}


def heldout_errors(paths: dict[str, str], system: Any, flight: Flight) -> dict[str, dict[str, float]]:
    """Per checkpoint (name -> path): the squared one-step error of its member 0 on a held-out recording,
    inside (pz <= 1.5 m) and outside the region; also f_hat's under ``"base"``."""
    import torch

    from saml_ros.core.model.io import load_model

    inside = flight.x[:, 2] <= 1.5

    def split(err: np.ndarray) -> dict[str, float]:
        return {"inside": float(err[inside].mean()) if inside.any() else math.nan,
                "outside": float(err[~inside].mean()) if (~inside).any() else math.nan, "all": float(err.mean())}

    out = {"base": split(((system.base_step_np(flight.x, flight.u) - flight.y) ** 2).sum(-1))}
    for name, path in paths.items():
        model = load_model(path, expect=system).model
        with torch.no_grad():
            dt = model.in_mean.dtype
            pred = model(torch.as_tensor(flight.x, dtype=dt), torch.as_tensor(flight.u, dtype=dt))[0].double().numpy()
        out[name] = split(((pred - flight.y) ** 2).sum(-1))
    return out


def time_solves(task: Any, guard: Any, models: dict[str, str | None], episodes: list[np.ndarray],
                progress: Any = None) -> dict[str, dict[str, float]]:
    """CPU time per solve (ms) of the MPC with each model (name -> checkpoint path, guarded as the demo; None: f_hat
    alone; ``"oracle"``: the true dynamics) on the SAME states: each episode of ``episodes`` (``(steps, 13)`` states
    of a recorded flight) is solved state after state, warm-started from the previous solve as in the closed loop.
    The models take turns episode by episode (interleaved: the machine's load affects them alike). Returns per
    name: mean and median CPU ms per solve, mean SQP iterations, ms per iteration, the solves, and whether the C
    kernel solved them."""
    from saml_ros.core.model.io import load_model
    from saml_ros.core.mpc import make_controller
    from saml_ros.core.mpc.guard import make_guarded_controller

    system = task.system()
    ctrls: dict[str, Any] = {}
    for name, path in models.items():
        if path is None or path == "oracle":
            ctrls[name] = make_controller(system, "oracle" if path == "oracle" else None, "fast", **task.mpc_options())
        else:
            loaded = load_model(path, expect=system)
            ctrl = make_guarded_controller(system, "fast", guard, **task.mpc_options())
            ctrl.set_model(loaded.model, 1, loaded.meta)
            ctrls[name] = ctrl
    times: dict[str, list[float]] = {name: [] for name in models}
    iters: dict[str, list[int]] = {name: [] for name in models}
    native: dict[str, bool] = {}
    for states in episodes:
        for name, ctrl in ctrls.items():
            ctrl.reset()
            for x in states:
                t0 = time.process_time()
                res = ctrl.solve(x, task.goal)
                times[name].append(time.process_time() - t0)
                iters[name].append(int(res.iterations))
            inner = getattr(ctrl, "learned", ctrl)
            native[name] = getattr(inner, "native_reason", "n/a") is None
            if progress is not None:
                progress.update(1)
    out: dict[str, dict[str, float]] = {}
    for name, t in times.items():
        mean_ms, it = 1e3 * float(np.mean(t)), float(np.mean(iters[name]))
        out[name] = {"mean_ms": mean_ms, "median_ms": 1e3 * float(np.median(t)), "iterations": it,
                     "ms_per_iteration": mean_ms / it if it > 0 else math.nan, "solves": len(t),
                     "native": native.get(name, False)}
    return out


def _per_seed(res: dict[str, Any], names: list[str], metric: str) -> np.ndarray:
    """``(n_seeds, n_starts)`` of ``metric`` for the arms ``names`` (one per seed, in seed order)."""
    return np.stack([np.asarray(res[n].metrics[metric], dtype=float) for n in names])


@single_threaded
def run(settings: CapacitySettings, out: Path, progress: bool = True) -> dict[str, Any]:
    """The sweep (see the module docstring); writes ``results.json``, ``results.md``, ``capacity.png``."""
    from saml_ros.core.spec import ProblemSpec
    from saml_ros.demo.evaluation import Arm, evaluate_arms, evaluation_starts
    from saml_ros.demo.landing import TASK_METRIC

    s = settings
    timer = Timer()
    info = machine_info()
    out.mkdir(parents=True, exist_ok=True)
    task, guard, episode_s = demo_task_and_guard()
    guard = replace(guard, monitor=replace(guard.monitor, constraint_strikes=int(s.constraint_watch[0]),
                                           constraint_tol=float(s.constraint_watch[1])),
                    task=replace(guard.task, enabled=bool(s.task_check)))
    if s.world:
        task = replace(task, world=tuple(sorted({**dict(task.world), **s.world}.items())))
    if s.steps:
        task = replace(task, steps=s.steps)
    system = task.system()
    sa_spec = ProblemSpec.for_system(system.paper_spec(), system)
    sa_spec = ProblemSpec.for_system({**sa_spec.to_dict(), "constraints": [
        {**c, "eps": s.eps} for c in sa_spec.to_dict()["constraints"]]}, system)
    specs = {"SA": sa_spec, "UA": sa_spec.uniform()}

    steps = int(round(s.data_time / system.dt))
    bar = progress_bar(steps * len(s.seeds) + int(round(s.heldout_time / system.dt)), "capacity: recording", progress)
    with timer("recording"):
        flights = {sd: record_flight(task, sd, s.data_time, bar) for sd in s.seeds}
        heldout = record_flight(task, s.heldout_seed, s.heldout_time, bar)
    bar.close()

    bar = progress_bar(len(s.sizes) * len(METHODS), "capacity: training", progress)
    paths: dict[str, str] = {}
    training: dict[str, Any] = {}
    with timer("training"):
        for hidden in s.sizes:
            for method in METHODS:
                t = train_size(system, specs[method], flights, hidden, s, out, method)
                training[f"{method} {size_name(hidden)}"] = {"seconds": t["seconds"], "transitions": t["transitions"]}
                for (kind, sd), path in t["paths"].items():
                    paths[arm_name(method, hidden, kind, sd)] = path
                bar.update(1)
    bar.close()
    with timer("held-out errors"):
        errors = heldout_errors(paths, system, heldout)

    starts = evaluation_starts(system, s.eval_starts, 0, s.eval_seed)["standard"]
    arms = [Arm("base", "base"), Arm("oracle", "oracle")]
    arms += [Arm(name, path, guard) for name, path in paths.items()]
    bar = progress_bar(len(arms) * len(starts), "capacity: closed loop", progress)
    with timer("closed loop"):
        res = evaluate_arms(arms, task, starts, "fast", s.workers, progress=bar.update)
    bar.close()

    timing_models: dict[str, str | None] = {"f_hat": None}
    for hidden in s.sizes:
        for kind in s.kinds:
            timing_models[f"{size_name(hidden)} {kind}"] = paths[arm_name("SA", hidden, kind, s.seeds[0])]
    timing_models["oracle"] = "oracle"
    bounds = [*heldout.starts, len(heldout.x)]
    episodes = [heldout.x[a:b] for a, b in zip(bounds[:-1], bounds[1:], strict=False)][: s.timing_starts]
    episodes = [e for e in episodes if len(e)]
    bar = progress_bar(len(timing_models) * len(episodes), "capacity: solve times", progress)
    with timer("timing"):
        timing = time_solves(task, guard, timing_models, episodes, bar)
    bar.close()

    base = np.asarray(res["base"].metrics[TASK_METRIC], dtype=float)
    oracle = np.asarray(res["oracle"].metrics[TASK_METRIC], dtype=float)
    rows: list[dict[str, Any]] = []
    for hidden in s.sizes:
        for kind in s.kinds:
            names = {m: [arm_name(m, hidden, kind, sd) for sd in s.seeds] for m in METHODS}
            per = {m: _per_seed(res, names[m], TASK_METRIC) for m in METHODS}
            hr = headroom(base, oracle, per)
            test = seed_test(per["UA"], per["SA"])
            rows.append({
                "size": size_name(hidden), "hidden": list(hidden), "kind": kind,
                "landing": {m: mean_ci(per[m].mean(1)) for m in METHODS},
                "captured": {m: hr.shares[m] for m in METHODS},
                "per_seed_captured": hr.per_seed_shares,
                "sa_minus_ua": test.by_seed, "sa_vs_ua_relative": test.relative,
                "verdict": verdict(hr.enough, test.by_seed),
                "enough": {m: bool(hr.shares[m].value >= ENOUGH) for m in METHODS},
                "worst": {m: float(per[m].max()) for m in METHODS},
                "far": {m: int(np.sum(per[m] > 1.0)) for m in METHODS},
                "failed_solves": {m: float(_per_seed(res, names[m], "failed_solves").mean()) for m in METHODS},
                "guard": {m: _guard_sum(res, names[m]) for m in METHODS},
                "heldout": {m: {k: mean_ci([errors[n][k] for n in names[m]]) for k in ("inside", "outside")}
                            for m in METHODS},
                "solve_ms": timing[f"{size_name(hidden)} {kind}"],
            })
    hr_all = headroom(base, oracle)
    data: dict[str, Any] = {
        "settings": s.__dict__, "world": dict(task.world), "task": task.__dict__, "episode_s": episode_s,
        "guard": {"max_disagreement": guard.max_disagreement, "bound_residual": guard.bound_residual,
                  "rollback": guard.rollback, "infeasible": guard.infeasible},
        "data": {str(sd): {"transitions": len(f.x), "contacts": f.contacts, "episodes": f.episodes,
                           "inside": float(np.mean(f.x[:, 2] <= 1.5))} for sd, f in flights.items()},
        "heldout_data": {"transitions": len(heldout.x), "inside": float(np.mean(heldout.x[:, 2] <= 1.5))},
        "base": {"landing": float(base.mean()), "worst": float(base.max()), "per_start": base},
        "oracle": {"landing": float(oracle.mean()), "worst": float(oracle.max()), "per_start": oracle},
        "headroom": hr_all.headroom, "heldout_base": errors["base"], "solve_times": timing, "rows": rows,
        "per_start": {a: r.metrics[TASK_METRIC] for a, r in res.items()}, "training": training,
        "machine": info,
    }
    data["recommendation"] = recommend(rows)
    with timer("figure"):
        fig = plot_capacity(data, out / "capacity.png")
    data["figures"] = [fig.name]
    data["timing"] = timer.to_dict()
    write_results(out, markdown(data, s, timer), data)
    return data


def _guard_sum(res: dict[str, Any], names: list[str]) -> dict[str, float]:
    total: dict[str, float] = {}
    for n in names:
        for k, v in res[n].guard.items():
            total[k] = total.get(k, 0.0) + float(v)
    return total


def recommend(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """Per method and kind, the smallest net (fewest weights; the small nets' solve times differ by less than the
    timing noise) whose captured share of the headroom is >= ENOUGH, and its solve time beside the largest's."""
    out: dict[str, Any] = {}
    for kind in ("single", "ens"):
        mine = [r for r in rows if r["kind"] == kind]
        if not mine:
            continue
        largest = max(mine, key=lambda r: _n_params(r["hidden"]))
        for m in METHODS:
            ok = [r for r in mine if r["captured"][m].value >= ENOUGH]
            best = min(ok, key=lambda r: _n_params(r["hidden"])) if ok else None
            out[f"{m} {kind}"] = None if best is None else {
                "size": best["size"], "solve_ms": best["solve_ms"]["mean_ms"],
                "captured": best["captured"][m], "largest": largest["size"],
                "largest_solve_ms": largest["solve_ms"]["mean_ms"]}
    return out


def _pct(e: Estimate) -> str:
    return e.pct(0)


def markdown(data: dict[str, Any], s: CapacitySettings, timer: Timer) -> str:
    """The sweep's table and reading."""
    hr = data["headroom"]
    world = ", ".join(f"{k} = {v:g}" for k, v in data["world"].items()) or "the paper's (no second effect)"
    lines = [
        "# Capacity sweep: net size against landing error and solve time, SA vs UA (`./dev experiment capacity`)",
        "",
        f"World: {world}. Task: the demo's landing on the pad at {tuple(data['task']['pad'])} m, guarded as the demo "
        f"(disagreement {data['guard']['max_disagreement']:g} for ensembles, residual bound, roll back, infeasible-plan "
        f"fallback) plus the constraint watch ({s.constraint_watch[0]} strikes of {s.constraint_watch[1]:g} m; 0: off). "
        f"Data: per seed {s.data_time:g} s of the demo's loop on f_hat (seeds {list(s.seeds)}, "
        f"{np.mean([d['transitions'] for d in data['data'].values()]):.0f} transitions, "
        f"{100 * np.mean([d['inside'] for d in data['data'].values()]):.0f} % with pz <= 1.5 m); {s.epochs} epochs, "
        f"ensembles of {s.ensemble} (single = member 0). Closed loop: the demo's {s.eval_starts} standard evaluation "
        f"starts (run seed {s.eval_seed}), paired; landing error |p_T - pad| per seed = mean over the starts; "
        "intervals: 95 % t over seeds (starts nested in seeds).",
        "",
        f"Base model f_hat: {data['base']['landing']:.4f} m (worst {data['base']['worst']:.3f} m); oracle: "
        f"{data['oracle']['landing']:.4f} m; headroom (base - oracle) / base = {hr.pct()}.",
        "",
    ]
    header = ["size", "kind", "solve, ms CPU [iterations]", "SA landing (m)", "UA landing (m)", "SA captured", "UA captured",
              "SA − UA (m)", "verdict", "held-out error in / out of region, SA", "UA"]
    table = []
    for r in data["rows"]:
        d = r["sa_minus_ua"]
        ho = {m: f"{r['heldout'][m]['inside'].value:.1e} / {r['heldout'][m]['outside'].value:.1e}" for m in METHODS}
        table.append([r["size"], r["kind"], f"{r['solve_ms']['mean_ms']:.2f} [{r['solve_ms']['iterations']:.1f}]",
                      r["landing"]["SA"].text(4), r["landing"]["UA"].text(4), _pct(r["captured"]["SA"]),
                      _pct(r["captured"]["UA"]), f"{fmt(d.diff, 4)} [{fmt(d.ci_low, 4)}, {fmt(d.ci_high, 4)}]",
                      r["verdict"], ho["SA"], ho["UA"]])
    lines += [md_table(header, table), ""]
    lines += ["Verdict: *holds* when the seed-level interval of SA − UA lies below 0; *does not hold* otherwise.",
              f"f_hat's held-out error: {data['heldout_base']['inside']:.1e} inside / "
              f"{data['heldout_base']['outside']:.1e} outside the region. Solve time: the guarded MPC with the "
              f"C kernel (learned models guarded as the demo), CPU ms per solve on the same states: "
              f"{s.timing_starts} episodes of the held-out recording, solved state after state with warm starts, all "
              f"models interleaved; in brackets the mean SQP iterations per solve; f_hat alone {data['solve_times']['f_hat']['mean_ms']:.2f} ms, the oracle (numpy path) "
              f"{data['solve_times']['oracle']['mean_ms']:.2f} ms.", ""]
    lines.append("Smallest net capturing >= 90 % of the headroom:")
    for key, rec in data["recommendation"].items():
        if rec is None:
            lines.append(f"* {key}: none of the sizes")
        else:
            lines.append(f"* {key}: {rec['size']} ({rec['solve_ms']:.2f} ms per solve against "
                         f"{rec['largest_solve_ms']:.2f} ms for {rec['largest']}; captures {rec['captured'].pct(0)})")
    lines += ["", "![capacity](capacity.png)", "", timer.markdown(), ""]
    return "\n".join(lines)


def _n_params(hidden: list[int]) -> int:
    """Weights of a quadrotor residual net with these hidden sizes (17 inputs, 13 outputs): orders the sizes."""
    dims = [17, *hidden, 13]
    return sum(a * b + b for a, b in zip(dims[:-1], dims[1:], strict=False))


def plot_capacity(data: dict[str, Any], path: Path) -> Path:
    """Landing error against solve time: SA and UA curves (single nets solid, ensembles dashed) with their
    seed-level intervals, the oracle and f_hat as horizontal lines."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from saml_ros.offline.plots import save_figure

    fig, ax = plt.subplots(figsize=(7.5, 5.0))
    colors = {"SA": "tab:blue", "UA": "tab:gray"}
    floor = 1e-4  # intervals reaching below it (e.g. below 0) end there on the log axis
    for kind, ls, marker in (("single", "-", "o"), ("ens", "--", "s")):
        rows = sorted((r for r in data["rows"] if r["kind"] == kind), key=lambda r: _n_params(r["hidden"]))
        if not rows:
            continue
        t = np.array([r["solve_ms"]["mean_ms"] for r in rows])
        for i, m in enumerate(METHODS):
            est = [r["landing"][m] for r in rows]
            y = np.array([e.value for e in est])
            lo = np.array([e.ci_low for e in est])
            hi = np.array([e.ci_high for e in est])
            shift = t * (1.0 + 0.015 * (i - 0.5))  # SA and UA side by side at the same solve time
            lo = np.where(np.isfinite(lo), np.maximum(lo, floor), y)
            hi = np.where(np.isfinite(hi), hi, y)
            err = np.vstack((np.maximum(y - lo, 0.0), np.maximum(hi - y, 0.0)))
            label = f"{m}, {'single net' if kind == 'single' else 'ensemble'}"
            ax.errorbar(shift, y, yerr=err, color=colors[m], ls=ls, marker=marker, ms=5, capsize=3, label=label)
            if i == 0:
                for r, tx, ty in zip(rows, shift, y, strict=True):
                    ax.annotate(r["size"], (tx, ty), textcoords="offset points", xytext=(4, 6), fontsize=7)
    ax.axhline(data["base"]["landing"], color="tab:orange", ls=":", label="base model f_hat")
    ax.axhline(max(data["oracle"]["landing"], floor), color="tab:green", ls=":",
               label=f"oracle (true dynamics){' (below the axis)' if data['oracle']['landing'] < floor else ''}")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("guarded MPC solve time with the C kernel (ms CPU per solve; labels: net size)")
    ax.set_ylabel("landing error |p_T - pad| (m), mean over starts, 95 % CI over seeds")
    ax.set_title("capacity: landing error against solve time (demo task, demo guard)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    return save_figure(fig, path)

