"""``./dev experiment NAME [--quick] [--out DIR] [--seeds S ...] [--set FIELD=VALUE ...]`` (``ros2 run saml_ros
experiment``).

Runs one of the paper's experiments (or ``all`` of them, ``--jobs`` at once, each in its own process) and writes ``results.md``,
``results.json`` and PNG figures into ``--out`` (default ``results/NAME``; for ``all``, ``--out`` is the parent
directory). ``claims`` collects the claims of the experiments already run under ``--out`` (default ``results``)
into ``--out/claims.md`` without running anything. ``--quick`` runs a reduced version (about a minute each); ``--set`` overrides a field of the
experiment's settings dataclass (a Python literal, e.g. ``--set drag=0.0`` or ``--set "profiles=('sticky_patch',)"``).
See docs/experiments.md.
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from saml_ros.experiments import EXPERIMENT_NAMES, SWEEPS
from saml_ros.experiments.run_all import default_jobs


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="experiment",
        description="Reproduce the paper's experiments: friction (double integrator SA vs UA + MPC), convergence "
                    "(duality-gap grid), paddle_ball (MuJoCo ball bouncing), quadrotor (landing with ground "
                    "effect), or all.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    p.add_argument("name", choices=(*EXPERIMENT_NAMES, *SWEEPS, "all", "claims"),
                   help="an experiment, all of them, 'claims' (rebuild claims.md from the results.json files "
                        "already under --out) or 'capacity' (the net-size sweep on the demo's landing; not part of "
                        "'all')")
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
    p.add_argument("--jobs", type=int, help="'all': experiments run at once, each in its own process (default: "
                                            "the cores available; 1: one after the other in this process)")
    return p


#: experiment -> (its settings class in ``saml_ros.experiments.<name>``, the field ``--seeds`` sets: ``seeds`` takes
#: them all, ``seed`` the first)
SETTINGS: dict[str, tuple[str, str]] = {
    "convergence": ("ConvergenceSettings", "seed"),
    "friction": ("FrictionSettings", "seeds"),
    "quadrotor": ("QuadrotorSettings", "seeds"),
    "paddle_ball": ("PaddleSettings", "seeds"),
    "capacity": ("CapacitySettings", "seeds"),
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


def collect_claims(parent: Path, names: Sequence[str] = EXPERIMENT_NAMES) -> tuple[list[Any], list[str]]:
    """The claims stored in ``parent/<name>/results.json`` of every experiment of ``names`` run there (or, where
    only its ``results.md`` is kept, as under docs/results/experiments, the claims table that file holds), and
    those names."""
    import json

    from saml_ros.experiments.headroom import Claim

    claims: list[Any] = []
    found: list[str] = []
    for name in names:
        path = parent / name / "results.json"
        if path.exists():
            found.append(name)
            claims += [Claim(**c) for c in json.loads(path.read_text()).get("claims", [])]
        elif (parent / name / "results.md").exists():
            read = claims_from_markdown((parent / name / "results.md").read_text(encoding="utf-8"))
            if read:
                found.append(name)
                claims += read
    return claims, found


def claims_from_markdown(text: str) -> list[Any]:
    """The claims of the first claims table in ``text`` (a results.md written with
    :func:`saml_ros.experiments.headroom.claims_table`) with the notes below it."""
    import re

    from saml_ros.experiments.headroom import CLAIMS_HEADER, Claim

    lines = text.splitlines()
    head = CLAIMS_HEADER.splitlines()[0]
    if head not in lines:
        return []
    i = lines.index(head) + 2
    claims: list[Any] = []
    while i < len(lines) and lines[i].startswith("|"):
        cells = [c.strip().replace("\\|", "|") for c in re.split(r"(?<!\\)\|", lines[i].strip())[1:-1]]
        if len(cells) == 6:
            experiment, claim, paper, ours, headroom, verdict = cells
            claims.append(Claim(experiment, claim, paper, ours, headroom, verdict.strip("*")))
        i += 1
    for line in lines[i:]:
        if line.startswith("#"):
            break
        for c in claims:
            prefix = f"* {c.experiment}, {c.claim}: "
            if line.startswith(prefix) and not c.note:
                c.note = line[len(prefix):]
                break
    return claims


def write_claims(parent: Path, claims: list[Any], title: str, footer: str) -> str:
    """Write ``parent/claims.md`` (the claims table under ``title``, then ``footer``); returns its text."""
    from saml_ros.experiments.headroom import claims_table

    text = f"# {title}\n\n{claims_table(claims)}\n\n{footer}\n"
    parent.mkdir(parents=True, exist_ok=True)
    (parent / "claims.md").write_text(text)
    return text


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="[%(levelname)s] %(name)s: %(message)s")
    if args.name == "claims":
        parent = args.out or Path("results")
        stored, ran = collect_claims(parent)
        if not ran:
            print(f"experiment claims: no results.json under {parent}/<experiment>/", file=sys.stderr)
            return 2
        print(write_claims(parent, stored, "Claims of the paper, one line each (`./dev experiment claims`)",
                           f"Collected from the results of: {', '.join(ran)} (under {parent})."))
        return 0
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
    if args.jobs is not None and args.jobs < 1:
        print("experiment: --jobs must be >= 1", file=sys.stderr)
        return 2
    if args.name == "all":
        for name in names:  # a bad --set fails here, before anything runs
            try:
                settings_for(name, args.quick, args.seeds, args.overrides)
            except ValueError as exc:
                print(f"experiment: {exc}", file=sys.stderr)
                return 2
        jobs = args.jobs or default_jobs()
        if jobs > 1:
            return run_all_parallel(args, names, min(jobs, len(names)))
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
        parent = args.out or Path("results")
        print(write_claims(parent, found, "Claims of the paper, one line each (`./dev experiment all"
                                          f"{' --quick' if args.quick else ''}`)",
                           f"All experiments: {time.perf_counter() - t_all:.1f} s wall, "
                           f"{time.process_time() - cpu0:.1f} s CPU."))
    return 0


def child_options(args: argparse.Namespace, names: list[str]) -> dict[str, list[str]]:
    """Each child's options under ``all``: ``--quick``, ``--seeds`` and every ``--set`` for all; ``--ray`` and
    ``--ray-cpus`` only for :data:`RAY_EXPERIMENTS` (the others refuse them)."""
    common = (["--quick"] if args.quick else []) + (["--seeds", *map(str, args.seeds)] if args.seeds else [])
    for item in args.overrides:
        common += ["--set", item]
    ray = (["--ray", args.ray] + (["--ray-cpus", str(args.ray_cpus)] if args.ray_cpus else [])) if args.ray else []
    return {n: common + (ray if n in RAY_EXPERIMENTS else []) for n in names}


def run_all_parallel(args: argparse.Namespace, names: list[str], jobs: int) -> int:
    """``all`` with ``jobs`` experiments at once (:mod:`.run_all`), then ``claims.md`` from their results."""
    from saml_ros.experiments.run_all import run_parallel

    parent = args.out or Path("results")
    options = child_options(args, names)
    t_all = time.perf_counter()
    print(f"experiment all{' (quick)' if args.quick else ''}: {len(names)} experiments, {jobs} at once -> {parent}",
          flush=True)
    failed, cpu = run_parallel(names, parent, options, jobs)
    claims, _ = collect_claims(parent, [n for n in names if n not in failed])
    print(write_claims(parent, claims, "Claims of the paper, one line each (`./dev experiment all"
                                          f"{' --quick' if args.quick else ''}`)",
                       f"All experiments: {time.perf_counter() - t_all:.1f} s wall, {cpu:.1f} s CPU "
                       f"({jobs} at once)."))
    if failed:
        print(f"experiment all: {', '.join(failed)} failed (see their run.log)", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
