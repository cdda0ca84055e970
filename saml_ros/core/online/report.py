"""What the learner node reports on ``/diagnostics`` and in its log, from the training process's counters
(ROS-free).

:func:`learner_diagnostics` turns the totals and per-source counts of the pairing, the learner's status, the
training process's own counters and the node's per-channel reception counts into the diagnostic values, level
(0 OK, 1 WARN, 2 ERROR as ``diagnostic_msgs``) and one-line message. The feasibility verdict of each constraint
(the status' ``verdict/<k>``: met, not converged, likely infeasible; docs/training.md) sets the level too: OK,
WARN, ERROR. The log lines of the lifecycle steps: :func:`configured_message`,
:func:`paused_message` and :func:`stopped_message`.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from msg_schemas.telemetry import ERROR, OK, REJECT_REASONS, TRAINING_SKIP_REASONS, WARN
from saml_ros.core.data.resampling import COUNTERS as RESAMPLE_COUNTERS

#: the training-health values of the learner's status reported on /diagnostics
HEALTH_KEYS: tuple[str, ...] = (
    "train_health/skipped", *(f"train_health/skipped/{r}" for r in TRAINING_SKIP_REASONS), "train_health/restores",
    "train_health/unhealthy_streak", "checkpoints_unhealthy",
)

if TYPE_CHECKING:
    from saml_ros.core.online import ReadyInfo, TrainingProcess
    from saml_ros.core.online.config import LearnerConfig
    from saml_ros.core.online.recent_counts import RecentCounts
    from saml_ros.core.spec import ProblemSpec

#: ``(path of a checkpoint just written or None, model version, updates)``, as the training process reports a
#: pause or a stop
Saved = tuple["str | None", int, int]

#: per channel: namespace, kind (state, applied_cmd, target), messages received, matched publishers
ChannelCount = tuple[str, str, int, int]
#: the ``optimization/<k>`` value of each ``verdict/<k>`` code (what ``diagnosis.VERDICT_CODES`` numbers): the
#: training history's convergence
VERDICT_NAMES: dict[int, str] = {0: "met", 1: "not converged", 2: "likely infeasible"}
#: the ``feasibility/<k>`` value of each ``heldout_verdict/<k>`` number (``telemetry.VERDICT_NUMBERS``): the verdict
#: read on the held-out stretches
HELDOUT_NAMES: dict[int, str] = {0: "met", 1: "unconfirmed", 2: "met on training data only", 3: "not met",
                                 4: "no held-out data"}


def _fmt(v: float, spec: str = ".4g") -> str:
    return f"{v:{spec}}" if math.isfinite(v) else "nan"


def feasibility_report(status: Mapping[str, float], constraints: Sequence[tuple[str, float]]) -> tuple[
        int, list[str], dict[str, Any]]:
    """``(level, message parts, values)`` of the constraints' verdicts in ``status``; ``constraints`` are ``(name,
    eps)``.

    ``feasibility/<k>`` is the verdict read on the **held-out stretches** (``heldout_verdict/<k>``, with
    ``heldout/<k>``, ``heldout_se/<k>``, ``heldout_n/<k>``, ``heldout_base/<k>``, ``training_lhs/<k>``): met
    (OK: the upper end of the 95 % interval is at most eps), unconfirmed, met on training data only, no held-out data
    (WARN), not met (ERROR once training has converged or looks infeasible, WARN while it is not converged), pending
    before training. ``optimization/<k>`` is the training history's diagnosis (``verdict/<k>``, ``lhs_min/<k>``,
    ``lambda_rising/<k>``, ``reachable/<k>``): likely infeasible is ERROR, not converged WARN."""
    level, parts = OK, []
    values: dict[str, Any] = {}
    for name, eps in constraints:
        code = status.get(f"verdict/{name}", math.nan)
        history = VERDICT_NAMES.get(int(code), "pending") if math.isfinite(code) else "pending"
        values[f"optimization/{name}"] = history
        for key in ("lhs_min", "reachable"):
            values[f"{key}/{name}"] = _fmt(status.get(f"{key}/{name}", math.nan), ".6g")
        rising = status.get(f"lambda_rising/{name}", math.nan)
        values[f"lambda_rising/{name}"] = int(rising) if math.isfinite(rising) else -1
        if history in ("not converged", "likely infeasible"):
            level = max(level, WARN if history == "not converged" else ERROR)
            reach = status.get(f"reachable/{name}", math.nan)
            parts.append(f"constraint '{name}' {history} in training (eps {eps:.4g}, reachable {reach:.4g})")
        hcode = status.get(f"heldout_verdict/{name}", math.nan)
        verdict = HELDOUT_NAMES.get(int(hcode), "pending") if math.isfinite(hcode) else "pending"
        values[f"feasibility/{name}"] = verdict
        mean, se = status.get(f"heldout/{name}", math.nan), status.get(f"heldout_se/{name}", math.nan)
        n_in = status.get(f"heldout_n/{name}", 0.0)
        base, train = status.get(f"heldout_base/{name}", math.nan), status.get(f"training_lhs/{name}", math.nan)
        values[f"heldout/{name}"] = _fmt(mean, ".6g")
        values[f"heldout_se/{name}"] = _fmt(se, ".3g")
        values[f"heldout_upper/{name}"] = _fmt(status.get(f"heldout_upper/{name}", math.nan), ".6g")
        values[f"heldout_n/{name}"] = int(n_in) if math.isfinite(n_in) else 0
        values[f"heldout_base/{name}"] = _fmt(base, ".6g")
        values[f"training_lhs/{name}"] = _fmt(train, ".6g")
        if verdict in ("met", "pending"):
            continue
        converged = history in ("met", "likely infeasible")
        level = max(level, ERROR if verdict == "not met" and converged else WARN)
        upper = status.get(f"heldout_upper/{name}", math.nan)
        held = (f"held-out {_fmt(mean)} +- {_fmt(se, '.2g')} (n {int(n_in)} in the region, upper bound {_fmt(upper)})"
                if n_in else "no held-out transition in the region yet")
        parts.append(f"constraint '{name}' {verdict} (eps {eps:.4g}; {held}; training {_fmt(train)}; "
                     f"f_hat {_fmt(base)})")
    return level, parts, values


#: the counters whose recent increase sets the level (see :func:`learner_diagnostics`)
LEVEL_COUNTERS: tuple[str, ...] = ("train_errors", "dropped", "rejected", "train_health/skipped",
                                   "checkpoints_unhealthy")


def level_counters(totals: Mapping[str, int], status: Mapping[str, float], process: Mapping[str, int]) -> dict[
        str, float]:
    """The cumulative counters of :data:`LEVEL_COUNTERS` (``rejected``: every reason summed), for a
    :class:`~saml_ros.core.online.recent_counts.RecentCounts` whose increases :func:`learner_diagnostics` takes."""
    return {"train_errors": float(process.get("train_errors", 0)), "dropped": float(process.get("dropped", 0)),
            "rejected": float(sum(totals.get(r, 0) for r in REJECT_REASONS)),
            "train_health/skipped": float(status.get("train_health/skipped", 0)),
            "checkpoints_unhealthy": float(status.get("checkpoints_unhealthy", 0))}


def learner_diagnostics(
    totals: Mapping[str, int],
    status: Mapping[str, float],
    process: Mapping[str, int],
    by_source: Mapping[str, Mapping[str, int]],
    namespaces: Sequence[str],
    channels: Sequence[ChannelCount],
    constraints: Sequence[tuple[str, float]] = (),
    error_after: int = 100,
    recent: Mapping[str, float] | None = None,
    notes: Mapping[str, str] | None = None,
) -> tuple[int, str, dict[str, Any]]:
    """``(level, message, values)`` of the learner's diagnostics.

    The values report counters as counters (they only grow); the level says how the learner is now, from the
    counters' increase over a recent window (``recent``) and the current state. Level: ERROR while checkpoint
    writes fail (``checkpoint_write_failures`` > 0: a full or read-only disk; the message starts with the cause,
    ``checkpoint_write_error``), while ``error_after`` or more consecutive training steps were skipped as unhealthy
    (``train_health/unhealthy_streak``), or when recently the training process failed or restarted
    (``train_errors``), data was dropped between the node and its training process (``dropped``) or a checkpoint
    could not be written because the model was unhealthy (``checkpoints_unhealthy``); WARN when recently a message
    was rejected or a training step skipped; OK otherwise. The feasibility verdict of each constraint sets the level
    too (:func:`feasibility_report`).

    Args:
        totals: pairing counts summed over the sources (``paired`` and each reject reason, ``time_resets``, ...).
        status: the learner's status (``buffer_size``, ``updates``, ``model_version``, the checkpoint-write numbers
            of :meth:`~saml_ros.core.online.storage.WriteBackoff.values`, ...).
        process: the training process's counters: ``train_errors``, ``train_restarts``, ``queued``, ``dropped``
            and, once it is ready, ``train_threads`` and ``train_flush_denormal``.
        by_source: pairing counts per namespace.
        namespaces: the namespaces paired, in order.
        channels: one :data:`ChannelCount` per subscription.
        constraints: ``(name, eps)`` of the spec's constraints (their verdicts: :func:`feasibility_report`).
        error_after: the ``health.error_after`` parameter.
        recent: the increase of each :data:`LEVEL_COUNTERS` counter over the recent window
            (:class:`~saml_ros.core.online.recent_counts.RecentCounts`); ``None``: since the start (the counters themselves).
        notes: the training process's text values (``checkpoint_write_error``).
    """
    values: dict[str, Any] = {"paired": totals.get("paired", 0)}
    for key in ("buffer_size", "updates", "model_version", "training", "checkpoints_written", "checkpoints_skipped",
                "unsaved_updates"):
        values[key] = int(status.get(key, 0))
    values.update(process)
    for reason in REJECT_REASONS:
        values[f"rejected/{reason}"] = totals.get(reason, 0)
    for key in ("time_resets", "reanchors", "expired", "overflow"):
        values[key] = totals.get(key, 0)
    for key in HEALTH_KEYS:
        values[key] = int(status.get(key, 0))
    write_error = (notes or {}).get("checkpoint_write_error", "")
    failing = int(status.get("checkpoint_write_failures", 0))
    values["checkpoint_write_error"] = write_error
    values["checkpoint_write_errors"] = int(status.get("checkpoint_write_errors", 0))
    values["checkpoint_write_failures"] = failing
    values["checkpoint_write_seconds"] = round(float(status.get("checkpoint_write_seconds", 0.0)), 3)
    age = status.get("checkpoint_age_s", math.nan)
    values["checkpoint_age_s"] = round(age, 1) if math.isfinite(age) else "nan"
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
    counts = level_counters(totals, status, process)
    grew = counts if recent is None else recent
    rejected = int(counts["rejected"])
    skipped, streak = values["train_health/skipped"], values["train_health/unhealthy_streak"]
    failed = grew.get("train_errors", 0) > 0 or grew.get("dropped", 0) > 0
    sick = streak >= error_after or grew.get("checkpoints_unhealthy", 0) > 0
    warned = grew.get("rejected", 0) > 0 or grew.get("train_health/skipped", 0) > 0
    level = ERROR if failed or sick or failing else (WARN if warned else OK)
    message = (f"paired {values['paired']}, buffer {values['buffer_size']}, updates {values['updates']}, "
               f"version {values['model_version']}, rejected {rejected}")
    if failing:
        message = f"checkpoint writes failing: {write_error or 'see checkpoint_write_errors'}; {message}"
    f_level, parts, f_values = feasibility_report(status, constraints)
    values.update(f_values)
    if skipped:
        message += f", training steps skipped {skipped}" + (f" ({streak} in a row)" if streak else "")
    if parts:
        message += "; " + "; ".join(parts)
    return max(level, f_level), message, values


def process_counters(trainer: TrainingProcess) -> dict[str, int]:
    """The training process's own counters for :func:`learner_diagnostics` (``process``)."""
    # failed checkpoint writes have their own values (checkpoint_write_*): train_errors are training and process errors
    out = {"train_errors": trainer.errors - trainer.error_counts["checkpoint"], "train_restarts": trainer.restarts,
           "queued": trainer.queued, "dropped": trainer.dropped}
    if trainer.ready is not None:
        out.update(train_threads=trainer.ready.threads, train_flush_denormal=int(trainer.ready.flush_denormal))
    return out


def configured_message(p: LearnerConfig, spec: ProblemSpec, ready: ReadyInfo, run_dir: Path, pid: int | None) -> str:
    """The log line of a finished ``configure``: what is learned, from where, and how the training process runs."""
    r = ready.resumed
    return (f"learner for {p.system!r}" + (f" (system file {p.system_file})" if p.system_file else "")
            + f" on {p.namespaces}: spec '{spec.raw.get('name')}' ({spec.describe()}), "
            f"model {p.model.kind} {ready.hidden}, run_dir {run_dir}, "
            + (f"resumed from version {r['version']} ({r['updates']} updates, lambda {r['lam']})" if r
               else "fresh start")
            + f"; training process pid {pid} ({ready.threads} torch thread(s), subnormals "
            + ("flushed" if ready.flush_denormal else "not flushed")
            + f"); training starts after {p.min_transitions} transitions once active; "
            + (f"held out (never trained on, verdicts read there): the last {p.heldout.fraction * p.heldout.period:g} s "
               f"of every {p.heldout.period:g} s of the stream" if p.heldout.fraction > 0 else
               "no held-out stretches (heldout.fraction 0): no held-out verdict"))


def paused_message(paused: Saved, unsaved: int = 0) -> str:
    """The log line of a ``deactivate`` (``unsaved``: updates not in a checkpoint, the status'
    ``unsaved_updates``)."""
    path, version, updates = paused
    if path is None and unsaved > 0:
        return (f"deactivated: training paused after {updates} updates; their checkpoint could not be written "
                f"({unsaved} updates not saved, checkpoint version {version} stays the latest)")
    written = "written" if path is not None else "is current"
    return f"deactivated: training paused after {updates} updates (checkpoint version {version} {written})"


def stopped_message(final: Saved | None, updates: float, paired: int, min_transitions: int,
                    step: str = "shutdown", unsaved: int = 0) -> tuple[bool, str]:
    """``(is an error, log line)`` of the training process's end in lifecycle ``step`` (``shutdown`` or
    ``cleanup``); ``final`` None: it did not stop in time; ``unsaved``: updates not in a checkpoint after the
    final write (its status' ``unsaved_updates``: the final checkpoint could not be written)."""
    if final is None:
        return True, f"{step}: the training process did not stop in time; it was killed"
    path, version, done = final
    if path is not None:
        return False, f"{step}: final checkpoint version {version} ({done} updates)"
    if unsaved > 0:
        return True, (f"{step}: the final checkpoint could not be written (the cause is logged above): {unsaved} "
                      f"updates are not saved; checkpoint version {version} stays the latest")
    if updates > 0 or version > 0:
        return False, f"{step}: checkpoint version {version} is current ({done} updates)"
    return False, (f"{step}: no checkpoint written, training never started ({paired}/{min_transitions} "
                   "transitions)")


def training_diagnostics(trainer: TrainingProcess, p: LearnerConfig, spec: ProblemSpec,
                         channels: Sequence[ChannelCount], lifecycle: str, invalid_transitions: int,
                         active: bool, recent: RecentCounts | None = None) -> tuple[int, str, dict[str, Any]]:
    """:func:`learner_diagnostics` of a running training process, with the node's lifecycle state
    (``lifecycle``, prefixed to the message while not ``active``) and its refused transitions; ``recent`` (updated
    here, once per report) sets the level from the counters' increase over its window."""
    totals, process = trainer.counts(), process_counters(trainer)
    grew = None if recent is None else recent.update(level_counters(totals, trainer.status, process))
    level, message, values = learner_diagnostics(
        totals, trainer.status, process, trainer.source_counts, p.namespaces, channels,
        [(t.name, t.eps) for t in spec.constraints], p.health.error_after, grew, trainer.notes)
    values["lifecycle"] = lifecycle
    values["invalid_transitions"] = invalid_transitions
    return level, (message if active else f"{lifecycle}: {message}"), values
