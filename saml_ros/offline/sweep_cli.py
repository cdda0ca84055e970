"""``sweep``: train a grid of models and map the in-region vs out-of-region error trade-off (saml_ros.offline.sweep).

    sweep --system friction --grid eps=0.02,0.035,0.05,0.08 --grid seed=0,1,2 --epochs 60 --samples 5000
    sweep --system friction --grid eps=0.03,0.05 --grid hidden=4x2,8x4 --task 10      # + MPC closed-loop cost
    sweep --system quadrotor --bag runs/bag1 runs/bag2 --grid eps=0.001,0.003 --ray local --ray-cpus 2
    sweep --system friction --grid eps=0.02,0.05 --ray auto       # on a running cluster (ray start --head)

Writes results.md (the table; * marks the Pareto front of the first constraint's held-out in/out error),
results.csv, results.json (with wall times) and pareto.png into --out. In-process and Ray runs of the same grid
give the same table.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from saml_ros.core.systems import SYSTEM_NAMES


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="sweep", description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__.split("\n", 1)[1])
    p.add_argument("--system", required=True, choices=SYSTEM_NAMES)
    p.add_argument("--spec", type=Path, help="problem spec YAML (default: the paper's spec for the system)")
    p.add_argument("--grid", action="append", default=[], metavar="AXIS=V1,V2,...",
                   help="a swept axis (repeatable): eps, eps.<constraint>, hidden (8x4), seed, samples, kind, "
                        "uniform, or a TrainConfig field (epochs, primal_lr, ...)")
    p.add_argument("--bag", type=Path, nargs="+", help="train on these recorded bags (80/20 split) instead of "
                                                        "generated data")
    p.add_argument("--samples", type=int, default=5000, help="generated training transitions per point")
    p.add_argument("--test-samples", type=int, default=5000, help="held-out generated transitions")
    p.add_argument("--epochs", type=int, default=50)
    p.add_argument("--hidden", help="hidden sizes of every point unless swept, e.g. 8x4 (default: the paper's)")
    p.add_argument("--task", type=int, metavar="STARTS", help="also run the MPC from STARTS fixed starts per point "
                                                             "(friction, quadrotor) and report its closed-loop cost")
    p.add_argument("--task-steps", type=int, default=40, help="closed-loop steps per start (default 40)")
    p.add_argument("--ray", help="run the points on Ray: local (a private instance), auto (the running cluster) "
                                 "or a cluster address; default: in this process")
    p.add_argument("--ray-cpus", type=int, help="CPUs of a --ray local instance (default: all)")
    p.add_argument("--device", default="cpu", help="training device: cpu | cuda | cuda:N (checked first)")
    p.add_argument("--out", type=Path, help="output directory (default: runs/sweep-<system>-<time>)")
    p.add_argument("--quiet", action="store_true", help="no per-point progress lines")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(sys.argv[1:] if argv is None else argv)
    from saml_ros.core.runtime.device import DeviceError, resolve_device
    from saml_ros.offline.parallel import RayUnavailable, check_ray
    from saml_ros.offline.sweep import (
        SweepError,
        SweepSetup,
        Task,
        parse_grid,
        parse_value,
        run_sweep,
        table,
        write_outputs,
    )

    try:
        resolve_device(args.device)
        check_ray(args.ray)
        grid = parse_grid(args.grid) if args.grid else {"seed": [0]}
        base: dict[str, object] = {"samples": args.samples, "epochs": args.epochs, "seed": 0}
        if args.hidden:
            base["hidden"] = parse_value("hidden", args.hidden)
        spec = None
        if args.spec is not None:
            import yaml

            spec = yaml.safe_load(args.spec.read_text())
        data = None
        if args.bag:
            data = _bag_data(args.bag, args.system)
        task = Task(starts=args.task, steps=args.task_steps) if args.task else None
        setup = SweepSetup(args.system, spec, base, task, data, args.test_samples, args.device)
    except (DeviceError, RayUnavailable, SweepError, OSError, ValueError) as exc:
        print(f"sweep: {exc}", file=sys.stderr)
        return 2
    out = args.out or Path("runs") / f"sweep-{args.system}-{time.strftime('%Y%m%d-%H%M%S')}"
    n = 1
    for values in grid.values():
        n *= len(values)
    print(f"sweep: {args.system}, {n} points ({' x '.join(f'{a} {len(v)}' for a, v in grid.items())}) on "
          f"{args.ray or 'this process'} -> {out}", flush=True)

    def progress(i: int, row: dict[str, Any]) -> None:
        if not args.quiet:
            print(f"sweep: point {i} trained in {float(row['train_seconds']):.2f} s", flush=True)

    try:
        result = run_sweep(grid, setup, ray=args.ray, num_cpus=args.ray_cpus, on_result=progress)
    except (SweepError, RayUnavailable) as exc:
        print(f"sweep: {exc}", file=sys.stderr)
        return 2
    paths = write_outputs(result, out)
    print(table(result), end="")
    print(f"sweep: {len(result.rows)} points in {result.wall_seconds:.1f} s wall ({result.backend}); "
          f"Pareto front: points {[result.rows[i]['point'] for i in result.pareto]}; "
          + ", ".join(f"{k} {v}" for k, v in paths.items()))
    return 0


def _bag_data(bags: Sequence[Path], system_name: str) -> tuple:
    """Transitions of ``bags`` split 80/20 (seed 10000) into train and held-out arrays."""
    import numpy as np

    from saml_ros.bags.transitions import transitions_from_bags
    from saml_ros.core.systems import get_system
    from saml_ros.offline.sweep import TEST_SEED

    x, u, y = transitions_from_bags(list(bags), get_system(system_name))
    if len(x) < 10:
        raise ValueError(f"only {len(x)} transitions in the bag(s); need at least 10")
    perm = np.random.default_rng(TEST_SEED).permutation(len(x))
    n_test = len(x) // 5
    test, train = perm[:n_test], perm[n_test:]
    return x[train], u[train], y[train], x[test], u[test], y[test]


if __name__ == "__main__":
    raise SystemExit(main())
