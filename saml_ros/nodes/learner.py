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

Wiring only: the parameters are :class:`saml_ros.core.learner_config.LearnerConfig`'s, the training is the
training process's. torch is imported only once :func:`main` has started that process (so both import it at
the same time, which halves the start-up).

Usage::

    ros2 run saml_ros learner --ros-args -r __ns:=/friction -p system:=friction \\
        --params-file config/learner.yaml
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import rclpy
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.node import Node
from rclpy.qos import HistoryPolicy

import msg_schemas.telemetry as tele
from msg_schemas import CHECKPOINT_QOS, RCLPY, TELEMETRY_QOS, QosSpec, get_schema
from msg_schemas.decode import make_decoder
from msg_schemas.names import join_topic
from saml_ros.core.checkpoint import CheckpointStore
from saml_ros.core.child_launch import LaunchedChild, discard_child, launch_child
from saml_ros.core.learner_config import LearnerConfig, learner_params
from saml_ros.core.learner_report import learner_diagnostics
from saml_ros.nodes.params import declare_params, probe_system
from saml_ros.nodes.runtime import catch_stop_signals, full_argv, init_rclpy, shutdown, spin_until_stopped, wants_help

if TYPE_CHECKING:
    from saml_ros.core.online import TrainingProcess

#: exit status for configuration errors (the node never starts)
CONFIG_ERROR = 2
NODE_NAME = "learner"


class ConfigError(Exception):
    """An unrecoverable configuration problem; the message says which parameter and why."""


def load_robot(path: str) -> Any:
    """The robot of system file ``path``, registered under its name; :class:`ConfigError` naming the problem."""
    from saml_ros.core.systems.system_file import SystemFileError
    from saml_ros.user_code import load_system_file

    try:
        return load_system_file(path)
    except SystemFileError as exc:
        raise ConfigError(f"parameter 'system_file': {exc}") from None


class LearnerNode(Node):
    """The learner; raises :class:`ConfigError` from the constructor on bad configuration."""

    def __init__(self, namespace: str | None, launched: Any = None) -> None:
        super().__init__(NODE_NAME, namespace=namespace)
        try:
            values = declare_params(self, learner_params())
            if values.get("system_file"):
                values["system"] = load_robot(values["system_file"]).name
            self.p = p = LearnerConfig.from_params(values, self.get_namespace())
            self.system = p.make_system()
            self.spec = p.load_spec(self.system)
        except ValueError as exc:
            raise ConfigError(str(exc)) from None
        self.schema = get_schema(p.system)
        self.run_dir = run_dir = Path(p.run_dir or f"runs/{p.system}").expanduser().resolve()
        try:
            CheckpointStore(run_dir, keep=p.checkpoint_keep)  # fail here, clearly, if it cannot be created
        except OSError as exc:
            raise ConfigError(f"parameter 'run_dir': cannot use {run_dir}: {exc}") from None
        sc = self.schema
        kinds = [("state", sc.state_topic, sc.state), ("applied_cmd", sc.applied_cmd_topic, sc.control)]
        if sc.target_pairing == "same":
            kinds.append(("target", sc.target_topic, sc.target))
        #: one channel per (namespace, kind): (namespace, kind, topic, message type)
        self.channels = [(ns, kind, join_topic(ns, name), codec.msg_type)
                         for ns in p.namespaces for kind, name, codec in kinds]
        #: channels whose messages have no header (a robot's cmd_vel): stamped with their receive time
        self.unstamped = [getattr(codec, "stamped", True) is False for _ in p.namespaces for _, _, codec in kinds]
        self.channel_qos = [sc.topic(name).qos for _ in p.namespaces for _, name, _ in kinds]
        self.received = [0] * len(self.channels)
        self.trainer = self._start_training(launched)
        self._create_interfaces()
        ready = self.trainer.ready
        assert ready is not None
        r = ready.resumed
        if r is not None:
            self._announce(r["path"], r["version"])
        self.get_logger().info(
            f"learner for {p.system!r}" + (f" (system file {p.system_file})" if p.system_file else "")
            + f" on {p.namespaces}: spec '{self.spec.raw.get('name')}' "
            f"({self.spec.describe()}), model {p.model_kind} {ready.hidden}, run_dir {run_dir}, "
            + (f"resumed from version {r['version']} ({r['updates']} updates, lambda {r['lam']})" if r
               else "fresh start")
            + f"; training process pid {self.trainer.pid} ({ready.threads} torch thread(s), subnormals "
            + ("flushed" if ready.flush_denormal else "not flushed")
            + f"); training starts after {p.min_transitions} transitions"
        )

    def _start_training(self, launched: Any) -> TrainingProcess:
        from saml_ros.core.online import ResumeError, TrainingProcess  # torch: the training process is running

        p = self.p
        try:
            setup = p.training_setup(self.system, self.spec, self.schema.target_pairing, str(self.run_dir),
                                     [(p.namespaces.index(ns), kind, topic) for ns, kind, topic, _ in self.channels],
                                     decoder=make_decoder)
        except ValueError as exc:
            raise ConfigError(str(exc)) from None
        trainer = TrainingProcess(setup, on_checkpoint=self._announce, on_log=self._child_log,
                                  on_error=self._child_error)
        try:
            trainer.start(launched=launched)
        except ResumeError as exc:
            raise ConfigError(str(exc)) from None
        except RuntimeError as exc:
            raise ConfigError(f"the training process could not start: {exc}") from None
        return trainer

    def _create_interfaces(self) -> None:
        self.data_group = MutuallyExclusiveCallbackGroup()
        self.timer_group = MutuallyExclusiveCallbackGroup()
        telemetry_qos = TELEMETRY_QOS.to_rclpy()
        self.pub_error = self.create_publisher(RCLPY.cls(tele.JOINT_STATE), tele.MODEL_ERROR_TOPIC, telemetry_qos)
        self.pub_ckpt = self.create_publisher(RCLPY.cls(tele.STRING), tele.CHECKPOINT_TOPIC, CHECKPOINT_QOS.to_rclpy())
        self.pub_diag = self.create_publisher(RCLPY.cls(tele.DIAGNOSTIC_ARRAY), tele.DIAGNOSTICS_TOPIC, telemetry_qos)
        # raw=True: the callback gets the serialized message, decoded in the training process; building Python
        # message objects here is most of a bare subscriber's per-message cost
        # KEEP_ALL: a burst that outruns the callbacks (e.g. while the training process imports torch) waits in
        # the reader queue instead of overwriting older transitions; reliable writers are slowed, not dropped
        def data_qos(spec: QosSpec) -> Any:  # the topic's QoS (a robot's file may make it best effort)
            qos = spec.to_rclpy()
            qos.history = HistoryPolicy.KEEP_ALL
            return qos

        self._subs = [
            self.create_subscription(RCLPY.cls(msg_type), topic, self._make_callback(ch),
                                     data_qos(self.channel_qos[ch]), callback_group=self.data_group, raw=True)
            for ch, (_, _, topic, msg_type) in enumerate(self.channels)
        ]
        self.create_timer(1.0 / self.p.telemetry_rate, self._publish_telemetry, callback_group=self.timer_group)
        self.create_timer(1.0 / self.p.diagnostics_rate, self._publish_diagnostics, callback_group=self.timer_group)

    # ---------------------------------------------------------------------------------------------- ingest
    def _make_callback(self, channel: int) -> Callable[..., None]:
        submit, received = self.trainer.submit_raw, self.received

        def callback(data: bytes) -> None:
            received[channel] += 1
            submit(channel, data)

        if not self.unstamped[channel]:
            return callback
        clock = self.get_clock()
        sim_time = bool(self.get_parameter("use_sim_time").value)

        def stamp_on_receipt(data: bytes, info: Any) -> None:
            # the middleware's receive time (the system clock, like the robot's stamps) unless on simulated time
            t = int(info["received_timestamp"]) if not sim_time and info else clock.now().nanoseconds
            received[channel] += 1
            submit(channel, (data, t))

        return stamp_on_receipt

    # ---------------------------------------------------------------------------------------------- training
    def _child_log(self, level: int, text: str) -> None:
        # one call site per severity: rclpy refuses a call site whose severity changes between calls
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

    # ---------------------------------------------------------------------------------------------- telemetry
    def _stamp_ns(self) -> int:
        return max(0, int(self.get_clock().now().nanoseconds))

    def _publish_telemetry(self) -> None:
        from saml_ros.core.online import assemble_telemetry  # imported by the training start already

        values = assemble_telemetry(self.spec.constraint_names, self.trainer.status, self.trainer.counts())
        self.pub_error.publish(tele.model_error_to_msg(values, self._stamp_ns()))

    def _publish_diagnostics(self) -> None:
        tr = self.trainer
        process = {"train_errors": tr.errors, "train_restarts": tr.restarts, "queued": tr.queued, "dropped": tr.dropped}
        if tr.ready is not None:
            process.update(train_threads=tr.ready.threads, train_flush_denormal=int(tr.ready.flush_denormal))
        channels = [(ns, kind, self.received[ch], self._subs[ch].get_publisher_count())
                    for ch, (ns, kind, _, _) in enumerate(self.channels)]
        level, message, values = learner_diagnostics(tr.counts(), tr.status, process, tr.source_counts,
                                                     self.p.namespaces, channels)
        entry = tele.DiagnosticEntry(self.get_fully_qualified_name(), level, message, values)
        self.pub_diag.publish(tele.diagnostics_to_msg([entry], self._stamp_ns()))


def create_node(launched: Any = None) -> LearnerNode:
    """Create the learner node (``rclpy.init`` must have been called). It lives in ``/<system>`` unless the
    command line remaps ``__ns``. ``launched``: a training interpreter from :func:`prelaunch_trainer`.
    Raises :class:`ConfigError`."""
    try:
        system, remapped = probe_system(NODE_NAME, file_param="system_file")
    except ValueError as exc:
        raise ConfigError(str(exc)) from None
    return LearnerNode(None if remapped else f"/{system}", launched)


def prelaunch_trainer() -> LaunchedChild:
    """Start the training interpreter before anything heavy is imported, so it imports torch while this
    process imports torch and reads its parameters (halves the node's start-up time)."""
    return launch_child()


def main(argv: Sequence[str] | None = None) -> int:
    """``learner [--ros-args ...]``: run until SIGINT / SIGTERM, then write a final checkpoint and exit 0."""
    stop = catch_stop_signals()
    args = full_argv(NODE_NAME, argv)
    if wants_help(args):
        print(__doc__)
        return 0

    launched = prelaunch_trainer()
    init_rclpy(args)
    node = None
    try:
        try:
            node = create_node(launched)
        except ConfigError as exc:
            rclpy.logging.get_logger(NODE_NAME).fatal(f"configuration error: {exc}")
            discard_child(launched)
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
