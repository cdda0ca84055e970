"""The MPC node (``ros2 run saml_ros mpc``): answers every ``state`` with a ``cmd`` from the newest model.

Subscribes ``state`` (DATA_QOS) and ``learner/checkpoint`` (CHECKPOINT_QOS, transient local); publishes
``cmd`` (stamped with the state it answers), ``mpc/status`` (one message per solve) and ``/diagnostics``.

* ``mode: lockstep``: every state is answered at once, in the subscription callback (a lockstep simulator
  waits for that answer). ``mode: realtime``: a steady-clock timer at ``rate_hz`` answers the newest state
  received since the last tick (older ones are skipped and counted).
* Models: the node starts on the base model f_hat when ``run_dir`` holds no checkpoint. A
  :class:`~saml_ros.core.model_watch.ModelWatcher` follows ``learner/checkpoint`` and polls ``run_dir``
  (``latest``) as a fallback, loads new checkpoints on a background thread and the control step swaps the
  ready model in between two solves. Incompatible or corrupt checkpoints are refused (log + counter +
  ``mpc/status`` ``checkpoints_refused``) and the current model is kept.
* Deadline: a control step (swap + solve + publish, from the state's arrival in lockstep or the timer tick in
  realtime) that takes longer than ``deadline_ms`` counts as a deadline miss.

Wiring only: the parameters are :class:`saml_ros.core.mpc.config.MPCConfig`'s, the work is
:class:`saml_ros.core.mpc.service.MPCService`'s. See docs/nodes.md for the parameters and examples.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from typing import Any

import numpy as np
import rclpy
import torch
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from sensor_msgs.msg import JointState
from std_msgs.msg import String

from msg_schemas import CHECKPOINT_QOS, DATA_QOS, RCLPY, TELEMETRY_QOS, SchemaError, get_schema
from msg_schemas.telemetry import (
    CHECKPOINT_TOPIC,
    DIAGNOSTICS_TOPIC,
    MPC_STATUS_TOPIC,
    OK,
    WARN,
    DiagnosticEntry,
    checkpoint_from_msg,
    diagnostics_to_msg,
    mpc_status_to_msg,
)
from saml_ros.core.mpc.config import MPCConfig
from saml_ros.core.mpc.service import Answer, MPCService
from saml_ros.core.mpc.shooting.qp import DEFAULT_BACKEND as QP_BACKEND
from saml_ros.core.systems import get_entry
from saml_ros.nodes.params import declare_params, probe_system
from saml_ros.nodes.runtime import catch_stop_signals, full_argv, init_rclpy, shutdown, spin_until_stopped, wants_help

#: exit code for invalid parameters (as argparse's usage errors)
USAGE_ERROR = 2


class MPCNode(Node):
    """See the module docstring; raises ``ValueError`` naming the parameter on bad configuration."""

    def __init__(self, system_name: str, namespace: str | None = None) -> None:
        super().__init__("mpc", namespace=namespace)
        self.config = config = MPCConfig.from_params(declare_params(self, MPCConfig.params(system_name)))
        if config.system != system_name:
            raise ValueError(f"parameter system={config.system!r} does not match the node's system {system_name!r}")
        self.schema = get_schema(system_name)
        self.cmd_pub = self.create_publisher(RCLPY.cls(self.schema.control.msg_type), self.schema.cmd_topic,
                                             DATA_QOS.to_rclpy())
        self.service = MPCService(config, self._send, self.get_logger())
        self.service.start()
        self.status_pub = self.create_publisher(JointState, MPC_STATUS_TOPIC, TELEMETRY_QOS.to_rclpy())
        self.diag_pub = self.create_publisher(DiagnosticArray, DIAGNOSTICS_TOPIC, TELEMETRY_QOS.to_rclpy())
        self.create_subscription(RCLPY.cls(self.schema.state.msg_type), self.schema.state_topic, self._on_state,
                                 DATA_QOS.to_rclpy())
        self.create_subscription(String, CHECKPOINT_TOPIC, self._on_checkpoint, CHECKPOINT_QOS.to_rclpy())
        steady = Clock(clock_type=ClockType.STEADY_TIME)
        if config.mode == "realtime":
            self.create_timer(1.0 / config.rate_hz, self._on_tick, clock=steady)
        self.create_timer(1.0 / max(config.diagnostics_rate, 1e-3), self._publish_diagnostics, clock=steady)
        horizon = f"T={config.horizon}" if get_entry(system_name).mpc_horizon else "one-shot"
        self.get_logger().info(
            f"{system_name} MPC ({config.solver}{', QP ' + QP_BACKEND if config.solver == 'fast' else ''}, "
            f"{horizon}, {config.mode}{f' at {config.rate_hz:g} Hz' if config.mode == 'realtime' else ''}, "
            f"deadline {1e3 * self.service.deadline_s:.0f} ms), goal {config.goal!r}, run_dir "
            f"{config.run_dir or '(none)'}"
        )

    # ------------------------------------------------------------------------------------------ callbacks
    def _on_checkpoint(self, msg: Any) -> None:
        try:
            info = checkpoint_from_msg(msg, CHECKPOINT_TOPIC)
        except SchemaError as exc:
            self.service.reject(exc.reason, str(exc))
            return
        self.service.notify(info.path, info.version, info.schema_hash)

    def _on_state(self, msg: Any) -> None:
        t_arrival = time.perf_counter()
        try:
            x, stamp = self.schema.state_from_msg(msg, self.schema.state_topic)
        except SchemaError as exc:
            self.service.reject(exc.reason, str(exc))
            return
        self._publish_status(self.service.receive(x, stamp, t_arrival))

    def _on_tick(self) -> None:
        self._publish_status(self.service.tick())

    # ------------------------------------------------------------------------------------------ publishing
    def _send(self, u: np.ndarray, stamp: int) -> None:
        self.cmd_pub.publish(self.schema.control_to_msg(u, stamp))

    def _publish_status(self, answer: Answer | None) -> None:
        if answer is not None:
            stamp, values = answer
            self.status_pub.publish(mpc_status_to_msg(values, stamp))

    def diagnostic_values(self) -> dict[str, Any]:
        """What ``/diagnostics`` reports (counters, model in use, checkpoint statistics)."""
        return self.service.diagnostic_values()

    def _publish_diagnostics(self) -> None:
        values = self.diagnostic_values()
        refused = values["checkpoints_refused"]
        version = self.service.model_version
        rollbacks = self.service.counters["rollbacks"]
        level = WARN if refused or rollbacks or self.service.counters["solver_errors"] else OK
        message = (f"model version {version}; {values['solves']} solves" if "solves" in values
                   else f"model version {version}; waiting for states")
        if refused:
            message += f"; {refused} checkpoint(s) refused, last: {values['last_refusal']}"
        if rollbacks:
            message += (f"; {rollbacks} roll back(s) by the live monitor (versions "
                        f"{values.get('guard_rolled_back_versions', '')} not used again)")
        entry = DiagnosticEntry(self.get_fully_qualified_name(), level, message, values)
        self.diag_pub.publish(diagnostics_to_msg([entry], self.get_clock().now().nanoseconds))

    def destroy_node(self) -> None:
        self.service.stop()
        super().destroy_node()


# ---------------------------------------------------------------------------------------------- main
def create_node() -> MPCNode:
    """Create the MPC node (``rclpy.init`` must have been called with ``args``).

    The node lives in ``/<system>`` unless the command line remaps ``__ns``: a probe node reads ``system``
    first, because the namespace must be known when the node is created.
    """
    system, remapped = probe_system("mpc")
    get_entry(system)  # a clear error for an unknown name
    return MPCNode(system, None if remapped else f"/{system}")


def main(argv: Sequence[str] | None = None) -> int:
    """``mpc [--ros-args ...]``: run the node until SIGINT / SIGTERM (exit 0); bad parameters exit 2."""
    args = full_argv("mpc", argv)
    if wants_help(args):
        print(__doc__)
        print("usage: mpc --ros-args [-p system:=quadrotor] [-p mode:=lockstep] [--params-file config/mpc.yaml] "
              "[-r __ns:=/quadrotor]")
        return 0
    stop = catch_stop_signals()
    torch.set_num_threads(1)  # checkpoints are tiny; extra threads would only contend for the cores
    init_rclpy(args)
    node = None
    try:
        try:
            node = create_node()
        except (ValueError, TypeError) as exc:
            rclpy.logging.get_logger("mpc").fatal(f"configuration error: {exc}")
            return USAGE_ERROR
        spin_until_stopped(node, stop)
        return 0
    finally:
        shutdown(node)


if __name__ == "__main__":
    raise SystemExit(main())
