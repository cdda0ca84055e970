"""Telemetry shared by every system namespace: model error, MPC status, checkpoints, diagnostics, clock.

Named scalar telemetry (``learner/model_error``, ``mpc/status``) uses ``sensor_msgs/JointState`` as a
*stamped named vector*: ``name[i]`` is the metric name and ``position[i]`` its value (``velocity`` and
``effort`` empty). Both PlotJuggler (series ``<topic>/<name>/position``) and Foxglove (``<topic>.position[i]``)
plot it with no plugin, unlike ``diagnostic_msgs`` whose values are strings. NaN is a legal telemetry value
("no data yet", e.g. the error inside a region no sample has visited) and is not rejected.

``learner/checkpoint`` is a ``std_msgs/String`` holding a small JSON object (see :class:`CheckpointInfo`),
published reliable + transient-local with depth 1 so a late MPC still receives the newest checkpoint.
``/diagnostics`` (``diagnostic_msgs/DiagnosticArray``, the ROS standard) carries each node's rejection
counters as key/value strings, one ``DiagnosticStatus`` per node named after the node.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from msg_schemas.base import (
    CHECKPOINT_QOS,
    CLOCK_QOS,
    RCLPY,
    TELEMETRY_QOS,
    FieldDoc,
    MessageFactory,
    SchemaError,
    TopicSpec,
    make_header,
    read_stamp,
    split_stamp,
)
from msg_schemas.codecs import JOINT_STATE

STRING = "std_msgs/msg/String"
DIAGNOSTIC_ARRAY = "diagnostic_msgs/msg/DiagnosticArray"
CLOCK = "rosgraph_msgs/msg/Clock"

MODEL_ERROR_TOPIC = "learner/model_error"
CHECKPOINT_TOPIC = "learner/checkpoint"
MPC_STATUS_TOPIC = "mpc/status"
DIAGNOSTICS_TOPIC = "/diagnostics"
CLOCK_TOPIC = "/clock"

#: rejection reasons counted by nodes as ``rejected/<reason>``: the :class:`~msg_schemas.base.SchemaError`
#: reasons, then the learner's pairing reasons, then ``bounds`` (a value outside the system's plausible range,
#: ``saml_ros.core.data.plausibility``)
REJECT_REASONS: tuple[str, ...] = (
    "shape", "names", "nan", "quaternion", "stamp", "format",
    "duplicate", "out_of_order", "late", "outlier", "unpaired", "bounds",
)  # fmt: skip
#: why the MPC refused a checkpoint (``checkpoints_refused/<reason>`` on /diagnostics): unreadable or foreign files
#: (``saml_ros.core.mpc.follower``), then a model that fails the acceptance checks (``saml_ros.core.mpc.acceptance``:
#: non-finite weights, predictions outside the plausible range, residuals beyond what the training data showed, a
#: held-out error worse than f_hat's on the same held-out data)
CHECKPOINT_REFUSAL_REASONS: tuple[str, ...] = (
    "incompatible", "corrupt", "missing", "error", "non_finite", "implausible", "residual", "heldout",
)  # fmt: skip
#: why the MPC answered a state with the system's safe command (``safe_commands/<reason>``): the solver raised,
#: returned a non-finite result, planned through states outside the plausible range (``implausible``: the model
#: predicts nonsense there), the state itself was outside the plausible range (``bounds``), or (only with
#: ``safe_on_infeasible``) the plan violated a constraint, or the state was older than ``state_timeout`` (``stale``:
#: also sent while no state arrives for that long)
SAFE_COMMAND_REASONS: tuple[str, ...] = ("solver_error", "non_finite", "implausible", "bounds", "infeasible", "stale")
#: why a training step was skipped and the last healthy state kept (``train_health/skipped/<reason>``): a non-finite
#: or exploding minibatch loss, gradient, or updated weights (``saml_ros.core.training.health``)
TRAINING_SKIP_REASONS: tuple[str, ...] = ("loss", "gradient", "weights")


# ----------------------------------------------------------------------------- stamped named vectors
def named_vector_to_msg(
    values: Mapping[str, float], stamp_ns: int, *, factory: MessageFactory = RCLPY, topic: str = "", frame_id: str = ""
) -> Any:
    """``{name: value}`` -> ``sensor_msgs/JointState`` with ``name`` = keys and ``position`` = values (float64)."""
    names = list(values)
    if any(not isinstance(n, str) or not n for n in names):
        raise SchemaError(topic, "name", "names", f"metric names must be non-empty strings, got {names}")
    return factory.make(
        JOINT_STATE,
        header=make_header(factory, stamp_ns, frame_id, topic),
        name=names,
        position=np.array([float(values[n]) for n in names], dtype=np.float64),
        velocity=np.zeros(0),
        effort=np.zeros(0),
    )


def named_vector_from_msg(msg: Any, topic: str = "") -> tuple[dict[str, float], int]:
    """``sensor_msgs/JointState`` -> ``({name: position}, stamp_ns)``; non-finite values are kept."""
    stamp = read_stamp(msg.header.stamp, topic)
    names = list(msg.name)
    values = np.asarray(msg.position, dtype=np.float64)
    if values.shape[0] != len(names):
        raise SchemaError(topic, "position", "shape", f"{len(names)} names but {values.shape[0]} values")
    if len(set(names)) != len(names) or any(not n for n in names):
        raise SchemaError(topic, "name", "names", f"metric names must be unique and non-empty, got {names}")
    return dict(zip(names, values.tolist(), strict=True)), stamp


# --------------------------------------------------------------------------------- learner/model_error
#: metrics reported once per model
MODEL_ERROR_GLOBAL: tuple[tuple[str, str, str], ...] = (
    ("objective", "loss", "objective estimate on the newest minibatch (the spec's loss)"),
    ("lagrangian", "loss", "objective + sum_k lambda_k * constraint_k"),
    ("buffer_size", "count", "transitions in the replay buffer"),
    ("updates", "count", "primal-dual updates so far"),
    ("model_version", "count", "version of the newest checkpoint written"),
)
#: metrics reported per constraint ``<k>`` as ``<prefix>/<k>``
MODEL_ERROR_PER_CONSTRAINT: tuple[tuple[str, str, str], ...] = (
    ("constraint", "loss", "constraint estimate g_k (<= 0 when satisfied)"),
    ("lambda", "1", "dual variable lambda_k"),
    ("error_in", "loss", "live one-step error of the current model inside region k (NaN: no sample yet)"),
    ("error_out", "loss", "live one-step error outside region k (NaN: no sample yet)"),
)


def model_error_names(constraints: Sequence[str], reject_reasons: Sequence[str] = REJECT_REASONS) -> list[str]:
    """The canonical ``learner/model_error`` names for a spec with the given constraint names, in order."""
    names = [n for n, _, _ in MODEL_ERROR_GLOBAL]
    names += [f"{prefix}/{c}" for c in constraints for prefix, _, _ in MODEL_ERROR_PER_CONSTRAINT]
    names += [f"rejected/{r}" for r in reject_reasons]
    return names


def _model_error_docs() -> tuple[FieldDoc, ...]:
    docs = [FieldDoc(n, u, "position[i]", f"/{n}/position", d) for n, u, d in MODEL_ERROR_GLOBAL]
    docs += [FieldDoc(f"{p}/<k>", u, "position[i]", f"/{p}/<k>/position", d) for p, u, d in MODEL_ERROR_PER_CONSTRAINT]
    docs.append(
        FieldDoc("rejected/<reason>", "count", "position[i]", "/rejected/<reason>/position",
                 "messages dropped, by reason: " + ", ".join(REJECT_REASONS))
    )  # fmt: skip
    return tuple(docs)


def model_error_to_msg(metrics: Mapping[str, float], stamp_ns: int, *, factory: MessageFactory = RCLPY) -> Any:
    """``learner/model_error`` message from ``{metric name: value}`` (see :func:`model_error_names`)."""
    return named_vector_to_msg(metrics, stamp_ns, factory=factory, topic=MODEL_ERROR_TOPIC)


def model_error_from_msg(msg: Any, topic: str = MODEL_ERROR_TOPIC) -> tuple[dict[str, float], int]:
    """``learner/model_error`` message -> ``({metric: value}, stamp_ns)``."""
    return named_vector_from_msg(msg, topic)


# ---------------------------------------------------------------------------------------- mpc/status
MPC_STATUS_FIELDS: tuple[tuple[str, str, str], ...] = (
    ("solve_time_ms", "ms", "wall-clock time of the last solve"),
    ("cost", "1", "optimal cost of the last solve"),
    ("iterations", "count", "solver iterations of the last solve"),
    ("model_version", "count", "checkpoint version of the model in use (0 = base model only)"),
    ("deadline_misses", "count", "solves that finished after their deadline, so far"),
)
#: values the MPC node appends to every ``mpc/status`` message after the standard ones (documented; optional for
#: other publishers)
MPC_STATUS_EXTRA: tuple[tuple[str, str, str], ...] = (
    ("success", "1", "1 when the last solve met every constraint, else 0"),
    ("safe", "1", "1 when the last answer was the system's safe command (failed or non-finite solve, implausible "
                  "state), else 0"),
    ("safe_commands", "count", "answers that were the safe command, so far (reasons on /diagnostics: "
                               "safe_commands/<reason>)"),
    ("step_ms", "ms", "the whole control step (swap + solve + publish)"),
    ("swap_ms", "ms", "the model swap in this step (0 = none)"),
    ("swaps", "count", "models swapped in, so far"),
    ("checkpoints_refused", "count", "checkpoints refused, so far (reasons on /diagnostics)"),
    ("checkpoints_gated", "count", "valid checkpoints held back by gate.*, so far"),
    ("solves", "count", "control steps, so far"),
    # only when a guard.* remedy is on
    ("guard_fallbacks", "count", "steps planned with f_hat because the ensemble disagreed by more than "
                                 "guard.max_disagreement on the learned plan, so far"),
    ("guard_base_solves", "count", "steps planned with f_hat (fallbacks, after a roll back, before any model)"),
    ("guard_rollbacks", "count", "roll backs by the live monitor (to the previous model, else f_hat), so far"),
    ("guard_clipped_solves", "count", "learned plans flown on which guard.bound_residual clipped phi, so far"),
    ("guard_disagreement", "state units", "ensemble disagreement sigma on the last learned plan checked (NaN: "
                                          "none yet or a single model)"),
    ("monitor_error_model", "squared state units", "live one-step squared error of the model in use, mean over "
                                                   "the monitor's window (NaN: empty, e.g. on f_hat)"),
    ("monitor_error_base", "squared state units", "the same for the base model f_hat on the same transitions"),
    ("live_error_model", "squared state units", "one-step squared error of the model in use on the last live "
                                                "transition (previous state, command sent, this state)"),
    ("live_error_base", "squared state units", "the same for f_hat"),
    ("model_source", "1", "1 = this step was planned with the learned model, 0 = with f_hat"),
)
MPC_STATUS_NAMES: tuple[str, ...] = tuple(n for n, _, _ in MPC_STATUS_FIELDS)


def mpc_status_values(values: Mapping[str, float]) -> dict[str, float]:
    """``values`` in ``mpc/status`` order (:data:`MPC_STATUS_NAMES`, then the extras); every standard name must be
    there (:class:`SchemaError` otherwise)."""
    missing = [n for n in MPC_STATUS_NAMES if n not in values]
    if missing:
        raise SchemaError(MPC_STATUS_TOPIC, "name", "names", f"missing status values {missing}")
    return {n: values[n] for n in MPC_STATUS_NAMES} | {k: v for k, v in values.items() if k not in MPC_STATUS_NAMES}


def mpc_status_to_msg(values: Mapping[str, float], stamp_ns: int, *, factory: MessageFactory = RCLPY) -> Any:
    """``mpc/status`` message; ``values`` must hold every name in :data:`MPC_STATUS_NAMES` (extras allowed). The
    MPC node publishes the same message as CDR bytes (:class:`msg_schemas.cdr.NamedVectorCdr` of
    :func:`mpc_status_values`)."""
    return named_vector_to_msg(mpc_status_values(values), stamp_ns, factory=factory, topic=MPC_STATUS_TOPIC)


def mpc_status_from_msg(msg: Any, topic: str = MPC_STATUS_TOPIC) -> tuple[dict[str, float], int]:
    """``mpc/status`` message -> ``({name: value}, stamp_ns)``; every standard name must be present."""
    values, stamp = named_vector_from_msg(msg, topic)
    missing = [n for n in MPC_STATUS_NAMES if n not in values]
    if missing:
        raise SchemaError(topic, "name", "names", f"missing status values {missing}")
    return values, stamp


# -------------------------------------------------------------------------------- learner/checkpoint
@dataclass(frozen=True)
class CheckpointInfo:
    """The ``learner/checkpoint`` announcement.

    Attributes:
        path: absolute path of the checkpoint file.
        version: checkpoint version (>= 1, increasing).
        schema_hash: ``System.schema_hash()`` of the layouts the model was trained on.
        time: when it was written, seconds (the learner's ROS clock; simulated time under ``use_sim_time``).
    """

    path: str
    version: int
    schema_hash: str
    time: float


_CHECKPOINT_KEYS = {"path": str, "version": int, "schema_hash": str, "time": float}


def checkpoint_to_msg(info: CheckpointInfo, *, factory: MessageFactory = RCLPY) -> Any:
    """``std_msgs/String`` with ``{"path", "version", "schema_hash", "time"}`` as compact JSON."""
    data = {"path": info.path, "version": int(info.version), "schema_hash": info.schema_hash, "time": float(info.time)}
    return factory.make(STRING, data=json.dumps(data, separators=(",", ":")))


def checkpoint_from_msg(msg: Any, topic: str = CHECKPOINT_TOPIC) -> CheckpointInfo:
    """Parse and validate a ``learner/checkpoint`` message; :class:`SchemaError` (reason ``format``) if malformed."""
    try:
        data = json.loads(msg.data)
    except (TypeError, ValueError) as exc:
        raise SchemaError(topic, "data", "format", f"not JSON: {exc}") from None
    if not isinstance(data, dict):
        raise SchemaError(topic, "data", "format", "expected a JSON object")
    for key, kind in _CHECKPOINT_KEYS.items():
        value = data.get(key)
        ok = isinstance(value, int | float) and not isinstance(value, bool) if kind is float else type(value) is kind
        if not ok:
            raise SchemaError(topic, f"data.{key}", "format", f"expected {kind.__name__}, got {value!r}")
    if data["version"] < 1 or not data["path"] or not math.isfinite(data["time"]):
        raise SchemaError(topic, "data", "format", f"invalid checkpoint announcement {data}")
    return CheckpointInfo(data["path"], data["version"], data["schema_hash"], float(data["time"]))


# ---------------------------------------------------------------------------------------- /diagnostics
#: DiagnosticStatus levels
OK, WARN, ERROR, STALE = 0, 1, 2, 3


@dataclass(frozen=True)
class DiagnosticEntry:
    """One ``diagnostic_msgs/DiagnosticStatus``: a node's counters as key/value strings.

    Attributes:
        name: the node's fully qualified name, e.g. ``"/quadrotor/learner"``.
        level: :data:`OK`, :data:`WARN`, :data:`ERROR` or :data:`STALE`.
        message: one-line summary.
        values: counters and other values (written with ``str()``; ints stay ints, floats use ``repr``).
        hardware_id: optional (empty for software nodes).
    """

    name: str
    level: int = OK
    message: str = ""
    values: Mapping[str, Any] = field(default_factory=dict)
    hardware_id: str = ""


def diagnostics_to_msg(entries: Sequence[DiagnosticEntry], stamp_ns: int, *, factory: MessageFactory = RCLPY) -> Any:
    """``diagnostic_msgs/DiagnosticArray`` with one status per entry."""
    status = []
    for e in entries:
        if e.level not in (OK, WARN, ERROR, STALE):
            raise SchemaError(DIAGNOSTICS_TOPIC, "status.level", "format", f"invalid level {e.level!r}")
        kv = [factory.make("diagnostic_msgs/msg/KeyValue", key=str(k), value=str(v)) for k, v in e.values.items()]
        status.append(
            factory.make(
                "diagnostic_msgs/msg/DiagnosticStatus",
                level=factory.byte(e.level),
                name=e.name,
                message=e.message,
                hardware_id=e.hardware_id,
                values=kv,
            )
        )
    return factory.make(DIAGNOSTIC_ARRAY, header=make_header(factory, stamp_ns, "", DIAGNOSTICS_TOPIC), status=status)


def diagnostics_from_msg(msg: Any, topic: str = DIAGNOSTICS_TOPIC) -> tuple[list[DiagnosticEntry], int]:
    """``DiagnosticArray`` -> ``(entries, stamp_ns)``; values stay strings."""
    stamp = read_stamp(msg.header.stamp, topic)
    entries = []
    for s in msg.status:
        level = s.level[0] if isinstance(s.level, bytes | bytearray) else int(s.level)
        entries.append(DiagnosticEntry(s.name, level, s.message, {kv.key: kv.value for kv in s.values}, s.hardware_id))
    return entries, stamp


# ----------------------------------------------------------------------------------------------- /clock
def clock_to_msg(stamp_ns: int, *, factory: MessageFactory = RCLPY) -> Any:
    """``rosgraph_msgs/Clock`` for simulated time ``stamp_ns``."""
    sec, nanosec = split_stamp(stamp_ns, CLOCK_TOPIC)
    return factory.make(CLOCK, clock=factory.make("builtin_interfaces/msg/Time", sec=sec, nanosec=nanosec))


def clock_from_msg(msg: Any, topic: str = CLOCK_TOPIC) -> int:
    """``rosgraph_msgs/Clock`` -> simulated time in ns."""
    return read_stamp(msg.clock, topic, "clock")


# ------------------------------------------------------------------------------------------ topic specs
def _status_docs() -> tuple[FieldDoc, ...]:
    docs = [FieldDoc(n, u, f"position[{i}]", f"/{n}/position", d) for i, (n, u, d) in enumerate(MPC_STATUS_FIELDS)]
    docs += [FieldDoc(n, u, "position[i]", f"/{n}/position", d) for n, u, d in MPC_STATUS_EXTRA]
    return tuple(docs)


#: the counters and values of ``/diagnostics`` that name a reason, with who reports them
DIAGNOSTICS_REASON_DOCS: tuple[tuple[str, str, str], ...] = (
    ("rejected/<reason>", "count", "every node: messages dropped, by reason: " + ", ".join(REJECT_REASONS)
     + " (bounds: a value outside the system's plausible range; the simulators count commands far outside the "
       "control box as bounds)"),
    ("<ns>/rejected/<reason>", "count", "learner: the same, per namespace"),
    ("checkpoints_refused/<reason>", "count", "mpc: checkpoints refused (the current model kept), by reason: "
     + ", ".join(CHECKPOINT_REFUSAL_REASONS)),
    ("safe_commands/<reason>", "count", "mpc: states answered with the system's safe command, by reason: "
     + ", ".join(SAFE_COMMAND_REASONS)),
    ("train_health/skipped/<reason>", "count", "learner: training steps skipped (the last healthy state kept), by "
     "reason: " + ", ".join(TRAINING_SKIP_REASONS) + "; train_health/skipped (all), train_health/restores (weights "
     "restored), train_health/unhealthy_streak (consecutive skipped steps: WARN after one, ERROR from "
     "health.error_after on), checkpoints_unhealthy (checkpoints not written: the model was not healthy)"),
    ("checkpoint_write_error", "1", "learner: while checkpoint writes fail (a full or read-only disk; level ERROR): "
     "the OS message, the path, the failed writes in a row, the time since the last good checkpoint and until the "
     "next attempt (text; \"\" while writes succeed); checkpoint_write_failures (in a row), checkpoint_write_errors "
     "(so far), checkpoint_age_s, checkpoint_write_seconds, unsaved_updates (docs/learner.md)"),
    ("feasibility/<k>", "1", "learner: the verdict on constraint k read on the held-out stretches of the stream (text, "
     "not plottable; docs/learner.md): met (the upper end of the 95 % interval at most eps_k) OK; unconfirmed, met on "
     "training data only, no held-out data WARN; not met WARN while training has not converged, else ERROR; pending "
     "before training. heldout/<k>, heldout_se/<k>, heldout_upper/<k>, heldout_n/<k>, heldout_base/<k> (f_hat on the "
     "same stretches), training_lhs/<k> beside it"),
    ("optimization/<k>", "1", "learner: the training history's diagnosis of constraint k: met, not converged, likely "
     "infeasible or pending (docs/training.md); not converged WARN, likely infeasible ERROR"),
    ("reachable/<k>", "loss", "learner: the left-hand side g_k + eps_k the model reaches now"),
    ("guard_rollbacks", "count", "mpc: roll backs by the live monitor (guard.rollback, on by default) to the "
     "previous model, else f_hat, and checkpoints refused before flying them (guard_refused_before_flight: worse "
     "than f_hat on the newest live transitions); guard_rolled_back_versions lists the versions never used again"),
    ("models_retired", "count", "mpc: models in use that failed the acceptance re-check on the states flown (not "
     "used any more); checkpoints_reannounced: checkpoints holding the model in use again (nothing done)"),
    ("multiple_publishers", "1", "learner, mpc: '<topic>: <node>, <node>; ...' for every subscribed state / command "
     "topic (the MPC: state and cmd) with more than one publisher, the nodes named from the ROS graph (text; WARN "
     "while not empty); <ns>/publisher_nodes/<kind> (learner) and publisher_nodes/<kind> (mpc) name each topic's"),
    ("<ns>/refused/<kind>", "count", "learner, with pairing.refuse_multiple_publishers: messages not paired because "
     "a topic of the namespace had several publishers"),
)


TELEMETRY_TOPICS: tuple[TopicSpec, ...] = (
    TopicSpec(MODEL_ERROR_TOPIC, JOINT_STATE, TELEMETRY_QOS, "learner", "anyone (PlotJuggler, Foxglove, record)",
              "Live one-step error of the current model in / out of each region, objective, constraints, "
              "lambdas, Lagrangian, buffer size, update count and rejection counters; JointState as a stamped "
              "named vector (names = metrics, values in position). <k> is a constraint name from the spec.",
              fields=_model_error_docs()),
    TopicSpec(CHECKPOINT_TOPIC, STRING, CHECKPOINT_QOS, "learner", "mpc, record",
              'Newest checkpoint as JSON {"path": str, "version": int, "schema_hash": str, "time": float s}; '
              "the stamp is `time`.",
              fields=(FieldDoc("version", "count", "data (JSON) .version", "(not plottable: JSON string)"),)),
    TopicSpec(MPC_STATUS_TOPIC, JOINT_STATE, TELEMETRY_QOS, "mpc", "anyone",
              "One message per solve; JointState as a stamped named vector. The standard names come first, "
              "solvers may append more.", fields=_status_docs()),
)  # fmt: skip

GLOBAL_TOPICS: tuple[TopicSpec, ...] = (
    TopicSpec(DIAGNOSTICS_TOPIC, DIAGNOSTIC_ARRAY, TELEMETRY_QOS, "every node", "rqt_runtime_monitor, Foxglove",
              "One DiagnosticStatus per node (name = node's full name) with its counters, e.g. "
              "rejected/<reason>, as key/value strings. The MPC's guard adds guard_fallbacks, guard_base_solves, "
              "guard_rollbacks, guard_bounded_solves, guard_clipped_solves, guard_task_fallbacks, "
              "guard_task_rollbacks (the task check: steps flown with f_hat's own plan, roll backs), "
              "guard_rolled_back_versions "
              "(comma-separated), "
              "monitor_error_model and monitor_error_base (level WARN after a roll back).",
              fields=tuple(FieldDoc(n, u, "status[i].values[j].value (string)", f"/<node name>/{n}", d)
                           for n, u, d in DIAGNOSTICS_REASON_DOCS)),
    TopicSpec(CLOCK_TOPIC, CLOCK, CLOCK_QOS, "the simulator running in lockstep", "every node (use_sim_time)",
              "Simulated time.", fields=(FieldDoc("clock", "s", "clock.sec + 1e-9 clock.nanosec", "/clock/sec"),)),
)  # fmt: skip
