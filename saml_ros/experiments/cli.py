"""``./dev experiment NAME [--quick] [--out DIR] [--seeds S ...] [--set FIELD=VALUE ...]`` (``ros2 run saml_ros
experiment``).

Runs one of the paper's experiments (or ``all`` of them, one after the other) and writes ``results.md``,
``results.json`` and PNG figures into ``--out`` (default ``results/NAME``; for ``all``, ``--out`` is the parent
directory). ``--quick`` runs a reduced version (about a minute each); ``--set`` overrides a field of the
experiment's settings dataclass (a Python literal, e.g. ``--set drag=0.0`` or ``--set "profiles=('sticky_patch',)"``).
See docs/experiments.md.
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
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="FIELD=VALUE",
                   help="override a settings field (Python literal; repeatable)")
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


def settings_for(name: str, quick: bool, seeds: list[int] | None, overrides: list[str] | None = None) -> Any:
    """The settings object of experiment ``name`` (paper defaults, or ``quick()``), with ``seeds`` and the
    ``FIELD=VALUE`` ``overrides`` applied; ``ValueError`` for an unknown field or a value that is no literal."""
    import ast
    import importlib
    from dataclasses import fields, replace

    if name not in SETTINGS:
        raise ValueError(f"unknown experiment {name!r}; valid: {', '.join(EXPERIMENT_NAMES)}")
    cls_name, seed_field = SETTINGS[name]
    cls = getattr(importlib.import_module(f"saml_ros.experiments.{name}"), cls_name)
    settings = cls.quick() if quick else cls()
    if seeds:
        settings = replace(settings, **{seed_field: seeds[0] if seed_field == "seed" else tuple(seeds)})
    known = {f.name for f in fields(settings)}
    changes: dict[str, Any] = {}
    for item in overrides or []:
        key, sep, text = item.partition("=")
        key = key.strip()
        if not sep or key not in known:
            raise ValueError(f"--set {item!r}: expected FIELD=VALUE with FIELD one of {sorted(known)}")
        try:
            value = ast.literal_eval(text.strip())
        except (ValueError, SyntaxError):
            value = text.strip()  # a bare word: a string
        if isinstance(getattr(settings, key), tuple) and isinstance(value, list):
            value = tuple(value)
        changes[key] = value
    return replace(settings, **changes) if changes else settings


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
    found: list[Any] = []
    cpu0, t_all = time.process_time(), time.perf_counter()
    for name in names:
        if args.name == "all":
            out = (args.out or Path("results")) / name
        else:
            out = args.out or Path("results") / name
        try:
            settings = settings_for(name, args.quick, args.seeds, args.overrides)
        except ValueError as exc:
            print(f"experiment: {exc}", file=sys.stderr)
            return 2
        t0 = time.perf_counter()
        print(f"experiment {name}{' (quick)' if args.quick else ''} -> {out}", flush=True)
        c0 = time.process_time()
        data = run_experiment(name, settings, out, progress=not args.no_progress, ray=args.ray,
                              ray_cpus=args.ray_cpus)
        found += data.get("claims", [])
        print((out / "results.md").read_text())
        print(f"experiment {name}: done in {time.perf_counter() - t0:.1f} s wall, {time.process_time() - c0:.1f} s "
              f"CPU; results in {out}/results.md, {out}/results.json and the PNG figures there", flush=True)
    if args.name == "all":
        from saml_ros.experiments.headroom import claims_table

        parent = args.out or Path("results")
        text = (f"# Claims of the paper, one line each (`./dev experiment all{' --quick' if args.quick else ''}`)\n\n"
                f"{claims_table(found)}\n\nAll experiments: {time.perf_counter() - t_all:.1f} s wall, "
                f"{time.process_time() - cpu0:.1f} s CPU.\n")
        (parent / "claims.md").write_text(text)
        print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
