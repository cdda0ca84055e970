"""Online learner node (``ros2 run saml_ros learner``): pairs simulator / robot data and trains the model live.

A thin rclpy wrapper over :class:`saml_ros.core.online.OnlineLearner` (see docs/learner.md):

* subscribes, per namespace in ``namespaces``, to ``state``, ``applied_cmd`` (and ``post_impact`` for the
  paddle ball) with ``DATA_QOS`` in one callback group, taking the *serialized* messages (``raw=True``): the
  callbacks only count and queue them (building Python message objects is most of a subscriber's cost);
* a niced training process (:class:`saml_ros.core.online.TrainingProcess`) gets them in batches, deserializes
  and converts them with msg_schemas (:func:`make_decoder`), pairs them per namespace (malformed / duplicate /
  out-of-order / late messages are counted under ``rejected/<reason>`` and logged, throttled per reason, never
  paired) and trains: replay buffer, primal-dual steps, the live model error, a checkpoint every
  ``checkpoint_period`` s. Training never competes with ingest for Python's GIL, and the OS runs this process
  first when CPUs are short;
* publishes ``learner/model_error`` (sensor_msgs/JointState, names -> values) at ``telemetry_rate``,
  ``learner/checkpoint`` (std_msgs/String JSON, transient local) after every checkpoint and ``/diagnostics``;
* on SIGINT / SIGTERM writes a final checkpoint and exits 0. Configuration errors (unknown system, bad spec,
  bad parameter, a run directory of another system) are logged and exit with status 2.

Usage::

    ros2 run saml_ros learner --ros-args -r __ns:=/friction -p system:=friction \\
        --params-file config/learner.yaml
"""

from __future__ import annotations

import dataclasses
import importlib
import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from saml_ros.nodes.runtime import (
    catch_stop_signals,
    full_argv,
    init_rclpy,
    process_main,
    shutdown,
    spin_until_stopped,
    wants_help,
)

#: exit status for configuration errors (the node never starts)
CONFIG_ERROR = 2
NODE_NAME = "learner"

#: ``train.*`` parameters: TrainConfig field -> description (``epochs`` is an offline-only field)
TRAIN_PARAM_DOCS: dict[str, str] = {
    "batch_size": "minibatch size M sampled from the replay buffer per update",
    "primal_lr": "learning rate alpha_theta of the model parameters",
    "dual_lr": "learning rate alpha_lambda of the dual variables (ascent on the constraint estimates)",
    "primal_optimizer": "'adam' (the paper) or 'sgd'",
    "dual_optimizer": "'adam' (the paper) or 'sgd'",
    "log_every": "updates between training-history rows kept in memory (0 = 100)",
    "seed": "seed of the model initialisation and the minibatch sampling",
    "dtype": "'float32' or 'float64' for the model and the minibatches",
    "engine": "offline training engine (not used by the online step loop)",
    "device": "training device: cpu | cuda | cuda:N (checked at start-up; a device that cannot be used is a "
              "configuration error)",
}


class ConfigError(Exception):
    """An unrecoverable configuration problem; the message says which parameter and why."""


@dataclass
class LearnerParams:
    """The node's parameters after validation (units in the names' descriptions, docs/learner.md)."""

    system: str
    namespaces: list[str]
    spec_file: str
    model_kind: str
    model_hidden: list[int]
    train: dict[str, Any]
    buffer_capacity: int
    buffer_policy: str
    min_transitions: int
    updates_per_second: float
    checkpoint_period: float
    checkpoint_keep: int
    run_dir: str
    resume: bool
    telemetry_rate: float
    telemetry_window: int
    diagnostics_rate: float
    dt: float
    pairing_window: int
    pairing_tolerance: float
    training_niceness: int
    train_threads: int


def normalize_namespace(ns: str) -> str:
    """``"friction"`` / ``"/friction/"`` -> ``"/friction"``; ``""`` / ``"/"`` -> ``"/"``."""
    ns = "/" + ns.strip().strip("/")
    return ns


def topic_in(ns: str, name: str) -> str:
    """Absolute topic ``name`` inside namespace ``ns``."""
    return f"/{name}" if ns == "/" else f"{ns}/{name}"


def _build_node_class() -> type:
    """The node class (built on demand so this module imports without rclpy for docs and tests)."""
    from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
    from rclpy.node import Node
    from rclpy.parameter import Parameter
    from rclpy.qos import HistoryPolicy

    import msg_schemas.telemetry as tele
    from msg_schemas import CHECKPOINT_QOS, DATA_QOS, TELEMETRY_QOS, get_schema
    from saml_ros.core.checkpoint import CheckpointStore
    from saml_ros.core.model_io import system_params
    from saml_ros.core.online import (
        LearnerSetup,
        LoopConfig,
        OnlineConfig,
        ResumeError,
        TrainingProcess,
        assemble_telemetry,
    )
    from saml_ros.core.pairing import PairingConfig
    from saml_ros.core.spec import ProblemSpec, SpecError
    from saml_ros.core.systems import get_system
    from saml_ros.core.trainer import TrainConfig

    # rcl_interfaces ships no type information; through importlib it is simply Any
    ParameterDescriptor = importlib.import_module("rcl_interfaces.msg").ParameterDescriptor

    class LearnerNode(Node):
        """The learner; raises :class:`ConfigError` from the constructor on bad configuration."""

        def __init__(self, namespace: str | None, launched: Any = None) -> None:
            super().__init__(NODE_NAME, namespace=namespace)
            self.p = p = self._read_parameters()
            try:
                self.system = get_system(p.system, **({"dt": p.dt} if p.dt > 0 else {}))
                self.schema = get_schema(p.system)
            except (ValueError, TypeError) as exc:
                raise ConfigError(f"parameter 'system' / 'dt': {exc}") from None
            self.spec = self._load_spec(p)
            try:
                train = TrainConfig.from_dict(p.train)
                config = OnlineConfig(
                    kind=p.model_kind, hidden=tuple(p.model_hidden) or None, train=train,
                    buffer_capacity=p.buffer_capacity, buffer_policy=p.buffer_policy,
                    min_transitions=p.min_transitions, telemetry_window=p.telemetry_window,
                    checkpoint_keep=p.checkpoint_keep,
                )
                pairing = PairingConfig.for_system(
                    self.system, self.schema.target_pairing, tolerance=p.pairing_tolerance, window=p.pairing_window,
                    max_slots=max(10_000, 10 * p.pairing_window),
                )
                loop = LoopConfig(updates_per_second=p.updates_per_second, telemetry_rate=p.telemetry_rate,
                                  checkpoint_period=p.checkpoint_period)
            except (ValueError, TypeError) as exc:
                raise ConfigError(str(exc)) from None
            self.run_dir = run_dir = Path(p.run_dir or f"runs/{p.system}").expanduser().resolve()
            try:
                CheckpointStore(run_dir, keep=p.checkpoint_keep)  # fail here, clearly, if it cannot be created
            except OSError as exc:
                raise ConfigError(f"parameter 'run_dir': cannot use {run_dir}: {exc}") from None
            sc = self.schema
            kinds = [("state", sc.state_topic, sc.state.msg_type), ("applied_cmd", sc.applied_cmd_topic,
                                                                    sc.control.msg_type)]
            if sc.target_pairing == "same":
                kinds.append(("target", sc.target_topic, sc.target.msg_type))
            #: one channel per (namespace, kind): (namespace, kind, topic, message type)
            self.channels = [(ns, kind, topic_in(ns, name), msg_type)
                             for ns in p.namespaces for kind, name, msg_type in kinds]
            self.received = [0] * len(self.channels)
            setup = LearnerSetup(
                system=p.system, system_params=system_params(self.system), spec=self.spec.to_dict(), config=config,
                run_dir=str(run_dir), resume=p.resume, loop=loop, niceness=p.training_niceness,
                threads=p.train_threads,
                sources=tuple((ns, pairing) for ns in p.namespaces),
                channels=tuple((p.namespaces.index(ns), kind) for ns, kind, _, _ in self.channels),
                decoder="saml_ros.nodes.learner:make_decoder",
                decoder_args=(p.system, [(kind, topic) for _, kind, topic, _ in self.channels]),
            )
            self.trainer = TrainingProcess(setup, on_checkpoint=self._announce, on_log=self._child_log,
                                           on_error=self._child_error)
            try:
                ready = self.trainer.start(launched=launched)
            except ResumeError as exc:
                raise ConfigError(str(exc)) from None
            except RuntimeError as exc:
                raise ConfigError(f"the training process could not start: {exc}") from None

            self.data_group = MutuallyExclusiveCallbackGroup()
            self.timer_group = MutuallyExclusiveCallbackGroup()
            self.pub_error = self.create_publisher(
                self._msg_type(tele.JOINT_STATE), tele.MODEL_ERROR_TOPIC, TELEMETRY_QOS.to_rclpy()
            )
            self.pub_ckpt = self.create_publisher(
                self._msg_type(tele.STRING), tele.CHECKPOINT_TOPIC, CHECKPOINT_QOS.to_rclpy()
            )
            self.pub_diag = self.create_publisher(
                self._msg_type(tele.DIAGNOSTIC_ARRAY), tele.DIAGNOSTICS_TOPIC, TELEMETRY_QOS.to_rclpy()
            )
            # raw=True: the callback gets the serialized message, decoded in the training process; building Python
            # message objects here is most of a bare subscriber's per-message cost
            # KEEP_ALL: a burst that outruns the callbacks (e.g. while the training process imports torch) waits in
            # the reader queue instead of overwriting older transitions; reliable writers are slowed, not dropped
            data_qos = DATA_QOS.to_rclpy()
            data_qos.history = HistoryPolicy.KEEP_ALL
            self._subs = [
                self.create_subscription(self._msg_type(msg_type), topic, self._make_callback(ch), data_qos,
                                         callback_group=self.data_group, raw=True)
                for ch, (_, _, topic, msg_type) in enumerate(self.channels)
            ]
            self.create_timer(1.0 / p.telemetry_rate, self._publish_telemetry, callback_group=self.timer_group)
            self.create_timer(1.0 / p.diagnostics_rate, self._publish_diagnostics, callback_group=self.timer_group)
            r = ready.resumed
            if r is not None:
                self._announce(r["path"], r["version"])
            self.get_logger().info(
                f"learner for {p.system!r} on {p.namespaces}: spec '{self.spec.raw.get('name')}' "
                f"({self.spec.describe()}), model {config.kind} {ready.hidden}, run_dir {run_dir}, "
                + (f"resumed from version {r['version']} ({r['updates']} updates, lambda {r['lam']})" if r
                   else "fresh start")
                + f"; training process pid {self.trainer.pid} ({ready.threads} torch thread(s), subnormals "
                + ("flushed" if ready.flush_denormal else "not flushed")
                + f"); training starts after {p.min_transitions} transitions"
            )

        # ------------------------------------------------------------------------------ parameters
        def _declare(self, name: str, default: Any, description: str, ptype: Any = None) -> Any:
            desc = ParameterDescriptor(description=description, dynamic_typing=isinstance(default, float))
            value = ptype if ptype is not None else default
            try:
                got = self.declare_parameter(name, value, desc).value
            except Exception as exc:  # noqa: BLE001 - rclpy raises several types for bad overrides
                raise ConfigError(f"parameter {name!r}: {exc}") from None
            if got is None:
                return default
            if isinstance(default, float):
                if isinstance(got, bool) or not isinstance(got, int | float) or not math.isfinite(got):
                    raise ConfigError(f"parameter {name!r}: expected a finite number, got {got!r}")
                return float(got)
            return got

        def _read_parameters(self) -> LearnerParams:
            d = self._declare
            system = d("system", "friction", "system name: friction | quadrotor | paddle_ball")
            namespaces = d("namespaces", [], "namespaces whose state/applied_cmd are paired (each separately, one "
                           "shared buffer); empty = this node's namespace", Parameter.Type.STRING_ARRAY)
            spec_file = d("spec_file", "", "problem spec YAML (docs/spec.md); empty = the paper's spec")
            kind = d("model.kind", "residual", "'residual' (f_hat + network) or 'full' (network only)")
            hidden = d("model.hidden", [], "hidden layer sizes; empty = the paper's sizes for the system",
                       Parameter.Type.INTEGER_ARRAY)
            train: dict[str, Any] = {}
            for f in dataclasses.fields(TrainConfig):
                if f.name == "epochs":
                    continue
                default = getattr(TrainConfig(), f.name)
                text = TRAIN_PARAM_DOCS.get(f.name, f"TrainConfig.{f.name}")
                train[f.name] = d(f"train.{f.name}", default, text)
            cap = d("buffer.capacity", 100_000, "replay buffer capacity (transitions)")
            policy = d("buffer.policy", "fifo", "eviction when full: 'fifo' (keep the newest) or 'reservoir'")
            min_tr = d("min_transitions", 1000, "transitions before training starts; the input/output "
                       "normalisation is fitted on them once and frozen")
            ups = d("updates_per_second", 0.0, "primal-dual updates per wall-clock second (0 = as fast as possible)")
            period = d("checkpoint_period", 10.0, "wall-clock seconds between checkpoints (only when there are "
                       "new updates)")
            keep = d("checkpoint_keep", 5, "checkpoint files kept in run_dir (older ones are pruned)")
            run_dir = d("run_dir", "", "checkpoint directory; empty = runs/<system> in the working directory")
            resume = d("resume", True, "load the newest valid checkpoint of run_dir (weights, normalisation, "
                       "lambda, optimizer state, update count)")
            rate = d("telemetry_rate", 5.0, "learner/model_error messages per second (Hz)")
            err_window = d("telemetry_window", 1000, "most recent transitions the live model error is computed on")
            diag = d("diagnostics_rate", 1.0, "/diagnostics messages per second (Hz)")
            dt = d("dt", 0.0, "sampling period of the simulator / robot in s (0 = the system's default); "
                   "pairs x_t with x_{t+dt} and sets the base model's step")
            window = d("pairing.window", 1000, "newest states (per namespace) whose stamps are remembered for "
                       "pairing; older incomplete entries are dropped (counted)")
            tol = d("pairing.tolerance", 1e-6, "s: stamps closer than this are the same stamp")
            nice = d("training_niceness", 10, "nice increment of the training process (0-19): the OS runs "
                     "ingest, simulators and the MPC first when CPUs are short")
            threads = d("train_threads", 1, "torch intra-op threads of the training process (0 = torch's default, "
                        "one per core); 1 is fastest for these small networks on a shared machine")
            checks = [
                (isinstance(namespaces, list) and all(isinstance(n, str) for n in namespaces), "namespaces",
                 "a list of strings"),
                (rate > 0, "telemetry_rate", "> 0"), (diag > 0, "diagnostics_rate", "> 0"),
                (ups >= 0, "updates_per_second", ">= 0"), (period > 0, "checkpoint_period", "> 0"),
                (keep >= 1, "checkpoint_keep", ">= 1"), (dt >= 0, "dt", ">= 0"),
                (window >= 2, "pairing.window", ">= 2"), (tol >= 0, "pairing.tolerance", ">= 0"),
                (0 <= nice <= 19, "training_niceness", "in 0..19"), (threads >= 0, "train_threads", ">= 0"),
            ]
            for ok, name, what in checks:
                if not ok:
                    raise ConfigError(f"parameter {name!r} must be {what}")
            node_ns = normalize_namespace(self.get_namespace())
            nss = [normalize_namespace(n) for n in namespaces] or [node_ns]
            if len(set(nss)) != len(nss):
                raise ConfigError(f"parameter 'namespaces' lists a namespace twice: {nss}")
            return LearnerParams(
                system=system, namespaces=nss, spec_file=spec_file, model_kind=kind, model_hidden=list(hidden),
                train=train, buffer_capacity=cap, buffer_policy=policy, min_transitions=min_tr,
                updates_per_second=ups, checkpoint_period=period, checkpoint_keep=keep, run_dir=run_dir,
                resume=resume, telemetry_rate=rate, telemetry_window=err_window, diagnostics_rate=diag, dt=dt,
                pairing_window=window, pairing_tolerance=tol, training_niceness=nice, train_threads=threads,
            )

        def _load_spec(self, p: LearnerParams) -> ProblemSpec:
            try:
                if p.spec_file:
                    return ProblemSpec.from_yaml(p.spec_file, self.system)
                return ProblemSpec.for_system(self.system.paper_spec(), self.system)
            except FileNotFoundError:
                raise ConfigError(f"parameter 'spec_file': no such file {p.spec_file!r}") from None
            except (SpecError, OSError) as exc:
                raise ConfigError(f"parameter 'spec_file': {exc}") from None

        @staticmethod
        def _msg_type(type_name: str) -> Any:
            from msg_schemas import RCLPY

            return RCLPY.cls(type_name)

        # ------------------------------------------------------------------------------ ingest
        def _make_callback(self, channel: int) -> Callable[[bytes], None]:
            submit, received = self.trainer.submit_raw, self.received

            def callback(data: bytes) -> None:
                received[channel] += 1
                submit(channel, data)

            return callback

        # ------------------------------------------------------------------------------ training process
        def _child_log(self, level: int, text: str) -> None:
            logger = self.get_logger()
            if level >= logging.ERROR:
                logger.error(text)
            elif level >= logging.WARNING:
                logger.warning(text)
            else:
                logger.info(text)

        def _child_error(self, what: str, text: str) -> None:
            self.get_logger().error(f"{what}: {text}")

        def _announce(self, path: str, version: int) -> None:
            info = tele.CheckpointInfo(str(path), int(version), self.system.schema_hash(),
                                       self.get_clock().now().nanoseconds * 1e-9)
            try:
                self.pub_ckpt.publish(tele.checkpoint_to_msg(info))
            except Exception as exc:  # noqa: BLE001 - e.g. the publisher is not created yet or already gone
                self.get_logger().warning(f"could not announce checkpoint {path}: {exc}")

        def stop(self) -> None:
            """Stop training: the training process writes a final checkpoint if there is anything new."""
            final = self.trainer.stop()
            status = self.trainer.status
            if final is None:
                self.get_logger().error("shutdown: the training process did not stop in time; it was killed")
            elif final[0] is not None:
                self._announce(final[0], final[1])
                self.get_logger().info(f"shutdown: final checkpoint version {final[1]} ({final[2]} updates)")
            elif status.get("updates", 0) > 0 or final[1] > 0:
                self.get_logger().info(f"shutdown: checkpoint version {final[1]} is current ({final[2]} updates)")
            else:
                paired = self.trainer.counts().get("paired", 0)
                self.get_logger().info(f"shutdown: no checkpoint written, training never started ({paired}/"
                                       f"{self.p.min_transitions} transitions)")

        # ------------------------------------------------------------------------------ telemetry
        def _stamp_ns(self) -> int:
            return max(0, int(self.get_clock().now().nanoseconds))

        def _publish_telemetry(self) -> None:
            values = assemble_telemetry(self.spec.constraint_names, self.trainer.status, self.trainer.counts())
            self.pub_error.publish(tele.model_error_to_msg(values, self._stamp_ns()))

        def _publish_diagnostics(self) -> None:
            totals = self.trainer.counts()
            st, tr = self.trainer.status, self.trainer
            values: dict[str, Any] = {"paired": totals.get("paired", 0)}
            for key in ("buffer_size", "updates", "model_version", "training", "checkpoints_written",
                        "checkpoints_skipped"):
                values[key] = int(st.get(key, 0))
            values.update(train_errors=tr.errors, train_restarts=tr.restarts, queued=tr.queued, dropped=tr.dropped)
            if tr.ready is not None:
                values.update(train_threads=tr.ready.threads, train_flush_denormal=int(tr.ready.flush_denormal))
            for reason in tele.REJECT_REASONS:
                values[f"rejected/{reason}"] = totals.get(reason, 0)
            for key in ("time_resets", "reanchors", "expired", "overflow"):
                values[key] = totals.get(key, 0)
            by_source = tr.source_counts
            for ns in self.p.namespaces:
                c = by_source.get(ns, {})
                values[f"{ns}/paired"] = c.get("paired", 0)
                for reason in tele.REJECT_REASONS:
                    values[f"{ns}/rejected/{reason}"] = c.get(reason, 0)
            for ch, (ns, kind, _, _) in enumerate(self.channels):
                values[f"{ns}/received/{kind}"] = self.received[ch]
                values[f"{ns}/publishers/{kind}"] = self._subs[ch].get_publisher_count()
            rejected = sum(totals.get(r, 0) for r in tele.REJECT_REASONS)
            level = tele.ERROR if tr.errors or tr.dropped else (tele.WARN if rejected else tele.OK)
            message = (f"paired {values['paired']}, buffer {values['buffer_size']}, updates {values['updates']}, "
                       f"version {values['model_version']}, rejected {rejected}")
            entry = tele.DiagnosticEntry(self.get_fully_qualified_name(), level, message, values)
            self.pub_diag.publish(tele.diagnostics_to_msg([entry], self._stamp_ns()))

    return LearnerNode


def make_decoder(args: tuple[str, list[tuple[str, str]]]) -> Callable[[int, bytes], tuple[Any, int]]:
    """Decoder of the node's raw messages, built in the training process (``LearnerSetup.decoder``).

    ``args = (system, [(kind, topic) per channel])``; the returned ``decode(channel, payload)`` deserializes the
    CDR bytes into the channel's stock message and converts it with msg_schemas, returning ``(vector, stamp_ns)``
    or raising :class:`msg_schemas.SchemaError` (reason ``shape``, ``names``, ``nan``, ...).
    """
    from rclpy.serialization import deserialize_message

    from msg_schemas import RCLPY, SchemaError, get_schema

    system, channels = args
    sc = get_schema(system)
    codecs = {"state": (sc.state, sc.state_from_msg), "applied_cmd": (sc.control, sc.control_from_msg),
              "target": (sc.target, sc.target_from_msg)}
    table = [(RCLPY.cls(codecs[kind][0].msg_type), codecs[kind][1], topic) for kind, topic in channels]

    def decode(channel: int, payload: bytes) -> tuple[Any, int]:
        cls, from_msg, topic = table[channel]
        try:
            msg = deserialize_message(payload, cls)
        except Exception as exc:  # noqa: BLE001 - malformed CDR
            raise SchemaError(topic, "(serialized)", "format", f"cannot deserialize: {exc}") from None
        vec, stamp = from_msg(msg, topic)
        return vec, stamp

    return decode


def create_node(launched: Any = None) -> Any:
    """Create the learner node (``rclpy.init`` must have been called). It lives in ``/<system>`` unless the
    command line remaps ``__ns``. ``launched``: a training interpreter from :func:`prelaunch_trainer`.
    Raises :class:`ConfigError`."""
    from rclpy.node import Node

    probe = Node(NODE_NAME)
    try:
        system = probe.declare_parameter("system", "friction").value
    except Exception as exc:  # noqa: BLE001
        raise ConfigError(f"parameter 'system': {exc}") from None
    remapped = probe.get_namespace() != "/"
    probe.destroy_node()
    cls = _build_node_class()
    return cls(None if remapped else f"/{system}", launched)


def prelaunch_trainer() -> Any:
    """Start the training interpreter before anything heavy is imported, so it imports torch while this
    process imports rclpy, torch and reads its parameters (halves the node's start-up time)."""
    from saml_ros.core.child_launch import launch_child

    return launch_child()


def _discard(launched: Any) -> None:
    """Let an unused training interpreter exit (it sees the connection close)."""
    proc, conn = launched
    conn.close()
    try:
        proc.wait(10)
    except Exception:  # noqa: BLE001
        proc.kill()


@process_main
def main(argv: Sequence[str] | None = None) -> int:
    """``learner [--ros-args ...]``: run until SIGINT / SIGTERM, then write a final checkpoint and exit 0."""
    stop = catch_stop_signals()
    args = full_argv(NODE_NAME, argv)
    if wants_help(args):
        print(__doc__)
        return 0

    launched = prelaunch_trainer()

    import rclpy

    init_rclpy(args)
    node = None
    try:
        try:
            node = create_node(launched)
        except ConfigError as exc:
            rclpy.logging.get_logger(NODE_NAME).fatal(f"configuration error: {exc}")
            _discard(launched)
            return CONFIG_ERROR
        try:
            spin_until_stopped(node, stop)
        finally:
            node.stop()
        return 0
    finally:
        shutdown(node)


if __name__ == "__main__":
    raise SystemExit(main())
