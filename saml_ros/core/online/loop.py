"""The training loop of an online learner (:func:`run_loop`): pacing the updates (:class:`LoopConfig`), reporting
status at the telemetry rate, checkpointing every ``checkpoint_period`` and on stop, with the whole inbox handled
before every chunk of updates (ingest goes first). It runs in the training process
(:mod:`~saml_ros.core.online.process`; the messages it takes and sends are :mod:`~saml_ros.core.online.messages`),
or in any thread owning the learner."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from saml_ros.core.online.ingest import RawIngest
from saml_ros.core.online.messages import (
    Batch,
    Checkpointed,
    ErrorReport,
    FromTrainer,
    Pause,
    Paused,
    RawMessages,
    Resume,
    SetLoop,
    Status,
    Stop,
    Stopped,
    ToTrainer,
)

if TYPE_CHECKING:
    from saml_ros.core.online.learner import OnlineLearner

#: ``send(message)``: one message to the parent (see :func:`run_loop` for the messages)
Send = Callable[[FromTrainer], None]


@dataclass(frozen=True)
class LoopConfig:
    """How a training loop paces itself.

    Attributes:
        updates_per_second: primal-dual updates per wall-clock second; 0 = as fast as possible.
        telemetry_rate: model metrics computed (and reported) per second, Hz.
        checkpoint_period: wall-clock seconds between checkpoints (only when there are new updates).
        chunk: most updates between two looks at the inbox and the clocks.
        chunk_seconds: wall-clock seconds of updates between two looks (the updates per chunk follow the measured
            time per update, at most ``chunk``): long enough that the per-call cost of drawing and preparing the
            minibatches is shared by many updates (:mod:`~saml_ros.core.online.updates`), short enough that
            ingest, pause and stop wait little.
    """

    updates_per_second: float = 0.0
    telemetry_rate: float = 5.0
    checkpoint_period: float = 10.0
    chunk: int = 500
    chunk_seconds: float = 0.02

    def __post_init__(self) -> None:
        if (self.updates_per_second < 0 or self.telemetry_rate <= 0 or self.checkpoint_period <= 0 or self.chunk < 1
                or self.chunk_seconds <= 0):
            raise ValueError(f"invalid loop configuration {self}")



def run_loop(learner: OnlineLearner, loop: LoopConfig, conn: Any, send: Send, raw: RawIngest | None = None,
             stop_requested: Callable[[], bool] | None = None, paused: bool = False) -> None:
    """The training loop of a training process (or any thread owning ``learner``).

    ``conn`` is the inbox (``poll(timeout)`` / ``recv()``) carrying :data:`~saml_ros.core.online.messages.ToTrainer`
    messages: :class:`Batch` (paired transitions), :class:`RawMessages` (messages for ``raw``), :class:`Pause`,
    :class:`Resume`, :class:`SetLoop` (pace by its loop from now on) and :class:`Stop`.
    The whole inbox is handled before every chunk of updates, so ingest goes first (a backlog longer than one
    telemetry period is handled a period at a time, with a status report in between). ``send`` reports
    :class:`Status` at ``loop.telemetry_rate`` (its ``notes``: text values, :func:`status_notes`),
    :class:`Checkpointed` after each save, :class:`ErrorReport` and, on stop, :class:`Stopped` after a final
    checkpoint (when there are updates not yet saved). A checkpoint write that fails is reported as
    ``ErrorReport("checkpoint", message)`` and tried again after a back-off of 1, 2, 4, ... checkpoint periods
    (:mod:`~saml_ros.core.online.storage`); training goes on meanwhile. Returns after a stop.
    ``stop_requested()`` True (the training process got
    :data:`~saml_ros.core.online.process.STOP_SIGNAL`) stops at once, as :class:`Stop` would, without handling
    what is still in the inbox: data not yet in the buffer cannot change the final checkpoint, and a backlog of
    it must not hold the shutdown past a launcher's grace period.

    Paused (from the start when ``paused``, or after :class:`Pause`: a managed learner that was deactivated) the
    loop still takes data into the buffer and reports its status, but makes no updates, computes no model
    metrics and writes no checkpoints;
    One function on purpose (longer than 80 lines): one event loop whose local state (pacing, paused, next
    report) every message kind and the training chunk share.
    :class:`Pause` first writes a checkpoint when there are unsaved updates and answers :class:`Paused`;
    :class:`Resume` goes back to training (the pacing restarts from then).
    """
    requested = stop_requested or (lambda: False)

    def report(metrics: bool = True) -> None:
        if metrics:
            learner.compute_model_metrics(paced=True)  # evaluations yield to the updates on a busy CPU
        if raw is not None:
            raw.check_orphans()
        send(Status(learner.status(), {p.name: dict(p.counts) for p in learner.sources}, status_notes(learner, loop)))

    metrics_period = 1.0 / loop.telemetry_rate
    next_metrics = 0.0
    paced_from: float | None = None
    paced_done = 0
    per_update = 0.0  # measured seconds per update (a running mean); 0 until the first chunk
    while True:
        # the inbox first, but at most one telemetry period at a time: a backlog must not silence the reports
        drain_until = time.monotonic() + metrics_period
        while True:
            msg: ToTrainer | None = Stop() if requested() else (
                conn.recv() if conn.poll() and time.monotonic() < drain_until else None)
            if msg is None:
                break
            match msg:
                case RawMessages(items):
                    if raw is not None:
                        raw.feed(items)
                case Batch(x, u, y, stamp_s, source):
                    learner.add_batch(x, u, y, stamp_s, source)
                case Pause():
                    saved = save_and_announce(learner, send) if learner.dirty and not paused else None
                    report()
                    paused, paced_from = True, None
                    send(Paused(str(saved[0]) if saved else None, learner.model_version, learner.updates))
                case Resume():
                    paused, paced_from = False, None
                case SetLoop(new_loop):  # new pacing (a parameter changed on the running node)
                    loop, paced_from = new_loop, None
                    metrics_period, next_metrics = 1.0 / loop.telemetry_rate, 0.0
                case Stop():
                    saved = save_and_announce(learner, send) if learner.dirty else None
                    report()
                    send(Stopped(str(saved[0]) if saved else None, learner.model_version, learner.updates))
                    return
        now = time.monotonic()
        if now >= next_metrics:
            report(metrics=not paused)  # paused: the counters only, the model has not changed
            next_metrics = now + metrics_period
        if paused:
            conn.poll(0.05)  # an interruptible sleep: wakes up when a message arrives
            continue
        if learner.checkpoint_due(loop.checkpoint_period):  # after a failed write: backed off (learner.writes)
            save_and_announce(learner, send, loop.checkpoint_period)
        if conn.poll():
            continue  # still a backlog: ingest before training
        if not learner.training:
            paced_from = None
            conn.poll(0.05)  # an interruptible sleep: wakes up when data arrives
            continue
        n = max(1, min(loop.chunk, int(loop.chunk_seconds / per_update))) if per_update > 0 else 1
        if loop.updates_per_second > 0:
            if paced_from is None:
                paced_from, paced_done = now, 0
            due = int((now - paced_from) * loop.updates_per_second) - paced_done
            if due <= 0:
                conn.poll(min(metrics_period, (paced_done + 1) / loop.updates_per_second - (now - paced_from)))
                continue
            n = min(due, n)
            paced_done += n
        try:
            started = learner.trainer is not None
            t0 = time.monotonic()
            done = learner.update(n)
            if done and started:
                # the call that starts training (normalisation fit, trainer and kernel set-up) is not an update's
                # cost: counted, it kept the chunks at one update for dozens of chunks
                # and a chunk faster than the mean is believed at once: one slow update (the first optimizer step's
                # imports, a preempted chunk) would otherwise hold the chunks small for ~20 chunks of the mean
                took = (time.monotonic() - t0) / done
                per_update = took if per_update == 0 or took < per_update else 0.8 * per_update + 0.2 * took
            if not done:  # the update budget (updates_per_transition) is spent: wait for data
                conn.poll(0.05)
        except Exception as exc:  # noqa: BLE001 - report, back off, keep going
            send(ErrorReport("training", f"training step failed ({type(exc).__name__}: {exc}); retrying in 1 s"))
            time.sleep(1.0)


def status_notes(learner: OnlineLearner, loop: LoopConfig) -> dict[str, str]:
    """The text values of a status report: ``checkpoint_write_error`` (the OS message, the path, the time since the
    last good checkpoint; ``""`` while writes succeed)."""
    return {"checkpoint_write_error": learner.writes.describe(loop.checkpoint_period)}


def save_and_announce(learner: OnlineLearner, send: Send, period_s: float | None = None) -> tuple[Path, int] | None:
    """Write a checkpoint and send :class:`Checkpointed`; a write error is sent as ``ErrorReport("checkpoint",
    message)`` (and ``None`` returned: :meth:`OnlineLearner.checkpoint_due` says when to try again,
    ``period_s`` the checkpoint period the message counts the back-off in)."""
    try:
        saved = learner.save_checkpoint()
    except OSError as exc:
        run_dir = learner.store.run_dir if learner.store else "?"
        retry = (f"; next attempt in {learner.writes.delay(period_s):.3g} s" if period_s is not None else "")
        kept = (f"the last good checkpoint, version {learner.model_version}, stays the latest" if learner.model_version
                else "no checkpoint written yet")
        send(ErrorReport("checkpoint", f"cannot write a checkpoint into {run_dir}: {exc} ({learner.writes.failures} "
                                       f"failed write(s) in a row, {learner.unsaved_updates} updates not yet saved; "
                                       f"{kept}){retry}"))
        return None
    if saved is not None:
        send(Checkpointed(str(saved[0]), saved[1]))
    return saved
