"""Sweep wall time in this process vs on a local Ray instance: ``./dev python -m bench.bench_sweep [--cpus 2]``.

The same grid (friction, eps x seed, generated data, no task) runs in-process and then on a private Ray instance
with ``--cpus`` CPUs (``sweep --ray local``); prints both wall times, their ratio, the Ray start-up time (first
unit dispatch included in the Ray wall time) and checks that both tables are identical. On this shared 2-core
machine Ray can at best halve the wall time of CPU-bound units; its start-up (a few seconds) is paid once per run.
"""

from __future__ import annotations

import argparse
import time

from saml_ros.offline.sweep import SweepSetup, run_sweep, table


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--cpus", type=int, default=2, help="CPUs of the local Ray instance")
    p.add_argument("--epochs", type=int, default=30)
    p.add_argument("--samples", type=int, default=5000)
    p.add_argument("--eps", type=float, nargs="+", default=[0.02, 0.035, 0.05, 0.08])
    p.add_argument("--seeds", type=int, default=2)
    args = p.parse_args()
    grid = {"eps": list(args.eps), "seed": list(range(args.seeds))}
    setup = SweepSetup("friction", None, {"samples": args.samples, "epochs": args.epochs, "seed": 0},
                       test_samples=5000)
    n = len(args.eps) * args.seeds
    print(f"bench_sweep: friction, {n} points (eps {args.eps} x {args.seeds} seeds), {args.samples} samples, "
          f"{args.epochs} epochs")
    t0 = time.perf_counter()
    here = run_sweep(grid, setup)
    t_here = time.perf_counter() - t0
    t0 = time.perf_counter()
    ray = run_sweep(grid, setup, ray="local", num_cpus=args.cpus)
    t_ray = time.perf_counter() - t0
    units = sum(r["train_seconds"] for r in here.rows)
    print(f"in-process:        {t_here:7.1f} s wall ({units:.1f} s of it training)")
    print(f"Ray local, {args.cpus} CPUs: {t_ray:7.1f} s wall (incl. starting and stopping Ray)")
    print(f"speed-up in-process / Ray: {t_here / t_ray:.2f}x; identical tables: {table(here) == table(ray)}")
    return 0 if table(here) == table(ray) else 1


if __name__ == "__main__":
    raise SystemExit(main())
