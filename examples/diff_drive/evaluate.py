"""Does the learned model dock the example robot better than its base model? A closed-loop evaluation under the
generic MPC of ``system.yaml``'s ``mpc:`` section (docs/your_robot.md, "Evaluate it").

    ./dev python examples/diff_drive/evaluate.py --seeds 3 --starts 30 --steps 600 --dock-steps 900 \
        --pose-eps 0.0005 --max-iter 1 -o runs/dd_eval

The task (headroom first: on the flat floor and from anywhere in the arena the oracle does not dock better than
f_hat, see docs/your_robot.md): the last stretch of the docking, from rest 0.7-1.1 m in front of the dock, straight
through the wet patch, which here also slopes down away from the dock (``dynamics.RAMP_SLIDE``: the base slides
back at up to 0.15 m/s whatever its wheels do; f_hat knows neither the slip nor the slide). The error is the
distance of the last state from the dock (x, y, v, w; ``saml_ros.experiments.robot_eval``).

Trains ``--seeds`` residual models (the file's 32-32 network and spec, one training seed and one data set each) on
what the learner would collect (:func:`dataset`): transitions of this robot's simulator while ``wander.py`` drives
(random starts, half of them in the dock approach, random commands held 0.1-1 s, a fifth of them stops), docking
runs under the MPC with f_hat, and (``--rounds 2``, the default) docking runs under the MPC with the first model,
then retrains on all of it: the online learner's loop, where the robot spends its time at the dock (``--dock-steps``
per run: 900 steps of 20 ms are about 6 s of approach and 12 s at rest at the dock). ``--pose-eps`` adds a
constraint on the pose fields in the dock approach to the file's spec (:func:`with_pose_constraint`). Each model must
pass the MPC node's checkpoint acceptance, then flies inside the guard the node runs by default (live monitor with
roll back: ``robot_eval.node_guard``, its margin scaled by the model's data as a checkpoint's evidence would) from its own ``--starts`` starts (nested in the seed, other starts than the
training runs') beside the base model f_hat and the oracle (the same planner on the true dynamics,
``dynamics.true_step_on_ramp``) for ``--steps`` steps of 20 ms, with the planner options of the file's ``mpc:``
section (``--max-iter 1``: every planner, docking runs included, takes one SQP step per control step, the real-time
iteration); the statistics use the seed as the unit; results.md and results.json go to ``-o``.

``--ensemble N``: each learned model is an ensemble of N networks (one training pass, different initialisations),
and every planner with a learned model (docking runs and evaluation) plans the members' mean (the generic planner's
solver option ``ensemble: mean``, docs/mpc.md).

``--task FILE`` plans (docking runs and evaluation) and scores another ``mpc:`` mapping than the file's, e.g.
``dock_task.yaml`` (a docking controller's cost, docs/your_robot.md); ``--horizon`` sets every planner's steps;
``--trajectories`` records every episode (trajectories.png, trajectories.npz); results.md ends with the last state's
mean error per field.

``--diagnose``: instead, the measurements behind this set-up for one seed: the one-step error of f_hat and of the
learned model at the dock (held at rest against the slide) beside the slide's own step, its mean (bias) per field,
the 20-step (horizon) errors driving straight and weaving (:func:`horizon_errors`) and on held-out docking runs
under the planner with the model (:func:`kstep_errors`), how many training transitions are near the dock at rest,
and for an ensemble its mean against each member planned alone in closed loop (:func:`members_alone`, ``--starts``).
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import json
import math
import sys
import time
from pathlib import Path

import numpy as np
import torch

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
import dynamics  # noqa: E402


def transitions(n: int, seed: int, slide: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``n`` transitions of the simulator at 20 ms while a wander node drives (the target's yaw unwrapped relative to
    the state, as the learner pairs an angle field)."""
    rng = np.random.default_rng(seed)
    xs: list[np.ndarray] = []
    us: list[np.ndarray] = []
    ys: list[np.ndarray] = []
    while len(xs) < n:
        if rng.random() < 0.5:
            start = (rng.uniform(0.7, 1.9), rng.uniform(-0.5, 0.5))
        else:
            start = (rng.uniform(-2.0, 2.0), rng.uniform(-2.0, 2.0))
        r = dynamics.DiffDrive(*start, rng.uniform(-math.pi, math.pi), slide=slide)
        for _ in range(int(rng.integers(2, 10))):
            # a fifth of the commands stop the robot: a robot's log has it standing still too (at its dock)
            u = np.zeros(2) if rng.random() < 0.2 else rng.uniform([-0.5, -1.5], [0.5, 1.5])
            for _ in range(int(rng.integers(5, 50))):
                x = r.state()
                r.step(u, 0.02)
                xs.append(x)
                us.append(u)
                ys.append(_paired(x, r.state()))
    return np.array(xs[:n]), np.array(us[:n]), np.array(ys[:n])


def _paired(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    y = y.copy()
    y[2] = x[2] + (y[2] - x[2] + math.pi) % (2 * math.pi) - math.pi
    return y


def docking_runs(system: object, model: object, runs: int, steps: int, seed: int,
                 explore: float = 0.1, max_iter: int | None = None, ensemble: str | None = None,
                 task: object = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Transitions of ``runs`` docking runs (starts of :func:`dynamics.sample_approach_starts` from ``seed``, not the
    evaluation's) under the file's MPC (or ``task``'s) planning with ``model`` (None: f_hat), ``steps`` steps each;
    with probability ``explore`` per step an operator's nudge (the plan's command plus noise, held 1-14 steps)."""
    from saml_ros.core.mpc.generic import GenericSQP

    rng = np.random.default_rng(seed)
    ctrl = GenericSQP(system, model, max_iter=max_iter, ensemble=ensemble, task=task)  # type: ignore[arg-type]
    xs: list[np.ndarray] = []
    us: list[np.ndarray] = []
    ys: list[np.ndarray] = []
    for x0 in dynamics.sample_approach_starts(runs, rng):
        ctrl.reset()
        sim = dynamics.make_robot_on_ramp(x0)
        held, hold = np.zeros(2), 0
        for _ in range(steps):
            x = sim.state()
            u = ctrl.solve(x).u
            if hold > 0:
                u, hold = held, hold - 1
            elif rng.random() < explore:
                held = np.clip(u + rng.normal(0.0, [0.1, 0.3]), [-0.5, -1.5], [0.5, 1.5])
                u, hold = held, int(rng.integers(0, 14))
            sim.step(u, 0.02)
            xs.append(x)
            us.append(u)
            ys.append(_paired(x, sim.state()))
    return np.array(xs), np.array(us), np.array(ys)


def with_pose_constraint(spec: dict, eps: float) -> dict:
    """The file's spec plus, for ``eps > 0``, a constraint on the pose fields in the dock approach (the file's
    ``dock_approach`` box): mean ``||(x, y, yaw) error||`` <= ``eps`` (m, rad per step), what the planner's
    progress along the approach turns on."""
    if eps <= 0:
        return spec
    spec = copy.deepcopy(spec)
    spec["constraints"].append({"name": "approach_pose", "loss": "l2", "fields": ["x", "y", "yaw"],
                                "region": {"box": {"x.x": [0.7, 1.9], "x.y": [-0.5, 0.5]}}, "eps": eps,
                                "mean": "conditional"})
    return spec


def train(system: object, spec: object, x: np.ndarray, u: np.ndarray, y: np.ndarray, seed: int,
          epochs: int, members: int = 1) -> object:
    """A residual model of the file's network on ``(x, u, y)`` with the file's spec (float64 for planning); an
    ensemble of ``members`` networks (independent initialisations, one pass) for ``members > 1``."""
    from saml_ros.core.model.network import DynamicsModel
    from saml_ros.core.training import PrimalDualTrainer, TrainConfig, Transitions

    model = DynamicsModel(system, tuple(system.paper_hidden), "residual", n_models=members,  # type: ignore[attr-defined]
                          seed=seed)
    model.fit_normalization(x, u, y)
    trainer = PrimalDualTrainer(model, spec, TrainConfig.paper(epochs=epochs, batch_size=256, primal_lr=3e-3,
                                                               seed=seed))
    trainer.fit(Transitions(model, spec, x, u, y))
    return model.double()


def dataset_and_model(system: object, spec: object, seed: int, args: argparse.Namespace,
                      log: object = print) -> tuple[object, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Round 1: wander transitions + docking runs under f_hat -> model; each further round (``--rounds``) adds
    docking runs under the newest model and retrains on everything (the online learner's loop)."""
    parts = [transitions(args.transitions, 100 + seed, dynamics.RAMP_SLIDE)]
    model = None
    for r in range(args.rounds):
        if args.dock_runs:
            parts.append(docking_runs(system, model, args.dock_runs, args.dock_steps, 500 + 10 * seed + r,
                                      max_iter=args.max_iter, ensemble=_ensemble_option(args),
                                      task=getattr(args, "task_obj", None)))
        x, u, y = (np.concatenate([p[i] for p in parts]) for i in range(3))
        model = train(system, spec, x, u, y, seed, args.epochs, getattr(args, "ensemble", 1))
        log(f"seed {seed} round {r + 1}: {len(x)} transitions")  # type: ignore[operator]
    return model, (x, u, y)


def _ensemble_option(args: argparse.Namespace) -> str | None:
    """The planner's ``ensemble`` solver option for ``--ensemble``: the members' mean for an ensemble."""
    return "mean" if getattr(args, "ensemble", 1) > 1 else None


def _predict(model: object) -> object:
    """``(x, u) -> next x`` of ``model`` as the planner predicts: an ensemble by the mean of its members."""
    n = int(getattr(model, "n_models", 1))

    def predict(x: np.ndarray, u: np.ndarray) -> np.ndarray:
        return np.mean([model.predict_np(x, u, i) for i in range(n)], axis=0)  # type: ignore[attr-defined]

    return predict


def diagnose(system: object, model: object, data: tuple[np.ndarray, np.ndarray, np.ndarray],
             **planner: object) -> str:
    """The measurements behind the set-up (module docstring, ``--diagnose``) as text."""
    rng = np.random.default_rng(5)
    rows = []
    for _ in range(200):  # the robot near the dock, held by a forward command against the slide for 0.6 s
        x0 = np.array([1.5 + rng.normal(0, 0.02), rng.normal(0, 0.01), rng.normal(0, 0.05), 0.0, 0.0])
        sim = dynamics.make_robot_on_ramp(x0)
        u = np.array([rng.uniform(0.1, 0.2), rng.normal(0, 0.02)])
        for _ in range(30):
            sim.step(u, 0.02)
        x = sim.state()
        sim.step(u, 0.02)
        rows.append((x, u, _paired(x, sim.state())))
    xs, us, ys = (np.array([r[i] for r in rows]) for i in range(3))
    base = system.base_step_np(xs, us)  # type: ignore[attr-defined]
    learned = _predict(model)(xs, us)  # type: ignore[operator]
    slide = np.mean([dynamics.slide_speed(float(a[0]), float(a[1]), dynamics.RAMP_SLIDE) for a in xs]) * 0.02
    lines = ["one-step error at the dock, held at rest against the slide (200 states; fields x, y (mm), yaw (mrad), "
             "v (mm/s), w (mrad/s)):",
             f"  the slide's own step (slide speed x 20 ms): {1e3 * slide:.3f} mm"]
    for label, pred in (("f_hat", base), ("learned", learned)):
        e = pred - ys
        lines.append(f"  {label:8s} mean |error| {np.round(1e3 * np.abs(e).mean(0), 4).tolist()}  "
                     f"mean error (bias) {np.round(1e3 * e.mean(0), 4).tolist()}")
    # the planner's model rounds only the network's Jacobians (solver_options.smoothing); rounding its values too
    # (what the planner did before) shifts every unit: the bias that costs at the dock
    from saml_ros.core.mpc.mlp_np import NumpyMLP

    mlp = NumpyMLP(model, 0)  # type: ignore[arg-type]
    eps2 = 0.2 ** 2
    h = xs @ mlp.w_x + us @ mlp.w_u + mlp.biases[0]
    for i in range(1, len(mlp.weights)):
        a = mlp.slopes[i - 1]
        h = (0.5 * (1 + a) * h + 0.5 * (1 - a) * np.sqrt(h * h + eps2)) @ mlp.weights[i] + mlp.biases[i]
    e = base + h - ys
    lines.append(f"  learned, values rounded by 0.2 too: mean error (bias) {np.round(1e3 * e.mean(0), 4).tolist()}")
    lines.append(horizon_errors(system, model))
    lines.append(kstep_errors(system, model, **planner))
    x, u, _ = data
    near = (np.abs(x[:, 0] - 1.5) < 0.1) & (np.abs(x[:, 1]) < 0.1) & (np.abs(x[:, 3]) < 0.05)
    lines.append(f"training transitions within 0.1 m of the dock at rest (|v| < 0.05 m/s): {int(near.sum())} of "
                 f"{len(x)}")
    return "\n".join(lines)


def kstep_errors(system: object, model: object, steps: int = 20, runs: int = 4, run_steps: int = 300,
                 seed: int = 7, **planner: object) -> str:
    """The ``steps``-step prediction error (the MPC's horizon, open loop under the commands the robot was really
    given) on held-out stretches: ``runs`` docking runs under the planner with ``model`` (new starts, no training
    run's), every window of ``steps`` steps of each; the error of the final position along the dock's axis (x:
    over-predicted progress is what the planner exploits) and across it, for f_hat, the model as planned (an
    ensemble by its mean) and each member, split by how much the window's commands turn (mean |w_cmd| below or
    above 0.5 rad/s: straight or weaving)."""
    from saml_ros.core.mpc.generic import GenericSQP

    ctrl = GenericSQP(system, model, **planner)  # type: ignore[arg-type]
    n_members = int(getattr(model, "n_models", 1))
    labels = ["f_hat", "model"] + ([f"member {i}" for i in range(n_members)] if n_members > 1 else [])
    preds = {"f_hat": system.base_step_np, "model": _predict(model)}  # type: ignore[attr-defined]
    for i in range(n_members if n_members > 1 else 0):
        preds[f"member {i}"] = lambda x, u, i=i: model.predict_np(x, u, i)  # type: ignore[attr-defined]
    errs: dict[str, dict[str, list[np.ndarray]]] = {k: {"straight": [], "weaving": []} for k in labels}
    for x0 in dynamics.sample_approach_starts(runs, np.random.default_rng(seed)):
        ctrl.reset()
        sim = dynamics.make_robot_on_ramp(x0)
        xs, us = [sim.state()], []
        for _ in range(run_steps):
            u = ctrl.solve(xs[-1]).u
            sim.step(u, 0.02)
            us.append(u)
            xs.append(sim.state())
        xa, ua = np.array(xs), np.array(us)
        starts = np.arange(0, run_steps - steps + 1)
        kind = np.where(np.array([np.abs(ua[i:i + steps, 1]).mean() for i in starts]) > 0.5, "weaving", "straight")
        for label in labels:
            x = xa[starts].copy()
            for t in range(steps):
                x = preds[label](x, ua[starts + t])  # type: ignore[operator]
            e = x[:, :2] - xa[starts + steps, :2]
            for k in ("straight", "weaving"):
                errs[label][k].append(e[kind == k])
    lines = [f"{steps}-step prediction error on held-out docking runs under the planner with this model ({runs} runs x "
             f"{run_steps} steps, every window; final x (along the dock's axis) and y, mm, model - true: mean "
             "(RMS)):"]
    for k in ("straight", "weaving"):
        n = sum(len(a) for a in errs["f_hat"][k])
        parts = []
        for label in labels:
            e = np.concatenate(errs[label][k]) if n else np.zeros((0, 2))
            if len(e):
                m, r = 1e3 * e.mean(0), 1e3 * np.sqrt((e ** 2).mean(0))
                parts.append(f"{label} x {m[0]:+.2f} ({r[0]:.2f}), y {m[1]:+.2f} ({r[1]:.2f})")
        lines.append(f"  {k} ({n} windows): " + ("; ".join(parts) if parts else "none"))
    return "\n".join(lines)


def members_alone(system: object, model: object, n_starts: int, steps: int, **planner: object) -> str:
    """An ensemble planned by its mean against each of its members planned alone, in closed loop inside the node's
    guard from the first seed's evaluation starts (``n_starts`` of them, ``steps`` steps): mean and worst final
    error and the episodes worse than f_hat's worst."""
    from saml_ros.experiments.robot_eval import evaluate_robot, node_guard

    n = int(getattr(model, "n_models", 1))
    models = {"mean": model} | {f"member {i}": model.member(i).double() for i in range(n)}  # type: ignore[attr-defined]
    starts = dynamics.sample_approach_starts(n_starts, np.random.default_rng(3000))
    ev = evaluate_robot(system, dynamics.make_robot_on_ramp, models, starts, steps, guard=node_guard(),
                        **{"ensemble": "mean", **planner})  # a member (an ensemble of one) is planned as itself
    b = ev.errors["base"]
    lines = [f"the ensemble's mean and each member planned alone, guarded, {n_starts} starts x {steps} steps (final "
             f"error, m): f_hat mean {b.mean():.4f} worst {b.max():.4f}"]
    for label in models:
        e = ev.errors[label]
        lines.append(f"  {label:9s} mean {e.mean():.4f} worst {e.max():.4f}, worse than f_hat's worst: "
                     f"{int((e > b.max()).sum())} of {len(e)}")
    return "\n".join(lines)


def horizon_errors(system: object, model: object, steps: int = 20) -> str:
    """The planner's view: the error (mm) of f_hat's and the learned model's ``steps``-step prediction (the MPC's
    horizon, open loop from the same state) of where the base ends, driving through the wet patch straight at full
    speed or weaving (full speed, yaw rate +-1.5 rad/s for half the horizon each): a model that over-predicts the
    progress of one manoeuvre more than another's is one the planner exploits (docs/your_robot.md, "Control it")."""
    rng = np.random.default_rng(6)
    x0s = np.column_stack([rng.uniform(0.6, 1.2, 100), rng.normal(0, 0.02, 100), rng.normal(0, 0.05, 100),
                           rng.uniform(0.1, 0.3, 100), np.zeros(100)])
    # the runaways' states (docs/your_robot.md): at the patch's edge, 0.4-0.6 rad off the axis, at speed
    turned = np.column_stack([rng.uniform(0.45, 0.8, 100), rng.normal(0, 0.03, 100),
                              rng.choice([-1.0, 1.0], 100) * rng.uniform(0.4, 0.6, 100), rng.uniform(0.25, 0.35, 100),
                              np.zeros(100)])
    out = [f"{steps}-step prediction error of the final x, y (mm; model - true; mean over 100 states in the patch "
           "heading along the axis, and of |y error| over 100 states 0.4-0.6 rad off it at the patch's edge):"]
    half = steps // 2
    plans = {"straight": [np.array([0.5, 0.0])] * steps,
             "weave": [np.array([0.5, 1.5])] * half + [np.array([0.5, -1.5])] * (steps - half)}
    for name, us in plans.items():
        err = {"f_hat": [], "learned": []}
        for x0 in x0s:
            sim = dynamics.make_robot_on_ramp(x0)
            for u in us:
                sim.step(u, 0.02)
            true = sim.state()
            for label, step in (("f_hat", system.base_step_np), ("learned", _predict(model))):  # type: ignore[attr-defined]
                x = x0[None].copy()
                for u in us:
                    x = step(x, u[None])
                err[label].append(x[0, :2] - true[:2])
        out.append(f"  {name:8s}: " + ", ".join(f"{k} x {1e3 * np.mean(v, 0)[0]:+.2f}, y {1e3 * np.mean(v, 0)[1]:+.2f}"
                                                  for k, v in err.items()))
    us = plans["straight"]
    err = {"f_hat": [], "learned": []}
    for x0 in turned:
        sim = dynamics.make_robot_on_ramp(x0)
        for u in us:
            sim.step(u, 0.02)
        for label, step in (("f_hat", system.base_step_np), ("learned", _predict(model))):  # type: ignore[attr-defined]
            x = x0[None].copy()
            for u in us:
                x = step(x, u[None])
            err[label].append(abs(x[0, 1] - sim.state()[1]))
    out.append("  straight, 0.4-0.6 rad off the axis: " + ", ".join(
        f"{k} mean |y error| {1e3 * np.mean(v):.2f}, worst {1e3 * np.max(v):.2f}" for k, v in err.items()))
    return "\n".join(out)


class Recorder:
    """The evaluation's simulator (``dynamics.make_robot_on_ramp``) recording every episode: ``episodes`` holds, in
    the order the evaluation flies them, ``(steps + 1, 7)`` arrays of each state and the command applied at it
    (NaN on the last state)."""

    def __init__(self) -> None:
        self.episodes: list[list[np.ndarray]] = []

    def __call__(self, x0: np.ndarray) -> object:
        sim = dynamics.make_robot_on_ramp(x0)
        rows = [np.r_[sim.state(), np.nan, np.nan]]
        self.episodes.append(rows)

        class Recording:
            def state(self) -> np.ndarray:
                return sim.state()

            def step(self, u: np.ndarray, dt: float) -> None:
                rows[-1][5:] = u
                sim.step(u, dt)
                rows.append(np.r_[sim.state(), np.nan, np.nan])

        return Recording()

    def by_controller(self, ev: object) -> dict[str, list[np.ndarray]]:
        """controller (``base``, ``oracle``, ``learned``: each seed's model) -> its episodes over all seeds, in the
        order ``evaluate_nested`` flies them (each seed's starts in turn, each start with every controller)."""
        out: dict[str, list[np.ndarray]] = {}
        it = iter(self.episodes)
        for label, run in ev.runs.items():  # type: ignore[attr-defined]
            labels = [k for k in run.errors if k != "pooled"]
            for i in range(len(run.starts)):
                for k in labels:
                    episode = np.array(next(it))
                    if not np.allclose(episode[-1, :5], run.finals[k][i]):
                        raise RuntimeError("the recorded episodes are not in the evaluation's order")
                    out.setdefault("learned" if k == label else k, []).append(episode)
        return out


def final_fields(ev: object, goal: np.ndarray) -> str:
    """What the final error consists of: per controller, the mean |last state - dock| per field (markdown)."""
    lines = ["| controller | x (mm) | y (mm) | yaw (mrad) | v (mm/s) | w (mrad/s) |", "|---|---|---|---|---|---|"]
    finals: dict[str, list[np.ndarray]] = {}
    for label, run in ev.runs.items():  # type: ignore[attr-defined]
        for k, f in run.finals.items():
            finals.setdefault("learned" if k == label else k, []).append(f)
    for k, fs in finals.items():
        e = 1e3 * np.abs(np.concatenate(fs) - goal).mean(0)
        lines.append(f"| {k} | " + " | ".join(f"{v:.2f}" for v in e) + " |")
    return "\n".join(lines)


def trajectory_figure(episodes: dict[str, list[np.ndarray]], path: Path, dt: float = 0.02) -> None:
    """``path`` (PNG): every episode's path (y against x), heading, yaw-rate command and distance from the dock
    over ``x, y, v, w`` against time, per controller."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(2, 2, figsize=(13, 8))
    colours = {"base": "C0", "oracle": "C2", "learned": "C3"}
    for label, eps in episodes.items():
        for j, e in enumerate(eps):
            t = dt * np.arange(len(e))
            ax[0, 0].plot(e[:, 0], 1e3 * e[:, 1], colours.get(label, "C1"), lw=0.7, label=label if j == 0 else None)
            ax[0, 1].plot(t, e[:, 2], colours.get(label, "C1"), lw=0.5)
            ax[1, 0].plot(t, e[:, 6], colours.get(label, "C1"), lw=0.4)
            ax[1, 1].plot(t, np.linalg.norm(e[:, [0, 1, 3, 4]] - [1.5, 0.0, 0.0, 0.0], axis=1), colours.get(label, "C1"),
                          lw=0.5)
    ax[0, 0].plot([1.5], [0.0], "k*", ms=10)
    ax[0, 0].set(xlabel="x (m)", ylabel="y (mm)", title="paths (dock: star)")
    ax[0, 0].legend()
    ax[0, 1].set(xlabel="t (s)", ylabel="yaw (rad)")
    ax[1, 0].set(xlabel="t (s)", ylabel="w_cmd (rad/s)")
    ax[1, 1].set(xlabel="t (s)", ylabel="distance from the dock (x, y, v, w)", yscale="log")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--seeds", type=int, default=3)
    p.add_argument("--starts", type=int, default=10, help="starts per seed")
    p.add_argument("--steps", type=int, default=500)
    p.add_argument("--transitions", type=int, default=30000, help="wander transitions per seed")
    p.add_argument("--dock-runs", type=int, default=16, help="docking runs per round (0: wander data only)")
    p.add_argument("--dock-steps", type=int, default=300, help="steps per docking run")
    p.add_argument("--rounds", type=int, default=2, help="training rounds (2: retrain with runs under the model)")
    p.add_argument("--epochs", type=int, default=200)
    p.add_argument("--pose-eps", type=float, default=0.0,
                   help="add a constraint on the pose fields in the dock approach (m per step; 0: the file's spec)")
    p.add_argument("--max-iter", type=int, default=None,
                   help="SQP iterations per control step of every planner (docking runs and evaluation); 1 = the "
                        "real-time iteration; default: the file's solver_options")
    p.add_argument("--unguarded", action="store_true", help="fly the bare planner (no guard, no acceptance)")
    p.add_argument("--ensemble", type=int, default=1,
                   help="members of each learned model (one training pass); > 1: every planner with a learned model "
                        "plans the members' mean (solver option ensemble: mean)")
    p.add_argument("--disagreement", type=float, default=0.0,
                   help="add cost.disagreement {x: W, y: W} (the ensemble members' variance of the one-step "
                        "prediction along the plan, docs/mpc.md) to the file's mpc: section for every planner "
                        "(0: the file's)")
    p.add_argument("--diagnose", action="store_true", help="the measurements behind the set-up (one seed)")
    p.add_argument("--save-models", action="store_true",
                   help="also write each trained model's weights to -o (seed<i>.pt, a torch state dict)")
    p.add_argument("--task", type=Path, help="a YAML file with an mpc: mapping to plan with (docking runs and "
                   "evaluation) and score instead of the file's, e.g. dock_task.yaml (here or a path)")
    p.add_argument("--horizon", type=int, default=None,
                   help="planning steps of every planner (docking runs and evaluation); default: the file's (20)")
    p.add_argument("--trajectories", action="store_true",
                   help="record every episode: trajectories.png and trajectories.npz in -o")
    p.add_argument("--start-seed", type=int, default=3000,
                   help="seed of the evaluation's starts (another than the default: a confirmation on new starts)")
    p.add_argument("-o", "--out", type=Path, required=True)
    args = p.parse_args()
    torch.set_num_threads(1)
    from saml_ros.core.model.evidence import DataEvidence
    from saml_ros.core.spec import ProblemSpec
    from saml_ros.experiments.robot_eval import acceptance, evaluate_nested, node_guard, task_from_file
    from saml_ros.user_code import load_system_file

    t0 = time.perf_counter()
    system = load_system_file(HERE / "system.yaml")
    spec = ProblemSpec.for_system(with_pose_constraint(system.paper_spec(), args.pose_eps), system)
    planner: dict[str, object] = {} if args.max_iter is None else {"max_iter": args.max_iter}
    task_path = args.task if args.task is None or args.task.exists() else HERE / args.task
    args.task_obj = task_from_file(system, task_path) if task_path else None
    if args.horizon is not None:
        from saml_ros.core.mpc.generic import system_task

        args.task_obj = dataclasses.replace(args.task_obj or system_task(system), horizon=args.horizon)
    if args.task_obj is not None:
        planner["task"] = args.task_obj
    if _ensemble_option(args):
        planner["ensemble"] = _ensemble_option(args)
    if args.disagreement > 0:  # on top of the planners' task (the file's mpc: section unless another is given)
        from saml_ros.core.mpc.generic import system_task

        task = getattr(args, "task_obj", None) or system_task(system)
        weights = np.zeros(system.state.size)
        weights[[list(system.state.names).index(f) for f in ("x", "y")]] = args.disagreement
        planner["task"] = args.task_obj = dataclasses.replace(task, w_disagreement=weights)
    args.out.mkdir(parents=True, exist_ok=True)
    if args.diagnose:
        model, data = dataset_and_model(system, spec, 0, args)
        text = diagnose(system, model, data, **planner)
        if int(getattr(model, "n_models", 1)) > 1:
            text += "\n" + members_alone(system, model, args.starts, args.steps, **planner)
        (args.out / "diagnose.txt").write_text(text + "\n")
        print(text)
        return 0
    models, metas = {}, {}
    for seed in range(args.seeds):
        model, (x, u, y) = dataset_and_model(system, spec, seed, args)
        refused = None if args.unguarded else acceptance(system, model, spec, x, u, y)
        if refused is not None:
            print(f"seed {seed}: the MPC node would refuse this model ({refused[0]}: {refused[1]}); it flies f_hat")
            model = None
        models[f"seed{seed}"] = model
        if args.save_models and model is not None:
            torch.save(model.state_dict(), args.out / f"seed{seed}.pt")  # type: ignore[attr-defined]
        # the checkpoint's evidence the learner would write: the guard's monitor scales its margin by it
        evidence = DataEvidence.from_data(system, x, u, y)
        metas[f"seed{seed}"] = {} if evidence is None else {"evidence": evidence.to_payload(tuple(system.target.names))[1]}
        print(f"trained seed {seed} ({time.perf_counter() - t0:.0f} s)", flush=True)
    recorder = Recorder() if args.trajectories else None
    ev = evaluate_nested(system, recorder or dynamics.make_robot_on_ramp, models,
                         dynamics.sample_approach_starts, args.starts, args.steps, seed=args.start_seed,
                         oracle=dynamics.true_step_on_ramp, guard=None if args.unguarded else node_guard(),
                         metas=metas, progress=lambda s: print(s, flush=True), **planner)
    goal = next(iter(ev.runs.values())).goal
    report = ev.report() + "\n\nfinal state, mean |last state - dock| per field:\n\n" + final_fields(ev, goal)
    (args.out / "results.json").write_text(json.dumps(ev.to_json(), indent=1))
    (args.out / "results.md").write_text(report + "\n")
    if recorder is not None:
        episodes = recorder.by_controller(ev)
        np.savez_compressed(args.out / "trajectories.npz", **{k: np.array(v) for k, v in episodes.items()})
        trajectory_figure(episodes, args.out / "trajectories.png")
    print(report)
    print(f"total {time.perf_counter() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
