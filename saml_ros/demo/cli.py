"""The main job (``./dev demo``): online model learning in a closed ROS 2 loop that measurably improves the control
of a quadrotor landing on a pad inside the ground effect, with guards that keep a learned model from flying it away.

``demo`` starts, as separate processes, the quadrotor simulator (lockstep), two learners on the same stream (the
paper's Sufficiently Accurate problem -- squared one-step error <= 0.001 where pz <= 1.5 m -- and the Uniformly
Accurate baseline, 5-member ensembles each) and the landing MPC, for a fixed simulated time
(:func:`saml_ros.bringup.run` with ``saml_ros.bringup.default_config("quadrotor")``). The MPC starts on the base
model f_hat, hot-swaps the SA learner's checkpoints and guards them (docs/mpc.md, "Guarded MPC"): steps where the
ensemble disagrees are planned with f_hat, the residual is bounded by the largest one in the data, and a live
monitor rolls back to the previous model (or f_hat) when the model in use predicts the flown transitions worse
than f_hat.

Then, ROS-free, from the SAME fresh start states (``--eval-starts`` from the simulator's sampler and
``--aggressive-starts`` far and fast ones), the same MPC flies the task on the simulator's dynamics with: the base
model, the oracle (the true dynamics: the most any model can give, measured first), the final SA checkpoint and
the final UA checkpoint (both guarded, as live). It prints the metrics that see what the model changes (landing
error, height error above the floor, settling time, overshoot, horizontal error, MPC cost), the oracle's headroom,
each learned model's gain with its 95 % CI and the fraction of the headroom it captures, SA vs UA, and the worst
cases; writes PNGs and ``demo_summary.json`` into the run directory (``--figures`` also copies the PNGs there).

``demo --offline [...]`` is the offline Sufficiently vs Uniformly Accurate comparison on the double integrator;
``demo --aggregate RUN_DIR ...`` pools several demo runs (:mod:`saml_ros.demo.aggregate`); ``demo --guards RUN_DIR``
and ``demo --spread RUN_DIR --start SET:I`` re-fly a run's checkpoint (:mod:`saml_ros.demo.guards`).
"""

from __future__ import annotations

import argparse
import json
import math
import shutil
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from saml_ros.demo.landing import FAR, METRICS, TASK_METRIC, WORLDS

#: simulated seconds of the live loop (36 landing episodes of 5 s; the in-region error is within 20 % of its
#: 300 s value after 150 s)
DEMO_SIM_TIME = 180.0
#: fresh starts of the paired evaluation from the simulator's sampler, and far / fast ones
DEMO_EVAL_STARTS = 30
DEMO_AGGRESSIVE_STARTS = 10
#: the live loop's speed limit (simulated seconds per wall second, the simulator's ``max_speed``): in lockstep the
#: two training processes share the 2 cores with the loop, so a faster MPC leaves them less CPU per simulated
#: second. Unlimited, the MPC's C kernel (5-5.8x real time) halved the learners' updates in the 180 s (2546-3201,
#: against 6358 with the numpy SQP at 3x); at 5x they made 7938 (docs/demo.md, "Time and speed").
#: ``--set sim.max_speed=0`` lifts it.
DEMO_MAX_SPEED = 5.0
#: the demo's default world (``--world``; :data:`~saml_ros.demo.landing.WORLDS`)
DEMO_WORLD = "wind"
#: starts drawn in the trajectory picture
PICTURE_STARTS = 4


def run_evaluation(run_dir: Path, config: dict[str, Any], n_standard: int, n_aggressive: int, seed: int,
                   workers: int | None = None) -> dict[str, Any] | None:
    """The paired evaluation of base, oracle, SA and UA (see the module docstring); None without an SA checkpoint."""
    from saml_ros.bringup.config import CHECKPOINTS, CHECKPOINTS_UA
    from saml_ros.demo.evaluation import (
        Arm,
        evaluate_arms,
        evaluation_starts,
        newest_checkpoint,
        paired_diff,
        run_task_and_guard,
        summarize,
    )

    sa = newest_checkpoint(run_dir / CHECKPOINTS)
    if sa is None:
        return None
    ua = newest_checkpoint(run_dir / CHECKPOINTS_UA)
    mpc = config["mpc"]
    task, guard = run_task_and_guard(config)
    system = task.system()
    arms = [Arm("base", "base"), Arm("oracle", "oracle"), Arm("SA", str(sa[0]), guard)]
    if ua is not None:
        arms.append(Arm("UA", str(ua[0]), guard))
    learned = [a.name for a in arms if a.learned]
    sets = evaluation_starts(system, n_standard, n_aggressive, seed)
    out: dict[str, Any] = {"task": task.__dict__, "guard": {"max_disagreement": guard.max_disagreement,
                                                           "bound_residual": guard.bound_residual,
                                                           "rollback": guard.rollback,
                                                           "infeasible": guard.infeasible},
                           "checkpoints": {"SA": [str(sa[0]), sa[1]], "UA": [str(ua[0]), ua[1]] if ua else None},
                           "sets": {}}
    for name, starts in sets.items():
        if not len(starts):
            continue
        t0 = time.monotonic()
        res = evaluate_arms(arms, task, starts, str(mpc.get("solver", "fast")), workers)
        summary = summarize(res, learned=learned)
        if "UA" in res:
            summary["sa_vs_ua"] = {k: paired_diff(res["UA"].metrics[k], res["SA"].metrics[k]) for k in METRICS}
        summary["per_start"] = {a: {k: r.metrics[k].tolist() for k in r.metrics} for a, r in res.items()}
        summary["seconds"] = time.monotonic() - t0
        summary["xs"] = {a: r.xs[:PICTURE_STARTS] for a, r in res.items()}
        out["sets"][name] = summary
    out["arms"] = [a.name for a in arms]
    out["learned"] = learned
    return out


def format_evaluation(ev: dict[str, Any]) -> str:
    """The evaluation tables and the checks of issue #10's "what must show"."""
    from saml_ros.demo.evaluation import format_table

    arms, learned = ev["arms"], ev["learned"]
    lines = [f"evaluation: the same MPC (pad at {tuple(ev['task']['pad'])} m, tilt <= {ev['task']['tilt_max']:g}) on "
             f"the simulator's dynamics from the same starts; SA = checkpoint v{ev['checkpoints']['SA'][1]}"
             + (f", UA = v{ev['checkpoints']['UA'][1]}" if ev["checkpoints"]["UA"] else "")
             + " (both guarded as live); differences are base - model (> 0: the model is better), 95 % t CI; "
               "captured = gain / oracle headroom [bootstrap 95 %]"]
    for name, s in ev["sets"].items():
        lines.append(f"\n{name} starts ({s['n']}, {s['seconds']:.0f} s):")
        lines.append(format_table(s, arms, learned))
        if "sa_vs_ua" in s:
            d = s["sa_vs_ua"][TASK_METRIC]
            lines.append(f"  SA vs UA, {METRICS[TASK_METRIC][0]}: UA - SA = {d['diff']:+.4f} m [{d['lo']:+.4f}, "
                         f"{d['hi']:+.4f}] (p = {d['p']:.2g}; SA lower on {100 * d['frac_b_better']:.0f}% of starts)")
        worst = ", ".join(f"{a} {s['worst'][a]:.3f} m ({s['far'][a]} > {FAR:g} m)" for a in arms)
        lines.append(f"  worst landing error: {worst}")
        for a, g in s["guard"].items():
            lines.append(f"  guard ({a}): {g.get('solves_base', 0):.0f} of {g.get('solves', 0):.0f} steps on f_hat, "
                         f"{g.get('fallbacks', 0):.0f} ensemble fallbacks, {g.get('infeasible_fallbacks', 0):.0f} "
                         f"infeasible-plan fallbacks, {g.get('task_fallbacks', 0):.0f} task-check fallbacks, "
                         f"{g.get('rollbacks', 0):.0f} roll backs ({g.get('task_rollbacks', 0):.0f} by the task check), "
                         f"{g.get('bounded', 0):.0f} steps with the residual bounded")
    lines.append("\n" + "\n".join(checks(ev)))
    return "\n".join(lines)


def checks(ev: dict[str, Any]) -> list[str]:
    """Issue #10's "what must show" on this run's numbers (gain CI, captured headroom, worst cases)."""
    out = ["checks:"]
    std = ev["sets"].get("standard")
    if std is not None and "SA" in ev["learned"]:
        row = std["metrics"][TASK_METRIC]
        g, c = row["gain/SA"], row.get("captured/SA", {})
        out.append(f"  SA gain over base on the landing error: {g['diff']:+.4f} m [{g['lo']:+.4f}, {g['hi']:+.4f}] "
                   f"-> CI excludes 0: {'yes' if g['lo'] > 0 else 'NO'}; captures "
                   f"{100 * c.get('capture', math.nan):.0f}% of the oracle's headroom (>= 50%: "
                   f"{'yes' if c.get('capture', 0) >= 0.5 else 'NO'})")
    for a in ev["learned"]:
        worst_l = max(s["worst"][a] for s in ev["sets"].values())
        worst_b = max(s["worst"]["base"] for s in ev["sets"].values())
        far = sum(s["far"][a] for s in ev["sets"].values())
        n = sum(s["n"] for s in ev["sets"].values())
        out.append(f"  {a}: {far} of {n} evaluation episodes end > {FAR:g} m from the pad; worst {worst_l:.3f} m vs "
                   f"base's worst {worst_b:.3f} m over the same starts (no worse: {'yes' if worst_l <= worst_b else 'NO'})")
    return out


def write_figures(ev: dict[str, Any] | None, res: Any, out_dir: Path) -> list[Path]:
    """The PNGs (trajectories, live model error, per-start landing errors) into ``out_dir``."""
    from saml_ros.demo.figures import plot_live_error, plot_paired, plot_trajectories

    figs = [plot_live_error(res.status_log, res.episodes, out_dir / "live_model_error.png")]
    if ev is not None and "standard" in ev["sets"]:
        xs = ev["sets"]["standard"]["xs"]
        pad = np.asarray(ev["task"]["pad"], dtype=np.float64)
        figs.append(plot_trajectories({a: xs[a] for a in ("base", "SA", "oracle") if a in xs}, pad,
                                      out_dir / "trajectories.png",
                                      title=f"the same {PICTURE_STARTS} starts: base model, learned (SA, guarded), "
                                            "oracle"))
        pairs = {name: (np.asarray(s["per_start"]["base"][TASK_METRIC]), np.asarray(s["per_start"]["SA"][TASK_METRIC]))
                 for name, s in ev["sets"].items() if "SA" in s["per_start"]}
        figs.append(plot_paired(pairs, out_dir / "paired_landing_error.png"))
    return figs


def demo_config(seed: int, sim_time: float, world: str = DEMO_WORLD) -> dict[str, Any]:
    """The quadrotor's bringup defaults with the UA learner, the simulator seed, the simulated time, the live
    loop's speed limit (:data:`DEMO_MAX_SPEED`) and the world (:data:`~saml_ros.demo.landing.WORLDS`: the
    simulator's ``system.*`` parameters, which the evaluation reads too)."""
    from saml_ros import bringup

    if world not in WORLDS:
        raise ValueError(f"unknown demo world {world!r}; valid: {sorted(WORLDS)}")
    config = bringup.default_config("quadrotor")
    config["sim_time"] = sim_time
    config["sim"]["seed"] = seed
    config["sim"].update({f"system.{k}": v for k, v in WORLDS[world].items()})
    config["sim"].setdefault("max_speed", DEMO_MAX_SPEED)
    config.setdefault("learner_ua", {})
    return config


def live_config(seed: int, sim_time: float, sets: list[str], world: str = DEMO_WORLD) -> dict[str, Any]:
    """:func:`demo_config` with ``--set`` overrides applied (the UA learner takes the learner's parameters,
    :func:`saml_ros.bringup.config.node_params`, unless one is set for it)."""
    from saml_ros import bringup

    config = demo_config(seed, sim_time, world)
    return bringup.apply_sets(config, sets) if sets else config


def closed_loop_main(argv: list[str]) -> int:
    """``demo``: the quadrotor closed loop, then the evaluation (see the module docstring)."""
    from saml_ros import bringup

    p = argparse.ArgumentParser(prog="demo", description=(__doc__ or "").split("\n\n")[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--offline", action="store_true",
                   help="the offline double-integrator comparison instead (see demo --offline --help)")
    p.add_argument("--aggregate", action="store_true",
                   help="pool the demo_summary.json of several run directories instead (demo --aggregate --help)")
    p.add_argument("--guards", action="store_true",
                   help="fly one run's final checkpoint with each guard setting instead (demo --guards --help)")
    p.add_argument("--sim-time", type=float, default=DEMO_SIM_TIME, help="simulated seconds of the live loop")
    p.add_argument("--eval-starts", type=int, default=DEMO_EVAL_STARTS,
                   help="fresh starts of the paired evaluation from the simulator's sampler (0 = none)")
    p.add_argument("--aggressive-starts", type=int, default=DEMO_AGGRESSIVE_STARTS,
                   help="far and fast starts of the paired evaluation (0 = none)")
    p.add_argument("--seed", type=int, default=0, help="simulator seed; also added to the evaluation seeds")
    p.add_argument("--world", choices=sorted(WORLDS), default=DEMO_WORLD,
                   help="paper: the ground effect alone; wind: plus a wind field above the pad's shelter (the "
                        "simulator, the oracle and the evaluation alike; docs/demo.md)")
    p.add_argument("--workers", type=int, help="evaluation processes (default: 2)")
    p.add_argument("--run-dir", type=Path, help="run directory (default: a new runs/bringup-quadrotor-...)")
    p.add_argument("--figures", type=Path, help="also copy the PNGs into this directory")
    p.add_argument("--domain-id", type=int, help="ROS_DOMAIN_ID (default: the environment's)")
    p.add_argument("--progress-period", type=float, default=10.0, help="wall seconds between progress lines")
    p.add_argument("--set", dest="sets", action="append", default=[], metavar="SECTION.PARAM=VALUE",
                   help="override a node parameter, as bringup's --set (an mpc.* value applies to the evaluation too; e.g. "
                        "learner.training_idle=false); repeatable")
    p.add_argument("--startup-timeout", type=float, default=300.0,
                   help="wall seconds the nodes may take to come up (a loaded machine: over 90 s was measured)")
    args = p.parse_args(argv)
    t0 = time.monotonic()
    config = live_config(args.seed, args.sim_time, args.sets, args.world)
    steps = int(config["sim"]["episode_steps"])
    pad = config["mpc"].get("goal.position")
    limit = float(config["sim"].get("max_speed", 0.0) or 0.0)
    pace = f" at most {limit:g}x real time" if limit > 0 else ""
    wind = " and a wind field above the pad's shelter (--world wind)" if WORLDS[args.world] else ""
    print(f"demo: quadrotor landing on a pad at {pad} m inside the ground effect{wind}, closed loop over ROS 2 (simulator "
          f"in lockstep{pace} + SA and UA learners + guarded MPC, separate processes), {args.sim_time:g} s of simulated time "
          f"= {args.sim_time / (steps * 0.1):.0f} landing episodes of {steps * 0.1:g} s; the MPC starts on the base "
          f"model and follows the SA learner's checkpoints", flush=True)
    res = bringup.run(config, bringup.RunOptions(run_dir=args.run_dir, domain_id=args.domain_id,
                                                 progress_period=args.progress_period,
                                                 startup_timeout=args.startup_timeout))
    print()
    live_text = bringup.format_summary(res)
    print(live_text, flush=True)
    t_live = time.monotonic() - t0
    ev, ev_text = None, ""
    # children that had to be killed after the loop ran its full time still left their checkpoints
    if (args.eval_starts > 0 or args.aggressive_starts > 0) and (res.ok or res.stop_reason == "sim_time"):
        print(f"\ndemo: paired evaluation of base, oracle, SA, UA from {args.eval_starts} standard + "
              f"{args.aggressive_starts} aggressive fresh starts ...", flush=True)
        ev = run_evaluation(res.run_dir, config, args.eval_starts, args.aggressive_starts, args.seed, args.workers)
        if ev is None:
            print("demo: the learner wrote no checkpoint: nothing to evaluate")
        else:
            ev_text = format_evaluation(ev)
            print(ev_text)
    figs = res_figs = write_figures(ev, res, res.run_dir / "figures")
    if args.figures is not None:
        args.figures.mkdir(parents=True, exist_ok=True)
        figs = [Path(shutil.copy(f, args.figures / f.name)) for f in figs]
    total = time.monotonic() - t0
    print(f"\ndemo: figures: {', '.join(str(f) for f in figs)}")
    print(f"demo: total wall time {total:.0f} s (live loop {t_live:.0f} s); run directory {res.run_dir}")
    live_learned = [e for e in res.episodes if e.model_first > 0]
    summary = {"bringup": {"sim_time": res.sim_time, "wall_time": res.wall_time, "stop_reason": res.stop_reason,
                           "error_before_after": res.error_before_after(), "model_versions": res.model_versions,
                           "guard": res.guard,
                           "live_learned_far": sum(e.error > FAR for e in live_learned),
                           "live_learned_worst": max((e.error for e in live_learned), default=math.nan),
                           "episodes": [{"error": e.error, "xy_error": e.xy_error, "model_first": e.model_first,
                                         "model_last": e.model_last, "t_start": e.t_start} for e in res.episodes]},
               "evaluation": _jsonable(ev), "wall_seconds": total, "live_seconds": t_live}
    (res.run_dir / "demo_summary.json").write_text(json.dumps(summary, indent=1, default=float))
    md = ["# demo run", "", f"`./dev demo {' '.join(argv)}`: total wall time {total:.0f} s (live loop {t_live:.0f} s)",
          "", "## live closed loop", "", "```", live_text, "```", "", "## paired evaluation", "", "```",
          ev_text or "(none)", "```", "", "## figures", ""] + [f"![{f.stem}](figures/{f.name})" for f in
                                                                res_figs]
    (res.run_dir / "demo_summary.md").write_text("\n".join(md) + "\n")
    print(f"demo: results in {res.run_dir / 'demo_summary.json'} and {res.run_dir / 'demo_summary.md'}")
    return 0 if res.ok else 1


def _jsonable(obj: Any) -> Any:
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items() if k != "xs"}
    if isinstance(obj, list | tuple):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.floating | np.integer):
        return obj.item()
    return obj


def main(argv: list[str] | None = None) -> int:
    """``demo`` (closed loop) or ``demo --offline ...`` (the offline comparison)."""
    args = list(sys.argv[1:] if argv is None else argv)
    if "--offline" in args:
        from saml_ros.demo.offline import offline_main

        args.remove("--offline")
        return offline_main(args)
    if "--guards" in args:
        from saml_ros.demo.guards import guards_main

        args.remove("--guards")
        return guards_main(args)
    if "--spread" in args:
        from saml_ros.demo.guards import spread_main

        args.remove("--spread")
        return spread_main(args)
    if "--aggregate" in args:
        from saml_ros.demo.aggregate import aggregate_main

        args.remove("--aggregate")
        return aggregate_main(args)
    return closed_loop_main(args)
