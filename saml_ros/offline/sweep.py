"""Sweeps: train a grid of models (eps x net size x seed, or any spec / training field) and map the trade-off.

Each grid point is one independent unit (:func:`run_point`): one model trained on generated data (from the
point's seed) or on transitions from bags, evaluated on one held-out set shared by all points: the mean
one-step error inside and outside each constraint region, the constraint value g_k = E[l_k | region] - eps_k
on held-out data (met when <= 0), the final multiplier, and with a task the MPC's closed-loop cost on the true
system from fixed starts. :func:`pareto_front` marks the points no other point beats both inside and outside the
first region; :func:`table` and :func:`plot` show them, so eps can be chosen from data. Units run in this process
or on Ray (:mod:`saml_ros.offline.parallel`) with identical results.

Grid axes (``--grid NAME=V1,V2,...``): ``eps`` (every constraint) or ``eps.<constraint>``; ``hidden`` (``8x4``;
``paper`` = the system's paper sizes); ``seed``; ``samples``; ``kind`` (``residual`` | ``full``); ``uniform``
(``true`` trains without constraints: the Uniformly Accurate baseline); and any TrainConfig field, bare or as
``train.<field>`` (``epochs``, ``batch_size``, ``primal_lr``, ``dual_lr``, ``primal_optimizer``, ...).
"""

from __future__ import annotations

import copy
import dataclasses
import itertools
import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from saml_ros.core.errors import SamlError
from saml_ros.core.training import TrainConfig

TRAIN_FIELDS = tuple(f.name for f in dataclasses.fields(TrainConfig) if f.name != "seed")
SPECIAL_AXES = ("eps", "hidden", "seed", "samples", "kind", "uniform")
#: held-out transitions and the seed of that set (the same for every point)
TEST_SEED = 10_000
#: task systems: start sampler and goal of the closed-loop cost
TASK_SYSTEMS = ("friction", "quadrotor")


class SweepError(SamlError, ValueError):
    """A sweep that cannot run as asked (unknown axis, bad value, task for a system without one)."""


@dataclass(frozen=True)
class Task:
    """Closed-loop MPC evaluation of each point: ``starts`` start states (seed ``seed``), ``steps`` steps each."""

    starts: int = 10
    steps: int = 40
    horizon: int = 10
    solver: str = "fast"
    seed: int = 0


@dataclass(frozen=True)
class SweepSetup:
    """What every point shares. ``spec`` is a spec dict (``None``: the paper's); ``data`` the bag transitions
    ``(x, u, y, x_test, u_test, y_test)`` or ``None`` for generated data; ``base`` the defaults of every axis."""

    system: str
    spec: Mapping[str, Any] | None
    base: Mapping[str, Any]
    task: Task | None = None
    data: tuple[np.ndarray, ...] | None = None
    test_samples: int = 5000
    device: str = "cpu"


@dataclass(frozen=True)
class Point:
    """One grid point: its axis values, in grid order, and the shared setup."""

    index: int
    values: tuple[tuple[str, Any], ...]
    setup: SweepSetup


def parse_value(axis: str, text: str) -> Any:
    """One ``--grid`` value of ``axis`` from text (``hidden``: ``8x4`` or ``paper``)."""
    name = axis.removeprefix("train.")
    try:
        if axis == "hidden":
            return None if text == "paper" else tuple(int(v) for v in text.lower().split("x"))
        if axis == "uniform":
            if text.lower() not in ("true", "false", "1", "0"):
                raise ValueError(text)
            return text.lower() in ("true", "1")
        if axis in ("seed", "samples") or (name in TRAIN_FIELDS and isinstance(getattr(TrainConfig(), name), int)):
            return int(text)
        if axis == "eps" or axis.startswith("eps.") or (name in TRAIN_FIELDS
                                                       and isinstance(getattr(TrainConfig(), name), float)):
            return float(text)
        return text
    except ValueError:
        raise SweepError(f"--grid {axis}: bad value {text!r}") from None


def parse_grid(items: Sequence[str]) -> dict[str, list[Any]]:
    """``["eps=0.02,0.05", "seed=0,1"]`` -> ``{"eps": [0.02, 0.05], "seed": [0, 1]}`` (axes checked)."""
    grid: dict[str, list[Any]] = {}
    for item in items:
        axis, sep, values = item.partition("=")
        axis = axis.strip()
        if not sep or not values:
            raise SweepError(f"--grid wants NAME=V1,V2,..., got {item!r}")
        check_axis(axis)
        if axis in grid:
            raise SweepError(f"--grid {axis} given twice")
        grid[axis] = [parse_value(axis, v.strip()) for v in values.split(",")]
    return grid


def check_axis(axis: str) -> None:
    name = axis.removeprefix("train.")
    if axis in SPECIAL_AXES or axis.startswith("eps.") or name in TRAIN_FIELDS:
        return
    raise SweepError(f"unknown sweep axis {axis!r}; valid: {', '.join(SPECIAL_AXES)}, eps.<constraint>, "
                     f"{', '.join(TRAIN_FIELDS)} (or train.<field>)")


def expand(grid: Mapping[str, Sequence[Any]], setup: SweepSetup) -> list[Point]:
    """Every combination of the grid's values (the last axis varies fastest)."""
    axes = list(grid)
    return [Point(i, tuple(zip(axes, combo, strict=True)), setup)
            for i, combo in enumerate(itertools.product(*(grid[a] for a in axes)))]


# --------------------------------------------------------------------------------------------- one point
def _point_spec(setup: SweepSetup, values: Mapping[str, Any]) -> tuple[Any, Any]:
    """``(system, the point's ProblemSpec with its eps)``."""
    from saml_ros.core.spec import ProblemSpec
    from saml_ros.core.systems import get_system

    system = get_system(setup.system)
    raw = copy.deepcopy(dict(setup.spec)) if setup.spec is not None else system.paper_spec()
    names = [c.get("name") for c in raw.get("constraints", [])]
    for axis, value in values.items():
        if axis == "eps":
            for c in raw.get("constraints", []):
                c["eps"] = float(value)
        elif axis.startswith("eps."):
            k = axis[len("eps."):]
            if k not in names:
                raise SweepError(f"--grid {axis}: the spec has no constraint {k!r} (it has {names})")
            raw["constraints"][names.index(k)]["eps"] = float(value)
    return system, ProblemSpec.for_system(raw, system)


def run_point(point: Point) -> dict[str, Any]:
    """Train and evaluate one grid point (a Ray-able unit: everything it needs is in ``point``); subnormal floats
    are flushed while it trains (as in the experiment runners) and the trainer's per-run infeasibility warnings
    are not logged (``met`` and ``g`` in the row say the same on held-out data)."""
    import logging

    import torch

    logger = logging.getLogger("saml_ros.trainer")
    level = logger.level
    torch.set_flush_denormal(True)
    logger.setLevel(logging.ERROR)
    try:
        return _run_point(point)
    finally:
        logger.setLevel(level)
        torch.set_flush_denormal(False)


def _run_point(point: Point) -> dict[str, Any]:
    import torch

    from saml_ros.core.runtime.device import resolve_device
    from saml_ros.offline.pipelines import evaluate_models, generate_datasets, train_models

    setup = point.setup
    values = {**setup.base, **dict(point.values)}
    system, spec = _point_spec(setup, values)
    seed = int(values.get("seed", 0))
    train_kw = {k.removeprefix("train."): v for k, v in values.items() if k.removeprefix("train.") in TRAIN_FIELDS}
    config = TrainConfig(**{**train_kw, "seed": seed, "device": str(resolve_device(setup.device))})
    if setup.data is not None:
        x, u, y, xt, ut, yt = setup.data
    else:
        x, u, y = (a[0] for a in generate_datasets(system, int(values["samples"]), [seed]))
        xt, ut, yt = system.make_dataset(setup.test_samples, np.random.default_rng(TEST_SEED))
    torch.manual_seed(seed)
    train_spec = spec.uniform() if values.get("uniform") else spec
    t0 = time.perf_counter()
    trained = train_models(system, train_spec, x, u, y, config, [seed], values.get("hidden"),
                           str(values.get("kind", "residual")))
    train_s = time.perf_counter() - t0
    ev = evaluate_models(trained.model, spec, xt, ut, yt)
    row: dict[str, Any] = {"point": point.index, **{a: _jsonable(v) for a, v in point.values}}
    row["objective"] = float(ev.objective[0])
    lam = trained.trainer.lam.numpy()
    for k, (name, region) in enumerate(zip(spec.constraint_names, ev.regions, strict=True)):
        row[f"err_in/{name}"] = float(region.inside[0])
        row[f"err_out/{name}"] = float(region.outside[0])
        row[f"g/{name}"] = float(ev.constraints[0, k])
        row[f"met/{name}"] = bool(ev.constraints[0, k] <= 0.0)
        row[f"lambda/{name}"] = float(lam[0, k]) if lam.size and not values.get("uniform") else 0.0
    if setup.task is not None:
        row["task_cost"] = task_cost(system, trained.model.member(0), setup.task)
    row["updates"] = int(trained.trainer.steps)
    row["train_seconds"] = train_s
    return row


def _jsonable(v: Any) -> Any:
    if isinstance(v, tuple):
        return "x".join(str(i) for i in v)
    return "paper" if v is None else v


def task_starts(system: Any, task: Task) -> np.ndarray:
    from saml_ros.systems.friction.world import friction_start
    from saml_ros.systems.quadrotor.world import quadrotor_start

    rng = np.random.default_rng(task.seed)
    if system.name == "friction":
        return np.stack([friction_start(rng) for _ in range(task.starts)])
    if system.name == "quadrotor":
        return np.stack([quadrotor_start(system, rng) for _ in range(task.starts)])
    raise SweepError(f"no MPC task for {system.name}; tasks: {', '.join(TASK_SYSTEMS)}")


def task_cost(system: Any, model: Any, task: Task) -> float:
    """Mean over the task's starts of the summed true stage cost (distance to the goal, m) of an MPC closed loop
    planning with ``model`` (``saml_ros.core.mpc``)."""
    from saml_ros.core.mpc import closed_loop, make_controller

    goal = np.zeros(1 if system.name == "friction" else 3)
    controller = make_controller(system, model, solver=task.solver, horizon=task.horizon)
    costs = [float(np.sum(closed_loop(system, controller, x0, task.steps, goal).stage_costs))
             for x0 in task_starts(system, task)]
    return float(np.mean(costs))


# ------------------------------------------------------------------------------------------ the whole sweep
@dataclass
class SweepResult:
    system: str
    axes: list[str]
    constraints: list[str]
    rows: list[dict[str, Any]]
    wall_seconds: float
    backend: str
    pareto: list[int] = field(default_factory=list)


def run_sweep(grid: Mapping[str, Sequence[Any]], setup: SweepSetup, ray: str | None = None,
              num_cpus: int | None = None, on_result: Callable[[int, dict[str, Any]], None] | None = None
              ) -> SweepResult:
    """Run every point of ``grid`` (on Ray when ``ray`` is set) and mark the Pareto front."""
    from saml_ros.offline.parallel import map_units

    if setup.task is not None and setup.system not in TASK_SYSTEMS:
        raise SweepError(f"--task: no MPC task for {setup.system}; tasks: {', '.join(TASK_SYSTEMS)}")
    points = expand(grid, setup)
    _point_spec(setup, dict(points[0].values))  # a bad eps axis fails here, before any training
    t0 = time.perf_counter()
    rows = map_units(run_point, points, ray=ray, num_cpus=num_cpus, on_result=on_result)
    wall = time.perf_counter() - t0
    constraints = [k.removeprefix("err_in/") for k in rows[0] if k.startswith("err_in/")]
    result = SweepResult(setup.system, list(grid), constraints, rows, wall, ray or "in-process")
    if constraints:
        k = constraints[0]
        result.pareto = pareto_front([(r[f"err_in/{k}"], r[f"err_out/{k}"]) for r in rows])
    return result


def pareto_front(points: Sequence[tuple[float, float]]) -> list[int]:
    """Indices of the points no other point beats in both coordinates (lower is better), sorted by the first."""
    keep = []
    for i, (a, b) in enumerate(points):
        if any(math.isnan(v) for v in (a, b)):
            continue
        dominated = any((c <= a and d <= b) and (c < a or d < b) for j, (c, d) in enumerate(points) if j != i)
        if not dominated:
            keep.append(i)
    return sorted(keep, key=lambda i: points[i])


def table_columns(result: SweepResult) -> list[str]:
    """The table's columns: the axes, then the metrics (wall times excluded: they differ run to run)."""
    metrics = ["objective"]
    for k in result.constraints:
        metrics += [f"err_in/{k}", f"err_out/{k}", f"g/{k}", f"met/{k}", f"lambda/{k}"]
    if result.rows and "task_cost" in result.rows[0]:
        metrics.append("task_cost")
    return ["point", *result.axes, *metrics, "updates"]


def _cell(v: Any) -> str:
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, float):
        return f"{v + 0.0:.6g}"  # + 0.0: no "-0"
    return str(v)


def table(result: SweepResult) -> str:
    """Markdown table of every point (``*`` = on the Pareto front of the first region's in/out error)."""
    cols = table_columns(result)
    lines = ["| " + " | ".join(["pareto", *cols]) + " |", "|" + "---|" * (len(cols) + 1)]
    for i, row in enumerate(result.rows):
        lines.append("| " + " | ".join(["*" if i in result.pareto else "", *(_cell(row[c]) for c in cols)]) + " |")
    return "\n".join(lines) + "\n"


def csv_text(result: SweepResult) -> str:
    cols = table_columns(result)
    out = [",".join(["pareto", *cols])]
    for i, row in enumerate(result.rows):
        out.append(",".join(["1" if i in result.pareto else "0", *(_cell(row[c]) for c in cols)]))
    return "\n".join(out) + "\n"


def plot(result: SweepResult, out: Path) -> Path:
    """In- vs out-of-region held-out error of the first constraint, one marker per point (dot: constraint met
    on held-out data, cross: not met), coloured by eps when eps is swept (a grey line joins the eps values of one
    setting of the other axes), the Pareto front dashed."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    k = result.constraints[0]
    xs = np.array([r[f"err_in/{k}"] for r in result.rows])
    ys = np.array([r[f"err_out/{k}"] for r in result.rows])
    met = np.array([r[f"met/{k}"] for r in result.rows])
    eps_axis = "eps" if "eps" in result.axes else (f"eps.{k}" if f"eps.{k}" in result.axes else None)
    colour = np.array([r[eps_axis] for r in result.rows], dtype=float) if eps_axis else np.zeros(len(xs))
    fig, ax = plt.subplots(figsize=(6.5, 4.5))
    sc = None
    for mask, marker, label in ((met, "o", "constraint met (held out)"), (~met, "x", "constraint not met")):
        if mask.any():
            sc = ax.scatter(xs[mask], ys[mask], c=colour[mask], marker=marker, cmap="viridis", label=label,
                            vmin=colour.min(), vmax=colour.max() if colour.max() > colour.min() else colour.min() + 1)
    if eps_axis:  # one thin line per setting of the other axes, through its eps values in order
        groups: dict[tuple[Any, ...], list[int]] = {}
        for i, r in enumerate(result.rows):
            groups.setdefault(tuple(r[a] for a in result.axes if a != eps_axis), []).append(i)
        for idx in groups.values():
            idx = sorted(idx, key=lambda i: result.rows[i][eps_axis])
            ax.plot(xs[idx], ys[idx], color="0.75", lw=0.8, zorder=0)
    front = result.pareto
    ax.plot(xs[front], ys[front], "k--", lw=1, label="Pareto front")
    for i in front:
        ax.annotate(str(result.rows[i]["point"]), (xs[i], ys[i]), fontsize=7, xytext=(3, 3), textcoords="offset points")
    if eps_axis and sc is not None:
        fig.colorbar(sc, ax=ax, label=eps_axis)
    ax.set_xlabel(f"held-out error inside {k}")
    ax.set_ylabel(f"held-out error outside {k}")
    ax.set_title(f"{result.system} sweep: {' x '.join(result.axes)} ({len(result.rows)} points)", fontsize=10)
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=100)
    plt.close(fig)
    return out


def write_outputs(result: SweepResult, out: Path) -> dict[str, Path]:
    """``results.md`` (table), ``results.csv``, ``results.json`` (rows incl. wall times) and ``pareto.png``."""
    import json

    out.mkdir(parents=True, exist_ok=True)
    paths = {"table": out / "results.md", "csv": out / "results.csv", "json": out / "results.json"}
    paths["table"].write_text(table(result))
    paths["csv"].write_text(csv_text(result))
    paths["json"].write_text(json.dumps({"system": result.system, "axes": result.axes, "backend": result.backend,
                                         "wall_seconds": result.wall_seconds, "pareto": result.pareto,
                                         "rows": result.rows}, indent=1))
    if result.constraints:
        paths["plot"] = plot(result, out / "pareto.png")
    return paths
