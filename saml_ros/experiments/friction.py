"""Double integrator with friction (paper, "Double Integrator with Friction"): SA vs UA model errors and MPC
performance on the true system.

Training: the paper's settings (4-2 PReLU residual net, 15,000 samples p ~ U[-2, 2], v ~ U[-2.5, 2.5],
u ~ U[-10, 10], Adam 1e-3 / 1e-4, batch 128, 200 epochs; the paper spec: conditional l2 <= 0.035 where
||[p, v]||_inf <= 0.5), one dataset and initialisation per seed, all seeds trained as one ensemble
(:func:`saml_ros.offline.pipelines.compare`).

Controller table: the MPC of paper eq. (double_integrator_mpc), T = 10, |u| <= 10, run on the TRUE system from
``n_starts`` random starts x_start = (p0 ~ U[-2, 2], v0 = 0) for ``steps`` closed-loop steps. The reported cost
is the paper's sum_t |x_t| with x the *position* (the paper's MPC writes x_1 = x_start and a separate
"x_dot_1 = 0", so its x is the position and x_dot the velocity) over the closed-loop states x_0 .. x_steps,
x_0 = x_start included as the paper's sum starts at x_1 = x_start; the normalised cost divides by |p0|.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from saml_ros.core.models import DynamicsModel
from saml_ros.core.mpc import closed_loop, make_controller
from saml_ros.core.systems.friction import FrictionDoubleIntegrator
from saml_ros.experiments.common import (
    PAIRED_HEADER,
    Timer,
    fmt,
    fmt_ms,
    fmt_p,
    machine_info,
    md_table,
    paired,
    paired_rate,
    progress_bar,
    save_models,
    single_threaded,
    train_paper_comparison,
    training_summary,
    write_results,
)
from saml_ros.experiments.plan_checks import PlanChecks
from saml_ros.offline.pipelines import Comparison
from saml_ros.offline.plots import plot_error_map, plot_training_curves, save_figure

#: the paper's controller-performance table (200 trials, mean ± std)
PAPER_COST = {"uniform": ("5.51 ± 3.46", "5.66 ± 0.89"), "sufficient": ("4.73 ± 3.38", "4.57 ± 0.73")}
#: the paper's model-error table (overall, in region, out of region)
PAPER_ERRORS = {"uniform": ("0.110 ± 0.098", "0.083 ± 0.054", "0.113 ± 0.10"),
                "sufficient": ("0.136 ± 0.126", "0.048 ± 0.040", "0.146 ± 0.13")}
#: a closed loop that ends farther than this from the origin (m) "got stuck" (friction holds it there)
STUCK_DISTANCE = 0.05
LABELS = {"uniform": "Uniformly Accurate", "sufficient": "Sufficiently Accurate", "base": "base model f_hat only"}


@dataclass
class FrictionSettings:
    """Experiment settings (defaults: the paper's, 5 seeds)."""

    seeds: tuple[int, ...] = (0, 1, 2, 3, 4)
    n_train: int = 15000
    epochs: int = 200
    n_test: int = 20000
    hidden: tuple[int, ...] = (4, 2)
    n_starts: int = 200
    steps: int = 30
    horizon: int = 10
    #: solvers to evaluate; "slsqp" is the paper's (scipy SLSQP), "fast" ours
    solvers: tuple[str, ...] = ("slsqp", "fast")
    #: SLSQP is ~20x slower: it runs on the models of the first ``slsqp_seeds`` seeds only
    slsqp_seeds: int = 1
    #: and on the first ``slsqp_starts`` starts only (None: all)
    slsqp_starts: int | None = None
    start_seed: int = 2024
    #: starts (p0, m) of the trajectory figure (fixed, not selected by outcome)
    traj_starts: tuple[float, ...] = (1.5, -1.0)

    @classmethod
    def quick(cls, seeds: tuple[int, ...] = (0, 1)) -> FrictionSettings:
        """Under a minute: 3000 samples, 30 epochs, 20 starts x 20 steps (SLSQP on 5 starts of one seed)."""
        return cls(seeds=seeds, n_train=3000, epochs=30, n_test=5000, n_starts=20, steps=20, slsqp_starts=5)


def starts(n: int, seed: int) -> np.ndarray:
    """``(n, 2)`` start states: p0 ~ U[-2, 2] m, v0 = 0."""
    p0 = np.random.default_rng(seed).uniform(-2.0, 2.0, n)
    return np.stack((p0, np.zeros(n)), axis=1)


def trajectory_cost(xs: np.ndarray) -> tuple[float, float]:
    """(sum_t |p_t| over x_0..x_K, the same divided by |p_0|) of a closed loop ``xs (K + 1, 2)``."""
    raw = float(np.abs(xs[:, 0]).sum())
    return raw, raw / max(abs(float(xs[0, 0])), 1e-12)


def evaluate_controller(system: FrictionDoubleIntegrator, model: DynamicsModel | None, solver: str,
                        x0s: np.ndarray, steps: int, horizon: int, bar: Any = None) -> dict[str, Any]:
    """Closed loops from every start: raw and normalised costs ``(S,)``, final states, plan checks."""
    ctrl = make_controller(system, model, solver, horizon=horizon)
    raw, norm, final, times = [], [], [], []
    checks = PlanChecks()
    for x0 in x0s:
        run = closed_loop(system, ctrl, x0, steps, on_step=checks.hook(system))
        r, nn = trajectory_cost(run.xs)
        raw.append(r)
        norm.append(nn)
        final.append(run.xs[-1])
        times.append(run.solve_times)
        if bar is not None:
            bar.update(1)
    t = np.concatenate(times)
    return {"raw": np.asarray(raw), "norm": np.asarray(norm), "final": np.asarray(final),
            "stuck": np.abs(np.asarray(final)[:, 0]) > STUCK_DISTANCE,
            "solve_time_mean": float(t.mean()), "solve_time_max": float(t.max()), "checks": checks}


@single_threaded
def run(settings: FrictionSettings, out: Path, progress: bool = True) -> dict[str, Any]:
    """Train, evaluate, control; write ``results.md``, ``results.json`` and figures into ``out``.

    Runs single-threaded with subnormals flushed (:func:`~saml_ros.experiments.common.single_threaded`)."""
    s = settings
    timer = Timer()
    info = machine_info()
    system = FrictionDoubleIntegrator()
    spec, cmp = train_paper_comparison(system, s.seeds, s.n_train, s.n_test, s.hidden, s.epochs, timer, progress)
    models = {"uniform": cmp.uniform.model, "sufficient": cmp.sufficient.model}
    x0s = starts(s.n_starts, s.start_seed)
    seed_count = {sol: min(len(s.seeds), s.slsqp_seeds) if sol == "slsqp" else len(s.seeds) for sol in s.solvers}
    start_sets = {sol: x0s[: s.slsqp_starts] if sol == "slsqp" else x0s for sol in s.solvers}
    total = sum(2 * seed_count[sol] * len(start_sets[sol]) for sol in s.solvers) + len(x0s)
    bar = progress_bar(total, "friction MPC closed loops", progress)
    control: dict[str, dict[str, Any]] = {}
    with timer("mpc"):
        for solver in s.solvers:
            res: dict[str, Any] = {}
            for label in ("uniform", "sufficient"):
                per_seed = [evaluate_controller(system, models[label].member(i), solver, start_sets[solver], s.steps,
                                                s.horizon, bar) for i in range(seed_count[solver])]
                res[label] = _stack(per_seed)
            res["seeds"] = list(s.seeds[: seed_count[solver]])
            res["n_starts"] = len(start_sets[solver])
            control[solver] = res
        base_solver = "fast" if "fast" in s.solvers else s.solvers[0]
        control["base"] = {"solver": base_solver,
                           "base": _stack([evaluate_controller(system, None, base_solver, x0s, s.steps, s.horizon,
                                                               bar)])}
    bar.close()
    with timer("figures"):
        figs = figures(system, cmp, s, out, stuck_start(control, x0s))
    data = {
        "settings": s.__dict__, "spec": spec.to_dict(), "starts": x0s[:, 0],
        "models": save_models(out, {"sufficient": cmp.sufficient, "uniform": cmp.uniform}),
        "model_errors": model_error_data(cmp),
        "control": control, "paired": paired_results(control),
        "training": training_summary(cmp),
        "figures": [f.name for f in figs], "timing": timer.to_dict(), "machine": info,
    }
    write_results(out, markdown(data, cmp, s, timer), data)
    return data


def _stack(per_seed: list[dict[str, Any]]) -> dict[str, Any]:
    """Stack per-seed results: costs ``(n_seeds, S)``, merged checks."""
    checks = PlanChecks()
    for r in per_seed:
        checks.merge(r["checks"])
    return {"raw": np.stack([r["raw"] for r in per_seed]), "norm": np.stack([r["norm"] for r in per_seed]),
            "stuck": np.stack([r["stuck"] for r in per_seed]),
            "final": np.stack([r["final"] for r in per_seed]),
            "solve_time_mean": float(np.mean([r["solve_time_mean"] for r in per_seed])),
            "solve_time_max": float(np.max([r["solve_time_max"] for r in per_seed])), "checks": checks}


def paired_results(control: dict[str, Any]) -> dict[str, Any]:
    """SA vs UA paired by (seed, start) for each solver, and by seed (per-seed means)."""
    out: dict[str, Any] = {}
    for solver, res in control.items():
        if solver == "base":
            continue
        ua, sa = res["uniform"], res["sufficient"]
        out[solver] = {
            "raw_by_start": paired(ua["raw"], sa["raw"]),
            "norm_by_start": paired(ua["norm"], sa["norm"]),
            "raw_by_seed": paired(ua["raw"].mean(1), sa["raw"].mean(1)),
            "stuck": paired_rate(ua["stuck"], sa["stuck"]),
        }
    return out


def model_error_data(cmp: Comparison) -> dict[str, Any]:
    """Held-out per-region errors ``(E,)`` of both models and the seed-paired comparisons."""
    out: dict[str, Any] = {}
    for rs, ru in zip(cmp.eval_sufficient.regions, cmp.eval_uniform.regions):
        out[rs.name] = {
            "frac_inside": rs.frac_inside,
            "uniform": {"overall": ru.overall, "inside": ru.inside, "outside": ru.outside},
            "sufficient": {"overall": rs.overall, "inside": rs.inside, "outside": rs.outside},
            "paired_by_seed": {k: paired(getattr(ru, k), getattr(rs, k)) for k in ("overall", "inside", "outside")},
        }
    return out


def markdown(data: dict[str, Any], cmp: Comparison, s: FrictionSettings, timer: Timer) -> str:
    lines = [
        "# Double integrator with friction: Sufficiently vs Uniformly Accurate",
        "",
        f"Seeds {list(s.seeds)}; {s.n_train} training samples per seed, {s.epochs} epochs, net {list(s.hidden)}; "
        f"held-out test set of {s.n_test}. MPC: T = {s.horizon}, |u| <= 10, {s.n_starts} starts p0 ~ U[-2, 2], "
        f"v0 = 0, {s.steps} closed-loop steps on the true system; cost = sum_t |p_t| over x_0..x_{s.steps}.",
        "",
        "## Model errors (held-out l2 error of the next state, m/s)",
        "",
    ]
    for name, r in data["model_errors"].items():
        rows = []
        for label in ("uniform", "sufficient"):
            e = r[label]
            rows.append([LABELS[label], fmt_ms(e["overall"]), fmt_ms(e["inside"]), fmt_ms(e["outside"]),
                         " / ".join(PAPER_ERRORS[label])])
        lines += [f"Constraint `{name}` ({100 * r['frac_inside']:.1f}% of the test data inside); mean ± std over "
                  f"{len(s.seeds)} seeds:", "",
                  md_table(["model", "overall", "inside region", "outside region",
                            "paper (overall / inside / outside)"], rows), "",
                  "Paired by seed (SA − UA):", "", PAIRED_HEADER]
        lines += [r["paired_by_seed"][k].row(k, 4) for k in ("overall", "inside", "outside")]
        lines.append("")
    lines += ["## Controller performance on the true system", ""]
    for solver, res in data["control"].items():
        if solver == "base":
            continue
        rows = []
        for label in ("uniform", "sufficient"):
            c = res[label]
            rows.append([LABELS[label], fmt_ms(c["raw"], 2), fmt_ms(c["norm"], 2),
                         f"{fmt(float(np.median(c['raw'])), 2)} / {fmt(float(np.median(c['norm'])), 2)}",
                         f"{100 * float(np.mean(c['stuck'])):.1f}%", " / ".join(PAPER_COST[label]),
                         f"{1e3 * c['solve_time_mean']:.1f}", f"{c['checks'].unsuccessful}/{c['checks'].solves}",
                         f"{c['checks'].max_u_violation:.1e}"])
        lines += [f"### Solver `{solver}` (models of seeds {res['seeds']}, {res['n_starts']} starts; mean ± std over "
                  "seeds x starts)", "",
                  md_table(["model", "Σ\\|p_t\\|", "Σ\\|p_t\\| / \\|p0\\|", "medians (raw / normalised)",
                            f"stuck (final \\|p\\| > {STUCK_DISTANCE} m)", "paper (raw / normalised)",
                            "ms / solve", "unsuccessful solves", "max \\|u\\| bound violation"], rows), "",
                  "Paired comparison (SA − UA; negative = SA better):", "", PAIRED_HEADER]
        p = data["paired"][solver]
        lines += [p["raw_by_start"].row("Σ\\|p_t\\|, paired by (seed, start)", 3),
                  p["norm_by_start"].row("Σ\\|p_t\\| / \\|p0\\|, paired by (seed, start)", 3),
                  p["raw_by_seed"].row("mean Σ\\|p_t\\| per seed, paired by seed", 3), "",
                  f"Stuck closed loops: UA {100 * p['stuck'].rate_a:.1f}%, SA {100 * p['stuck'].rate_b:.1f}% "
                  f"({p['stuck'].only_a} only with UA, {p['stuck'].only_b} only with SA; exact McNemar "
                  f"p = {fmt_p(p['stuck'].p_mcnemar)}).", ""]
    b = data["control"]["base"]
    c = b["base"]
    lines += [f"Base model f_hat alone (solver `{b['solver']}`): Σ\\|p_t\\| = {fmt_ms(c['raw'], 2)}, normalised "
              f"{fmt_ms(c['norm'], 2)}, stuck {100 * float(np.mean(c['stuck'])):.1f}%.", ""]
    lines += ["## Figures", ""] + [f"![{f}]({f})" for f in data["figures"]] + ["", timer.markdown(), ""]
    return "\n".join(lines)


def stuck_start(control: dict[str, Any], x0s: np.ndarray) -> float:
    """The start (p0, m) whose closed loop with the seed-0 Sufficiently Accurate model ended farthest from the
    origin (first solver): a diagnostic example *selected by outcome*."""
    solver = next(k for k in control if k != "base")
    final = np.asarray(control[solver]["sufficient"]["final"])[0, :, 0]
    return float(x0s[int(np.argmax(np.abs(final))), 0])


def figures(system: FrictionDoubleIntegrator, cmp: Comparison, s: FrictionSettings, out: Path,
            worst_p0: float) -> list[Path]:
    """Error map at u = 1, training curves, closed-loop trajectories from the fixed starts, and from the start
    where the SA closed loop ended farthest from the origin (labelled as selected by outcome)."""
    figs = [
        plot_error_map(system, {"Uniformly Accurate": cmp.uniform.model.member(0),
                                "Sufficiently Accurate": cmp.sufficient.model.member(0)},
                       out / "friction_error_map_u1.png", u=1.0),
        plot_training_curves({"sufficient": cmp.sufficient.history, "uniform": cmp.uniform.history},
                             out / "friction_training_curves.png"),
        plot_trajectories(system, cmp, s, s.traj_starts, out / "friction_trajectories.png"),
        plot_trajectories(system, cmp, s, (worst_p0,), out / "friction_stuck_example.png",
                          " — selected: SA's worst final |p|"),
    ]
    return figs


def plot_trajectories(system: FrictionDoubleIntegrator, cmp: Comparison, s: FrictionSettings,
                      p0s: tuple[float, ...], path: Path, note: str = "") -> Path:
    """Position and control over time from each start ``p0s`` (m), SA vs UA (seed 0 models) and f_hat alone."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    solver = s.solvers[0]
    models: dict[str, DynamicsModel | None] = {"uniform": cmp.uniform.model.member(0),
                                               "sufficient": cmp.sufficient.model.member(0), "base": None}
    colors = {"uniform": "tab:gray", "sufficient": "tab:blue", "base": "tab:orange"}
    fig, axes = plt.subplots(2, len(p0s), figsize=(5.5 * max(len(p0s), 1.6), 5.5), sharex=True, squeeze=False)
    t = np.arange(s.steps + 1) * system.dt
    for j, p0 in enumerate(p0s):
        for label, model in models.items():
            ro = closed_loop(system, make_controller(system, model, solver, horizon=s.horizon), np.array([p0, 0.0]),
                             s.steps)
            raw, norm = trajectory_cost(ro.xs)
            axes[0, j].plot(t, ro.xs[:, 0], color=colors[label], label=f"{LABELS[label]} (cost {raw:.2f})",
                            ls="--" if label == "base" else "-")
            axes[1, j].step(t[:-1], ro.us[:, 0], where="post", color=colors[label],
                            ls="--" if label == "base" else "-")
        axes[0, j].axhline(0.0, color="k", lw=0.6)
        axes[0, j].axhspan(-0.5, 0.5, color="red", alpha=0.06)
        axes[0, j].set_title(f"start p0 = {p0:.3g} m, v0 = 0 (solver {solver}){note}", fontsize=10)
        axes[0, j].legend(fontsize=7)
        axes[0, j].set_ylabel("position p (m)")
        axes[1, j].set_ylabel("control u (m/s²)")
        axes[1, j].set_xlabel("time (s)")
    fig.tight_layout()
    return save_figure(fig, path)
