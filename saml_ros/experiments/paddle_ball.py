"""Ball bouncing (paper, "Ball Bouncing"): full and residual impact models, Uniformly vs Sufficiently Accurate,
evaluated by an MPC that bounces a ball in the MuJoCo world towards a target.

Data: random bounces in the MuJoCo world (:func:`saml_ros.core.worlds.paddle_world.collect_impacts`; the paper's
"42 minutes" of bounces are about 2500 impacts) and a separate validation set from another world and seed.

Models: 128-128 PReLU, input ``[x^-, u]``, output the post-impact ball velocity; ``full`` (no base model) and
``residual`` (on the base model with the wrong restitution and no paddle-normal bias). Sufficiently Accurate =
the paper's normalised objective (``PaddleBall.paper_spec``: E[||e|| / ||v+||] over ||v+|| >= 0.1 m/s, s.t.
E[||e|| | ||v+|| < 0.1] <= 0.1 m/s); Uniformly Accurate = the paper's unconstrained problem, the plain l2 error
over all impacts (:func:`uniform_spec`). Adam with lr 1e-3 for the primal AND the dual variables (paper).

Control trials (paper eq. ball_paddle_opt): per trial a ball is dropped so that it reaches the impact plane at
px, py ~ U[-1, 1] m with vx, vy ~ U[-1, 1], vz ~ U[-6, -2] m/s; target_xy ~ U[-1, 1]^2 m, v_min ~ U[3, 4) m/s,
v_max = v_min + U[1, 2] m/s, roll and pitch in ``[-0.4, 0.4]`` rad. The controller gets the predicted
pre-impact state (``world.next_impact``), its command is applied, and the world runs until the ball is back at
the impact height: landing error = distance of that point to target_xy. Failure = the paddle does not keep
the ball bouncing: the world reports a failure, the impact is not the planned one (``on_plan`` False), the ball
is not sent up, or it comes down outside the paddle's reach.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from saml_ros.core.models import DynamicsModel
from saml_ros.core.mpc import Controller, MPCResult, make_controller
from saml_ros.core.spec import ProblemSpec
from saml_ros.core.systems.paddle_ball import PaddleBall, landing_point, roll_pitch_from_normal
from saml_ros.core.training import TrainConfig
from saml_ros.core.worlds.paddle_world import CollectStats, PaddleBallWorld, collect_impacts, impacts_to_arrays
from saml_ros.experiments.common import (
    PAIRED_HEADER,
    Timer,
    flush_denormals,
    fmt_ms,
    fmt_p,
    machine_info,
    md_table,
    paired,
    paired_rate,
    progress_bar,
    quiet_trainer_warnings,
    save_models,
    single_threaded,
    write_results,
)
from saml_ros.experiments.plan_checks import bound_violation
from saml_ros.offline.pipelines import TrainedModels, train_models
from saml_ros.offline.plots import save_figure

PAPER = {("full", "uniform"): ("20.8%", "0.3136"), ("full", "sufficient"): ("0.8%", "0.2124"),
         ("residual", "uniform"): ("0%", "0.164"), ("residual", "sufficient"): ("0%", "0.156")}
SPEC_LABELS = {"uniform": "Uniform", "sufficient": "Sufficient"}
#: failure reason of a ball the world's paddle hits again right after the impact, while the ball still rises
REHIT = "hit again while rising"
#: tolerance on the roll / pitch / relative-speed bounds of a returned command (rad, m/s)
GOAL_TOL = 1e-6


def uniform_spec() -> dict[str, Any]:
    """The paper's Uniformly Accurate problem for the ball: mean l2 error of the post-impact velocity, no constraint."""
    return {"name": "uniform_l2",
            "objective": {"loss": "l2", "fields": ["vx", "vy", "vz"], "region": None, "mean": "unconditional"},
            "constraints": []}


@dataclass
class PaddleSettings:
    """Experiment settings (defaults: the paper's where it gives them)."""

    seeds: tuple[int, ...] = (0, 1, 2)
    n_impacts: int = 2500
    n_val: int = 1000
    #: the paper does not state the epochs; 500 passes over 2500 impacts (about 10k updates)
    epochs: int = 500
    hidden: tuple[int, ...] = (128, 128)
    kinds: tuple[str, ...] = ("full", "residual")
    n_trials: int = 500
    solver: str = "fast"
    roll: tuple[float, float] = (-0.4, 0.4)
    pitch: tuple[float, float] = (-0.4, 0.4)
    #: control trials run with the models of the first ``mpc_seeds`` seeds
    mpc_seeds: int = 3
    data_seed: int = 0
    trial_seed: int = 7
    timestep: float = 0.002
    extra: dict[str, Any] = field(default_factory=dict)

    @classmethod
    def quick(cls, seeds: tuple[int, ...] = (0,)) -> PaddleSettings:
        """Under a minute: 400 impacts, 150 epochs, 30 trials."""
        return cls(seeds=seeds, n_impacts=400, n_val=200, epochs=150, n_trials=30, mpc_seeds=1)


@dataclass(frozen=True)
class Trial:
    """One control trial: the ball's drop (apex position and velocity) and the controller's parameters."""

    apex: np.ndarray  # (3,) m
    velocity: np.ndarray  # (3,) m/s, horizontal
    target_xy: np.ndarray  # (2,) m
    v_min: float
    v_max: float


def make_trials(n: int, seed: int, g: float = 9.81) -> list[Trial]:
    """``n`` trials (see the module docstring); the ball reaches the impact plane with the drawn state."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        p = rng.uniform(-1.0, 1.0, 2)
        vh = rng.uniform(-1.0, 1.0, 2)
        vz = rng.uniform(-6.0, -2.0)
        t_fall = -vz / g
        apex = np.array([*(p - vh * t_fall), vz * vz / (2.0 * g)])
        target = rng.uniform(-1.0, 1.0, 2)
        v_min = rng.uniform(3.0, 4.0)
        v_max = v_min + rng.uniform(1.0, 2.0)
        out.append(Trial(apex, np.array([*vh, 0.0]), target, float(v_min), float(v_max)))
    return out


def make_goal(trial: Trial, s: PaddleSettings) -> Any:
    """The controller's goal for a trial (``saml_ros.core.mpc.paddle_goal``)."""
    from saml_ros.core.mpc import paddle_goal

    return paddle_goal(target_xy=trial.target_xy, roll=s.roll, pitch=s.pitch, v_rel=(trial.v_min, trial.v_max))


def command_violation(system: PaddleBall, res: MPCResult, x_pre: np.ndarray, trial: Trial,
                      s: PaddleSettings) -> dict[str, float]:
    """How far the returned command leaves the control box, the roll/pitch bounds and the relative-speed bounds
    (|v_ball^- - v_paddle| in [v_min, v_max]); 0 = inside."""
    u = np.asarray(res.u, dtype=float)
    box = max(bound_violation(res.plan_u, system.control_low, system.control_high),
              bound_violation(u[None], system.control_low, system.control_high))
    roll, pitch = (float(a) for a in roll_pitch_from_normal(torch.as_tensor(u[3:6])))
    angle = max(0.0, s.roll[0] - roll, roll - s.roll[1], s.pitch[0] - pitch, pitch - s.pitch[1])
    v_rel = float(np.linalg.norm(x_pre[3:6] - u[0:3]))
    speed = max(0.0, trial.v_min - v_rel, v_rel - trial.v_max)
    return {"box": box, "angle": angle, "speed": speed}


def run_trial(world: PaddleBallWorld, ctrl: Controller, trial: Trial, s: PaddleSettings,
              record: bool = False) -> dict[str, Any]:
    """Run one trial (see the module docstring); returns outcome, landing error and the command's checks."""
    system = world.system
    world.reset(trial.apex, trial.velocity)
    _, x_pre = world.next_impact()
    res = ctrl.solve(x_pre, make_goal(trial, s))
    out: dict[str, Any] = {"failed": True, "reason": "", "error": float("nan"), "solve_time": res.solve_time,
                           "solver_success": bool(res.success), "x_pre": x_pre, "u": np.asarray(res.u)}
    out["violation"] = command_violation(system, res, x_pre, trial, s)
    pred = np.asarray(res.plan_x, dtype=float)
    if pred.shape[-1] >= 6 and np.all(np.isfinite(pred[0, 3:6])):
        out["predicted_landing"] = landing_point(torch.as_tensor(x_pre[None, :3]),
                                                 torch.as_tensor(pred[:1, 3:6]), system.g)[0].numpy()
    try:
        world.set_command(np.asarray(res.u, dtype=float))
    except ValueError as exc:
        out["reason"] = f"invalid command: {exc}"
        return out
    track: list[np.ndarray] = [world.ball_state[:3]] if record else []
    imp = None
    dt = world.timestep
    for _ in range(int(world.options.impact_timeout / dt) + 1):
        got = world.step(1)
        if record:
            track.append(world.ball_state[:3])
        if got:
            imp = got[0]
            break
        if world.failed():
            break
    if imp is None:
        out["reason"] = world.failure_reason or "no impact"
        return _finish(out, track)
    out["v_post"] = imp.post_velocity
    if not imp.on_plan:
        out["reason"] = "impact not as planned"
        return _finish(out, track)
    if imp.post_velocity[2] <= 0.0:
        out["reason"] = "ball not sent up"
        return _finish(out, track)
    z_ref = float(imp.pre[2])
    prev = world.ball_state
    landing = None
    for _ in range(int(4.0 / dt)):
        got = world.step(1)
        st = world.ball_state
        if record:
            track.append(st[:3])
        if got:
            if got[0].pre[5] < 0.0:  # met by the paddle on its way down: continue its free flight to z_ref
                landing = ballistic_crossing(got[0].pre, z_ref, system.g)
                out["landing_z"] = z_ref
                break
            out["reason"] = REHIT  # e.g. by the paddle rushing to the next impact point
            return _finish(out, track)
        if st[5] < 0.0 and st[2] <= z_ref:
            a = (prev[2] - z_ref) / max(prev[2] - st[2], 1e-12)
            landing, out["landing_z"] = prev[:2] + a * (st[:2] - prev[:2]), z_ref
            break
        prev = st
    if landing is None:
        out["reason"] = "ball did not come back down"
        return _finish(out, track)
    out["landing"] = landing
    out["error"] = float(np.linalg.norm(landing - trial.target_xy))
    if max(abs(float(landing[0])), abs(float(landing[1]))) > world.options.reach + world.options.paddle_half_size:
        out["reason"] = "out of reach"
        return _finish(out, track)
    out["failed"] = False
    return _finish(out, track)


def ballistic_crossing(state: np.ndarray, z_ref: float, g: float) -> np.ndarray:
    """xy (m) where a ball in free flight from ``state`` ``[p, v]`` (6,) descends through height ``z_ref``."""
    pz, vz = float(state[2]), float(state[5])
    disc = max(vz * vz + 2.0 * g * (pz - z_ref), 0.0)
    t = max((vz + np.sqrt(disc)) / g, 0.0)
    return np.asarray(state[0:2] + state[3:5] * t, dtype=float)


def _finish(out: dict[str, Any], track: list[np.ndarray]) -> dict[str, Any]:
    if track:
        out["track"] = np.stack(track)
    return out


def collect(s: PaddleSettings, n: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, CollectStats]:
    """``n`` on-plan random impacts from a world seeded ``seed``: ``(x, u, y)`` and the collection stats."""
    world = PaddleBallWorld(timestep=s.timestep, seed=seed)
    stats = CollectStats()
    impacts = collect_impacts(world, n, np.random.default_rng(seed + 1), stats=stats)
    x, u, y = impacts_to_arrays(impacts)
    return x, u, y, stats


def validation_errors(model: DynamicsModel | None, system: PaddleBall, x: np.ndarray, u: np.ndarray,
                      y: np.ndarray) -> dict[str, Any]:
    """Per member: l2 error ``(E, N)``, mean l2, normalised error on fast balls, l2 on slow balls (< 0.1 m/s)."""
    if model is None:
        pred = system.base_step_np(x, u)[None]
    else:
        with torch.no_grad():
            dt = model.in_mean.dtype
            pred = model(torch.as_tensor(x, dtype=dt), torch.as_tensor(u, dtype=dt)).double().numpy()
    err = np.linalg.norm(pred - y[None], axis=-1)
    speed = np.linalg.norm(y, axis=-1)
    fast = speed >= 0.1
    return {"err": err, "speed": speed, "l2": err.mean(1), "normalized_fast": (err[:, fast] / speed[fast]).mean(1),
            "l2_slow": err[:, ~fast].mean(1) if (~fast).any() else np.full(err.shape[0], np.nan),
            "n_slow": int((~fast).sum())}


@single_threaded
def run(settings: PaddleSettings, out: Path, progress: bool = True) -> dict[str, Any]:
    """Collect, train, validate, run the control trials; write results and figures into ``out``.

    Runs single-threaded with subnormals flushed (:func:`~saml_ros.experiments.common.single_threaded`)."""
    s = settings
    timer = Timer()
    info = machine_info()
    system = PaddleBall()
    specs = {"sufficient": ProblemSpec.for_system(system.paper_spec(), system),
             "uniform": ProblemSpec.for_system(uniform_spec(), system)}
    with timer("collect"):
        x, u, y, stats = collect(s, s.n_impacts, s.data_seed)
        xv, uv, yv, _ = collect(s, s.n_val, s.data_seed + 1000)
    config = TrainConfig(epochs=s.epochs, batch_size=128, primal_lr=1e-3, dual_lr=1e-3)
    trained: dict[tuple[str, str], TrainedModels] = {}
    with timer("train"), quiet_trainer_warnings(), flush_denormals():
        for kind in s.kinds:
            for label, spec in specs.items():
                trained[(kind, label)] = train_models(system, spec, x, u, y, config, list(s.seeds), s.hidden, kind,
                                                      progress, f"{kind} {label}")
    val = {f"{k}/{lab}": validation_errors(tm.model, system, xv, uv, yv) for (k, lab), tm in trained.items()}
    val["base"] = validation_errors(None, system, xv, uv, yv)
    trials = make_trials(s.n_trials, s.trial_seed, system.g)
    k = min(s.mpc_seeds, len(s.seeds))
    models: dict[str, list[DynamicsModel | None]] = {"base": [None]}
    for (kind, label), tm in trained.items():
        models[f"{kind}/{label}"] = [tm.model.member(i) for i in range(k)]
    bar = progress_bar(sum(len(v) for v in models.values()) * len(trials), "paddle-ball control trials", progress)
    world = PaddleBallWorld(timestep=s.timestep, seed=s.trial_seed)
    control: dict[str, Any] = {}
    tracks: dict[str, np.ndarray] = {}
    with timer("control"):
        for name, members in models.items():
            rows = []
            for model in members:
                ctrl = make_controller(system, model, s.solver)
                for j, trial in enumerate(trials):
                    r = run_trial(world, ctrl, trial, s, record=(j == 0 and model is members[0]))
                    if "track" in r:
                        tracks[name] = r.pop("track")
                    rows.append(r)
                    bar.update(1)
            control[name] = summarize(rows)
    bar.close()
    pairs = paired_control(control, s)
    with timer("figures"):
        figs = [plot_error_scatter(val, s, out / "paddle_error_vs_speed.png"),
                plot_tracks(tracks, trials[0], out / "paddle_trajectory.png")]
    data = {"settings": s.__dict__, "specs": {k2: v.to_dict() for k2, v in specs.items()},
            "models": save_models(out, {f"{k2[0]}/{k2[1]}": tm for k2, tm in trained.items()}),
            "data": {"n_train": len(x), "n_val": len(xv), "collect": stats.__dict__,
                     "frac_slow_train": float(np.mean(np.linalg.norm(y, axis=1) < 0.1))},
            "validation": {k2: {m: v for m, v in d.items() if m not in ("err", "speed")} for k2, d in val.items()},
            "control": control, "paired": pairs,
            "training": {f"{k2[0]}/{k2[1]}": {"seconds": tm.train_seconds, "engine": tm.trainer.engine_used,
                                              "lambda": tm.trainer.lam} for k2, tm in trained.items()},
            "trials": [{"target_xy": t.target_xy, "v_min": t.v_min, "v_max": t.v_max, "apex": t.apex}
                       for t in trials],
            "figures": [f.name for f in figs], "timing": timer.to_dict(), "machine": info}
    write_results(out, markdown(data, s, timer), data)
    return data


def summarize(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """Per-trial arrays (failed, error, solve time, violations) and failure reasons of one model's trials."""
    reasons: dict[str, int] = {}
    for r in rows:
        if r["failed"]:
            reasons[r["reason"]] = reasons.get(r["reason"], 0) + 1
    return {
        "failed": np.array([r["failed"] for r in rows]),
        "lost": np.array([r["failed"] and r["reason"] != REHIT for r in rows]),
        "error": np.array([np.nan if r["failed"] else r["error"] for r in rows]),
        "error_any": np.array([r["error"] for r in rows]),
        "solve_time": np.array([r["solve_time"] for r in rows]),
        "solver_success": np.array([r["solver_success"] for r in rows]),
        "max_box_violation": max(r["violation"]["box"] for r in rows),
        "max_angle_violation": max(r["violation"]["angle"] for r in rows),
        "max_speed_violation_success": max([r["violation"]["speed"] for r in rows if r["solver_success"]],
                                           default=0.0),
        "reasons": reasons,
    }


def paired_control(control: dict[str, Any], s: PaddleSettings) -> dict[str, Any]:
    """Per kind, Uniform vs Sufficient paired by trial: failures (McNemar) and landing errors where both succeeded."""
    out: dict[str, Any] = {}
    for kind in s.kinds:
        ua, sa = control.get(f"{kind}/uniform"), control.get(f"{kind}/sufficient")
        if ua is None or sa is None:
            continue
        both = ~ua["failed"] & ~sa["failed"]
        out[kind] = {"failure": paired_rate(ua["failed"], sa["failed"]),
                     "lost": paired_rate(ua["lost"], sa["lost"]),
                     "error_both_ok": paired(ua["error"][both], sa["error"][both])}
    return out


def markdown(data: dict[str, Any], s: PaddleSettings, timer: Timer) -> str:
    d = data["data"]
    lines = [
        "# Ball bouncing: full and residual models, Uniformly vs Sufficiently Accurate",
        "",
        f"{d['n_train']} training impacts from the MuJoCo world ({d['collect']['sim_time'] / 60:.1f} simulated "
        f"minutes of random bounces, {100 * d['frac_slow_train']:.1f}% slow balls), {d['n_val']} validation "
        f"impacts; nets {list(s.hidden)}, {s.epochs} epochs, Adam 1e-3 / 1e-3, seeds {list(s.seeds)}. "
        f"{s.n_trials} control trials per model (solver `{s.solver}`, roll in {list(s.roll)}, pitch in "
        f"{list(s.pitch)} rad), models of the first {min(s.mpc_seeds, len(s.seeds))} seed(s).",
        "",
        "## Controller performance (MuJoCo)",
        "",
    ]
    rows = []
    for name, c in data["control"].items():
        kind, _, label = name.partition("/")
        paper = PAPER.get((kind, label), ("", ""))
        rows.append([f"{kind} {SPEC_LABELS.get(label, '')}".strip() if label else "base model f_hat only",
                     f"{100 * float(np.mean(c['failed'])):.1f}%", f"{100 * float(np.mean(c['lost'])):.1f}%",
                     fmt_ms(c["error"], 3),
                     f"{paper[0]} / {paper[1]}" if paper[0] else "",
                     f"{1e3 * float(np.mean(c['solve_time'])):.1f}",
                     f"{int(np.sum(~c['solver_success']))}/{len(c['solver_success'])}",
                     f"{c['max_box_violation']:.1e} / {c['max_angle_violation']:.1e}",
                     ", ".join(f"{k}: {v}" for k, v in c["reasons"].items())])
    lines += [md_table(["model", "failure", f"failure without '{REHIT}'", "landing error (m), successful trials",
                        "paper failure / mean error",
                        "ms / solve", "unsuccessful solves", "max box / roll-pitch violation", "failure reasons"],
                       rows), ""]
    lines += ["Paired by trial (Sufficient − Uniform):", ""]
    for kind, p in data["paired"].items():
        f = p["failure"]
        lines.append(f"- {kind}: failures Uniform {100 * f.rate_a:.1f}% vs Sufficient {100 * f.rate_b:.1f}%, "
                     f"{f.only_a} trials failed only with Uniform, {f.only_b} only with Sufficient, exact McNemar "
                     f"p = {fmt_p(f.p_mcnemar)}; without '{REHIT}': {100 * p['lost'].rate_a:.1f}% vs "
                     f"{100 * p['lost'].rate_b:.1f}%, McNemar p = {fmt_p(p['lost'].p_mcnemar)}")
    lines += ["", PAIRED_HEADER]
    lines += [p["error_both_ok"].row(f"{kind}: landing error (m), trials both succeeded", 4)
              for kind, p in data["paired"].items()]
    lines += ["", "## Model errors on the validation impacts", ""]
    rows = []
    for name, v in data["validation"].items():
        rows.append([name, fmt_ms(v["l2"], 4), fmt_ms(v["normalized_fast"], 4),
                     fmt_ms(v["l2_slow"], 4) + f" (n = {v['n_slow']})"])
    lines += [md_table(["model", "mean \\|e\\| (m/s)", "mean \\|e\\| / \\|v+\\|, \\|v+\\| >= 0.1",
                        "mean \\|e\\|, \\|v+\\| < 0.1"], rows)]
    lines += ["", "## Figures", ""] + [f"![{f}]({f})" for f in data["figures"]] + ["", timer.markdown(), ""]
    return "\n".join(lines)


def plot_error_scatter(val: dict[str, Any], s: PaddleSettings, path: Path) -> Path:
    """Model error against the true post-impact speed, per kind, Uniform vs Sufficient (member 0), with the
    constraint region's boundary (|v+| = 0.1, blue) and the constraint bound (eps = 0.1 m/s, red)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    kinds = [k for k in s.kinds if f"{k}/uniform" in val]
    fig, axes = plt.subplots(1, len(kinds), figsize=(6 * len(kinds), 4.4), squeeze=False)
    for ax, kind in zip(axes[0], kinds):
        for label, color in (("uniform", "tab:gray"), ("sufficient", "tab:blue")):
            v = val[f"{kind}/{label}"]
            ax.scatter(v["speed"], v["err"][0], s=5, alpha=0.5, color=color, label=f"{SPEC_LABELS[label]}")
        ax.axvline(0.1, color="blue", ls=":", lw=1.2, label="constraint region |v+| < 0.1")
        ax.plot([0, 0.1], [0.1, 0.1], color="red", ls=":", lw=1.5, label="constraint bound eps = 0.1")
        ax.set_xlabel("|v+| true post-impact speed (m/s)")
        ax.set_ylabel("model error |v+_pred - v+| (m/s)")
        ax.set_title(f"{kind} model (validation impacts)")
        ax.legend(fontsize=8)
    fig.tight_layout()
    return save_figure(fig, path)


def plot_tracks(tracks: dict[str, np.ndarray], trial: Trial, path: Path) -> Path:
    """The first trial's ball trajectory under each model (side view x-z and top view x-y; red = target)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a1, a2) = plt.subplots(1, 2, figsize=(11, 4.4))
    for name, tr in tracks.items():
        ls = "--" if name == "base" else "-"
        a1.plot(tr[:, 0], tr[:, 2], ls=ls, label=name)
        a2.plot(tr[:, 0], tr[:, 1], ls=ls, label=name)
        a2.plot(tr[-1, 0], tr[-1, 1], "o", ms=4, color=a2.lines[-1].get_color())
    a2.plot(*trial.target_xy, "o", color="red", ms=9, label="target")
    a1.axhline(0.0, color="k", lw=0.6)
    a1.set_xlabel("x (m)")
    a1.set_ylabel("z (m)")
    a2.set_xlabel("x (m)")
    a2.set_ylabel("y (m)")
    a2.set_aspect("equal", "datalim")
    a2.legend(fontsize=7)
    fig.suptitle(f"trial 0: target ({trial.target_xy[0]:.2f}, {trial.target_xy[1]:.2f}) m, "
                 f"|v_rel| in [{trial.v_min:.2f}, {trial.v_max:.2f}] m/s")
    fig.tight_layout()
    return save_figure(fig, path)

