"""Online learner node (``ros2 run saml_ros learner``): pairs simulator / robot data and trains the model live.

Wiring over :class:`saml_ros.core.online.TrainingProcess` with :class:`saml_ros.core.online.config.LearnerConfig`
(docs/learner.md): it subscribes to each namespace's ``state``, ``applied_cmd`` (and the paddle ball's
``post_impact``) as serialized messages (:mod:`saml_ros.nodes.raw_ingest`); a niced training process decodes,
pairs (bad input counted under ``rejected/<reason>``), trains and checkpoints every ``checkpoint_period`` s; the
node publishes ``learner/model_error``, ``learner/checkpoint`` (transient local) and ``/diagnostics``. A managed
node ("Lifecycle" in docs/learner.md; ``autostart`` walks configure and activate, a configuration error exits 2);
SIGINT / SIGTERM (or ``shutdown``) write a final checkpoint and exit 0. torch is imported only once :func:`main`
has started the training interpreter (both import it at once, which halves the start-up). Usage::

    ros2 run saml_ros learner --ros-args -r __ns:=/friction -p system:=friction --params-file config/learner.yaml
"""
from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import rclpy
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.clock import Clock, ClockType

import msg_schemas.telemetry as tele
from msg_schemas import CHECKPOINT_QOS, RCLPY, TELEMETRY_QOS, get_schema
from msg_schemas.decode import make_decoder
from saml_ros.core.data.publishers import PublisherGate, node_label, publisher_report
from saml_ros.core.errors import SamlError
from saml_ros.core.model.checkpoint import CheckpointStore
from saml_ros.core.online.config import LearnerConfig, learner_params
from saml_ros.core.online.recent_counts import RecentCounts
from saml_ros.core.online.report import (
    configured_message,
    paused_message,
    stopped_message,
    training_diagnostics,
)
from saml_ros.core.runtime.child_launch import LaunchedChild, discard_child, launch_child
from saml_ros.core.runtime.lifecycle import LIFECYCLE_PARAMS, TransitionRefused
from saml_ros.nodes.managed import ManagedNode, run_managed
from saml_ros.nodes.raw_ingest import subscribe_raw
from saml_ros.nodes.ros_params import ParamGuard, current_values, probe_system, start_params
from saml_ros.nodes.runtime import catch_stop_signals, full_argv, init_rclpy, log_at, process_main, shutdown, wants_help

if TYPE_CHECKING:
    from saml_ros.core.online import TrainingProcess

#: exit status for configuration errors (the node never starts)
CONFIG_ERROR = 2
NODE_NAME = "learner"
#: parameters that cannot both be given
EXCLUSIVE = (("system", "system_file"),)


class ConfigError(SamlError):
    """An unrecoverable configuration problem; the message says which parameter and why."""


class LearnerNode(ManagedNode):
    """The learner (a managed node, see the module docstring); ``launched``: a training interpreter from
    :func:`prelaunch_trainer`, used by the first ``configure``."""

    def __init__(self, namespace: str | None, launched: Any = None) -> None:
        super().__init__(NODE_NAME, namespace)
        self._table = learner_params()
        self.trainer: TrainingProcess | None = None
        try:
            start_params(self, self._table, self._check_values, EXCLUSIVE, earlier=self.param_problems)
        except SamlError as exc:
            raise ConfigError(str(exc)) from None
        self.params_guard = ParamGuard(self, self._table, self._check_values, self._apply_live, exclusive=EXCLUSIVE,
                                       extra=LIFECYCLE_PARAMS)
        self._launched = launched
        self._subs: list[Any] = []
        self._pubs: list[Any] = []  # made by configure, destroyed by cleanup
        self._timers: list[Any] = []
        self.active = False

    # ---------------------------------------------------------------------------------------------- lifecycle
    def configure_node(self) -> None:
        try:
            self.p, self.system, self.spec = self._check_values(current_values(self, self._table))
        except SamlError as exc:
            raise TransitionRefused(str(exc)) from None
        p = self.p
        self.schema = get_schema(p.system)
        self.run_dir = run_dir = Path(p.checkpoint.run_dir or f"runs/{p.system}").expanduser().resolve()
        try:
            CheckpointStore(run_dir, keep=p.checkpoint.keep)  # fail here, clearly, if it cannot be created
        except OSError as exc:
            raise TransitionRefused(f"parameter 'run_dir': cannot use {run_dir}: {exc}") from None
        self.channels = p.channels(self.schema)
        self.unstamped, self.channel_qos = p.channel_traits(self.schema)  # no header: stamped on receipt
        self.received = [0] * len(self.channels)
        self.gate = PublisherGate([ns for ns, _, _, _ in self.channels], p.pairing.refuse_multiple_publishers)
        self._shared = ""  # the last multiple_publishers value logged
        launched, self._launched = self._launched, None
        try:  # imports torch (the training interpreter is importing it meanwhile)
            self.trainer = p.start_training(self.system, self.spec, self.schema, str(run_dir), make_decoder,
                                            paused=True, launched=launched, cancelled=self.stop_requested,
                                            on_checkpoint=self._announce, on_log=self._child_log,
                                            on_error=self._child_error)
        except SamlError as exc:  # a bad setting or run directory, a start that failed or was cancelled
            raise TransitionRefused(str(exc)) from None
        self._create_publishers()
        ready = self.trainer.ready
        assert ready is not None
        if ready.resumed is not None:
            self._announce(ready.resumed["path"], ready.resumed["version"])
        self.get_logger().info(configured_message(p, self.spec, ready, run_dir, self.trainer.pid))

    def activate_node(self) -> None:
        assert self.trainer is not None
        self._subscribe()
        self.trainer.resume()
        self.active = True

    def deactivate_node(self) -> None:
        self._unsubscribe()
        self.active = False
        if self.trainer is not None:
            paused = self.trainer.pause()
            if paused is None:
                raise RuntimeError("the training process did not pause within 30 s")
            self.get_logger().info(paused_message(paused, int(self.trainer.status.get("unsaved_updates", 0))))

    def cleanup_node(self, step: str = "cleanup") -> None:
        self._unsubscribe()
        self.active = False
        if self.trainer is not None:
            self.stop(step)
            self.trainer = None
        for timer in self._timers:
            self.destroy_timer(timer)
        for pub in self._pubs:
            self.destroy_publisher(pub)
        self._timers, self._pubs = [], []

    def shutdown_node(self, state: str) -> None:
        self.cleanup_node("shutdown")  # active: no pause first, the stop writes the final checkpoint at once

    def _check_values(self, values: dict[str, Any]) -> tuple[LearnerConfig, Any, Any]:
        """Configure's validation of parameter values (also of a change on the running node): a configured node
        checks against the robot it runs, and loads a system file only when unconfigured, as configure does."""
        configured = self.trainer is not None

        def system_of(path: str) -> str:
            if configured:
                return self.p.system
            from saml_ros.user_code import load_robot_param

            return load_robot_param(path).name

        return LearnerConfig.validated(values, self.get_namespace(), system_of)

    def _apply_live(self, live: dict[str, Any]) -> None:
        """Parameters that apply at once (the training loop's pacing, the telemetry and diagnostics rates); an
        unconfigured node reads them at configure."""
        if self.trainer is None:
            return
        self.p = self.p.with_params(live)
        self.trainer.set_loop(self.p.loop_config())
        self._telemetry_timer.timer_period_ns = int(1e9 / self.p.telemetry.rate)
        self._diagnostics_timer.timer_period_ns = int(1e9 / self.p.telemetry.diagnostics_rate)

    def discard_prelaunched(self) -> None:
        """Let an unused pre-launched training interpreter exit."""
        if self._launched is not None:
            discard_child(self._launched)
            self._launched = None

    def _create_publishers(self) -> None:
        self.data_group = MutuallyExclusiveCallbackGroup()
        self.timer_group = MutuallyExclusiveCallbackGroup()
        telemetry_qos = TELEMETRY_QOS.to_rclpy()
        self.pub_error = self.create_publisher(RCLPY.cls(tele.JOINT_STATE), tele.MODEL_ERROR_TOPIC, telemetry_qos)
        self.pub_ckpt = self.create_publisher(RCLPY.cls(tele.STRING), tele.CHECKPOINT_TOPIC, CHECKPOINT_QOS.to_rclpy())
        self.pub_diag = self.create_publisher(RCLPY.cls(tele.DIAGNOSTIC_ARRAY), tele.DIAGNOSTICS_TOPIC, telemetry_qos)
        self._pubs = [self.pub_error, self.pub_ckpt, self.pub_diag]
        self._recent = RecentCounts()  # the /diagnostics level: what the counters did in the last minute
        # wall-clock (steady) timers: with use_sim_time a lockstep loop at 10x real time would publish 10x as often
        steady = Clock(clock_type=ClockType.STEADY_TIME)
        self._timers = [
            self.create_timer(1.0 / self.p.telemetry.rate, self._publish_telemetry, callback_group=self.timer_group,
                              clock=steady),
            self.create_timer(1.0 / self.p.telemetry.diagnostics_rate, self._publish_diagnostics, callback_group=self.timer_group,
                              clock=steady),
        ]
        self._telemetry_timer, self._diagnostics_timer = self._timers  # periods change with their parameters

    def _subscribe(self) -> None:
        assert self.trainer is not None
        self._subs = subscribe_raw(self, self.channels, self.channel_qos, self.unstamped, self.trainer.submit_raw,
                                   self.received, self.data_group, self.gate.admit, self.gate.set_count)

    def _unsubscribe(self) -> None:
        for sub in self._subs:
            self.destroy_subscription(sub)
        self._subs = []

    # ---------------------------------------------------------------------------------------------- training
    def _child_log(self, level: int, text: str) -> None:
        log_at(self.get_logger(), level, text)

    def _child_error(self, what: str, text: str) -> None:
        self.get_logger().error(f"{what}: {text}")

    def _announce(self, path: str, version: int) -> None:
        info = tele.CheckpointInfo(str(path), int(version), self.system.schema_hash(),
                                   self.get_clock().now().nanoseconds * 1e-9)
        try:
            self.pub_ckpt.publish(tele.checkpoint_to_msg(info))
        except Exception as exc:  # noqa: BLE001 - e.g. the publisher is not created yet or already gone
            self.get_logger().warning(f"could not announce checkpoint {path}: {exc}")

    def stop(self, step: str = "shutdown") -> None:
        """End the training process (in lifecycle ``step``): it writes a final checkpoint if there is anything
        new."""
        assert self.trainer is not None
        final = self.trainer.stop()
        if final is not None and final[0] is not None:
            self._announce(final[0], final[1])
        error, text = stopped_message(final, self.trainer.status.get("updates", 0),
                                      self.trainer.counts().get("paired", 0), self.p.min_transitions, step,
                                      int(self.trainer.status.get("unsaved_updates", 0)))
        log_at(self.get_logger(), logging.ERROR if error else logging.INFO, text)

    # ---------------------------------------------------------------------------------------------- telemetry
    def _stamp_ns(self) -> int:
        return max(0, int(self.get_clock().now().nanoseconds))

    def _publish_telemetry(self) -> None:
        from saml_ros.core.online import assemble_telemetry  # imported by the training start already

        if not self.active or self.trainer is None:
            return
        stamp = self._stamp_ns()
        if stamp == 0:  # use_sim_time and no /clock yet: nothing to stamp it with (as the ROS-time timer did)
            return
        values = assemble_telemetry(self.spec.constraint_names, self.trainer.status, self.trainer.counts())
        self.pub_error.publish(tele.model_error_to_msg(values, stamp))

    def _publish_diagnostics(self) -> None:
        tr = self.trainer
        if tr is None:
            return
        channels = [(ns, kind, self.received[ch], self._subs[ch].get_publisher_count() if self._subs else 0)
                    for ch, (ns, kind, _, _) in enumerate(self.channels)]
        level, message, values = training_diagnostics(tr, self.p, self.spec, channels, self.state_label,
                                                      self.invalid_transitions, self.active, self._recent)
        values["parameter_changes_refused"] = self.params_guard.refused
        p_level, parts, p_values = self._check_publishers()
        level, values = max(level, p_level), {**values, **p_values}
        message = "; ".join([message, *parts])
        entry = tele.DiagnosticEntry(self.get_fully_qualified_name(), level, message, values)
        self.pub_diag.publish(tele.diagnostics_to_msg([entry], self._stamp_ns()))

    def _check_publishers(self) -> tuple[int, list[str], dict[str, Any]]:
        """Several publishers on a subscribed topic (:func:`~saml_ros.core.data.publishers.publisher_report`; the node
        names from the ROS graph), logged when it changes."""
        # the resolved names (a remapped topic) once subscribed
        topics = [sub.topic_name for sub in self._subs] if self._subs else [c[2] for c in self.channels]
        nodes = {topic: [node_label(i.node_namespace, i.node_name) for i in self.get_publishers_info_by_topic(topic)]
                 for topic in set(topics)}
        matched = [sub.get_publisher_count() for sub in self._subs] if self._subs else []
        level, parts, values = publisher_report([(ns, kind, topic) for (ns, kind, _, _), topic in
                                                 zip(self.channels, topics, strict=True)], nodes,
                                                matched, self.gate.refuse, self.gate.refused)
        if values["multiple_publishers"] != self._shared:
            self._shared = values["multiple_publishers"]
            log_at(self.get_logger(), logging.WARNING if parts else logging.INFO,
                   parts[0] if parts else "one publisher per topic again")
        return level, parts, values


def create_node(launched: Any = None) -> LearnerNode:
    """Create the learner node (``rclpy.init`` must have been called). It lives in ``/<system>`` unless the
    command line remaps ``__ns``. ``launched``: a training interpreter from :func:`prelaunch_trainer`.
    Raises :class:`ConfigError`."""
    try:
        system, remapped = probe_system(NODE_NAME, file_param="system_file")
    except SamlError as exc:
        raise ConfigError(str(exc)) from None
    return LearnerNode(None if remapped else f"/{system}", launched)


def prelaunch_trainer() -> LaunchedChild:
    """Start the training interpreter before anything heavy is imported, so it imports torch while this
    process imports torch and reads its parameters (halves the node's start-up time)."""
    return launch_child()


@process_main
def main(argv: Sequence[str] | None = None) -> int:
    """``learner [--ros-args ...]``: run until SIGINT / SIGTERM (or ``shutdown``), then write a final checkpoint
    and exit 0; exit 2 when the node cannot be created or, with ``autostart``, not configured."""
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
            return run_managed(node, stop, CONFIG_ERROR)
        finally:
            node.discard_prelaunched()
    finally:
        shutdown(node)


if __name__ == "__main__":
    raise SystemExit(main())
