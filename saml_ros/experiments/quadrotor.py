"""Quadrotor landing with ground effect (paper, "Quadrotor with ground effects").

Training: residual 16-8 PReLU nets on 10,000 states sampled as the paper (``Quadrotor.sample_inputs``),
Adam 1e-3 / 1e-4, the paper's 3000 epochs; Sufficiently Accurate = the paper spec (squared error, constraint
squared error <= 0.001 where pz <= 1.5 m, see docs/spec.md), Uniformly Accurate = the same without the
constraint. Several seeds train as one ensemble (one dataset and initialisation per seed).

Control: the paper's landing MPC (T = 10, 0 <= u <= 10 N, pz >= 0.2 m on every predicted state, |qw_T - 1| <=
0.05, cost sum_t ||p_t - 0||_2) from random starts (x, y ~ U[-2, 2] m, z ~ U[1, 3] m, level, at rest:
``saml_ros.core.worlds.sim_core.quadrotor_start``), run for ``steps`` steps on the TRUE system with the simulator's ground
contact (``saml_ros.core.worlds.sim_core.quadrotor_model``: the centre of mass cannot go below 0.1 m). The reported cost
is sum_{t=1..steps} ||p_t||_2 over the closed-loop positions.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from saml_ros.core.models import DynamicsModel
from saml_ros.core.mpc import ClosedLoopRun, MPCResult, closed_loop, make_controller
from saml_ros.core.systems.quadrotor import Quadrotor
from saml_ros.experiments.common import (
    PAIRED_HEADER,
    Timer,
    fmt,
    fmt_ms,
    machine_info,
    md_table,
    paired,
    progress_bar,
    save_models,
    single_threaded,
    train_paper_comparison,
    training_summary,
    write_results,
)
from saml_ros.experiments.plan_checks import PlanChecks
from saml_ros.offline.pipelines import Comparison
from saml_ros.offline.plots import plot_training_curves, save_figure

PAPER = {"mpc_cost": {"sufficient": "4.21 ± 1.88", "uniform": "4.55 ± 1.90"},
         "loss": {"sufficient": "6.52e-4", "uniform": "6.16e-4"},
         "constraint": {"sufficient": "1.00e-4", "uniform": "8.28e-4"}}
LABELS = {"uniform": "Uniformly Accurate", "sufficient": "Sufficiently Accurate", "base": "base model f_hat only"}
MIN_HEIGHT = 0.2
#: a landing whose final xy error exceeds this (m) missed the target
MISS_DISTANCE = 0.1


@dataclass
class QuadrotorSettings:
    """Experiment settings (defaults: the paper's training; MPC budget chosen for this machine)."""

    seeds: tuple[int, ...] = (0, 1, 2)
    n_train: int = 10000
    epochs: int = 3000
    n_test: int = 20000
    hidden: tuple[int, ...] = (16, 8)
    n_starts: int = 30
    steps: int = 50
    horizon: int = 10
    solver: str = "fast"
    #: the MPC runs with the models of the first ``mpc_seeds`` seeds
    mpc_seeds: int = 3
    #: also run the base model f_hat alone
    base: bool = True
    start_seed: int = 4242
    landing_height: float = 0.1

    @classmethod
    def quick(cls, seeds: tuple[int, ...] = (0,)) -> QuadrotorSettings:
        """Under a minute: 3000 samples, 40 epochs, 2 starts x 15 steps, no base-model run."""
        return cls(seeds=seeds, n_train=3000, epochs=40, n_test=5000, n_starts=2, steps=15, base=False)


def landing_starts(system: Quadrotor, n: int, seed: int) -> np.ndarray:
    """``(n, 13)`` level, motionless starts at x, y ~ U[-2, 2] m, z ~ U[1, 3] m (the simulator's sampler)."""
    from saml_ros.core.worlds.sim_core import quadrotor_start

    rng = np.random.default_rng(seed)
    return np.stack([quadrotor_start(system, rng) for _ in range(n)])


def plant(system: Quadrotor, landing_height: float) -> Callable[[np.ndarray, np.ndarray], np.ndarray]:
    """The simulated true system: ``true_step`` then the simulator's ground contact; ``(13,), (4,) -> (13,)``."""
    from saml_ros.core.worlds.sim_core import FastStep, quadrotor_model

    step = FastStep(system)
    model = quadrotor_model(system, landing_height)
    constrain = model.constrain
    assert constrain is not None

    def f(x: np.ndarray, u: np.ndarray) -> np.ndarray:
        return constrain(step(x, u))[0]

    return f


def height_violation(res: MPCResult) -> float:
    """Largest violation (m) of pz >= 0.2 m over the predicted states x_1..x_T of a plan (NaN: no prediction)."""
    pz = np.asarray(res.plan_x)[1:, 2]
    if not np.all(np.isfinite(pz)):
        return float("nan")
    return float(max(0.0, np.max(MIN_HEIGHT - pz)))


def rollout_metrics(ro: ClosedLoopRun) -> dict[str, float]:
    """Cost sum_{t>=1} ||p_t||, final distance to the target, final xy error, final height, time below 0.3 m."""
    p = ro.xs[:, 0:3]
    dist = np.linalg.norm(p[1:], axis=1)
    low = np.nonzero(p[:, 2] <= 0.3)[0]
    return {"cost": float(dist.sum()), "final_dist": float(dist[-1]),
            "final_xy": float(np.linalg.norm(p[-1, :2])), "final_z": float(p[-1, 2]),
            "steps_to_low": float(low[0]) if low.size else float("nan")}


def evaluate_controller(system: Quadrotor, model: DynamicsModel | None, s: QuadrotorSettings, x0s: np.ndarray,
                        bar: Any = None) -> dict[str, Any]:
    """Closed loops from every start with one model: metrics per start and merged plan checks."""
    ctrl = make_controller(system, model, s.solver, horizon=s.horizon)
    f = plant(system, s.landing_height)
    metrics: list[dict[str, float]] = []
    checks = PlanChecks()
    xs, times = [], []
    for x0 in x0s:
        ro = closed_loop(system, ctrl, x0, s.steps, goal=np.zeros(3), true_step=f,
                         on_step=checks.hook(system, height_violation))
        metrics.append(rollout_metrics(ro))
        xs.append(ro.xs)
        times.append(ro.solve_times)
        if bar is not None:
            bar.update(1)
    out: dict[str, Any] = {k: np.array([m[k] for m in metrics]) for k in metrics[0]}
    t = np.concatenate(times)
    out.update({"checks": checks, "xs": np.stack(xs), "solve_time_mean": float(t.mean()),
                "solve_time_max": float(t.max())})
    return out


def model_errors(cmp: Comparison, system: Quadrotor, n_test: int, seed: int = 10_000) -> dict[str, Any]:
    """Per member on a fresh test set: E[l], E[l I] (the paper's E[g I] row), E[l | I], in-region fraction."""
    import torch

    xt, ut, yt = system.make_dataset(n_test, np.random.default_rng(seed))
    inside = xt[:, 2] <= 1.5
    out: dict[str, Any] = {"frac_inside": float(inside.mean())}
    for label, tm in (("uniform", cmp.uniform), ("sufficient", cmp.sufficient)):
        with torch.no_grad():
            dt = tm.model.in_mean.dtype
            pred = tm.model(torch.as_tensor(xt, dtype=dt), torch.as_tensor(ut, dtype=dt)).double().numpy()
        err = ((pred - yt[None]) ** 2).sum(-1)  # (E, N) squared error over the 13 fields
        out[label] = {"loss": err.mean(1), "loss_times_indicator": (err * inside).mean(1),
                      "loss_given_region": err[:, inside].mean(1), "loss_outside": err[:, ~inside].mean(1)}
    base = ((system.base_step_np(xt, ut) - yt) ** 2).sum(-1)
    out["base"] = {"loss": float(base.mean()), "loss_times_indicator": float((base * inside).mean()),
                   "loss_given_region": float(base[inside].mean())}
    out["paired_by_seed"] = {k: paired(out["uniform"][k], out["sufficient"][k])
                             for k in ("loss", "loss_times_indicator", "loss_given_region")}
    return out


@single_threaded
def run(settings: QuadrotorSettings, out: Path, progress: bool = True) -> dict[str, Any]:
    """Train SA and UA, evaluate their errors and the landing MPC; write results and figures into ``out``.

    Runs single-threaded with subnormals flushed (:func:`~saml_ros.experiments.common.single_threaded`)."""
    s = settings
    timer = Timer()
    info = machine_info()
    system = Quadrotor()
    spec, cmp = train_paper_comparison(system, s.seeds, s.n_train, min(s.n_test, 10000), s.hidden, s.epochs, timer,
                                       progress)
    with timer("test errors"):
        errors = model_errors(cmp, system, s.n_test)
    x0s = landing_starts(system, s.n_starts, s.start_seed)
    k = min(s.mpc_seeds, len(s.seeds))
    bar = progress_bar((2 * k + int(s.base)) * len(x0s), f"quadrotor landing MPC ({s.solver})", progress)
    control: dict[str, Any] = {}
    with timer("mpc"):
        for label, tm in (("uniform", cmp.uniform), ("sufficient", cmp.sufficient)):
            per_seed = [evaluate_controller(system, tm.model.member(i), s, x0s, bar) for i in range(k)]
            control[label] = _stack(per_seed)
        if s.base:
            control["base"] = _stack([evaluate_controller(system, None, s, x0s, bar)])
    bar.close()
    pairs = {m: paired(control["uniform"][m], control["sufficient"][m])
             for m in ("cost", "final_dist", "final_xy", "final_z")}
    with timer("figures"):
        figs = [plot_landing(control, x0s, out / "quadrotor_landing.png"),
                plot_training_curves({"sufficient": cmp.sufficient.history, "uniform": cmp.uniform.history},
                                     out / "quadrotor_training_curves.png")]
    data = {"settings": s.__dict__, "spec": spec.to_dict(), "starts": x0s, "errors": errors,
            "models": save_models(out, {"sufficient": cmp.sufficient, "uniform": cmp.uniform}),
            "control": {k2: {m: v for m, v in c.items() if m != "xs"} for k2, c in control.items()},
            "paired_control": pairs,
            "training": training_summary(cmp),
            "figures": [f.name for f in figs], "timing": timer.to_dict(), "machine": info}
    write_results(out, markdown(data, s, timer), data)
    return data


def _stack(per_seed: list[dict[str, Any]]) -> dict[str, Any]:
    checks = PlanChecks()
    for r in per_seed:
        checks.merge(r["checks"])
    out: dict[str, Any] = {k: np.stack([r[k] for r in per_seed]) for k in per_seed[0]
                           if isinstance(per_seed[0][k], np.ndarray)}
    out["checks"] = checks
    out["solve_time_mean"] = float(np.mean([r["solve_time_mean"] for r in per_seed]))
    out["solve_time_max"] = float(np.max([r["solve_time_max"] for r in per_seed]))
    return out


def markdown(data: dict[str, Any], s: QuadrotorSettings, timer: Timer) -> str:
    e = data["errors"]
    lines = [
        "# Quadrotor landing with ground effect: Sufficiently vs Uniformly Accurate",
        "",
        f"Seeds {list(s.seeds)}; {s.n_train} training states per seed, {s.epochs} epochs, net {list(s.hidden)}; "
        f"test set {s.n_test} ({100 * e['frac_inside']:.1f}% with pz <= 1.5 m). MPC ({s.solver}): T = {s.horizon}, "
        f"{s.n_starts} starts, {s.steps} steps on the true system with ground contact at "
        f"{s.landing_height} m; models of the first {min(s.mpc_seeds, len(s.seeds))} seed(s).",
        "",
        "## Model errors on the test set (squared error over the 13 state fields)",
        "",
    ]
    rows = []
    for label in ("uniform", "sufficient"):
        r = e[label]
        rows.append([LABELS[label], fmt_ms(r["loss"], 3, True), fmt_ms(r["loss_times_indicator"], 3, True),
                     fmt_ms(r["loss_given_region"], 3, True), fmt_ms(r["loss_outside"], 3, True),
                     f"{PAPER['loss'][label]} / {PAPER['constraint'][label]}"])
    rows.append([LABELS["base"], fmt(e["base"]["loss"], 3, True), fmt(e["base"]["loss_times_indicator"], 3, True),
                 fmt(e["base"]["loss_given_region"], 3, True), "", ""])
    lines += [md_table(["model", "E[l]", "E[l I]", "E[l \\| pz <= 1.5]", "E[l \\| pz > 1.5]",
                        "paper E[l] / E[g I]"], rows), "", "Paired by seed (SA − UA):", "", PAIRED_HEADER]
    lines += [e["paired_by_seed"][k].row(k, 3, True) for k in ("loss", "loss_times_indicator", "loss_given_region")]
    lines += ["", "## Landing MPC on the true system", ""]
    rows = []
    for label in ("uniform", "sufficient", "base"):
        if label not in data["control"]:
            continue
        c = data["control"][label]
        ch = c["checks"]
        rows.append([LABELS[label], fmt_ms(c["cost"], 2), fmt(float(np.median(c["cost"])), 2),
                     fmt_ms(c["final_xy"], 3), f"{int(np.sum(c['final_xy'] > MISS_DISTANCE))}/{c['final_xy'].size}",
                     fmt_ms(c["final_z"], 3),
                     PAPER["mpc_cost"].get(label, ""), f"{1e3 * c['solve_time_mean']:.0f}",
                     f"{ch.unsuccessful}/{ch.solves}", f"{ch.max_u_violation:.1e}",
                     f"{ch.max_state_violation_success:.1e}"])
    lines += [md_table(["model", "Σ_t \\|p_t\\| (cost)", "median cost", "final xy error (m)",
                        f"final xy error > {MISS_DISTANCE} m", "final height (m)", "paper MPC cost",
                        "ms / solve", "unsuccessful solves", "max u bound violation",
                        "max height violation (successful plans)"], rows),
              "", "Paired by (seed, start) (SA − UA; negative = SA better):", "", PAIRED_HEADER]
    lines += [data["paired_control"][m].row(m, 3) for m in ("cost", "final_dist", "final_xy", "final_z")]
    lines += ["", "## Figures", ""] + [f"![{f}]({f})" for f in data["figures"]] + ["", timer.markdown(), ""]
    return "\n".join(lines)


def plot_landing(control: dict[str, Any], x0s: np.ndarray, path: Path) -> Path:
    """The first start's closed-loop trajectories (seed-0 models): 3D, x-z and y-z views; target = red dot."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    colors = {"uniform": "tab:gray", "sufficient": "tab:blue", "base": "tab:orange"}
    fig = plt.figure(figsize=(15, 4.6))
    ax3 = fig.add_subplot(1, 3, 1, projection="3d")
    axz = fig.add_subplot(1, 3, 2)
    ayz = fig.add_subplot(1, 3, 3)
    for label, c in control.items():
        p = c["xs"][0, 0][:, 0:3]
        kw: dict[str, Any] = {"color": colors[label], "ls": ":" if label != "sufficient" else "--", "marker": ".", "ms": 3}
        ax3.plot(p[:, 0], p[:, 1], p[:, 2], label=LABELS[label], **kw)
        axz.plot(p[:, 0], p[:, 2], label=LABELS[label], **kw)
        ayz.plot(p[:, 1], p[:, 2], **kw)
        for ax, (a, b) in ((axz, (0, 2)), (ayz, (1, 2))):
            ax.plot(p[-1, a], p[-1, b], "o", color=colors[label], ms=7)
    ax3.scatter([0], [0], [0], color="red", s=40)
    for ax, name in ((axz, "x"), (ayz, "y")):
        ax.plot(0, 0, "o", color="red", ms=8)
        ax.axhline(MIN_HEIGHT, color="k", lw=0.6, ls=":")
        ax.axhspan(0, 1.5, color="red", alpha=0.05)
        ax.set_xlabel(f"{name} (m)")
        ax.set_ylabel("z (m)")
    ax3.set_xlabel("x (m)")
    ax3.set_ylabel("y (m)")
    ax3.set_zlabel("z (m)")
    axz.legend(fontsize=8)
    x0 = x0s[0, :3]
    fig.suptitle(f"Landing from ({x0[0]:.2f}, {x0[1]:.2f}, {x0[2]:.2f}) m: closed loop on the true system "
                 "(dots = steps, circle = last state; shaded: ground-effect zone, dotted: MPC height bound)")
    fig.tight_layout()
    return save_figure(fig, path)
