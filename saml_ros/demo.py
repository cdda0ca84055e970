"""The main job (``./dev demo``): online model learning in a closed ROS 2 loop — quadrotor landing with ground effect.

``demo`` starts, as separate processes, the quadrotor simulator (lockstep), the learner (the paper's Sufficiently
Accurate problem: squared one-step error <= 0.001 where pz <= 1.5 m) and the landing MPC, for a fixed simulated
time (:func:`saml_ros.bringup.run` with ``saml_ros.bringup.default_config("quadrotor")``, the quadrotor registry
entry's ``bringup`` defaults).
The MPC starts on the base model f_hat (no ground effect) and hot-swaps each checkpoint the learner writes.

Then it prints a before/after summary:

1. live, from the topics: the learner's one-step error inside the region (first vs last reports) and the landing
   error (distance from the target at the end of each 5 s episode) of the episodes flown on the base model vs
   the last episodes flown on learned models;
2. an evaluation with identical start states (ROS-free, the same MPC code and the simulator's dynamics with its
   ground contact): the final checkpoint vs the base model from ``--eval-starts`` fresh starts, paired.

``demo --offline [--seeds N --epochs N --samples N --test-samples N --out DIR]`` is the earlier offline
comparison (Sufficiently vs Uniformly Accurate on the double integrator with friction), unchanged.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from saml_ros.core.spec import ProblemSpec
from saml_ros.core.systems import get_system
from saml_ros.core.training import TrainConfig
from saml_ros.offline.pipelines import compare
from saml_ros.offline.plots import plot_comparison, plot_error_map, plot_training_curves

#: simulated seconds of the live loop (60 landing episodes of 5 s)
DEMO_SIM_TIME = 300.0
#: fresh start states of the paired evaluation
DEMO_EVAL_STARTS = 10
#: seed of the evaluation starts (the simulator's episodes use seed 0)
EVAL_SEED = 4242


# ------------------------------------------------------------------------------------------- offline
def offline_main(argv: list[str] | None = None) -> int:
    """``demo --offline``: Sufficiently vs Uniformly Accurate on the double integrator with friction.

    Trains both models with the paper's settings (4-2 PReLU residual net, 15k samples, Adam 1e-3 / 1e-4,
    200 epochs, region ||[p, v]||_inf <= 0.5, eps = 0.035) for several seeds at once, evaluates them on a
    held-out test set, prints the comparison and writes figures to ``--out``.
    """
    p = argparse.ArgumentParser(prog="demo --offline",
                                description="Sufficiently vs Uniformly Accurate on the double integrator with "
                                            "friction (offline)",
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--seeds", type=int, default=3, help="models per formulation (trained as one ensemble)")
    p.add_argument("--epochs", type=int, default=200)
    p.add_argument("--samples", type=int, default=15000)
    p.add_argument("--test-samples", type=int, default=20000)
    p.add_argument("--out", type=Path, default=Path("results/demo"))
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.ERROR)  # per-seed feasibility warnings are summarised below
    system = get_system("friction")
    spec = ProblemSpec.for_system(system.paper_spec(), system)
    print(f"demo: double integrator with friction; {spec.describe()}")
    print(f"demo: training {args.seeds} Sufficiently + {args.seeds} Uniformly Accurate 4-2 PReLU residual "
          f"models, {args.samples} samples, {args.epochs} epochs ...")
    t0 = time.perf_counter()
    cmp = compare(system, spec, TrainConfig(epochs=args.epochs), list(range(args.seeds)), args.samples,
                  args.test_samples, progress=True)
    elapsed = time.perf_counter() - t0
    args.out.mkdir(parents=True, exist_ok=True)
    table = cmp.table()
    wins = cmp.per_seed_wins()[0]
    verdict = ("holds" if cmp.claim_holds() else "does NOT hold")
    lam = cmp.sufficient.trainer.lam.numpy().ravel()
    summary = (
        f"{table}\n"
        f"Sufficiently Accurate is more accurate inside the region for {wins}/{args.seeds} seeds; the paper's "
        f"claim (better inside, worse outside) {verdict} on average.\n"
        f"Final lambda per seed: {np.round(lam, 3).tolist()}; wall time {elapsed:.0f} s.\n"
    )
    print()
    print(summary)
    figs = [
        plot_training_curves({"sufficient": cmp.sufficient.history, "uniform": cmp.uniform.history},
                             args.out / "training_curves.png", title="double integrator: primal-dual training"),
        plot_comparison(cmp, args.out / "errors_by_region.png"),
        plot_error_map(system, {"Sufficiently Accurate (seed 0)": cmp.sufficient.model.member(0),
                                "Uniformly Accurate (seed 0)": cmp.uniform.model.member(0)},
                       args.out / "error_map_u1.png"),
    ]
    (args.out / "summary.md").write_text(summary)
    (args.out / "summary.json").write_text(json.dumps({
        "claim_holds": cmp.claim_holds(), "wins_inside": wins, "seconds": elapsed,
        "sufficient": {r.name: {"inside": r.inside.tolist(), "outside": r.outside.tolist(),
                                "overall": r.overall.tolist()} for r in cmp.eval_sufficient.regions},
        "uniform": {r.name: {"inside": r.inside.tolist(), "outside": r.outside.tolist(),
                             "overall": r.overall.tolist()} for r in cmp.eval_uniform.regions},
    }, indent=2))
    print("demo: figures: " + ", ".join(str(f) for f in figs))
    return 0


# ---------------------------------------------------------------------------------------- closed loop
def evaluate(run_dir: Path, config: dict[str, Any], n_starts: int, steps: int) -> dict[str, Any] | None:
    """Paired landings from ``n_starts`` fresh starts: the newest valid checkpoint in ``run_dir`` vs the base model.

    Returns per-start metrics of both (``final_dist``, ``final_xy``, ``final_z``, ``cost``), the checkpoint
    version and the paired comparisons, or ``None`` when the run left no checkpoint.
    """
    from saml_ros.core.checkpoint import CheckpointStore
    from saml_ros.core.model_io import model_from_payload
    from saml_ros.core.mpc import closed_loop, make_controller
    from saml_ros.experiments.common import paired
    from saml_ros.experiments.quadrotor import landing_starts, plant, rollout_metrics

    store = CheckpointStore(run_dir)
    found = store.load_latest_valid()
    if found is None:
        return None
    system = get_system("quadrotor")
    loaded = model_from_payload(found.arrays, found.meta, expect=system, path=found.path)
    mpc = config["mpc"]
    goal = np.asarray(mpc.get("goal.position", [0.0, 0.0, 0.0]), dtype=np.float64)
    options = {"horizon": int(mpc.get("horizon", 10))}
    options.update({k.split(".", 1)[1]: v for k, v in mpc.items() if k.startswith("task.")})
    landing_height = float(config["sim"].get("landing_height", 0.1))
    f = plant(system, landing_height)  # type: ignore[arg-type]
    starts = landing_starts(system, n_starts, EVAL_SEED)  # type: ignore[arg-type]
    out: dict[str, Any] = {"version": loaded.version, "path": str(found.path), "starts": starts.tolist()}
    for label, model in (("base", None), ("learned", loaded.model)):
        ctrl = make_controller(system, model, str(mpc.get("solver", "fast")), **options)
        rows = [rollout_metrics(closed_loop(system, ctrl, x0, steps, goal=goal, true_step=f)) for x0 in starts]
        out[label] = {k: [r[k] for r in rows] for k in rows[0]}
    out["paired"] = {k: paired(out["base"][k], out["learned"][k]).to_dict()
                     for k in ("final_dist", "final_xy", "final_z", "cost")}
    return out


def format_evaluation(ev: dict[str, Any]) -> str:
    """The evaluation table: means and medians of base vs learned, paired over the same starts."""
    n = len(ev["starts"])
    lines = [f"evaluation: {n} fresh starts (seed {EVAL_SEED}), same MPC, simulator dynamics; checkpoint "
             f"version {ev['version']} vs the base model f_hat",
             f"  {'metric':<36} {'mean: base':>10} {'learned':>8} {'median: base':>13} {'learned':>8} "
             f"{'learned - base [95% CI]':>26} {'learned better':>15}"]
    names = {"final_dist": "landing error |p_T - target| (m)", "final_xy": "horizontal landing error (m)",
             "final_z": "final height (m; MPC keeps >= 0.2)", "cost": "MPC cost sum_t |p_t - target| (m)"}
    for key, label in names.items():
        p = ev["paired"][key]
        med_a, med_b = float(np.median(ev["base"][key])), float(np.median(ev["learned"][key]))
        ci = f"{p['diff']:+.3f} [{p['ci_low']:+.3f}, {p['ci_high']:+.3f}]"
        lines.append(f"  {label:<36} {p['mean_a']:>10.3f} {p['mean_b']:>8.3f} {med_a:>13.3f} {med_b:>8.3f} "
                     f"{ci:>26} {100 * p['frac_b_better']:>14.0f}%")
    worst = int(np.argmax(np.asarray(ev["learned"]["final_dist"]) - np.asarray(ev["base"]["final_dist"])))
    lines.append(f"  worst start for the learned model: #{worst} (landing error {ev['base']['final_dist'][worst]:.3f} m "
                 f"with f_hat, {ev['learned']['final_dist'][worst]:.3f} m learned)")
    return "\n".join(lines)


def closed_loop_main(argv: list[str]) -> int:
    """``demo``: the quadrotor closed loop, then the summary (see the module docstring)."""
    from saml_ros import bringup

    p = argparse.ArgumentParser(prog="demo", description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--offline", action="store_true",
                   help="the offline double-integrator comparison instead (see demo --offline --help)")
    p.add_argument("--sim-time", type=float, default=DEMO_SIM_TIME, help="simulated seconds of the live loop")
    p.add_argument("--eval-starts", type=int, default=DEMO_EVAL_STARTS,
                   help="fresh starts of the paired evaluation (0 = skip it)")
    p.add_argument("--run-dir", type=Path, help="run directory (default: a new runs/bringup-quadrotor-...)")
    p.add_argument("--domain-id", type=int, help="ROS_DOMAIN_ID (default: the environment's)")
    p.add_argument("--progress-period", type=float, default=10.0, help="wall seconds between progress lines")
    args = p.parse_args(argv)
    t0 = time.monotonic()
    config = bringup.default_config("quadrotor")
    config["sim_time"] = args.sim_time
    steps = int(config["sim"]["episode_steps"])
    print(f"demo: quadrotor landing with ground effect, closed loop over ROS 2 (simulator in lockstep + learner "
          f"+ MPC, separate processes), {args.sim_time:g} s of simulated time = {args.sim_time / (steps * 0.1):.0f} "
          f"landing episodes of {steps * 0.1:g} s; the MPC starts on the base model and follows the learner's "
          f"checkpoints", flush=True)
    res = bringup.run(config, bringup.RunOptions(run_dir=args.run_dir, domain_id=args.domain_id,
                                                 progress_period=args.progress_period))
    print()
    print(bringup.format_summary(res), flush=True)
    ev = None
    if args.eval_starts > 0 and res.ok:
        print(f"\ndemo: evaluating the final checkpoint vs the base model from {args.eval_starts} fresh starts ...",
              flush=True)
        t_eval = time.monotonic()
        ev = evaluate(res.run_dir / "checkpoints", config, args.eval_starts, steps)
        if ev is None:
            print("demo: the learner wrote no checkpoint: nothing to evaluate")
        else:
            print(format_evaluation(ev))
            print(f"  ({time.monotonic() - t_eval:.0f} s)")
    total = time.monotonic() - t0
    print(f"\ndemo: total wall time {total:.0f} s; run directory {res.run_dir} (logs/, checkpoints/, params/)")
    summary = {"bringup": {"sim_time": res.sim_time, "wall_time": res.wall_time, "stop_reason": res.stop_reason,
                           "error_before_after": res.error_before_after(), "model_versions": res.model_versions,
                           "episodes": [{"error": e.error, "xy_error": e.xy_error, "model_first": e.model_first,
                                         "model_last": e.model_last, "t_start": e.t_start} for e in res.episodes]},
               "evaluation": ev, "wall_seconds": total}
    (res.run_dir / "demo_summary.json").write_text(json.dumps(summary, indent=2, default=float))
    return 0 if res.ok else 1


def main(argv: list[str] | None = None) -> int:
    """``demo`` (closed loop) or ``demo --offline ...`` (the offline comparison, unchanged)."""
    args = list(sys.argv[1:] if argv is None else argv)
    if "--offline" in args:
        args.remove("--offline")
        return offline_main(args)
    return closed_loop_main(args)


if __name__ == "__main__":
    raise SystemExit(main())
