"""Shared pieces of the experiment runners: paired statistics, markdown tables, result files, timing.

Every runner writes into its output directory ``results.md`` (markdown tables), ``results.json`` (every
number, JSON) and PNG figures. Comparisons of Uniformly vs Sufficiently Accurate are *paired* (by start
state, trial or seed): :func:`paired` reports the mean difference ``sufficient - uniform`` with a 95 %
Student-t confidence interval, the paired t-test p-value and the Wilcoxon signed-rank p-value.
"""

from __future__ import annotations

import functools
import json
import logging
import math
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, ParamSpec, TypeVar

import numpy as np
import torch

if TYPE_CHECKING:
    from saml_ros.core.dynamics.system import System
    from saml_ros.core.spec import ProblemSpec
    from saml_ros.offline.pipelines import Comparison


# the statistics live below the demo and the experiments (saml_ros.core.paired); re-exported for the experiments
from saml_ros.core.paired import (
    PAIRED_HEADER as PAIRED_HEADER,
)
from saml_ros.core.paired import (
    Paired as Paired,
)
from saml_ros.core.paired import (
    PairedRate as PairedRate,
)
from saml_ros.core.paired import (
    fmt as fmt,
)
from saml_ros.core.paired import (
    fmt_ms as fmt_ms,
)
from saml_ros.core.paired import (
    fmt_p as fmt_p,
)
from saml_ros.core.paired import (  # noqa: F401
    mean_std as mean_std,
)
from saml_ros.core.paired import (
    paired as paired,
)
from saml_ros.core.paired import (
    paired_rate as paired_rate,
)


# --------------------------------------------------------------------------------------------- output
def to_jsonable(obj: Any) -> Any:
    """Recursively convert numpy / torch values and dataclass-like objects into JSON-serialisable ones."""
    if isinstance(obj, dict):
        return {str(k): to_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [to_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return to_jsonable(obj.tolist())
    if isinstance(obj, torch.Tensor):
        return to_jsonable(obj.detach().cpu().tolist())
    if isinstance(obj, (np.floating, float)):
        f = float(obj)
        return f if math.isfinite(f) else None
    if isinstance(obj, (np.integer,)):
        return int(obj)
    if isinstance(obj, (np.bool_,)):
        return bool(obj)
    if isinstance(obj, Path):
        return str(obj)
    if hasattr(obj, "to_dict"):
        return to_jsonable(obj.to_dict())
    return obj


def write_results(out: Path, markdown: str, data: dict[str, Any]) -> None:
    """Write ``out/results.md`` and ``out/results.json``."""
    out.mkdir(parents=True, exist_ok=True)
    (out / "results.md").write_text(markdown if markdown.endswith("\n") else markdown + "\n")
    (out / "results.json").write_text(json.dumps(to_jsonable(data), indent=1))


def md_table(header: Sequence[str], rows: Sequence[Sequence[str]]) -> str:
    """A markdown table."""
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(str(c) for c in r) + " |" for r in rows]
    return "\n".join(lines)


@dataclass
class Timer:
    """Wall-clock seconds per named phase (``with timer("train"): ...``)."""

    phases: dict[str, float] = field(default_factory=dict)
    start: float = field(default_factory=time.perf_counter)

    @contextmanager
    def __call__(self, name: str) -> Iterator[None]:
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self.phases[name] = self.phases.get(name, 0.0) + time.perf_counter() - t0

    @property
    def total(self) -> float:
        return time.perf_counter() - self.start

    def to_dict(self) -> dict[str, float]:
        return {**{k: round(v, 2) for k, v in self.phases.items()}, "total": round(self.total, 2)}

    def markdown(self) -> str:
        parts = ", ".join(f"{k} {v:.1f} s" for k, v in self.phases.items())
        return f"Wall time {self.total:.1f} s ({parts})."


def progress_bar(total: int, desc: str, enabled: bool) -> Any:
    """A tqdm bar (disabled when ``enabled`` is False or stderr is not a terminal and tqdm decides so)."""
    from tqdm import tqdm

    return tqdm(total=total, desc=desc, disable=not enabled, dynamic_ncols=True, mininterval=0.5)


@contextmanager
def quiet_trainer_warnings() -> Iterator[None]:
    """Silence the trainer's per-member infeasibility warnings (the runners record them in results.json)."""
    logger = logging.getLogger("saml_ros.trainer")
    old = logger.level
    logger.setLevel(logging.ERROR)
    try:
        yield
    finally:
        logger.setLevel(old)


@contextmanager
def flush_denormals() -> Iterator[None]:
    """Flush subnormal floats to zero (e.g. while training): subnormal values arising in training slowed a 128-128
    full paddle-ball model 20x on this CPU (20 epochs: 3.2 s without, 0.16 s with flushing)."""
    torch.set_flush_denormal(True)
    try:
        yield
    finally:
        torch.set_flush_denormal(False)


@contextmanager
def compute_settings(threads: int = 1) -> Iterator[None]:
    """What every runner runs under: ``threads`` torch intra-op threads and flushed subnormals.

    One thread because the experiments' tensors are small and this 2-core machine is shared: measured while
    other jobs ran (load ~6), 100 epochs of a 15-member 16-8 ensemble on 5000 samples took 68.5 s with 2
    threads and 4.3 s with 1 (the threads wait for each other when the cores are oversubscribed).
    """
    old = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        with flush_denormals():
            yield
    finally:
        torch.set_num_threads(old)


P = ParamSpec("P")
R = TypeVar("R")


def single_threaded(run: Callable[P, R]) -> Callable[P, R]:
    """Decorator of the runners' ``run``: the whole run under :func:`compute_settings` (one torch thread,
    subnormals flushed), restored afterwards."""

    @functools.wraps(run)
    def wrapper(*args: P.args, **kwargs: P.kwargs) -> R:
        with compute_settings():
            return run(*args, **kwargs)

    return wrapper


# --------------------------------------------------------------------------------------------- training
def train_paper_comparison(system: System, seeds: Sequence[int], n_train: int, n_test: int, hidden: Sequence[int],
                           epochs: int, timer: Timer, progress: bool,
                           spec_dict: dict[str, Any] | None = None) -> tuple[ProblemSpec, Comparison]:
    """Sufficiently vs Uniformly Accurate models of ``system`` on its paper spec (or ``spec_dict``), one dataset and
    initialisation per seed, all seeds as one ensemble (:func:`saml_ros.offline.pipelines.compare`; Adam 1e-3 /
    1e-4, batch 128), timed as ``timer("train")``; returns the spec and the comparison."""
    from saml_ros.core.spec import ProblemSpec
    from saml_ros.core.training import TrainConfig
    from saml_ros.offline.pipelines import compare

    spec = ProblemSpec.for_system(system.paper_spec() if spec_dict is None else spec_dict, system)
    config = TrainConfig.paper(epochs=epochs, batch_size=128, primal_lr=1e-3, dual_lr=1e-4)
    with timer("train"), quiet_trainer_warnings(), flush_denormals():
        cmp = compare(system, spec, config, list(seeds), n_train, n_test, hidden, progress=progress)
    return spec, cmp


def training_summary(cmp: Comparison) -> dict[str, Any]:
    """The ``training`` entry of ``results.json``: seconds per model, the engine, the final multipliers and the
    feasibility warnings of the Sufficiently Accurate training."""
    trainer = cmp.sufficient.trainer
    return {"train_seconds": {"sufficient": cmp.sufficient.train_seconds, "uniform": cmp.uniform.train_seconds},
            "engine": trainer.engine_used, "lambda_final": trainer.lam[:, 0],
            "feasibility_warnings": trainer.feasibility().messages()}


def save_models(out: Path, trained: dict[str, Any]) -> dict[str, str]:
    """Save each trained ensemble (``name -> TrainedModels``) as a checkpoint run directory ``out/models/<name>``
    (load with ``saml_ros.core.model.io.load_model``; member i was trained with seed ``seeds[i]``).
    Returns ``name -> checkpoint path``."""
    from saml_ros.core.model.checkpoint import CheckpointStore
    from saml_ros.core.training import save_checkpoint

    paths = {}
    for name, tm in trained.items():
        path, _ = save_checkpoint(CheckpointStore(out / "models" / name.replace("/", "_")), tm.trainer,
                                  extra={"seeds": list(tm.seeds)})
        paths[name] = str(path.relative_to(out))
    return paths


def machine_info() -> dict[str, Any]:
    """Facts that affect wall times: CPU count, torch threads, load average."""
    import os

    load = os.getloadavg() if hasattr(os, "getloadavg") else (math.nan,) * 3
    return {"cpus": os.cpu_count(), "torch_threads": torch.get_num_threads(), "loadavg_start": list(load)}
