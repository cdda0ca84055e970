"""``./dev experiment NAME [--quick] [--out DIR] [--seeds S ...]`` (``ros2 run saml_ros experiment``).

Runs one of the paper's experiments (or ``all`` of them, one after the other) and writes ``results.md``,
``results.json`` and PNG figures into ``--out`` (default ``results/NAME``; for ``all``, ``--out`` is the parent
directory). ``--quick`` runs a reduced version (under about a minute each). See docs/experiments.md.
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path
from typing import Any

from saml_ros.experiments import EXPERIMENT_NAMES


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="experiment",
        description="Reproduce the paper's experiments: friction (double integrator SA vs UA + MPC), convergence "
                    "(duality-gap grid), paddle_ball (MuJoCo ball bouncing), quadrotor (landing with ground "
                    "effect), or all.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    p.add_argument("name", choices=(*EXPERIMENT_NAMES, "all"))
    p.add_argument("--quick", action="store_true", help="reduced settings (about a minute per experiment)")
    p.add_argument("--out", type=Path, help="output directory (default: results/NAME; for 'all': results)")
    p.add_argument("--seeds", type=int, nargs="+",
                   help="training seeds (friction, quadrotor, paddle_ball); for convergence the first value is "
                        "the base seed of the datasets")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    p.add_argument("--ray", help="run the independent units (convergence: the grid cells) on Ray: local, auto or "
                                 "a cluster address (same numbers as in-process; other experiments run in-process)")
    p.add_argument("--ray-cpus", type=int, help="CPUs of a --ray local instance (default: all)")
    return p


#: experiment -> (its settings class in ``saml_ros.experiments.<name>``, the field ``--seeds`` sets: ``seeds`` takes
#: them all, ``seed`` the first)
SETTINGS: dict[str, tuple[str, str]] = {
    "convergence": ("ConvergenceSettings", "seed"),
    "friction": ("FrictionSettings", "seeds"),
    "quadrotor": ("QuadrotorSettings", "seeds"),
    "paddle_ball": ("PaddleSettings", "seeds"),
}


def settings_for(name: str, quick: bool, seeds: list[int] | None) -> Any:
    """The settings object of experiment ``name`` (paper defaults, or ``quick()``), with ``seeds`` applied."""
    import importlib
    from dataclasses import replace

    if name not in SETTINGS:
        raise ValueError(f"unknown experiment {name!r}; valid: {', '.join(EXPERIMENT_NAMES)}")
    cls_name, seed_field = SETTINGS[name]
    cls = getattr(importlib.import_module(f"saml_ros.experiments.{name}"), cls_name)
    settings = cls.quick() if quick else cls()
    if not seeds:
        return settings
    return replace(settings, **{seed_field: seeds[0] if seed_field == "seed" else tuple(seeds)})


#: experiments whose independent units run on Ray with ``--ray``
RAY_EXPERIMENTS = ("convergence",)


def run_experiment(name: str, settings: Any, out: Path, progress: bool = True, ray: str | None = None,
                   ray_cpus: int | None = None) -> dict[str, Any]:
    """Run experiment ``name`` with ``settings`` into ``out``; returns its results dict."""
    import importlib

    module = importlib.import_module(f"saml_ros.experiments.{name}")
    kwargs = {"ray": ray, "ray_cpus": ray_cpus} if name in RAY_EXPERIMENTS and ray else {}
    result: dict[str, Any] = module.run(settings, out, progress, **kwargs)
    return result


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="[%(levelname)s] %(name)s: %(message)s")
    names = list(EXPERIMENT_NAMES) if args.name == "all" else [args.name]
    if args.seeds is not None and len(set(args.seeds)) != len(args.seeds):
        print("experiment: --seeds must be distinct", file=sys.stderr)
        return 2
    if args.ray:
        from saml_ros.offline.parallel import RayUnavailable, check_ray

        try:
            check_ray(args.ray)
        except RayUnavailable as exc:
            print(f"experiment: {exc}", file=sys.stderr)
            return 2
        if not set(names) & set(RAY_EXPERIMENTS):
            print(f"experiment: --ray applies to {', '.join(RAY_EXPERIMENTS)} only", file=sys.stderr)
            return 2
    for name in names:
        if args.name == "all":
            out = (args.out or Path("results")) / name
        else:
            out = args.out or Path("results") / name
        settings = settings_for(name, args.quick, args.seeds)
        t0 = time.perf_counter()
        print(f"experiment {name}{' (quick)' if args.quick else ''} -> {out}", flush=True)
        run_experiment(name, settings, out, progress=not args.no_progress, ray=args.ray, ray_cpus=args.ray_cpus)
        print((out / "results.md").read_text())
        print(f"experiment {name}: done in {time.perf_counter() - t0:.1f} s; results in {out}/results.md, "
              f"{out}/results.json and the PNG figures there", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
