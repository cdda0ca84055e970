"""Online Sufficiently Accurate model learning, ROS-free: ingest -> replay buffer -> primal-dual updates.

:class:`OnlineLearner` owns everything the learner node does except ROS:

* one :class:`~saml_ros.core.pairing.StampPairer` per source (robot / namespace), fed ``(kind, stamp, vector)``
  events by :meth:`OnlineLearner.ingest`; paired transitions go into one shared
  :class:`~saml_ros.core.buffer.ReplayBuffer` and into a small window of the most recent transitions;
* the model and the :class:`~saml_ros.core.trainer.PrimalDualTrainer`, created once ``min_transitions``
  transitions have arrived: the input/output normalisation is fitted on exactly those transitions and then
  frozen (it is part of the model, so it is checkpointed and restored with it);
* the update loop (:meth:`update`: ``n`` primal-dual steps on minibatches sampled from the buffer);
* live telemetry (:meth:`compute_model_metrics`, :meth:`telemetry`): the one-step error of the *current*
  model on the most recent transitions inside / outside each constraint region, the objective, constraint
  estimates and Lagrangian (means over the minibatches since the previous telemetry), lambda, buffer size,
  update count and rejection counters, named as :func:`msg_schemas.telemetry.model_error_names`;
* periodic checkpoints (:meth:`save_checkpoint`, via :func:`saml_ros.core.model_io.save_checkpoint`) and
  resume from the newest *valid* checkpoint of a run directory (weights, normalisation, lambda, optimizer
  states, update count).

Threads: one thread may call :meth:`ingest` (per source) while another calls :meth:`update`,
:meth:`compute_model_metrics` and :meth:`save_checkpoint`; :meth:`telemetry` is cheap and may be called from
any thread. The model is guarded by one lock; the buffer and the recent window have their own.

Processes: :class:`TrainingProcess` runs the training side (:func:`run_loop` over an :class:`OnlineLearner`
built from a picklable :class:`LearnerSetup`) in a separate, niced interpreter and is fed paired transitions in
batches, so ingest in the parent never competes with training for the GIL (the learner node pairs in its own
process and uses this; see docs/learner.md for the measurements).
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import math
import os
import signal
import subprocess
import sys
import threading
import time
from collections import deque
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from msg_schemas.telemetry import REJECT_REASONS, model_error_names
from saml_ros.core.buffer import Policy, ReplayBuffer
from saml_ros.core.checkpoint import CheckpointError, CheckpointStore, read_checkpoint
from saml_ros.core.child_launch import LaunchedChild, launch_child
from saml_ros.core.model_io import MODEL_KIND, LoadedModel, model_from_payload, save_checkpoint
from saml_ros.core.models import MODEL_KINDS, DynamicsModel
from saml_ros.core.pairing import AddResult, PairingConfig, StampPairer, Transition, total_counts
from saml_ros.core.spec import ProblemSpec
from saml_ros.core.systems.base import System
from saml_ros.core.trainer import PrimalDualTrainer, TrainConfig

log = logging.getLogger("saml_ros.online")

#: extra ``learner/model_error`` values appended after the canonical names
EXTRA_METRICS: tuple[tuple[str, str, str], ...] = (
    ("paired", "count", "transitions paired so far (all sources)"),
    ("window", "count", "recent transitions the live errors are computed on"),
    ("error_all", "loss", "live one-step error of the current model on the recent window (the objective's loss)"),
    ("training", "1", "1 while primal-dual updates run, 0 while waiting for min_transitions"),
)
#: extra per-constraint values (``<name>/<k>``)
EXTRA_PER_CONSTRAINT: tuple[tuple[str, str, str], ...] = (
    ("n_in", "count", "recent transitions inside region k (error_in is NaN when 0)"),
)
#: history rows the trainer keeps in memory (older rows are dropped; online training never ends)
HISTORY_ROWS = 1000


def assemble_telemetry(
    constraint_names: Sequence[str], status: Mapping[str, float], counts: Mapping[str, int]
) -> dict[str, float]:
    """``learner/model_error`` values in order: :func:`~msg_schemas.telemetry.model_error_names` first, then
    :data:`EXTRA_METRICS` and ``n_in/<k>``.

    Args:
        constraint_names: the spec's constraint names.
        status: :meth:`OnlineLearner.status` (missing model values are NaN).
        counts: pairing counters (:meth:`OnlineLearner.counts` or :func:`~saml_ros.core.pairing.total_counts`).
    """
    out: dict[str, float] = {}
    for n in model_error_names(constraint_names):
        if n.startswith("rejected/"):
            out[n] = float(counts.get(n.removeprefix("rejected/"), 0))
        else:
            out[n] = float(status.get(n, math.nan))
    out["paired"] = float(counts.get("paired", 0))
    for n, _, _ in EXTRA_METRICS:
        if n != "paired":
            out[n] = float(status.get(n, math.nan))
    for c in constraint_names:
        out[f"n_in/{c}"] = float(status.get(f"n_in/{c}", 0.0))
    return out


class ResumeError(RuntimeError):
    """The run directory holds checkpoints that contradict the configuration (another system, another
    architecture, other constraints): resuming would silently mix two runs."""


@dataclass
class OnlineConfig:
    """Configuration of an :class:`OnlineLearner`.

    Attributes:
        kind: ``"residual"`` (f_hat + phi) or ``"full"`` (phi only).
        hidden: hidden layer sizes; ``None`` = the system's ``paper_hidden``.
        train: primal-dual hyper-parameters (``epochs`` is not used online).
        buffer_capacity: replay buffer rows (>= min_transitions).
        buffer_policy: ``"fifo"`` or ``"reservoir"`` (see docs/buffer.md).
        min_transitions: transitions needed before training starts (normalisation is fitted on the first
            ``min_transitions``); training also pauses while the buffer holds fewer (e.g. right after a resume).
        telemetry_window: most recent transitions the live model error is computed on.
        checkpoint_keep: checkpoint files kept in the run directory (older ones are pruned).
    """

    kind: str = "residual"
    hidden: tuple[int, ...] | None = None
    train: TrainConfig = field(default_factory=TrainConfig)
    buffer_capacity: int = 100_000
    buffer_policy: str = "fifo"
    min_transitions: int = 1000
    telemetry_window: int = 1000
    checkpoint_keep: int = 5

    def __post_init__(self) -> None:
        if self.kind not in MODEL_KINDS:
            raise ValueError(f"model kind must be one of {list(MODEL_KINDS)}, got {self.kind!r}")
        if self.hidden is not None:
            self.hidden = tuple(int(h) for h in self.hidden)
            if any(h < 1 for h in self.hidden):
                raise ValueError(f"hidden layer sizes must be >= 1, got {list(self.hidden)}")
        if self.min_transitions < 2:
            raise ValueError(f"min_transitions must be >= 2 (normalisation needs a spread), got {self.min_transitions}")
        if self.buffer_capacity < self.min_transitions:
            raise ValueError(
                f"buffer capacity ({self.buffer_capacity}) must be >= min_transitions ({self.min_transitions})"
            )
        if self.buffer_policy not in ("fifo", "reservoir"):
            raise ValueError(f"buffer policy must be 'fifo' or 'reservoir', got {self.buffer_policy!r}")
        if self.telemetry_window < 1 or self.checkpoint_keep < 1:
            raise ValueError("telemetry_window and checkpoint_keep must be >= 1")


@dataclass
class ResumeInfo:
    """What :class:`OnlineLearner` resumed from.

    Attributes:
        path, version: the checkpoint loaded.
        updates: its update count.
        lam: its lambda, ``(K,)``.
        skipped: ``(path, reason)`` of newer checkpoints that were unreadable or inconsistent.
    """

    path: Path
    version: int
    updates: int
    lam: list[float]
    skipped: list[tuple[Path, str]]


class _Recent:
    """Ring of the ``size`` most recent transitions (thread-safe)."""

    def __init__(self, size: int, n_x: int, n_u: int, n_y: int) -> None:
        self._rows = np.zeros((size, n_x + n_u + n_y))
        self._split = (n_x, n_x + n_u)
        self._n = 0
        self._lock = threading.Lock()

    def add(self, x: np.ndarray, u: np.ndarray, y: np.ndarray) -> None:
        with self._lock:
            row = self._rows[self._n % len(self._rows)]
            a, b = self._split
            row[:a], row[a:b], row[b:] = x, u, y
            self._n += 1

    def add_batch(self, x: np.ndarray, u: np.ndarray, y: np.ndarray) -> None:
        rows = np.concatenate([x, u, y], axis=1)[-len(self._rows):]
        with self._lock:
            idx = (self._n + np.arange(len(rows))) % len(self._rows)
            self._rows[idx] = rows
            self._n += len(rows)

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        with self._lock:
            rows = self._rows[: min(self._n, len(self._rows))].copy()
        a, b = self._split
        return rows[:, :a], rows[:, a:b], rows[:, b:]


class OnlineLearner:
    """Online primal-dual learning of one system's dynamics model from paired transitions.

    Args:
        system: the system (its layouts, base model f_hat and dt).
        spec: the Sufficiently Accurate problem.
        config: see :class:`OnlineConfig`.
        store: run directory for checkpoints (``None``: no checkpoints).
        resume: load the newest valid checkpoint of ``store`` (if any) at construction.
        clock: time source for checkpoint periods (seconds); ``time.monotonic`` by default.

    Raises:
        ResumeError: ``resume`` found a checkpoint of another system or with another architecture /
            constraint set.
    """

    def __init__(
        self,
        system: System,
        spec: ProblemSpec,
        config: OnlineConfig | None = None,
        *,
        store: CheckpointStore | None = None,
        resume: bool = True,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.system, self.spec = system, spec
        self.config = cfg = config or OnlineConfig()
        self.store = store
        self._clock = clock
        n_x, n_u, n_y = system.state.size, system.control.size, system.target.size
        policy: Policy = "reservoir" if cfg.buffer_policy == "reservoir" else "fifo"
        self.buffer = ReplayBuffer(cfg.buffer_capacity, n_x, n_u, n_y, policy, seed=cfg.train.seed)
        self.model = DynamicsModel(system, cfg.hidden, cfg.kind, n_models=1, seed=cfg.train.seed)
        self.model.to(cfg.train.torch_dtype)
        self.trainer: PrimalDualTrainer | None = None
        self._recent = _Recent(cfg.telemetry_window, n_x, n_u, n_y)
        self._sources: list[StampPairer] = []
        self._lock = threading.RLock()
        self._rng = np.random.default_rng(cfg.train.seed)
        self._acc_n = 0
        self._acc_obj = 0.0
        self._acc_con = np.zeros(spec.n_constraints)
        self._last_obj = math.nan
        self._last_con = np.full(spec.n_constraints, math.nan)
        self.model_version = 0
        self._saved_updates: int | None = None
        self._saved_at = clock()
        self.checkpoints_written = 0
        self.checkpoints_skipped = 0
        self.resumed: ResumeInfo | None = None
        self._metrics: dict[str, float] = {}
        if store is not None and resume:
            self._resume(store)
        self.compute_model_metrics()

    # ------------------------------------------------------------------------------------------ sources
    def add_source(self, name: str, pairing: PairingConfig) -> int:
        """Register a source (robot / namespace) with its pairing rule; returns its index."""
        p = StampPairer(pairing, source=len(self._sources), name=name)
        for reason in REJECT_REASONS:
            p.counts.setdefault(reason, 0)
        self._sources.append(p)
        return p.source

    @property
    def sources(self) -> list[StampPairer]:
        return list(self._sources)

    def ingest(self, source: int, kind: str, stamp_ns: int, vector: Any) -> AddResult:
        """Feed one event of ``source`` (see :meth:`StampPairer.add`); completed transitions are added."""
        res = self._sources[source].add(kind, stamp_ns, vector)
        for tr in res.transitions:
            self.add(tr)
        return res

    def reject(self, source: int, reason: str, kind: str | None = None) -> None:
        """Count a ``kind`` message of ``source`` dropped before pairing (``reason``: a SchemaError reason)."""
        self._sources[source].reject(reason, kind)

    def add(self, tr: Transition) -> None:
        """Add one paired transition to the buffer and the recent window."""
        self.buffer.add(tr.x, tr.u, tr.y, stamp=tr.stamp_ns * 1e-9, source=tr.source)
        self._recent.add(tr.x, tr.u, tr.y)

    def add_batch(self, x: np.ndarray, u: np.ndarray, y: np.ndarray, stamp: Any = 0.0, source: Any = 0) -> None:
        """Add ``B`` paired transitions at once: ``x (B, n_x)``, ``u (B, n_u)``, ``y (B, n_y)``, ``stamp`` in s and
        ``source`` scalars or ``(B,)`` (much cheaper per row than :meth:`add`)."""
        if len(x) == 0:
            return
        self.buffer.add_batch(x, u, y, stamp=stamp, source=source)
        self._recent.add_batch(np.asarray(x, np.float64), np.asarray(u, np.float64), np.asarray(y, np.float64))

    def counts(self) -> dict[str, int]:
        """All sources' pairing and rejection counters, summed."""
        return total_counts(dict(list(p.counts.items())) for p in self._sources)

    # ------------------------------------------------------------------------------------------ training
    @property
    def updates(self) -> int:
        """Primal-dual updates so far (including those of the checkpoint resumed from)."""
        tr = self.trainer
        return 0 if tr is None else tr.steps

    @property
    def training(self) -> bool:
        """True when :meth:`update` would take steps now."""
        if self.trainer is None:
            return self.buffer.total_added >= self.config.min_transitions
        return len(self.buffer) >= self.config.min_transitions

    @property
    def lam(self) -> np.ndarray:
        """Current lambda ``(K,)`` (zeros before training starts)."""
        tr = self.trainer
        return np.zeros(self.spec.n_constraints) if tr is None else tr.lam[0].double().numpy().copy()

    def update(self, n_steps: int) -> int:
        """Run up to ``n_steps`` primal-dual updates; returns how many ran (0 while waiting for data).

        The first call after ``min_transitions`` transitions arrived fits the normalisation on them and
        creates the trainer.
        """
        if n_steps <= 0 or not self.training:
            return 0
        with self._lock:
            if self.trainer is None:
                self._start_training()
            tr = self.trainer
            assert tr is not None
            bsz, dt = self.config.train.batch_size, self.config.train.torch_dtype
            for _ in range(n_steps):
                xb, ub, yb = self.buffer.sample(bsz, self._rng)
                vals = tr.step(torch.from_numpy(xb).to(dt), torch.from_numpy(ub).to(dt), torch.from_numpy(yb).to(dt))
                self._acc_n += 1
                self._acc_obj += float(vals.objective[0])
                if self.spec.n_constraints:
                    self._acc_con += vals.constraints[0].double().numpy()
                if tr.steps % (self.config.train.log_every or 100) == 0:
                    tr.log_point()
                    _trim_history(tr)
            return n_steps

    def _start_training(self) -> None:
        m = self.config.min_transitions
        rows = self.buffer.arrays()  # oldest first: the first min_transitions ever added (capacity >= m)
        self.model.fit_normalization(rows.x[:m], rows.u[:m], rows.y[:m])
        self.trainer = PrimalDualTrainer(self.model, self.spec, self.config.train)
        log.info("training started: normalisation fitted on the first %d transitions and frozen", m)

    # ------------------------------------------------------------------------------------------ telemetry
    def compute_model_metrics(self) -> dict[str, float]:
        """Evaluate the current model on the recent window and summarise training since the last call.

        Heavier than :meth:`telemetry` (one forward pass over the window): call it at the telemetry rate
        from the thread that trains. Returns (and caches for :meth:`telemetry`) the model part of the metrics.
        """
        x, u, y = self._recent.arrays()
        out: dict[str, float] = {}
        with self._lock:
            if self._acc_n:
                self._last_obj = self._acc_obj / self._acc_n
                self._last_con = self._acc_con / self._acc_n
                self._acc_n, self._acc_obj = 0, 0.0
                self._acc_con = np.zeros(self.spec.n_constraints)
            lam = self.lam
            errs: dict[str, dict[str, torch.Tensor]] = {}
            err_all = math.nan
            if len(x):
                with torch.no_grad():
                    xt, ut, yt = (torch.from_numpy(a) for a in (x, u, y))
                    dt = self.model.in_mean.dtype
                    pred = self.model(xt.to(dt), ut.to(dt)).double()
                    errs = self.spec.region_errors(xt, ut, yt, pred)
                    err_all = float(self.spec.objective.per_sample(pred, yt).mean())
            updates, version = self.updates, self.model_version
        out["objective"] = self._last_obj
        out["lagrangian"] = self._last_obj + float(np.sum(lam * self._last_con)) if self.spec.n_constraints else (
            self._last_obj
        )
        out["updates"] = float(updates)
        out["model_version"] = float(version)
        for k, name in enumerate(self.spec.constraint_names):
            e = errs.get(name)
            out[f"constraint/{name}"] = float(self._last_con[k])
            out[f"lambda/{name}"] = float(lam[k])
            out[f"error_in/{name}"] = float(e["in"][0]) if e else math.nan
            out[f"error_out/{name}"] = float(e["out"][0]) if e else math.nan
            out[f"n_in/{name}"] = float(e["n_in"][0]) if e else 0.0
        out["window"] = float(len(x))
        out["error_all"] = err_all
        self._metrics = out
        return dict(out)

    def status(self) -> dict[str, float]:
        """The last :meth:`compute_model_metrics` plus live buffer size, update count, model version,
        training flag and checkpoint counters (what a training process reports to its node)."""
        out = dict(self._metrics)
        out.update(
            buffer_size=float(len(self.buffer)),
            updates=float(self.updates),
            model_version=float(self.model_version),
            training=1.0 if self.training else 0.0,
            checkpoints_written=float(self.checkpoints_written),
            checkpoints_skipped=float(self.checkpoints_skipped),
        )
        return out

    def telemetry(self) -> dict[str, float]:
        """The full ``learner/model_error`` values (:func:`assemble_telemetry` of :meth:`status` and
        :meth:`counts`). Model values come from the last :meth:`compute_model_metrics`; counters, buffer size
        and update count are live."""
        return assemble_telemetry(self.spec.constraint_names, self.status(), self.counts())

    # ------------------------------------------------------------------------------------------ checkpoints
    @property
    def dirty(self) -> bool:
        """True when the trainer has updates not yet in a checkpoint."""
        return self.trainer is not None and self.updates != self._saved_updates

    def checkpoint_due(self, period_s: float) -> bool:
        """True when ``period_s`` seconds passed since the last save (or start) and there is something new."""
        return self.dirty and self._clock() - self._saved_at >= period_s

    def save_checkpoint(self, extra: Mapping[str, Any] | None = None) -> tuple[Path, int] | None:
        """Write the next checkpoint into the store (``None`` if no store or no trainer yet).

        Raises:
            OSError: the run directory is not writable (the caller logs and retries later).
        """
        if self.store is None or self.trainer is None:
            return None
        with self._lock:
            counts = self.counts()
            info = {
                "paired": counts.get("paired", 0),
                "sources": [p.name for p in self._sources],
                "min_transitions": self.config.min_transitions,
                "buffer_size": len(self.buffer),
                **dict(extra or {}),
            }
            metrics = {k: v for k, v in self._metrics.items() if isinstance(v, float)}
            path, version = save_checkpoint(self.store, self.trainer, metrics, {"learner": info})
            self.model_version = version
            self._saved_updates = self.trainer.steps
            self._saved_at = self._clock()
            self.checkpoints_written += 1
            return path, version

    def _resume(self, store: CheckpointStore) -> None:
        """Load the newest valid checkpoint of ``store`` (see the class docstring)."""
        skipped: list[tuple[Path, str]] = []
        try:
            first = store.load_latest_valid()
        except CheckpointError as exc:  # files exist, none readable
            versions = store.versions()
            self.checkpoints_skipped += len(versions)
            log.error("resume: no readable checkpoint in %s, starting from scratch (%s)", store.run_dir, exc)
            return
        if first is None:
            log.info("resume: no checkpoint in %s yet, starting from scratch", store.run_dir)
            return
        skipped.extend(first.skipped)
        candidates: list[tuple[Path, int, dict[str, np.ndarray] | None, dict[str, Any] | None]] = [
            (first.path, first.version, first.arrays, first.meta)
        ]
        candidates += [(store.path_for(v), v, None, None) for v in reversed(store.versions()) if v < first.version]
        for path, version, arrays, meta in candidates:
            if arrays is None or meta is None:
                try:
                    arrays, meta = read_checkpoint(path)
                except CheckpointError as exc:
                    skipped.append((path, str(exc)))
                    continue
            try:
                loaded = self._check_and_rebuild(arrays, meta, path)
                trainer = self._make_trainer(loaded)
            except ResumeError:
                raise
            except Exception as exc:  # noqa: BLE001 - CheckpointError, or torch refusing inconsistent states
                skipped.append((path, str(exc) if isinstance(exc, CheckpointError) else f"{path}: {exc}"))
                continue
            self._adopt(trainer, path, version, skipped)
            return
        self.checkpoints_skipped += len(skipped)
        log.error("resume: no usable checkpoint in %s, starting from scratch: %s", store.run_dir,
                  "; ".join(r for _, r in skipped))

    def _check_and_rebuild(self, arrays: dict[str, np.ndarray], meta: dict[str, Any], path: Path) -> LoadedModel:
        sysname = meta.get("system")
        if meta.get("kind") == MODEL_KIND and (
            sysname != self.system.name or meta.get("schema_hash") != self.system.schema_hash()
        ):
            raise ResumeError(
                f"{path} is a checkpoint of system {sysname!r} (schema {meta.get('schema_hash')}), but this learner "
                f"trains {self.system.name!r} (schema {self.system.schema_hash()}): use another run_dir or resume:=false"
            )
        loaded = model_from_payload(arrays, meta, expect=self.system, path=path)
        arch = loaded.model.architecture()
        want = self.model.architecture()
        diffs = [f"{k}: checkpoint {arch[k]!r}, configured {want[k]!r}" for k in ("kind", "hidden", "n_models")
                 if arch[k] != want[k]]
        if loaded.spec.constraint_names != self.spec.constraint_names:
            diffs.append(
                f"constraints: checkpoint {loaded.spec.constraint_names}, configured {self.spec.constraint_names}"
            )
        if diffs:
            raise ResumeError(
                f"{path} does not match the configured learner ({'; '.join(diffs)}): use another run_dir, "
                "resume:=false, or the checkpoint's settings"
            )
        if loaded.spec.to_dict() != self.spec.to_dict():
            log.warning("resume: %s was trained with another spec (same constraints %s); continuing with the "
                        "configured spec and the checkpoint's lambda", path, self.spec.constraint_names)
        return loaded

    def _make_trainer(self, loaded: LoadedModel) -> PrimalDualTrainer:
        cfg = self.config.train
        trainer = dataclasses.replace(loaded, spec=self.spec).trainer(cfg)
        # torch optimizers restore the learning rate saved with their state: the configured one wins
        for opt, lr in ((trainer.primal_opt, cfg.primal_lr), (trainer.dual_opt, cfg.dual_lr)):
            for group in opt.param_groups:
                group["lr"] = lr
        return trainer

    def _adopt(self, trainer: PrimalDualTrainer, path: Path, version: int, skipped: list[tuple[Path, str]]) -> None:
        cfg = self.config.train
        self.model = trainer.model
        self.model.train()
        self.trainer = trainer
        self.model_version = version
        self._saved_updates = trainer.steps
        self._rng = np.random.default_rng([cfg.seed, version])  # a fresh minibatch sequence per resume
        self.checkpoints_skipped += len(skipped)
        self.resumed = ResumeInfo(path, version, trainer.steps, self.lam.tolist(), list(skipped))
        for p, why in skipped:
            log.warning("resume: skipped %s: %s", p, why)
        log.info("resume: loaded %s (version %d, %d updates, lambda %s)", path, version, trainer.steps,
                 self.lam.tolist())


def _trim_history(tr: PrimalDualTrainer) -> None:
    h = tr.history
    extra = len(h.step) - HISTORY_ROWS
    if extra > 0:
        for name in ("step", "epoch", "objective", "constraints", "lambdas", "lagrangian", "wall_time"):
            del getattr(h, name)[:extra]


# ------------------------------------------------------------------------------------ training process
@dataclass(frozen=True)
class LoopConfig:
    """How a training loop paces itself.

    Attributes:
        updates_per_second: primal-dual updates per wall-clock second; 0 = as fast as possible.
        telemetry_rate: model metrics computed (and reported) per second, Hz.
        checkpoint_period: wall-clock seconds between checkpoints (only when there are new updates).
        chunk: updates between two looks at the inbox and the clocks.
    """

    updates_per_second: float = 0.0
    telemetry_rate: float = 5.0
    checkpoint_period: float = 10.0
    chunk: int = 10

    def __post_init__(self) -> None:
        if self.updates_per_second < 0 or self.telemetry_rate <= 0 or self.checkpoint_period <= 0 or self.chunk < 1:
            raise ValueError(f"invalid loop configuration {self}")


@dataclass(frozen=True)
class LearnerSetup:
    """Everything a training process needs to build its :class:`OnlineLearner` (picklable).

    Attributes:
        system, system_params: ``get_system(system, **system_params)``.
        spec: the problem spec as a dict (``ProblemSpec.to_dict()``).
        config: the learner configuration.
        run_dir: checkpoint directory (``None``: no checkpoints).
        resume: resume from the newest valid checkpoint of ``run_dir``.
        loop: pacing of the training loop.
        niceness: added to the training process's nice value, so the OS runs ingest (and simulators, MPC)
            first when CPUs are short; 0 keeps the parent's priority.
        threads: torch intra-op threads of the training process; 0 = torch's default (one per core). One is
            fastest for these small networks on a shared 2-core machine (docs/performance.md).
        flush_denormal: flush subnormal floats to zero in the training process (they can slow training by
            an order of magnitude; docs/performance.md).
        sources: ``(name, pairing)`` of each source, in index order (for raw messages; see below).
        channels: ``(source index, kind)`` of each raw-message channel.
        decoder: ``"module:function"``; ``function(decoder_args)`` returns ``decode(channel, payload) ->
            (vector, stamp_ns)`` for raw messages (it raises an exception with a ``reason`` attribute, e.g.
            ``msg_schemas.SchemaError``, for a malformed one). Keeps message formats (and rclpy) out of core.
        decoder_args: picklable argument of the decoder factory.
    """

    system: str
    system_params: dict[str, Any]
    spec: dict[str, Any]
    config: OnlineConfig
    run_dir: str | None = None
    resume: bool = True
    loop: LoopConfig = field(default_factory=LoopConfig)
    niceness: int = 10
    threads: int = 1
    flush_denormal: bool = True
    sources: tuple[tuple[str, PairingConfig], ...] = ()
    channels: tuple[tuple[int, str], ...] = ()
    decoder: str | None = None
    decoder_args: Any = None

    def __post_init__(self) -> None:
        if self.threads < 0:
            raise ValueError(f"threads must be >= 0 (0 = torch's default), got {self.threads}")

    def build(self) -> OnlineLearner:
        from saml_ros.core.systems import get_system

        system = get_system(self.system, **self.system_params)
        spec = ProblemSpec.for_system(self.spec, system)
        store = None if self.run_dir is None else CheckpointStore(self.run_dir, keep=self.config.checkpoint_keep)
        learner = OnlineLearner(system, spec, self.config, store=store, resume=self.resume)
        for name, pairing in self.sources:
            learner.add_source(name, pairing)
        return learner

    def make_decoder(self) -> Callable[[int, Any], tuple[Any, int]] | None:
        """The raw-message decoder (imports ``decoder``'s module), or None."""
        if self.decoder is None:
            return None
        import importlib

        module, func = self.decoder.split(":")
        factory: Callable[[Any], Callable[[int, Any], tuple[Any, int]]] = getattr(
            importlib.import_module(module), func
        )
        return factory(self.decoder_args)


class Throttle:
    """Per-key log throttling: the first event of each key is logged at once, later ones at most every
    ``period`` seconds with the number suppressed in between."""

    def __init__(self, emit: Callable[[str], Any], period: float = 5.0) -> None:
        self._emit, self._period = emit, period
        self._state: dict[str, tuple[float, int]] = {}

    def __call__(self, key: str, message: str) -> None:
        now = time.monotonic()
        last, suppressed = self._state.get(key, (-math.inf, 0))
        if now - last < self._period:
            self._state[key] = (last, suppressed + 1)
            return
        self._state[key] = (now, 0)
        more = f" ({suppressed} more '{key}' since the last report)" if suppressed else ""
        self._emit(f"rejected/{key}: {message}{more}")


class RawIngest:
    """Decodes raw (serialized) messages and feeds them to an :class:`OnlineLearner`'s pairers; every
    rejection is counted and logged (throttled per reason)."""

    def __init__(self, learner: OnlineLearner, channels: Sequence[tuple[int, str]],
                 decode: Callable[[int, Any], tuple[Any, int]]) -> None:
        self.learner, self.channels, self.decode = learner, list(channels), decode
        self.throttle = Throttle(log.warning)
        self._unpaired = 0

    def feed(self, items: Sequence[tuple[int, Any]]) -> None:
        """``[(channel, payload), ...]`` in arrival order."""
        learner = self.learner
        for channel, payload in items:
            src, kind = self.channels[channel]
            try:
                vec, stamp = self.decode(channel, payload)
            except Exception as exc:  # noqa: BLE001 - any malformed message is counted, never fatal
                reason = getattr(exc, "reason", None) or "format"
                learner.reject(src, reason, kind)
                self.throttle(reason, str(exc) if reason != "format" else f"{type(exc).__name__}: {exc}")
                continue
            res = learner.ingest(src, kind, stamp, vec)
            if res.rejected is not None:
                self.throttle(res.rejected, res.detail)
            elif res.detail:
                log.warning(res.detail)

    def check_orphans(self) -> None:
        """Log (throttled) when messages left the pairing window without ever being paired."""
        unpaired = self.learner.counts().get("unpaired", 0)
        if unpaired > self._unpaired:
            self.throttle("unpaired", f"{unpaired - self._unpaired} message(s) left the pairing window without "
                                      "ever being paired")
        self._unpaired = unpaired


def run_loop(learner: OnlineLearner, loop: LoopConfig, conn: Any, send: Callable[[tuple[Any, ...]], None],
             raw: RawIngest | None = None, stop_requested: Callable[[], bool] | None = None) -> None:
    """The training loop of a training process (or any thread owning ``learner``).

    ``conn`` is the inbox (``poll(timeout)`` / ``recv()``) carrying ``("batch", x, u, y, stamp_s, source)``
    (paired transitions), ``("raw", [(channel, payload), ...])`` (messages for ``raw``) and ``("stop",)``.
    The whole inbox is handled before every chunk of updates, so ingest goes first. ``send`` reports
    ``("status", status, {source name: counters})`` at ``loop.telemetry_rate``, ``("checkpoint", path,
    version)`` after each save, ``("error", what, message)`` and, on stop, ``("stopped", path | None, version,
    updates)`` after a final checkpoint (when there are updates not yet saved). Returns after a stop.
    ``stop_requested()`` True (the training process got :data:`STOP_SIGNAL`) stops at once, as ``("stop",)``
    would, without handling what is still in the inbox: data not yet in the buffer cannot change the final
    checkpoint, and a backlog of it must not hold the shutdown past a launcher's grace period.
    """
    requested = stop_requested or (lambda: False)

    def report() -> None:
        learner.compute_model_metrics()
        if raw is not None:
            raw.check_orphans()
        send(("status", learner.status(), {p.name: dict(p.counts) for p in learner.sources}))

    metrics_period = 1.0 / loop.telemetry_rate
    next_metrics = 0.0
    paced_from: float | None = None
    paced_done = 0
    while True:
        while True:
            msg: Any = ("stop",) if requested() else (conn.recv() if conn.poll() else None)
            if msg is None:
                break
            if msg[0] == "raw":
                if raw is not None:
                    raw.feed(msg[1])
            elif msg[0] == "batch":
                learner.add_batch(*msg[1:])
            elif msg[0] == "stop":
                saved = _save(learner, send) if learner.dirty else None
                report()
                path = str(saved[0]) if saved else None
                send(("stopped", path, learner.model_version, learner.updates))
                return
        now = time.monotonic()
        if now >= next_metrics:
            report()
            next_metrics = now + metrics_period
        if learner.checkpoint_due(loop.checkpoint_period):
            _save(learner, send)
        if not learner.training:
            paced_from = None
            conn.poll(0.05)  # an interruptible sleep: wakes up when data arrives
            continue
        n = loop.chunk
        if loop.updates_per_second > 0:
            if paced_from is None:
                paced_from, paced_done = now, 0
            due = int((now - paced_from) * loop.updates_per_second) - paced_done
            if due <= 0:
                conn.poll(min(metrics_period, (paced_done + 1) / loop.updates_per_second - (now - paced_from)))
                continue
            n = min(due, loop.chunk)
            paced_done += n
        try:
            learner.update(n)
        except Exception as exc:  # noqa: BLE001 - report, back off, keep going
            send(("error", "training", f"training step failed ({type(exc).__name__}: {exc}); retrying in 1 s"))
            time.sleep(1.0)


def _save(learner: OnlineLearner, send: Callable[[tuple[Any, ...]], None]) -> tuple[Path, int] | None:
    try:
        saved = learner.save_checkpoint()
    except OSError as exc:
        run_dir = learner.store.run_dir if learner.store else "?"
        send(("error", "checkpoint", f"cannot write a checkpoint into {run_dir}: {exc}"))
        return None
    if saved is not None:
        send(("checkpoint", str(saved[0]), saved[1]))
    return saved


class _PipeLogHandler(logging.Handler):
    """Ships ``saml_ros.*`` log records of the training process to its parent as ``("log", level, text)``."""

    def __init__(self, send: Callable[[tuple[Any, ...]], None]) -> None:
        super().__init__()
        self._send = send

    def emit(self, record: logging.LogRecord) -> None:
        with contextlib.suppress(Exception):
            self._send(("log", record.levelno, self.format(record)))


def _die_with_parent() -> None:
    """Linux: SIGKILL this process when its parent dies (a killed learner never leaves a trainer behind that
    keeps writing checkpoints into the run directory)."""
    with contextlib.suppress(Exception):
        import ctypes

        libc = ctypes.CDLL("libc.so.6", use_errno=True)
        pr_set_pdeathsig = 1
        libc.prctl(pr_set_pdeathsig, signal.SIGKILL)
        if os.getppid() == 1:  # the parent died before prctl took effect
            os._exit(0)


def child_entry(fd: int) -> None:
    """Entry point of a training process started by :class:`TrainingProcess`: ``fd`` is its end of a socket
    pair; the first message on it is the :class:`LearnerSetup`."""
    from multiprocessing.connection import Connection

    conn = Connection(fd)
    try:
        setup = conn.recv()
    except (EOFError, OSError):
        _exit_now()
    _child_main(conn, setup)
    _exit_now()


def _exit_now() -> None:
    """End the training process without the interpreter's teardown: its work is saved and reported (or there was
    none), and torch's teardown takes 1-5 s on a loaded 2-core machine, which the node's shutdown would wait for."""
    logging.shutdown()
    with contextlib.suppress(Exception):
        sys.stdout.flush()
        sys.stderr.flush()
    os._exit(0)


def apply_compute_settings(threads: int, flush_denormal: bool) -> dict[str, Any]:
    """Set this process's torch intra-op ``threads`` (0 = leave torch's default) and subnormal flushing.

    Returns what torch reports afterwards: ``{"threads": torch.get_num_threads(), "flush_denormal": bool}``
    (``flush_denormal`` is False where the CPU cannot flush, e.g. without SSE3).
    """
    if threads > 0:
        torch.set_num_threads(threads)
    flushing = bool(torch.set_flush_denormal(flush_denormal)) and flush_denormal
    return {"threads": torch.get_num_threads(), "flush_denormal": flushing}


#: what :meth:`TrainingProcess.stop` sends the training process: save now, skip the inbox (see :func:`run_loop`)
STOP_SIGNAL = signal.SIGUSR1


def _child_main(conn: Any, setup: LearnerSetup) -> None:
    _die_with_parent()
    # the terminal's Ctrl-C reaches the whole process group: the parent decides when training stops, and tells
    # this process with STOP_SIGNAL (then the ("stop",) message) so that it stops without working off its inbox
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    stop_flag: list[int] = []
    signal.signal(STOP_SIGNAL, lambda signum, frame: stop_flag.append(signum))
    if setup.niceness:
        with contextlib.suppress(OSError):
            os.nice(setup.niceness)
    compute = apply_compute_settings(setup.threads, setup.flush_denormal)
    lock = threading.Lock()

    def send(msg: tuple[Any, ...]) -> None:
        with lock:
            conn.send(msg)

    handler = _PipeLogHandler(send)
    root = logging.getLogger("saml_ros")
    root.addHandler(handler)
    root.setLevel(logging.INFO)
    try:
        try:
            learner = setup.build()
            decode = setup.make_decoder()
        except ResumeError as exc:
            send(("fatal", "resume", str(exc)))
            return
        except Exception as exc:  # noqa: BLE001 - reported to the parent, which exits with a message
            send(("fatal", "error", f"{type(exc).__name__}: {exc}"))
            return
        r = learner.resumed
        info = None if r is None else {"path": str(r.path), "version": r.version, "updates": r.updates,
                                       "lam": r.lam, "skipped": [(str(p), why) for p, why in r.skipped]}
        raw = None if decode is None else RawIngest(learner, setup.channels, decode)
        log.info("training process: %d torch intra-op thread(s), subnormal floats %s", compute["threads"],
                 "flushed to zero" if compute["flush_denormal"] else "not flushed")
        send(("ready", info, list(learner.model.hidden), learner.status(), compute))
        run_loop(learner, setup.loop, conn, send, raw, stop_requested=lambda: bool(stop_flag))
    except (EOFError, OSError):
        return  # the parent is gone


@dataclass
class ReadyInfo:
    """What a training process reported when it was ready.

    Attributes:
        resumed: ``{"path", "version", "updates", "lam", "skipped"}`` of the checkpoint it resumed from, or None.
        hidden: the model's hidden layer sizes.
        status: its first :meth:`OnlineLearner.status`.
        threads: torch intra-op threads the training process runs with.
        flush_denormal: whether it flushes subnormal floats to zero.
    """

    resumed: dict[str, Any] | None
    hidden: list[int]
    status: dict[str, float]
    threads: int
    flush_denormal: bool


class TrainingProcess:
    """Runs the training side of an :class:`OnlineLearner` in a child process fed with transitions.

    Why a process: the learner's ingest (rclpy callbacks: decode, pair) and primal-dual training are both
    Python; in one process they share the GIL, and training would take CPU time from ingest (measured: the
    node then loses messages at under a third of a bare subscriber's rate; docs/learner.md). In a child process training runs
    on another CPU when there is one, and at a higher nice value (:attr:`LearnerSetup.niceness`) it yields
    the CPU to ingest when there is not.

    The child owns the buffer, model, trainer, checkpoints and resume (and, for raw messages, the decoding and
    pairing: :class:`RawIngest`); this handle ships paired transitions (:meth:`submit`) or raw messages
    (:meth:`submit_raw`) to it in batches every 5 ms (a shipper thread, so submitting never blocks) and receives
    status, per-source counters, checkpoint announcements, log records and errors (a reader thread, calling the
    callbacks). If the child dies
    unexpectedly it is restarted (resuming from the newest checkpoint) and ``on_error`` is told.

    Args:
        setup: how to build the learner in the child.
        on_status: called with each status dict (:meth:`OnlineLearner.status`).
        on_checkpoint: called with ``(path, version)`` after each checkpoint.
        on_log: called with ``(level, text)`` for the child's log records.
        on_error: called with ``(what, message)`` for training / checkpoint errors and restarts.
        max_queue: transitions held while the child cannot take them; beyond that they are dropped
            (counted in :attr:`dropped`).
    """

    def __init__(
        self,
        setup: LearnerSetup,
        *,
        on_status: Callable[[dict[str, float]], None] | None = None,
        on_checkpoint: Callable[[str, int], None] | None = None,
        on_log: Callable[[int, str], None] | None = None,
        on_error: Callable[[str, str], None] | None = None,
        max_queue: int = 200_000,
    ) -> None:
        self.setup = setup
        self.on_status = on_status or (lambda s: None)
        self.on_checkpoint = on_checkpoint or (lambda p, v: None)
        self.on_log = on_log or (lambda lvl, text: log.log(lvl, text))
        self.on_error = on_error or (lambda what, text: log.error(text))
        self.max_queue = max_queue
        self.status: dict[str, float] = {}
        #: per-source pairing counters of the child, ``{source name: {counter: value}}`` (see pairing.COUNTERS)
        self.source_counts: dict[str, dict[str, int]] = {}
        #: what the running training process reported when it was ready (after a restart: the new one's)
        self.ready: ReadyInfo | None = None
        self.dropped = 0
        self.restarts = 0
        self.errors = 0
        self._outbox: deque[Transition] = deque()
        self._raw: deque[tuple[int, Any]] = deque()
        self._send_lock = threading.Lock()
        self._stopping = threading.Event()
        self._stopped = threading.Event()
        self._final: tuple[str | None, int, int] | None = None
        self._proc: subprocess.Popen[bytes] | None = None
        self._conn: Any = None
        self._threads: list[threading.Thread] = []

    # ---------------------------------------------------------------------------------------- lifecycle
    def start(self, timeout: float = 120.0, launched: LaunchedChild | None = None) -> ReadyInfo:
        """Start the child (or use ``launched``, from :func:`launch_child`) and wait until it has built its
        learner (and resumed).

        Raises:
            ResumeError: the run directory contradicts the configuration.
            RuntimeError: the child could not build its learner or did not answer within ``timeout`` s.
        """
        ready = self._spawn(self.setup, timeout, launched)
        for target, name in ((self._ship, "learner-ship"), (self._read, "learner-read")):
            t = threading.Thread(target=target, name=name, daemon=True)
            t.start()
            self._threads.append(t)
        return ready

    def _spawn(self, setup: LearnerSetup, timeout: float, launched: LaunchedChild | None = None) -> ReadyInfo:
        proc, parent = launched if launched is not None else launch_child()
        parent.send(setup)
        deadline = time.monotonic() + timeout
        while True:
            left = deadline - time.monotonic()
            if left <= 0 or not parent.poll(left):
                proc.kill()
                proc.wait(5)
                raise RuntimeError(f"the training process did not start within {timeout:.0f} s")
            try:
                msg = parent.recv()
            except (EOFError, OSError):
                exit_code = proc.wait(5)
                raise RuntimeError(f"the training process exited during start-up (exit code {exit_code})") from None
            if msg[0] == "log":
                self.on_log(msg[1], msg[2])
            elif msg[0] == "fatal":
                proc.wait(10)
                raise (ResumeError if msg[1] == "resume" else RuntimeError)(msg[2])
            elif msg[0] == "ready":
                self._proc, self._conn = proc, parent
                self.status = msg[3]
                self.ready = ReadyInfo(msg[1], msg[2], msg[3], msg[4]["threads"], msg[4]["flush_denormal"])
                return self.ready

    def stop(self, timeout: float = 60.0) -> tuple[str | None, int, int] | None:
        """Ask the child for a final checkpoint now and wait for it to exit.

        What is still queued here or in the child's inbox is dropped (it is not in the buffer yet, so it cannot
        change the final checkpoint): :data:`STOP_SIGNAL` makes the child save at once, however far behind its
        ingest is. Returns ``(path of the final checkpoint or None if nothing was new, model version, updates)``,
        or None if the child did not answer within ``timeout`` s (it is then killed).
        """
        self._stopping.set()
        if self._proc is not None and self._proc.poll() is None:
            with contextlib.suppress(OSError):
                self._proc.send_signal(STOP_SIGNAL)
        for t in self._threads:
            if t.name == "learner-ship":
                t.join(timeout)
        try:
            with self._send_lock:
                self._conn.send(("stop",))
        except (OSError, ValueError):
            pass
        self._stopped.wait(timeout)
        if self._proc is not None:
            try:
                self._proc.wait(5.0 if self._stopped.is_set() else 0.1)
            except subprocess.TimeoutExpired:
                self._proc.kill()
                self._proc.wait(5.0)
        return self._final

    @property
    def pid(self) -> int | None:
        return None if self._proc is None else int(self._proc.pid)

    # ---------------------------------------------------------------------------------------- data
    def submit(self, tr: Transition) -> None:
        """Queue one transition for the child (never blocks; see ``max_queue``)."""
        if len(self._outbox) >= self.max_queue:
            self.dropped += 1
            return
        self._outbox.append(tr)

    def submit_raw(self, channel: int, payload: Any) -> None:
        """Queue one raw message for the child's decoder (never blocks; see ``max_queue``). Called from one
        thread per channel set (an rclpy callback group), it only appends to a deque."""
        if len(self._raw) >= self.max_queue:
            self.dropped += 1
            return
        self._raw.append((channel, payload))

    @property
    def queued(self) -> int:
        return len(self._outbox) + len(self._raw)

    def counts(self) -> dict[str, int]:
        """The child's pairing counters summed over sources (as of its last status)."""
        return total_counts(self.source_counts.values())

    def _ship(self) -> None:
        """Send queued data in batches every few ms (a blocking pipe write stalls this thread only); returns as
        soon as :meth:`stop` is called (the child no longer reads data then)."""
        while True:
            if self._stopping.is_set():
                return
            n = len(self._raw)
            if n:
                items = [self._raw.popleft() for _ in range(n)]
                try:
                    with self._send_lock:
                        self._conn.send(("raw", items))
                except (OSError, ValueError):  # the child is being restarted: keep them
                    self._raw.extendleft(reversed(items))
                    time.sleep(0.1)
            n = len(self._outbox)
            if n:
                trs = [self._outbox.popleft() for _ in range(n)]
                batch = (
                    "batch",
                    np.stack([t.x for t in trs]),
                    np.stack([t.u for t in trs]),
                    np.stack([t.y for t in trs]),
                    np.array([t.stamp_ns for t in trs], dtype=np.float64) * 1e-9,
                    np.array([t.source for t in trs], dtype=np.int64),
                )
                try:
                    with self._send_lock:
                        self._conn.send(batch)
                except (OSError, ValueError):  # the child is being restarted: keep the batch
                    self._outbox.extendleft(reversed(trs))
                    time.sleep(0.1)
            time.sleep(0.005)

    def _read(self) -> None:
        while True:
            conn = self._conn
            try:
                msg = conn.recv()
            except (EOFError, OSError):
                if self._stopping.is_set():
                    self._stopped.set()
                    return
                self._restart()
                continue
            kind = msg[0]
            if kind == "status":
                self.status = msg[1]
                self.source_counts = msg[2]
                self.on_status(msg[1])
            elif kind == "checkpoint":
                self.on_checkpoint(msg[1], msg[2])
            elif kind == "log":
                self.on_log(msg[1], msg[2])
            elif kind == "error":
                self.errors += 1
                self.on_error(msg[1], msg[2])
            elif kind == "stopped":
                self._final = (msg[1], msg[2], msg[3])
                self._stopped.set()
                return

    def _restart(self) -> None:
        code = None
        if self._proc is not None:
            try:
                code = self._proc.wait(5.0)
            except subprocess.TimeoutExpired:  # its end of the connection broke but it lives on: end it
                self._proc.kill()
                code = self._proc.wait(5.0)
        self.errors += 1
        self.restarts += 1
        self.on_error("process", f"the training process exited unexpectedly (exit code {code}); restarting it "
                                 "from the newest checkpoint (the replay buffer starts empty)")
        time.sleep(0.5)
        setup = dataclasses.replace(self.setup, resume=True)
        while not self._stopping.is_set():
            try:
                with self._send_lock:
                    self._spawn(setup, 120.0)
                return
            except Exception as exc:  # noqa: BLE001 - keep trying; ingest goes on meanwhile
                self.on_error("process", f"restarting the training process failed: {exc}; retrying in 5 s")
                time.sleep(5.0)
