"""The online learner's state, ROS-free: :class:`OnlineLearner` (and its :class:`OnlineConfig`).

It owns the replay buffer and recent window (fed through its :class:`~saml_ros.core.online.ingest.Ingest`), the
model and the :class:`~saml_ros.core.training.PrimalDualTrainer`, created once ``min_transitions`` transitions
have arrived: the input/output normalisation is fitted on exactly those transitions and then frozen (it is part
of the model, so it is checkpointed and restored with it). :meth:`OnlineLearner.update` takes ``n`` primal-dual
steps on minibatches sampled from the buffer (the fast engine's path: :mod:`~saml_ros.core.online.updates`);
:meth:`OnlineLearner.compute_model_metrics` and :meth:`OnlineLearner.telemetry` report (:mod:`~saml_ros.core.online.telemetry`); checkpoints are written by
:meth:`OnlineLearner.save_checkpoint` and resumed from at construction (:mod:`~saml_ros.core.online.resume`).

Threads: one thread may call :meth:`OnlineLearner.ingest` (per source) while another calls
:meth:`OnlineLearner.update`, :meth:`OnlineLearner.compute_model_metrics` and
:meth:`OnlineLearner.save_checkpoint`; :meth:`OnlineLearner.telemetry` is cheap and may be called from any
thread. The model is guarded by one lock; the buffer and the recent window have their own.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch

from saml_ros.core.data.buffer import Policy, ReplayBuffer
from saml_ros.core.data.pairing import AddResult, PairingConfig, StampPairer, Transition
from saml_ros.core.data.plausibility import Plausibility
from saml_ros.core.data.resampling import ResampleConfig, ResamplingPairer
from saml_ros.core.dynamics.system import System
from saml_ros.core.model.checkpoint import CheckpointStore
from saml_ros.core.model.evidence import DataEvidence
from saml_ros.core.model.io import UnhealthyModel
from saml_ros.core.model.network import DynamicsModel
from saml_ros.core.online.heldout import META_KEY as HELDOUT_KEY
from saml_ros.core.online.heldout import HeldoutReport, HeldoutSet, evaluate
from saml_ros.core.online.ingest import Ingest, RecentWindow
from saml_ros.core.online.options import OnlineConfig
from saml_ros.core.online.resume import ResumeInfo, resume_newest
from saml_ros.core.online.storage import WriteBackoff
from saml_ros.core.online.telemetry import StepAverages, assemble_telemetry, feasibility_metrics, model_metrics
from saml_ros.core.online.updates import OnlineUpdates
from saml_ros.core.spec import ProblemSpec
from saml_ros.core.training import PrimalDualTrainer, save_checkpoint
from saml_ros.core.training.health import TrainingHealth

log = logging.getLogger("saml_ros.online")

#: history rows the trainer keeps in memory (older rows are dropped; online training never ends)
HISTORY_ROWS = 1000
#: the checkpoint's recorded residual bound: this times the largest residual in the buffer, per field ...
RESIDUAL_MARGIN = 1.5
#: ... and at least this (state units): fields whose residual is exactly 0 (e.g. positions) keep a little room
RESIDUAL_FLOOR = 1e-3
#: the ``meta["learner"]`` key it is recorded under (read by :func:`saml_ros.core.mpc.guard.residual_bound`)
RESIDUAL_BOUND_KEY = "residual_bound"
#: the normalisation is refitted (the function kept, :meth:`DynamicsModel.renormalize`) when the training buffer's
#: spread of an input or of the residual grew beyond this factor times the fitted one, or the mean of an input moved
#: by more than the fitted spread (statistics clipped to the 1st..99th percentiles; a spread never shrinks)
RENORM_FACTOR = 2.0
#: with ``paced`` (:meth:`OnlineLearner.compute_model_metrics`, what the training loop asks for) the held-out
#: evaluation and the model metrics take at most this share of the training thread's CPU time: each is put off until
#: the updates since its previous run used ``(1 - EVAL_SHARE) / EVAL_SHARE`` times its measured cost. On a busy CPU a
#: niced training process gets little time, and evaluations paced by the wall clock alone ate most of it (measured
#: on the diff-drive: one held-out evaluation costs about 280 updates, the 5 Hz model metrics 120 updates a second)
EVAL_SHARE = 0.1
#: ... but a paced evaluation is never put off longer than this (s of the learner's clock; the held-out one: this
#: many ``heldout_period``), so the values follow new data while few or no updates run
METRICS_MAX_DELAY = 2.0
HELDOUT_MAX_PERIODS = 10.0


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
        self.model = DynamicsModel(system, cfg.hidden, cfg.kind, n_models=cfg.n_models, seed=cfg.train.seed)
        self.model.to(cfg.train.torch_dtype)
        self.trainer: PrimalDualTrainer | None = None
        self._updates: OnlineUpdates | None = None
        self._recent = RecentWindow(cfg.telemetry_window, n_x, n_u, n_y)
        #: the held-out stretches of the stream (never in the replay buffer)
        self.heldout = HeldoutSet(cfg.heldout, n_x, n_u, n_y)
        self.ingest_path = Ingest(self.buffer, self._recent, Plausibility.for_system(system, cfg.plausible_bounds),
                                  heldout=self.heldout)
        self._lock = threading.RLock()
        self._rng = np.random.default_rng(cfg.train.seed)
        self._averages = StepAverages(spec.n_constraints)
        self.model_version = 0
        self._saved_updates: int | None = None
        self._saved_at = clock()
        self.checkpoints_written = 0
        self.checkpoints_skipped = 0
        #: checkpoints not written because the model had non-finite values
        self.checkpoints_unhealthy = 0
        #: failed checkpoint writes (full or read-only disk, ...): when to try again, what /diagnostics says
        self.writes = WriteBackoff(clock)
        self._evidence: DataEvidence | None = None
        self.resumed: ResumeInfo | None = None
        self._metrics: dict[str, float] = {}
        #: the newest held-out report (:meth:`evaluate_heldout`), and when it was made (the learner's clock)
        self.heldout_report: HeldoutReport | None = None
        self._heldout_at = -math.inf
        #: updates and training transitions of this process since training started (the update budget)
        self._budget_from: tuple[int, int] | None = None
        self.renormalizations = 0
        #: the exponential average of the weights (``average_updates``), and which model checkpoints publish:
        #: ``"latest"`` (the trainer's weights) or ``"average"`` (chosen on the held-out stretches)
        self.average: DynamicsModel | None = None
        self.published = "latest"
        #: CPU time (s, the training thread's) spent in updates, and per paced evaluation its last cost, the update
        #: CPU time then and when it ran (:data:`EVAL_SHARE`)
        self._update_cpu = 0.0
        self._paced: dict[str, tuple[float, float, float]] = {}
        if store is not None and resume:
            self._resume(store)
        self.compute_model_metrics()

    # ------------------------------------------------------------------------------------------ ingest
    def add_source(self, name: str, pairing: PairingConfig | ResampleConfig) -> int:
        """Register a source (robot / namespace) with its pairing rule; returns its index."""
        return self.ingest_path.add_source(name, pairing)

    @property
    def sources(self) -> list[StampPairer | ResamplingPairer]:
        return self.ingest_path.sources

    def ingest(self, source: int, kind: str, stamp_ns: int, vector: Any) -> AddResult:
        """Feed one event of ``source`` (see :meth:`StampPairer.add`); completed transitions are added."""
        return self.ingest_path.ingest(source, kind, stamp_ns, vector)

    def reject(self, source: int, reason: str, kind: str | None = None) -> None:
        """Count a ``kind`` message of ``source`` dropped before pairing (``reason``: a SchemaError reason)."""
        self.ingest_path.reject(source, reason, kind)

    def add(self, tr: Transition) -> None:
        """Add one paired transition to the buffer and the recent window."""
        self.ingest_path.add(tr)

    def add_batch(self, x: np.ndarray, u: np.ndarray, y: np.ndarray, stamp: Any = 0.0, source: Any = 0) -> None:
        """Add ``B`` paired transitions at once (see :meth:`Ingest.add_batch`)."""
        self.ingest_path.add_batch(x, u, y, stamp, source)

    def counts(self) -> dict[str, int]:
        """All sources' pairing and rejection counters, summed."""
        return self.ingest_path.counts()

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

    def update_budget(self) -> int | None:
        """Updates :meth:`update` may still take now under ``updates_per_transition`` (None: no limit)."""
        rate = self.config.updates_per_transition
        if rate <= 0:
            return None
        if self._budget_from is None:  # training has not started in this process: the first call may start it
            return int(rate * self.buffer.total_added)
        updates0, added0 = self._budget_from
        allowed = rate * (self.buffer.total_added - added0 + self.config.min_transitions)
        return max(0, int(allowed) - (self.updates - updates0))

    def update(self, n_steps: int) -> int:
        """Run up to ``n_steps`` primal-dual updates; returns how many ran (0 while waiting for data, or when the
        update budget of ``updates_per_transition`` is spent until more data arrives).

        The first call after ``min_transitions`` transitions arrived fits the normalisation on them and
        creates the trainer.
        """
        if n_steps <= 0 or not self.training:
            return 0
        budget = self.update_budget()
        if budget is not None:
            n_steps = min(n_steps, budget)
            if n_steps <= 0:
                return 0
        with self._lock:
            if self.trainer is None:
                self._start_training()
            assert self.trainer is not None
            if self._budget_from is None:
                self._budget_from = (self.updates, self.buffer.total_added)
            if self._updates is None or self._updates.trainer is not self.trainer:
                self._updates = OnlineUpdates(self.trainer, HISTORY_ROWS, self.config.n_models)
            cpu = time.thread_time()
            self._updates.run(n_steps, self.buffer, self._rng, self._averages)
            self._average_in(n_steps)
            self._update_cpu += time.thread_time() - cpu
            return n_steps

    @torch.no_grad()
    def _average_in(self, n: int) -> None:
        """Move the weight average towards the trainer's weights after ``n`` updates (time constant
        ``average_updates``; the first call copies them)."""
        tau = self.config.average_updates
        if tau <= 0:
            return
        if self.average is None:
            self.average = _copy_model(self.model)
            return
        keep = math.exp(-n / tau)
        for pa, pm in zip(self.average.net.parameters(), self.model.net.parameters(), strict=True):
            pa.mul_(keep).add_(pm, alpha=1.0 - keep)

    def _start_training(self) -> None:
        m = self.config.min_transitions
        rows = self.buffer.arrays()  # oldest first: the first min_transitions ever added (capacity >= m)
        self.model.fit_normalization(rows.x[:m], rows.u[:m], rows.y[:m])
        self.trainer = PrimalDualTrainer(self.model, self.spec, self.config.train, self.config.health)
        log.info("training started: normalisation fitted on the first %d transitions%s", m,
                 " (refitted when the data drifts)" if self.config.renormalize else " and frozen")

    def _training_sample(self) -> Any:
        """A uniform sample (at most ``heldout.train_sample`` rows) of the training buffer, time order kept."""
        rows = self.buffer.arrays()
        k = self.config.heldout.train_sample
        if len(rows.x) <= k:
            return rows
        pick = np.sort(np.random.default_rng([1, self.updates]).choice(len(rows.x), size=k, replace=False))
        return type(rows)(*(a[pick] for a in rows))

    @torch.no_grad()
    def _maybe_renormalize(self, rows: Any) -> bool:
        """Refit the normalisation on ``rows`` (the training sample) when it drifted (:data:`RENORM_FACTOR`),
        keeping the model's function and rescaling the optimizer's moments of the weights that absorbed it."""
        tr = self.trainer
        if tr is None or not self.config.renormalize or len(rows.x) < self.config.min_transitions:
            return False
        model = self.model
        mean, std, ostd = model.normalization_of(rows.x, rows.u, rows.y, robust=True)
        old_m, old_s, old_o = (b[0].double() for b in (model.in_mean, model.in_std, model.out_std))
        ratio = torch.cat([(std / old_s).reshape(-1), (ostd / old_o).reshape(-1)])
        moved = ((mean - old_m).abs() / old_s).max()
        if not (bool(torch.isfinite(ratio).all()) and bool(torch.isfinite(mean).all())):
            return False
        if not (ratio.max() > RENORM_FACTOR or moved > 1.0):
            return False
        # a spread only grows: a narrower stretch of data must not blow up a field the model has seen move more
        std, ostd = torch.maximum(std, old_s), torch.maximum(ostd, old_o)
        saved = {k: v.clone() for k, v in model.state_dict().items()}
        rows_f, cols_f = model.renormalize(mean, std, ostd)
        if not all(bool(torch.isfinite(v).all()) for v in model.state_dict().values()):
            model.load_state_dict(saved)
            log.warning("normalisation not refitted: the refitted weights would not be finite")
            return False
        if self.average is not None:  # the same normalisation before, so the same exact change
            self.average.renormalize(mean, std, ostd)
            if not all(bool(torch.isfinite(v).all()) for v in self.average.state_dict().values()):
                self.average = None  # started again from the trainer's weights
        net = model.net
        for param, factor in ((net.weights[0], rows_f), (net.weights[-1], cols_f), (net.biases[-1], cols_f)):
            state = tr.primal_opt.state.get(param, {})
            f = factor.to(param.dtype)
            if isinstance(state.get("exp_avg"), torch.Tensor):
                state["exp_avg"].div_(f)
            if isinstance(state.get("exp_avg_sq"), torch.Tensor):
                state["exp_avg_sq"].div_(f * f)
            if isinstance(state.get("momentum_buffer"), torch.Tensor):
                state["momentum_buffer"].div_(f)
        self._updates = None  # the update path is rebuilt on the new normalisation
        self.renormalizations += 1
        log.info("normalisation refitted on %d training transitions (spread ratio %.3g..%.3g, mean moved %.3g "
                 "spreads); the model's function is kept", len(rows.x), float(ratio.min()), float(ratio.max()),
                 float(moved))
        return True

    def evaluate_heldout(self) -> HeldoutReport | None:
        """Evaluate the model on the held-out stretches and a sample of the training buffer (refitting the
        normalisation first when the training data drifted); None before training. With a weight average
        (``average_updates``) both the trainer's weights and the average are evaluated, and the one that does
        better on the held-out stretches (:func:`heldout_score`) becomes :attr:`published`; the report is the
        published model's. Cached for telemetry."""
        if self.trainer is None:
            return None
        with self._lock:
            rows = self._training_sample()
            self._maybe_renormalize(rows)
            held = self.heldout.arrays()
            report = evaluate(self.model, self.spec, held, rows, self.config.heldout, updates=self.updates)
            self.published = "latest"
            if self.average is not None and len(held.x):
                other = evaluate(self.average, self.spec, held, rows, self.config.heldout, updates=self.updates)
                if heldout_score(other) < heldout_score(report):
                    report, self.published = other, "average"
            report.published = self.published
        self.heldout_report = report
        self._heldout_at = self._clock()
        return report

    def published_model(self) -> DynamicsModel:
        """The model checkpoints publish (:attr:`published`: the trainer's weights or their average)."""
        return self.average if self.published == "average" and self.average is not None else self.model

    # ------------------------------------------------------------------------------------------ telemetry
    def _due(self, name: str, min_interval: float, max_delay: float) -> bool:
        """Whether the paced evaluation ``name`` may run now (:data:`EVAL_SHARE`): ``min_interval`` s since its last
        run and either enough update CPU time since then or ``max_delay`` s."""
        last = self._paced.get(name)
        if last is None:
            return True
        cost, cpu0, t0 = last
        waited = self._clock() - t0
        if waited < min_interval:
            return False
        return self._update_cpu - cpu0 >= cost * (1.0 - EVAL_SHARE) / EVAL_SHARE or waited >= max_delay

    def _ran(self, name: str, cpu0: float) -> None:
        self._paced[name] = (time.thread_time() - cpu0, self._update_cpu, self._clock())

    def compute_model_metrics(self, paced: bool = False) -> dict[str, float]:
        """Evaluate the current model on the recent window and summarise training since the last call.

        Heavier than :meth:`telemetry` (one forward pass over the window): call it at the telemetry rate
        from the thread that trains. Returns (and caches for :meth:`telemetry`) the model part of the metrics
        (:func:`~saml_ros.core.online.telemetry.model_metrics`) and the feasibility diagnosis of the training
        history (:func:`~saml_ros.core.online.telemetry.feasibility_metrics`). The held-out evaluation
        (:meth:`evaluate_heldout`) runs first when ``heldout_period`` has passed since the last.

        ``paced`` (the training loop): while training, each of the two evaluations runs only when the updates since
        its previous run used nine times its cost in CPU time (:data:`EVAL_SHARE`), or after
        :data:`METRICS_MAX_DELAY` s (the held-out one: :data:`HELDOUT_MAX_PERIODS` periods); otherwise the cached
        metrics are returned. So a training process that gets little CPU spends it on updates.
        """
        training = paced and self.trainer is not None
        if training and not self._due("metrics", 0.0, METRICS_MAX_DELAY):
            return dict(self._metrics)
        window = self._recent.arrays()
        period = self.config.heldout_period
        if self.trainer is not None and self._clock() - self._heldout_at >= period and (
                not training or self._due("heldout", period, HELDOUT_MAX_PERIODS * period)):
            cpu = time.thread_time()
            self.evaluate_heldout()
            self._ran("heldout", cpu)
        cpu = time.thread_time()
        with self._lock:
            out = model_metrics(self.model, self.spec, window, self._averages.take(), self.lam, self.updates,
                                self.model_version)
            out.update(feasibility_metrics(self.trainer, self.spec))
        if self.heldout_report is not None:
            out.update(self.heldout_report.metrics(0))
        self._metrics = out
        if training:
            self._ran("metrics", cpu)
        return dict(out)

    def status(self) -> dict[str, float]:
        """The last :meth:`compute_model_metrics` plus live buffer size, update count, model version,
        training flag and checkpoint counters (what a training process reports to its node)."""
        out = dict(self._metrics)
        budget = self.update_budget()
        out.update(
            buffer_size=float(len(self.buffer)),
            heldout_buffer=float(len(self.heldout)),
            update_budget=math.nan if budget is None else float(budget),
            renormalizations=float(self.renormalizations),
            updates=float(self.updates),
            model_version=float(self.model_version),
            training=1.0 if self.training else 0.0,
            checkpoints_written=float(self.checkpoints_written),
            checkpoints_skipped=float(self.checkpoints_skipped),
            checkpoints_unhealthy=float(self.checkpoints_unhealthy),
            unsaved_updates=float(self.unsaved_updates),
            **self.writes.values(),
        )
        tr = self.trainer
        if tr is not None:
            out.update({k: float(v) for k, v in tr.health.counters().items()})
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

    @property
    def unsaved_updates(self) -> int:
        """Updates not yet in a checkpoint (all of them before the first one)."""
        return 0 if self.trainer is None else self.updates - (self._saved_updates or 0)

    def checkpoint_due(self, period_s: float) -> bool:
        """True when ``period_s`` seconds passed since the last save (or start) and there is something new, and,
        after a failed write, the back-off allows the next attempt (:class:`~saml_ros.core.online.storage.WriteBackoff`:
        1, 2, 4, ... periods after the failure)."""
        now = self._clock()
        return self.dirty and now - self._saved_at >= period_s and self.writes.may_write(period_s, now)

    def save_checkpoint(self, extra: Mapping[str, Any] | None = None) -> tuple[Path, int] | None:
        """Write the next checkpoint into the store (``None`` if no store or no trainer yet, or if the model is not
        healthy: a non-finite weight is never written; counted in ``checkpoints_unhealthy`` and logged).

        The checkpoint holds the model's and f_hat's errors on the held-out stretches, with the training values and
        verdicts (``meta["heldout"]``, :meth:`evaluate_heldout` of the weights written), the training health
        (``meta["health"]``) and the evidence of the data
        (:class:`~saml_ros.core.model.evidence.DataEvidence` of the replay buffer, its residual maximum merged with
        that of every earlier checkpoint of this process, and a probe set drawn from the buffer).

        A write that fails with an ``OSError`` (a full or read-only disk) is recorded in :attr:`writes` (which
        makes :meth:`checkpoint_due` back off) and raised; nothing already written changes (``latest`` keeps naming
        the last good checkpoint). The first good write after failures is logged.

        Raises:
            OSError: the run directory is not writable (the caller logs it; :meth:`checkpoint_due` says when to
                try again).
        """
        if self.store is None or self.trainer is None:
            return None
        t0 = time.perf_counter()
        try:
            return self._save(extra)
        finally:
            self.writes.spent(time.perf_counter() - t0)

    def _save(self, extra: Mapping[str, Any] | None) -> tuple[Path, int] | None:
        assert self.store is not None and self.trainer is not None
        with self._lock:
            rows = self.buffer.arrays()
            fresh = DataEvidence.from_data(self.system, rows.x, rows.u, rows.y, np.random.default_rng([0, self.updates]))
            evidence = fresh.merged(self._evidence, self.buffer.total_added) if fresh is not None else self._evidence
            counts = self.counts()
            info = {
                "paired": counts.get("paired", 0),
                "sources": [p.name for p in self.sources],
                "min_transitions": self.config.min_transitions,
                "buffer_size": len(self.buffer),
                **dict(extra or {}),
            }
            bound = self.residual_bound()
            if bound is not None:
                info[RESIDUAL_BOUND_KEY] = bound.tolist()
            report = self.evaluate_heldout()  # of exactly the weights written (the normalisation refit first)
            metrics = {k: v for k, v in self._metrics.items() if isinstance(v, float)}
            extra_meta: dict[str, Any] = {"learner": info}
            if report is not None:
                metrics.update(report.metrics(0))
                extra_meta[HELDOUT_KEY] = report.to_meta()
            if report is not None:
                info["published"] = self.published
            raw = None
            if self.published == "average" and self.average is not None:  # the weights the held-out data chose
                raw = {k: v.clone() for k, v in self.model.state_dict().items()}
                self.model.load_state_dict(self.average.state_dict())
            try:
                path, version = save_checkpoint(self.store, self.trainer, metrics, extra_meta, evidence)
            except UnhealthyModel as exc:
                self.checkpoints_unhealthy += 1
                self._saved_at = self._clock()  # retry at the next period, not at once
                log.error("checkpoint not written: %s", exc)
                return None
            except OSError as exc:
                self.writes.failed(exc, str(self.store.run_dir))
                raise
            finally:
                if raw is not None:  # training goes on from the trainer's own weights
                    self.model.load_state_dict(raw)
            ended, outage = self.writes.succeeded()
            if ended:
                log.warning("checkpoint version %d written to %s: writing works again after %d failed write(s), "
                            "%.1f s without a good checkpoint", version, path, ended, outage)
            self._evidence = evidence
            self.model_version = version
            self._saved_updates = self.trainer.steps
            self._saved_at = self._clock()
            self.checkpoints_written += 1
            return path, version

    def residual_bound(self, margin: float = RESIDUAL_MARGIN, floor: float = RESIDUAL_FLOOR) -> np.ndarray | None:
        """Per target field, ``margin`` times the largest ``|y - f_hat(x, u)|`` in the buffer (at least ``floor``):
        how large the residual ever was in the data, which the MPC's guard may clip phi to (``guard.bound_residual``,
        :mod:`saml_ros.core.mpc.guard`). ``(n_y,)``; None for a full model or an empty buffer."""
        if self.config.kind != "residual" or len(self.buffer) == 0:
            return None
        rows = self.buffer.arrays()
        resid = np.abs(rows.y - self.system.base_step_np(rows.x, rows.u))
        return np.maximum(margin * resid.max(0), floor)

    def _resume(self, store: CheckpointStore) -> None:
        """Adopt the newest valid checkpoint of ``store`` (see :func:`~saml_ros.core.online.resume.resume_newest`)."""
        cfg = self.config.train
        found, n_skipped = resume_newest(store, self.system, self.spec, self.model.architecture(), cfg)
        self.checkpoints_skipped += n_skipped
        if found is None:
            return
        trainer, path, version = found.trainer, found.path, found.version
        trainer.health = TrainingHealth(self.config.health)
        self._evidence = found.evidence
        self.model = trainer.model
        self.model.train()
        self.trainer = trainer
        self.model_version = version
        self._saved_updates = trainer.steps
        self._rng = np.random.default_rng([cfg.seed, version])  # a fresh minibatch sequence per resume
        self.resumed = ResumeInfo(path, version, trainer.steps, self.lam.tolist(), list(found.skipped))
        for p, why in found.skipped:
            log.warning("resume: skipped %s: %s", p, why)
        log.info("resume: loaded %s (version %d, %d updates, lambda %s)", path, version, trainer.steps,
                 self.lam.tolist())


def heldout_score(report: HeldoutReport) -> tuple[float, float]:
    """How a model did on the held-out stretches, smaller is better: ``(violation, objective)``, compared in that
    order. ``violation`` sums over constraints and members ``max(0, heldout - eps) / eps`` (a constraint without
    held-out samples in its region counts 0); ``objective`` is the members' mean held-out objective."""
    viol = 0.0
    for t in report.constraints:
        eps = t.eps or 0.0
        for est in t.model:
            if est.n and math.isfinite(est.mean) and eps > 0:
                viol += max(0.0, est.mean - eps) / eps
    objs = [e.mean for e in report.objective.model if e.n and math.isfinite(e.mean)]
    return viol, (sum(objs) / len(objs) if objs else math.inf)


def _copy_model(model: DynamicsModel) -> DynamicsModel:
    """A separate model with ``model``'s architecture, weights and normalisation (no gradients)."""
    out = DynamicsModel(model.system, model.hidden, model.kind, n_models=model.n_models, inputs=model.inputs)
    out.to(model.in_mean.dtype)
    out.load_state_dict(model.state_dict())
    out.requires_grad_(False)
    return out
