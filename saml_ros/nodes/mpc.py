"""The MPC node (``ros2 run saml_ros mpc``): answers every ``state`` with a ``cmd`` from the newest model.

Subscribes ``state`` (DATA_QOS) and ``learner/checkpoint`` (CHECKPOINT_QOS, transient local), and the paddle
ball's ``post_impact`` while the live monitor's roll back is on (``guard.rollback``, the default); publishes
``cmd`` (stamped with the state it answers), ``mpc/status`` (one message per solve) and ``/diagnostics``
(several publishers on ``state`` or ``cmd`` are named there, WARN).

* ``mode: lockstep``: every state is answered at once, in the subscription callback (a lockstep simulator
  waits for that answer). ``mode: realtime``: a steady-clock timer at ``rate_hz`` answers the newest state
  received since the last tick (older ones are skipped and counted).
* Models: the node starts on the base model f_hat when ``run_dir`` holds no checkpoint. A
  :class:`~saml_ros.core.mpc.follower.ModelWatcher` follows ``learner/checkpoint`` and polls ``run_dir``
  (``latest``) as a fallback, loads new checkpoints on a background thread and the control step swaps the
  ready model in between two solves. Incompatible, corrupt or unacceptable checkpoints (non-finite weights,
  implausible predictions, residuals beyond the training data's: :mod:`saml_ros.core.mpc.acceptance`) are refused
  (log + counter + ``mpc/status`` ``checkpoints_refused``) and the current model is kept.
* Failure path: a state outside the system's plausible range, a failed or non-finite solve is answered with the
  system's safe command (``safe = 1`` and ``safe_commands`` on ``mpc/status``, ``safe_commands/<reason>`` on
  ``/diagnostics``).
* Deadline: a control step (swap + solve + publish, from the state's arrival in lockstep or the timer tick in
  realtime) that takes longer than ``deadline_ms`` counts as a deadline miss.
* A robot described by a system file (``system_file:=robot.yaml`` with an ``mpc:`` section; docs/your_robot.md,
  "Control it"): the node lives in ``/<name>`` (unless remapped), reads the robot's state on its own topic and type
  and commands it on its own command topic and type through the file's field paths, plans with the generic
  planner (``saml_ros.core.mpc.generic``), takes goals (and a reference path) from the topics the section names (a
  NaN or out-of-bounds goal is refused, counted ``rejected/goal``, the last goal kept), and sends the safe command
  for a state older than ``state_timeout`` or while none arrives for that long (``safe_commands/stale``). A bad
  file ends the node at start with exit 2 and a line naming the key.
* A managed node (docs/nodes.md, "Lifecycle"): ``configure`` reads and validates the parameters, builds the
  controller and loads the newest checkpoint, ``activate`` subscribes ``state`` and commands, ``deactivate``
  unsubscribes (no ``cmd`` at all: the robot side falls back to its safe command after its command timeout,
  as the simulators do), ``cleanup`` releases everything. With ``autostart`` (default) it walks configure and
  activate itself and bad parameters exit 2; a managed node stays unconfigured with the reason logged.

Wiring only: the parameters are :class:`saml_ros.core.mpc.config.MPCConfig`'s, the work is
:class:`saml_ros.core.mpc.service.MPCService`'s. See docs/nodes.md for the parameters and examples.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.clock import Clock, ClockType
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState
from std_msgs.msg import String

from msg_schemas import CHECKPOINT_QOS, DATA_QOS, RCLPY, TELEMETRY_QOS, SchemaError, get_schema
from msg_schemas.cdr import CdrCodec, NamedVectorCdr
from msg_schemas.telemetry import (
    CHECKPOINT_TOPIC,
    DIAGNOSTICS_TOPIC,
    MPC_STATUS_TOPIC,
    OK,
    WARN,
    DiagnosticEntry,
    checkpoint_from_msg,
    diagnostics_to_msg,
    mpc_status_values,
)
from saml_ros.core.data.publishers import node_label, state_command_report
from saml_ros.core.errors import SamlError
from saml_ros.core.mpc.config import EXECUTOR_CHOICES, EXECUTORS, MPCConfig, choose_executor
from saml_ros.core.mpc.service import Answer, MPCService
from saml_ros.core.mpc.shooting.qp import DEFAULT_BACKEND as QP_BACKEND
from saml_ros.core.params import ParamErrors
from saml_ros.core.runtime.lifecycle import LIFECYCLE_PARAMS, TransitionRefused
from saml_ros.core.systems import get_entry
from saml_ros.nodes.managed import ManagedNode, run_managed
from saml_ros.nodes.ros_params import ParamGuard, current_values, probe_system, start_params
from saml_ros.nodes.runtime import (
    catch_stop_signals,
    full_argv,
    init_rclpy,
    process_main,
    shutdown,
    single_torch_thread,
    wants_help,
)

#: exit code for invalid parameters (as argparse's usage errors)
USAGE_ERROR = 2
#: parameters that cannot both be given (a system file names its system)
EXCLUSIVE = (("system", "system_file"),)


class MPCNode(ManagedNode):
    """See the module docstring; raises :class:`~saml_ros.core.params.ParamErrors` naming the parameter when
    rclpy refuses a value."""

    def __init__(self, system_name: str, namespace: str | None = None) -> None:
        super().__init__("mpc", namespace)
        self.system_name = system_name
        self.table = MPCConfig.params(system_name)
        start_params(self, self.table, MPCConfig.from_params, EXCLUSIVE, earlier=self.param_problems)
        self.params_guard = ParamGuard(self, self.table, MPCConfig.from_params, self._apply_live, exclusive=EXCLUSIVE,
                                       extra=LIFECYCLE_PARAMS)
        self.schema = get_schema(system_name)
        # state and cmd as CDR bytes without message objects (msg_schemas.cdr), the lockstep path's cost
        self._state_cdr, self._control_cdr = CdrCodec(self.schema.state), CdrCodec(self.schema.control)
        # a robot's state without a header (e.g. Float64MultiArray) is stamped on receipt, from the message object
        self._unstamped_state = not getattr(self.schema.state, "stamped", True)
        self._status_cdr = NamedVectorCdr()
        self.service: MPCService | None = None
        self.state_sub: Any = None
        self.target_sub: Any = None  # the paddle ball's post_impact, for the live monitor (guard.rollback)
        self._entities: list[tuple[Callable[[Any], Any], Any]] = []  # (destroy, entity) made by configure

    # ------------------------------------------------------------------------------------------ lifecycle
    def configure_node(self) -> None:
        try:
            values = current_values(self, self.table)
            if values.get("system_file"):  # read again: a file edited since the node started is checked now
                from saml_ros.user_code import load_robot_param

                if load_robot_param(values["system_file"]).name != self.system_name:
                    raise ParamErrors([f"parameter 'system_file': {values['system_file']} now names another robot "
                                       f"than {self.system_name!r}"])
            config = MPCConfig.from_params(values)
        except SamlError as exc:
            raise TransitionRefused(str(exc)) from None
        if config.system != self.system_name:
            raise TransitionRefused(f"parameter system={config.system!r} does not match the node's system "
                                    f"{self.system_name!r}")
        self.service = service = MPCService(config, self._send, self.get_logger())
        service.start()
        steady = Clock(clock_type=ClockType.STEADY_TIME)
        # cmd is a lifecycle publisher: it publishes only while the node is active
        self.cmd_pub = self.create_lifecycle_publisher(RCLPY.cls(self.schema.control.msg_type),
                                                       self.schema.cmd_topic, self._qos(self.schema.cmd_topic))
        self.status_pub = self.create_publisher(JointState, MPC_STATUS_TOPIC, TELEMETRY_QOS.to_rclpy())
        self.diag_pub = self.create_publisher(DiagnosticArray, DIAGNOSTICS_TOPIC, TELEMETRY_QOS.to_rclpy())
        self._entities = [
            (self.destroy_lifecycle_publisher, self.cmd_pub),
            (self.destroy_publisher, self.status_pub),
            (self.destroy_publisher, self.diag_pub),
            (self.destroy_subscription, self.create_subscription(String, CHECKPOINT_TOPIC, self._on_checkpoint,
                                                                 CHECKPOINT_QOS.to_rclpy())),
        ]
        self._diag_timer = self.create_timer(1.0 / config.diagnostics_rate, self._publish_diagnostics, clock=steady)
        self._entities.append((self.destroy_timer, self._diag_timer))
        if config.mode == "realtime":
            self._entities.append((self.destroy_timer, self.create_timer(1.0 / config.rate_hz, self._on_tick,
                                                                         clock=steady)))
        if config.state_timeout > 0:  # no state for state_timeout: the safe command
            self._entities.append((self.destroy_timer, self.create_timer(0.5 * config.state_timeout,
                                                                         self._on_watchdog, clock=steady)))
        tracker = service.tracker
        if tracker is not None:  # a robot's goal and reference topics (its mpc: section)
            task = tracker.task
            goal_qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
            for spec, callback in ((task.goal_topic, self._on_goal), (task.reference, self._on_reference)):
                if spec is not None:
                    self._entities.append((self.destroy_subscription, self.create_subscription(
                        RCLPY.cls(spec.type), spec.topic, callback, goal_qos)))
        horizon = f"T={config.horizon}" if get_entry(self.system_name).mpc_horizon else "one-shot"
        self.get_logger().info(
            f"{self.system_name} MPC ({config.solver}{', QP ' + QP_BACKEND if config.solver == 'fast' else ''}, "
            f"{horizon}, {config.mode}{f' at {config.rate_hz:g} Hz' if config.mode == 'realtime' else ''}, "
            f"deadline {1e3 * service.deadline_s:.0f} ms), goal {config.goal!r}, run_dir "
            f"{config.run_dir or '(none)'}; commands once active"
        )
        planner = service.diagnostic_values().get("planner")
        if planner:
            self.get_logger().info(f"planner: {planner}; commands {self.schema.control.msg_type} on "
                                   f"{self.resolve_topic_name(self.schema.cmd_topic)}")

    def _apply_live(self, live: dict[str, Any]) -> None:
        """Parameters that apply at once: the goal, ``safe_on_infeasible``, ``deadline_ms``, ``poll_period`` and
        ``diagnostics_rate``; an unconfigured node reads them at configure."""
        service = self.service
        if service is None:
            return
        config = MPCConfig.from_params(current_values(self, self.table))
        goal_changed = not np.array_equal(np.asarray(config.goal, dtype=object), np.asarray(service.config.goal,
                                                                                          dtype=object))
        service.config = config  # read by every solve (safe_on_infeasible, state_timeout, ...)
        if goal_changed:  # the goal.* parameters changed: plan for them (a goal from a topic stays otherwise)
            service.set_goal(config.goal)
        service.deadline_s = config.deadline_s(service.system.dt)
        service.watcher.poll_period = config.poll_period
        self._diag_timer.timer_period_ns = int(1e9 / config.diagnostics_rate)

    def activate_node(self) -> None:
        qos = self._qos(self.schema.state_topic)
        if self.service is not None and self.service.config.system_file:
            # a robot does not wait for answers: a planner slower than the state stream answers the newest state,
            # never a backlog of old ones (which would only get the safe command as stale)
            qos.depth = 1
        # raw: the CDR bytes are read without a message object (msg_schemas.cdr; malformed ones as before)
        self.state_sub = self.create_subscription(RCLPY.cls(self.schema.state.msg_type), self.schema.state_topic,
                                                  self._on_state, qos, raw=not self._unstamped_state)
        if self.service is not None and self.service.guarded is not None and \
                self.schema.target_topic != self.schema.state_topic:
            self.target_sub = self.create_subscription(RCLPY.cls(self.schema.target.msg_type),
                                                       self.schema.target_topic, self._on_target, DATA_QOS.to_rclpy())

    def deactivate_node(self) -> None:
        if self.state_sub is not None:
            self.destroy_subscription(self.state_sub)
            self.state_sub = None
        if self.target_sub is not None:
            self.destroy_subscription(self.target_sub)
            self.target_sub = None
        if self.service is not None:
            self.service.pending = None  # realtime: a state received while active is not answered later

    def cleanup_node(self) -> None:
        self.deactivate_node()
        for destroy, entity in self._entities:
            destroy(entity)
        self._entities = []
        if self.service is not None:
            self.service.stop()
            self.service = None

    # ------------------------------------------------------------------------------------------ callbacks
    def _on_checkpoint(self, msg: Any) -> None:
        assert self.service is not None
        try:
            info = checkpoint_from_msg(msg, CHECKPOINT_TOPIC)
        except SchemaError as exc:
            self.service.reject(exc.reason, str(exc))
            return
        self.service.notify(info.path, info.version, info.schema_hash)

    def _on_state(self, msg: Any) -> None:
        assert self.service is not None
        t_arrival = time.perf_counter()
        now_ns = self.get_clock().now().nanoseconds
        try:
            if self._unstamped_state:
                codec: Any = self.schema.state  # a FieldPathCodec: an unstamped message takes its receipt time
                x, stamp = codec.from_msg(msg, self.schema.state_topic, receipt_ns=now_ns)
            else:
                x, stamp = self._state_cdr.decode(msg, self.schema.state_topic)
        except SchemaError as exc:
            self.service.reject(exc.reason, str(exc))
            return
        self._publish_status(self.service.receive(x, stamp, t_arrival, now_ns))

    def _on_target(self, msg: Any) -> None:
        assert self.service is not None
        try:
            y, stamp = self.schema.target_from_msg(msg)
        except SchemaError as exc:
            self.service.reject(exc.reason, str(exc))
            return
        self.service.receive_target(y, stamp)

    def _on_tick(self) -> None:
        if self.service is not None and self.state_sub is not None:
            self._publish_status(self.service.tick(self.get_clock().now().nanoseconds))

    def _on_watchdog(self) -> None:
        if self.service is not None and self.state_sub is not None:
            self._publish_status(self.service.watchdog(time.perf_counter(), self.get_clock().now().nanoseconds))

    def _on_goal(self, msg: Any) -> None:
        if self.service is not None and self.service.tracker is not None:
            task = self.service.tracker.task
            self.service.goal_message(msg, task.goal_topic.topic if task.goal_topic else "")

    def _on_reference(self, msg: Any) -> None:
        if self.service is not None and self.service.tracker is not None:
            task = self.service.tracker.task
            self.service.reference_message(msg, self.get_clock().now().nanoseconds,
                                           task.reference.topic if task.reference else "")

    def _qos(self, topic: str) -> Any:
        """The QoS of ``topic`` in the system's schema (a system file's ``qos``), else the data QoS."""
        try:
            return self.schema.topic(topic).qos.to_rclpy()
        except (KeyError, ValueError, SchemaError):
            return DATA_QOS.to_rclpy()

    # ------------------------------------------------------------------------------------------ publishing
    def _send(self, u: np.ndarray, stamp: int) -> None:
        self.cmd_pub.publish(self._control_cdr.encode(u, stamp, self.schema.cmd_topic))

    def _publish_status(self, answer: Answer | None) -> None:
        if answer is not None:
            stamp, values = answer  # the JointState mpc_status_to_msg builds, as CDR bytes
            self.status_pub.publish(self._status_cdr.encode(mpc_status_values(values), stamp, MPC_STATUS_TOPIC))

    def _publish_diagnostics(self) -> None:
        if self.service is None:
            return
        values = self.service.diagnostic_values()
        values["lifecycle"] = state = self.state_label
        # publishers this node's state subscription has matched (its own side of discovery: a state sent
        # before it matched is dropped by DDS, whatever the publisher's subscription count says)
        values["state_publishers"] = self.state_sub.get_publisher_count() if self.state_sub is not None else 0
        values["invalid_transitions"] = self.invalid_transitions
        values["parameter_changes_refused"] = self.params_guard.refused
        refused = values["checkpoints_refused"]
        version = self.service.model_version
        rollbacks = self.service.counters["rollbacks"]
        safe = values["safe_commands"]
        level = WARN if refused or safe or rollbacks or self.service.counters["solver_errors"] else OK
        message = (f"model version {version}; {values['solves']} solves" if "solves" in values
                   else f"model version {version}; waiting for states")
        if safe:
            message += f"; {safe} safe command(s) sent"
        if refused:
            message += f"; {refused} checkpoint(s) refused, last: {values['last_refusal']}"
        if rollbacks:
            message += (f"; {rollbacks} roll back(s) by the live monitor (versions "
                        f"{values.get('guard_rolled_back_versions', '')} not used again)")
        if self.state_sub is not None:  # two robots on state, a second controller on cmd: named (WARN)
            p_level, parts, p_values = self._check_publishers()
            level, message = max(level, p_level), "; ".join([message, *parts])
            values.update(p_values)
        if state != "active":
            message = f"{state}: {message}"
        entry = DiagnosticEntry(self.get_fully_qualified_name(), level, message, values)
        self.diag_pub.publish(diagnostics_to_msg([entry], self.get_clock().now().nanoseconds))

    def _check_publishers(self) -> tuple[int, list[str], dict[str, Any]]:
        """:func:`~saml_ros.core.data.publishers.state_command_report` of ``state`` and ``cmd`` from the ROS graph."""
        topics = [("state", self.state_sub.topic_name), ("cmd", self.cmd_pub.topic_name)]
        nodes = {topic: [node_label(i.node_namespace, i.node_name) for i in self.get_publishers_info_by_topic(topic)]
                 for _, topic in topics}
        return state_command_report(topics, nodes)

    def destroy_node(self) -> None:
        if self.service is not None:
            self.service.stop()
        super().destroy_node()


# ---------------------------------------------------------------------------------------------- main
def create_node() -> MPCNode:
    """Create the MPC node (``rclpy.init`` must have been called with ``args``).

    The node lives in ``/<system>`` unless the command line remaps ``__ns``: a probe node reads ``system`` (and
    ``system_file``) first, because the namespace must be known when the node is created. A system file is loaded
    here (its robot registered; ``ParamErrors`` naming the file and key when it is wrong); ``system`` next to
    ``system_file`` is refused by the node's start-up check (both named).

    Raises:
        SamlError: (:class:`~saml_ros.core.params.ParamErrors`) a bad ``system`` / ``system_file`` or a value rclpy
            refuses, each named.
    """
    system, remapped = probe_system("mpc", file_param="system_file")
    path, _ = _probe_system_file()
    if path:
        from saml_ros.user_code import load_robot_param

        system = load_robot_param(path).name
    try:
        get_entry(system)  # a clear error for an unknown name
    except ValueError as exc:
        raise ParamErrors([str(exc)]) from None
    return MPCNode(system, None if remapped else f"/{system}")


def _probe_system_file() -> tuple[str, bool]:
    """The ``system_file`` parameter of the command line (a short-lived probe node)."""
    from rclpy.node import Node

    probe = Node("mpc")
    try:
        value = probe.declare_parameter("system_file", "").value
    except Exception as exc:  # noqa: BLE001 - rclpy raises several types for bad overrides
        raise ParamErrors([f"parameter 'system_file': {exc}"]) from None
    finally:
        remapped = probe.get_namespace() != "/"
        probe.destroy_node()
    return str(value or ""), remapped


@process_main
def main(argv: Sequence[str] | None = None) -> int:
    """``mpc [--ros-args ...]``: run the node until SIGINT / SIGTERM (exit 0); bad parameters exit 2."""
    args = full_argv("mpc", argv)
    if wants_help(args):
        print(__doc__)
        print("usage: mpc --ros-args [-p system:=quadrotor | -p system_file:=robot.yaml] [-p mode:=lockstep] "
              "[--params-file config/mpc.yaml] [-r __ns:=/quadrotor]")
        return 0
    stop = catch_stop_signals()
    single_torch_thread()  # checkpoints are tiny; extra threads would only contend for the cores
    init_rclpy(args)
    node = None
    try:
        try:
            node = create_node()
            # the executor is chosen before configure (which reads the other parameters)
            executor = str(node.get_parameter("executor").value)
            if executor not in EXECUTOR_CHOICES:
                raise ParamErrors([f"parameter 'executor' must be auto or one of {list(EXECUTORS)}, got "
                                   f"{executor!r}"])
            executor = choose_executor(executor, str(node.get_parameter("mode").value))
        except SamlError as exc:
            rclpy.logging.get_logger("mpc").fatal(f"configuration error: {exc}")
            return USAGE_ERROR
        return run_managed(node, stop, USAGE_ERROR, executor=executor)
    finally:
        shutdown(node)


if __name__ == "__main__":
    raise SystemExit(main())
