"""Quadrotor landing with ground effect (paper, "Quadrotor with ground effects"), with the base model and the
oracle as the two ends of what a model can do, from starts inside the ground-effect region and above it.

System: the paper's quadrotor; by default (``drag = 0.3``) the true model also has a linear air drag
``v' -= dt drag v`` that f_hat does not know. Without it the residual is exactly zero above 1.5 m, so the
Uniformly Accurate net already spends its whole capacity near the ground and no eps can make SA better there
(docs/experiments.md, "Quadrotor"); ``drag = 0`` runs the paper's system as printed.

Training: residual 16-8 PReLU nets on 10,000 states sampled as the paper (``Quadrotor.sample_inputs``), Adam
1e-3 / 1e-4, the paper's 3000 epochs; Sufficiently Accurate = the paper spec with the loss ``loss``
(``"squared_l2"``, what the paper's numbers fit, or the paper's printed ``"l2"``) and the bound ``eps`` on
E[l | pz <= 1.5]; Uniformly Accurate = the same without the constraint. Several seeds train as one ensemble (one
dataset and initialisation per seed).

Control: the paper's landing MPC (T = 10, 0 <= u <= 10 N, pz >= 0.2 m on every predicted state, |qw_T - 1| <=
0.05, cost sum_t ||p_t - 0||_2) from level starts at rest, x, y ~ U[-2, 2] m and z in each band of ``bands``
("ground": U[0.3, 1.5] m, inside the ground effect; "above": U[1.5, 3] m), run for ``steps`` steps on the TRUE
system with the simulator's ground contact (the centre of mass cannot go below 0.1 m). Reported: the paper's cost
sum_{t=1..steps} ||p_t||_2, and the **hover error**: the mean distance over the last ``settle_steps`` steps to
(0, 0, min_height), the best point the height bound allows (what the ground-effect model decides: a base model
hovers above it, an exact one at it).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from saml_ros.core.mpc import ClosedLoopRun, MPCResult, closed_loop, make_controller
from saml_ros.core.mpc.dynamics_np import ORACLE, PredictionModel
from saml_ros.core.systems import get_system
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
from saml_ros.experiments.headroom import Claim, claims_table, headroom, power, seed_test, verdict
from saml_ros.experiments.plan_checks import PlanChecks
from saml_ros.offline.pipelines import Comparison
from saml_ros.offline.plots import plot_training_curves, save_figure
from saml_ros.systems.quadrotor.model import Quadrotor

PAPER = {"mpc_cost": {"sufficient": "4.21 ± 1.88", "uniform": "4.55 ± 1.90"},
         "loss": {"sufficient": "6.52e-4", "uniform": "6.16e-4"},
         "constraint": {"sufficient": "1.00e-4", "uniform": "8.28e-4"}}
LABELS = {"uniform": "Uniformly Accurate", "sufficient": "Sufficiently Accurate", "base": "base model f_hat only",
          "oracle": "oracle (true dynamics)"}
ARMS = ("uniform", "sufficient", "base", "oracle")
MIN_HEIGHT = 0.2
#: a landing whose final xy error exceeds this (m) missed the target
MISS_DISTANCE = 0.1


@dataclass
class QuadrotorSettings:
    """Experiment settings (defaults: the paper's training, 5 seeds; MPC budget chosen for this machine)."""

    seeds: tuple[int, ...] = (0, 1, 2, 3, 4)
    n_train: int = 10000
    epochs: int = 3000
    n_test: int = 20000
    hidden: tuple[int, ...] = (16, 8)
    #: linear drag of the true model (1/s); 0 = the paper's system
    drag: float = 0.3
    #: loss of the objective and the constraint: "squared_l2" (fits the paper's numbers) or "l2" (as printed)
    loss: str = "squared_l2"
    #: bound on E[l | pz <= 1.5] (in the units of ``loss``); 1.7e-3 = just above what the 16-8 net can reach in
    #: the region with drag 0.3 (docs/experiments.md; the paper's 1e-3 is out of its reach: --set eps=0.001)
    eps: float = 1.7e-3
    #: start bands: name -> (z_min, z_max) m
    bands: dict[str, tuple[float, float]] = field(default_factory=lambda: {"ground": (0.3, 1.5),
                                                                         "above": (1.5, 3.0)})
    n_starts: int = 10
    steps: int = 50
    settle_steps: int = 20
    horizon: int = 10
    solver: str = "fast"
    #: the MPC runs with the models of the first ``mpc_seeds`` seeds
    mpc_seeds: int = 5
    start_seed: int = 4242
    landing_height: float = 0.1
    #: tilt bound of every arm's MPC, |qx_t|, |qy_t| <= tilt_max on every predicted step (the demo's 0.2; inf = the
    #: paper's problem, where learned models planned steep banks outside their data and some landings flew away)
    tilt_max: float = 0.2
    #: fly the learned models with the demo's guard for a single model (residual bounded by 1.5 x the largest one
    #: of the seed's training data, live monitor with roll back, f_hat's plan where the learned plan breaks a
    #: constraint f_hat's keeps; docs/demo.md); False = unguarded, as the paper
    guard: bool = True

    @classmethod
    def quick(cls, seeds: tuple[int, ...] = (0, 1)) -> QuadrotorSettings:
        """About a minute: 3000 samples, 40 epochs, 2 starts per band x 15 steps."""
        return cls(seeds=seeds, n_train=3000, epochs=40, n_test=5000, n_starts=2, steps=15, settle_steps=5)


def spec_dict(system: Quadrotor, loss: str, eps: float) -> dict[str, Any]:
    """The paper's quadrotor spec with the objective's and the constraint's loss ``loss`` and the bound ``eps``."""
    if loss not in ("squared_l2", "l2"):
        raise ValueError(f"quadrotor experiment: loss must be 'squared_l2' or 'l2', got {loss!r}")
    d = system.paper_spec()
    d["objective"]["loss"] = loss
    d["constraints"][0]["loss"] = loss
    d["constraints"][0]["eps"] = float(eps)
    return d


def landing_starts(system: Quadrotor, n: int, seed: int, z: tuple[float, float] | None = None) -> np.ndarray:
    """``(n, 13)`` level, motionless starts at x, y ~ U[-2, 2] m, height ~ U[z]; ``z`` None: the simulator's
    sampler (``saml_ros.systems.quadrotor.world.quadrotor_start``, z ~ U[1, 3] m; the demo's evaluation)."""
    rng = np.random.default_rng(seed)
    if z is None:
        from saml_ros.systems.quadrotor.world import quadrotor_start

        return np.stack([quadrotor_start(system, rng) for _ in range(n)])
    return np.stack([system.hover_state((rng.uniform(-2, 2), rng.uniform(-2, 2), rng.uniform(*z)))
                     for _ in range(n)])


def plant(system: Quadrotor, landing_height: float) -> Callable[[np.ndarray, np.ndarray], np.ndarray]:
    """The simulated true system: ``true_step`` then the simulator's ground contact; ``(13,), (4,) -> (13,)``."""
    from saml_ros.core.worlds.sim_core import FastStep
    from saml_ros.systems.quadrotor.world import quadrotor_model

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


def rollout_metrics(ro: ClosedLoopRun, settle_steps: int = 20) -> dict[str, float]:
    """Cost sum_{t>=1} ||p_t||, hover error (mean distance to (0, 0, 0.2) over the last ``settle_steps``), final
    distance to the target, final xy error, final height."""
    p = ro.xs[:, 0:3]
    dist = np.linalg.norm(p[1:], axis=1)
    rest = np.linalg.norm(p[-settle_steps:] - np.array([0.0, 0.0, MIN_HEIGHT]), axis=1)
    return {"cost": float(dist.sum()), "hover": float(rest.mean()), "final_dist": float(dist[-1]),
            "final_xy": float(np.linalg.norm(p[-1, :2])), "final_z": float(p[-1, 2])}


def evaluate_controller(system: Quadrotor, model: PredictionModel, s: QuadrotorSettings, x0s: np.ndarray,
                        bar: Any = None, bound: np.ndarray | None = None) -> dict[str, Any]:
    """Closed loops from every start with one model: metrics per start and merged plan checks. A learned model
    flies with the demo's single-model guard when ``s.guard`` (``bound``: its residual bound; the monitor and the
    roll back start afresh at every start), else unguarded; every arm has the tilt bound ``s.tilt_max``."""
    from saml_ros.core.model.network import DynamicsModel
    from saml_ros.core.mpc.guard import GuardConfig, make_guarded_controller

    options = {"horizon": s.horizon, "tilt_max": s.tilt_max}
    guarded = s.guard and isinstance(model, DynamicsModel)
    if guarded:
        config = GuardConfig(bound_residual=bound is not None, rollback=True, infeasible=True)
        ctrl: Any = make_guarded_controller(system, s.solver, config, **options)
        meta = {"learner": {"residual_bound": bound.tolist()}} if bound is not None else {}
    else:
        ctrl = make_controller(system, model, s.solver, **options)
    f = plant(system, s.landing_height)
    metrics: list[dict[str, float]] = []
    checks = PlanChecks()
    xs, times = [], []
    for x0 in x0s:
        hook = checks.hook(system, height_violation)
        if guarded:
            ctrl.reset_models()
            ctrl.set_model(model, 1, meta)
            check = hook

            def hook(step: Any, check: Any = check) -> None:
                check(step)
                ctrl.observe(step.x, step.result.u, step.x_next)

        ro = closed_loop(system, ctrl, x0, s.steps, goal=np.zeros(3), true_step=f, on_step=hook)
        metrics.append(rollout_metrics(ro, s.settle_steps))
        xs.append(ro.xs)
        times.append(ro.cpu_times)
        if bar is not None:
            bar.update(1)
    out: dict[str, Any] = {k: np.array([m[k] for m in metrics]) for k in metrics[0]}
    out.update({"checks": checks, "xs": np.stack(xs), "cpu_per_solve": float(np.concatenate(times).mean()),
                "guard": {k: float(v) for k, v in getattr(ctrl, "counters", {}).items()}})
    return out


def residual_bounds(system: Quadrotor, s: QuadrotorSettings) -> list[np.ndarray]:
    """Per seed, the residual bound the guard clips phi to: 1.5 x the largest ``|y - f_hat(x, u)|`` of that seed's
    training data (at least 1e-3), as the online learner records it."""
    from saml_ros.core.online.learner import RESIDUAL_FLOOR, RESIDUAL_MARGIN
    from saml_ros.offline.pipelines import generate_datasets

    x, u, y = generate_datasets(system, s.n_train, list(s.seeds), None)
    out = []
    for i in range(len(s.seeds)):
        resid = np.abs(y[i] - system.base_step_np(x[i], u[i]))
        out.append(np.maximum(RESIDUAL_MARGIN * resid.max(0), RESIDUAL_FLOOR))
    return out


def model_errors(cmp: Comparison, system: Quadrotor, n_test: int, loss: str, seed: int = 10_000) -> dict[str, Any]:
    """Per member on a fresh test set, with the spec's loss: E[l], E[l I], E[l | I], E[l | not I], in-region
    fraction; and the base model's."""
    import torch

    xt, ut, yt = system.make_dataset(n_test, np.random.default_rng(seed))
    inside = xt[:, 2] <= 1.5

    def per_sample(pred: np.ndarray) -> np.ndarray:
        sq = ((pred - yt) ** 2).sum(-1)
        return sq if loss == "squared_l2" else np.sqrt(sq)

    out: dict[str, Any] = {"frac_inside": float(inside.mean())}
    for label, tm in (("uniform", cmp.uniform), ("sufficient", cmp.sufficient)):
        with torch.no_grad():
            dt = tm.model.in_mean.dtype
            pred = tm.model(torch.as_tensor(xt, dtype=dt), torch.as_tensor(ut, dtype=dt)).double().numpy()
        err = per_sample(pred)  # (E, N)
        out[label] = {"loss": err.mean(1), "loss_times_indicator": (err * inside).mean(1),
                      "loss_given_region": err[:, inside].mean(1), "loss_outside": err[:, ~inside].mean(1)}
    base = per_sample(system.base_step_np(xt, ut))
    out["base"] = {"loss": float(base.mean()), "loss_times_indicator": float((base * inside).mean()),
                   "loss_given_region": float(base[inside].mean()), "loss_outside": float(base[~inside].mean())}
    out["paired_by_seed"] = {k: paired(out["uniform"][k], out["sufficient"][k])
                             for k in ("loss", "loss_times_indicator", "loss_given_region", "loss_outside")}
    return out


@single_threaded
def run(settings: QuadrotorSettings, out: Path, progress: bool = True) -> dict[str, Any]:
    """Train SA and UA, evaluate their errors and the landing MPC per start band; write results and figures.

    Runs single-threaded with subnormals flushed (:func:`~saml_ros.experiments.common.single_threaded`)."""
    s = settings
    timer = Timer()
    info = machine_info()
    system = get_system("quadrotor", drag=s.drag)
    assert isinstance(system, Quadrotor)
    spec, cmp = train_paper_comparison(system, s.seeds, s.n_train, min(s.n_test, 10000), s.hidden, s.epochs, timer,
                                       progress, spec_dict(system, s.loss, s.eps))
    with timer("test errors"):
        errors = model_errors(cmp, system, s.n_test, s.loss)
    k = min(s.mpc_seeds, len(s.seeds))
    bounds = residual_bounds(system, s) if s.guard else [None] * len(s.seeds)
    bar = progress_bar((2 * k + 2) * s.n_starts * len(s.bands), f"quadrotor landing MPC ({s.solver})", progress)
    control: dict[str, Any] = {}
    starts: dict[str, np.ndarray] = {}
    with timer("mpc"):
        for band, z in s.bands.items():
            x0s = landing_starts(system, s.n_starts, s.start_seed, z)
            starts[band] = x0s
            res: dict[str, Any] = {}
            for label, tm in (("uniform", cmp.uniform), ("sufficient", cmp.sufficient)):
                res[label] = _stack([evaluate_controller(system, tm.model.member(i), s, x0s, bar, bounds[i])
                                     for i in range(k)])
            ends: tuple[tuple[str, PredictionModel], ...] = (("base", None), ("oracle", ORACLE))
            for label, model in ends:
                res[label] = _stack([evaluate_controller(system, model, s, x0s, bar)])
            control[band] = res
    bar.close()
    stats = {band: control_stats(res) for band, res in control.items()}
    with timer("figures"):
        figs = [plot_landing(control, starts, out / "quadrotor_landing.png"),
                plot_training_curves({"sufficient": cmp.sufficient.history, "uniform": cmp.uniform.history},
                                     out / "quadrotor_training_curves.png")]
    data: dict[str, Any] = {
        "settings": s.__dict__, "system": system.params(), "spec": spec.to_dict(), "starts": starts,
        "errors": errors, "eps_relation": eps_relation(errors, s.eps),
        "models": save_models(out, {"sufficient": cmp.sufficient, "uniform": cmp.uniform}),
        "control": {b: {a: {m: v for m, v in c.items() if m != "xs"} for a, c in r.items()} for b, r in control.items()},
        "stats": stats, "training": training_summary(cmp),
        "figures": [f.name for f in figs], "timing": timer.to_dict(), "machine": info}
    data["claims"] = claims(data, s)
    write_results(out, markdown(data, s, timer), data)
    return data


def _stack(per_seed: list[dict[str, Any]]) -> dict[str, Any]:
    checks = PlanChecks()
    for r in per_seed:
        checks.merge(r["checks"])
    out: dict[str, Any] = {k: np.stack([r[k] for r in per_seed]) for k in per_seed[0]
                           if isinstance(per_seed[0][k], np.ndarray)}
    out["checks"] = checks
    out["guard"] = {k: sum(r["guard"].get(k, 0.0) for r in per_seed) for r in per_seed for k in r["guard"]}
    out["cpu_per_solve"] = float(np.mean([r["cpu_per_solve"] for r in per_seed]))
    return out


#: the paper's effect on the landing cost: SA 4.21 vs UA 4.55, (SA - UA) / UA = -7.5 %
PAPER_EFFECT = 0.075


def control_stats(res: dict[str, Any]) -> dict[str, Any]:
    """Per metric (cost, hover error): headroom with the learned arms' shares, the seed-level SA vs UA test, and
    (cost) the seeds a test needs to resolve the paper's effect, 7.5 % of UA's cost, at the measured spread."""
    out: dict[str, Any] = {}
    for metric in ("cost", "hover"):
        arms = {"UA": res["uniform"][metric], "SA": res["sufficient"][metric]}
        out[metric] = {"headroom": headroom(res["base"][metric][0], res["oracle"][metric][0], arms),
                       "sa_vs_ua": seed_test(res["uniform"][metric], res["sufficient"][metric])}
        if metric == "cost":
            diffs = np.nanmean(res["sufficient"][metric], 1) - np.nanmean(res["uniform"][metric], 1)
            out[metric]["power"] = power(diffs, PAPER_EFFECT * float(np.nanmean(res["uniform"][metric])))
    return out


def eps_relation(errors: dict[str, Any], eps: float) -> dict[str, float]:
    """UA's and SA's in-region error in units of eps (the paper implies about 1.8 and 1.1; docs/experiments.md)."""
    ua = float(np.mean(errors["uniform"]["loss_given_region"]))
    sa = float(np.mean(errors["sufficient"]["loss_given_region"]))
    return {"eps": eps, "ua_in_region": ua, "sa_in_region": sa, "ua_over_eps": ua / eps, "sa_over_eps": sa / eps,
            "eps_over_ua": eps / ua}


def claims(data: dict[str, Any], s: QuadrotorSettings) -> list[Claim]:
    name = f"quadrotor (drag {s.drag:g})"
    e = data["errors"]["paired_by_seed"]["loss_given_region"]
    out = [Claim(name, "SA's error near the ground (E[l | pz <= 1.5]) is below UA's",
                 "1.00e-4 vs 8.28e-4 (row read as E[l | I] − eps: 1.1e-3 vs 1.83e-3)",
                 f"{fmt(e.mean_b, 3, True)} vs {fmt(e.mean_a, 3, True)}; SA − UA {fmt(e.diff, 2, True)} "
                 f"[{fmt(e.ci_low, 2, True)}, {fmt(e.ci_high, 2, True)}] ({e.n} seeds)", "n/a (model error)",
                 verdict(True, e))]
    for band, st in data["stats"].items():
        for metric, what, paper in (("cost", "landing MPC cost Σ‖p_t‖", "4.21 vs 4.55 (−7.5 %)"),
                                    ("hover", "hover error at the height bound (our metric)", "—")):
            h, t = st[metric]["headroom"], st[metric]["sa_vs_ua"]
            p = t.by_seed
            note = f"SA captures {h.shares['SA'].pct(0)}, UA {h.shares['UA'].pct(0)} of the headroom"
            if metric == "cost":
                pw = st[metric]["power"]
                ua = p.mean_a
                excluded = np.isfinite(p.ci_low) and p.ci_low > -PAPER_EFFECT * ua
                note += (f"; the interval is {100 * (p.ci_low / ua):+.1f} to {100 * (p.ci_high / ua):+.1f} % of UA's "
                         f"cost: the paper's −{100 * PAPER_EFFECT:.1f} % is {'excluded' if excluded else 'inside it'}; "
                         f"{pw.line('', 2)}")
            out.append(Claim(name, f"SA's {what} is below UA's, starts {band}", paper,
                             f"{fmt(p.mean_b)} vs {fmt(p.mean_a)} ({100 * t.relative:+.1f} %); SA − UA {fmt(p.diff)} "
                             f"[{fmt(p.ci_low)}, {fmt(p.ci_high)}] ({p.n} seeds)", h.headroom.pct(),
                             verdict(h.enough, p), note))
    return out


def markdown(data: dict[str, Any], s: QuadrotorSettings, timer: Timer) -> str:
    e = data["errors"]
    er = data["eps_relation"]
    lines = [
        "# Quadrotor landing with ground effect: SA vs UA, base model and oracle, starts near and above the ground",
        "",
        f"Seeds {list(s.seeds)}; {s.n_train} training states per seed, {s.epochs} epochs, net {list(s.hidden)}; "
        f"true model drag {s.drag:g} 1/s; loss `{s.loss}`, eps = {s.eps:g} on E[l | pz <= 1.5]; test set "
        f"{s.n_test} ({100 * e['frac_inside']:.1f}% with pz <= 1.5 m). MPC ({s.solver}): T = {s.horizon}, "
        f"{s.n_starts} starts per band, {s.steps} steps on the true system with ground contact at "
        f"{s.landing_height} m; hover error = mean distance to (0, 0, {MIN_HEIGHT}) over the last {s.settle_steps} "
        f"steps; models of the first {min(s.mpc_seeds, len(s.seeds))} seed(s). Every arm's MPC keeps the tilt "
        f"|qx|, |qy| <= {s.tilt_max:g}; learned models fly "
        + ("with the demo's single-model guard (residual bound, roll back, infeasible-plan fallback)" if s.guard
           else "unguarded") + ". Primary test: SA − UA across seeds "
        "(per-seed means over the starts); pooling (seed, start) pairs is pseudo-replication.",
        "",
        "## Claims", "", claims_table(data["claims"]), "",
        f"## Model errors on the test set (`{s.loss}` over the 13 state fields)",
        "",
    ]
    rows = []
    for label in ("uniform", "sufficient"):
        r = e[label]
        rows.append([LABELS[label], fmt_ms(r["loss"], 3, True), fmt_ms(r["loss_times_indicator"], 3, True),
                     fmt_ms(r["loss_given_region"], 3, True), fmt_ms(r["loss_outside"], 3, True),
                     f"{PAPER['loss'][label]} / {PAPER['constraint'][label]}"])
    b = e["base"]
    rows.append([LABELS["base"], fmt(b["loss"], 3, True), fmt(b["loss_times_indicator"], 3, True),
                 fmt(b["loss_given_region"], 3, True), fmt(b["loss_outside"], 3, True), ""])
    lines += [md_table(["model", "E[l]", "E[l I]", "E[l \\| pz <= 1.5]", "E[l \\| pz > 1.5]",
                        "paper E[l] / \"E[g I]\""], rows), "", "Paired by seed (SA − UA):", "", PAIRED_HEADER]
    lines += [e["paired_by_seed"][k].row(k, 3, True)
              for k in ("loss", "loss_times_indicator", "loss_given_region", "loss_outside")]
    lam = data["training"]["lambda_final"]
    lines += ["", f"eps and the net: UA's in-region error is {er['ua_over_eps']:.2f} eps (eps = "
              f"{er['eps_over_ua']:.2f} x UA's), SA's {er['sa_over_eps']:.2f} eps; SA's final multipliers "
              f"{', '.join(f'{float(v):.2f}' for v in lam)}.", "", "## Landing MPC on the true system", ""]
    for band, res in data["control"].items():
        st = data["stats"][band]
        rows = []
        for label in ARMS:
            c = res[label]
            ch = c["checks"]
            rows.append([LABELS[label], fmt_ms(c["cost"], 2), fmt_ms(c["hover"], 3), fmt_ms(c["final_xy"], 3),
                         f"{int(np.sum(c['final_xy'] > MISS_DISTANCE))}/{c['final_xy'].size}", fmt_ms(c["final_z"], 3),
                         PAPER["mpc_cost"].get(label, ""), f"{1e3 * c['cpu_per_solve']:.1f}",
                         f"{ch.unsuccessful - ch.unavoidable} (+{ch.unavoidable})/{ch.solves}",
                         _guard_text(c.get("guard", {})), f"{ch.max_u_violation:.1e}",
                         f"{ch.max_state_violation_success:.1e}"])
        z = s.bands[band]
        lines += [f"### Starts `{band}` (z ~ U[{z[0]}, {z[1]}] m)", "",
                  md_table(["model", "Σ_t \\|p_t\\| (cost)", "hover error (m)", "final xy error (m)",
                            f"final xy error > {MISS_DISTANCE} m", "final height (m)", "paper MPC cost",
                            "CPU ms / solve", "unsuccessful solves (+ unavoidable: state already below the bound)",
                            "guard: steps on f_hat, roll backs", "max u bound violation",
                            "max height violation (successful plans)"], rows), ""]
        for metric, what in (("cost", "cost"), ("hover", "hover error")):
            lines += [f"* {what}: {st[metric]['headroom'].line()}.", f"* {what}: {st[metric]['sa_vs_ua'].line(3)}."]
            if "power" in st[metric]:
                lines.append(f"* {what}, power against the paper's effect ({100 * PAPER_EFFECT:.1f} % of UA's cost): "
                             f"{st[metric]['power'].line('', 2)}.")
        lines.append("")
    lines += ["## Figures", ""] + [f"![{f}]({f})" for f in data["figures"]] + ["", timer.markdown(), ""]
    return "\n".join(lines)


def _guard_text(g: dict[str, float]) -> str:
    """``"12 / 500, 0"``: the guard's steps planned with f_hat of its solves, and its roll backs ("—" unguarded)."""
    if not g:
        return "—"
    return f"{g.get('solves_base', 0):.0f} / {g.get('solves', 0):.0f}, {g.get('rollbacks', 0):.0f}"


def plot_landing(control: dict[str, Any], starts: dict[str, np.ndarray], path: Path) -> Path:
    """The first start of each band: closed-loop x-z trajectories (seed-0 models) and the last steps' heights."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    colors = {"uniform": "tab:gray", "sufficient": "tab:blue", "base": "tab:orange", "oracle": "tab:green"}
    bands = list(control)
    fig, axes = plt.subplots(2, len(bands), figsize=(6.5 * len(bands), 7.5), squeeze=False)
    for j, band in enumerate(bands):
        ax, az = axes[0, j], axes[1, j]
        for label, c in control[band].items():
            p = c["xs"][0, 0][:, 0:3]
            kw: dict[str, Any] = {"color": colors[label], "ls": "-" if label == "sufficient" else ":", "marker": ".",
                                  "ms": 3}
            ax.plot(np.hypot(p[:, 0], p[:, 1]), p[:, 2], label=LABELS[label], **kw)
            az.plot(np.arange(len(p)), p[:, 2], **kw)
        for a in (ax, az):
            a.axhline(MIN_HEIGHT, color="k", lw=0.6, ls=":")
            a.axhspan(0, 1.5, color="red", alpha=0.04)
        x0 = starts[band][0, :3]
        ax.set_title(f"{band}: start ({x0[0]:.2f}, {x0[1]:.2f}, {x0[2]:.2f}) m")
        ax.set_xlabel("horizontal distance to the target (m)")
        ax.set_ylabel("z (m)")
        ax.legend(fontsize=8)
        az.set_xlabel("step")
        az.set_ylabel("z (m)")
        az.set_ylim(0.15, 0.4)
        az.set_title("height near the ground (dotted: the MPC's bound 0.2 m)")
    fig.tight_layout()
    return save_figure(fig, path)
