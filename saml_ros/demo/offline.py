"""``demo --offline``: Sufficiently vs Uniformly Accurate on the double integrator with friction (offline)."""

from __future__ import annotations

import argparse
import json
import logging
import time
from pathlib import Path

import numpy as np

from saml_ros.core.spec import ProblemSpec
from saml_ros.core.systems import get_system
from saml_ros.core.training import TrainConfig
from saml_ros.offline.pipelines import compare
from saml_ros.offline.plots import plot_comparison, plot_error_map, plot_training_curves


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
    cmp = compare(system, spec, TrainConfig.paper(epochs=args.epochs), list(range(args.seeds)), args.samples,
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
