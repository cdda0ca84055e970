"""What the learner node reports on ``/diagnostics``, from the training process's counters (ROS-free).

:func:`learner_diagnostics` turns the totals and per-source counts of the pairing, the learner's status, the
training process's own counters and the node's per-channel reception counts into the diagnostic values, level
(0 OK, 1 WARN, 2 ERROR as ``diagnostic_msgs``) and one-line message.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

from msg_schemas.telemetry import ERROR, OK, REJECT_REASONS, WARN
from saml_ros.core.resampling import COUNTERS as RESAMPLE_COUNTERS

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
    for key in RESAMPLE_COUNTERS:  # a robot's own topics (resampled): intervals, gaps, jitter, unstamped, ...
        if key in totals and key not in values and not key.startswith("received/"):
            values[key] = totals[key]
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
