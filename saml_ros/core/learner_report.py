"""What the learner node reports on ``/diagnostics`` and in its log, from the training process's counters
(ROS-free).

:func:`learner_diagnostics` turns the totals and per-source counts of the pairing, the learner's status, the
training process's own counters and the node's per-channel reception counts into the diagnostic values, level
(0 OK, 1 WARN, 2 ERROR as ``diagnostic_msgs``) and one-line message; :func:`configured_message`,
:func:`paused_message` and :func:`stopped_message` are the log lines of the lifecycle steps.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from msg_schemas.telemetry import ERROR, OK, REJECT_REASONS, WARN

if TYPE_CHECKING:
    from saml_ros.core.learner_config import LearnerConfig
    from saml_ros.core.online import ReadyInfo, TrainingProcess
    from saml_ros.core.spec import ProblemSpec

#: ``(path of a checkpoint just written or None, model version, updates)``, as the training process reports a
#: pause or a stop
Saved = tuple["str | None", int, int]

#: per channel: namespace, kind (state, applied_cmd, target), messages received, matched publishers
ChannelCount = tuple[str, str, int, int]


def learner_diagnostics(
    totals: Mapping[str, int],
    status: Mapping[str, float],
    process: Mapping[str, int],
    by_source: Mapping[str, Mapping[str, int]],
    namespaces: Sequence[str],
    channels: Sequence[ChannelCount],
) -> tuple[int, str, dict[str, Any]]:
    """``(level, message, values)`` of the learner's diagnostics.

    Args:
        totals: pairing counts summed over the sources (``paired`` and each reject reason, ``time_resets``, ...).
        status: the learner's status (``buffer_size``, ``updates``, ``model_version``, ...).
        process: the training process's counters: ``train_errors``, ``train_restarts``, ``queued``, ``dropped``
            and, once it is ready, ``train_threads`` and ``train_flush_denormal``.
        by_source: pairing counts per namespace.
        namespaces: the namespaces paired, in order.
        channels: one :data:`ChannelCount` per subscription.
    """
    values: dict[str, Any] = {"paired": totals.get("paired", 0)}
    for key in ("buffer_size", "updates", "model_version", "training", "checkpoints_written", "checkpoints_skipped"):
        values[key] = int(status.get(key, 0))
    values.update(process)
    for reason in REJECT_REASONS:
        values[f"rejected/{reason}"] = totals.get(reason, 0)
    for key in ("time_resets", "reanchors", "expired", "overflow"):
        values[key] = totals.get(key, 0)
    for ns in namespaces:
        c = by_source.get(ns, {})
        values[f"{ns}/paired"] = c.get("paired", 0)
        for reason in REJECT_REASONS:
            values[f"{ns}/rejected/{reason}"] = c.get(reason, 0)
    for ns, kind, received, publishers in channels:
        values[f"{ns}/received/{kind}"] = received
        values[f"{ns}/publishers/{kind}"] = publishers
    rejected = sum(totals.get(r, 0) for r in REJECT_REASONS)
    failed = process.get("train_errors", 0) or process.get("dropped", 0)
    level = ERROR if failed else (WARN if rejected else OK)
    message = (f"paired {values['paired']}, buffer {values['buffer_size']}, updates {values['updates']}, "
               f"version {values['model_version']}, rejected {rejected}")
    return level, message, values


def process_counters(trainer: TrainingProcess) -> dict[str, int]:
    """The training process's own counters for :func:`learner_diagnostics` (``process``)."""
    out = {"train_errors": trainer.errors, "train_restarts": trainer.restarts, "queued": trainer.queued,
           "dropped": trainer.dropped}
    if trainer.ready is not None:
        out.update(train_threads=trainer.ready.threads, train_flush_denormal=int(trainer.ready.flush_denormal))
    return out


def configured_message(p: LearnerConfig, spec: ProblemSpec, ready: ReadyInfo, run_dir: Path, pid: int | None) -> str:
    """The log line of a finished ``configure``: what is learned, from where, and how the training process runs."""
    r = ready.resumed
    return (f"learner for {p.system!r} on {p.namespaces}: spec '{spec.raw.get('name')}' ({spec.describe()}), "
            f"model {p.model_kind} {ready.hidden}, run_dir {run_dir}, "
            + (f"resumed from version {r['version']} ({r['updates']} updates, lambda {r['lam']})" if r
               else "fresh start")
            + f"; training process pid {pid} ({ready.threads} torch thread(s), subnormals "
            + ("flushed" if ready.flush_denormal else "not flushed")
            + f"); training starts after {p.min_transitions} transitions once active")


def paused_message(paused: Saved) -> str:
    """The log line of a ``deactivate``."""
    path, version, updates = paused
    written = "written" if path is not None else "is current"
    return f"deactivated: training paused after {updates} updates (checkpoint version {version} {written})"


def stopped_message(final: Saved | None, updates: float, paired: int, min_transitions: int,
                    step: str = "shutdown") -> tuple[bool, str]:
    """``(is an error, log line)`` of the training process's end in lifecycle ``step`` (``shutdown`` or
    ``cleanup``); ``final`` None: it did not stop in time."""
    if final is None:
        return True, f"{step}: the training process did not stop in time; it was killed"
    path, version, done = final
    if path is not None:
        return False, f"{step}: final checkpoint version {version} ({done} updates)"
    if updates > 0 or version > 0:
        return False, f"{step}: checkpoint version {version} is current ({done} updates)"
    return False, (f"{step}: no checkpoint written, training never started ({paired}/{min_transitions} "
                   "transitions)")
