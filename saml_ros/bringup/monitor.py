"""bringup's ROS layer: the monitor node that reads the loop's topics for progress, the stop condition and the
summary (:class:`Monitor`). The only bringup module that imports rclpy.
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping
from typing import Any

import numpy as np
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from sensor_msgs.msg import JointState
from std_msgs.msg import String

from msg_schemas import CHECKPOINT_QOS, DATA_QOS, RCLPY, TELEMETRY_QOS, SchemaError, get_schema
from msg_schemas.telemetry import (
    CHECKPOINT_TOPIC,
    MODEL_ERROR_TOPIC,
    MPC_STATUS_TOPIC,
    model_error_from_msg,
    mpc_status_from_msg,
)
from saml_ros.bringup.results import BringupResult, EpisodeTracker
from saml_ros.core.systems import get_entry


class Monitor:
    """The bringup's own ROS node: reads the loop's topics for progress, stop condition and summary."""

    def __init__(self, system: str, namespace: str, goal: np.ndarray, result: BringupResult) -> None:
        self.system = get_entry(system).make_system()
        self.schema = get_schema(system)
        self.result = result
        self.namespace = namespace
        self.node = Node("bringup_monitor", namespace=namespace)
        self.executor = SingleThreadedExecutor()
        self.executor.add_node(self.node)
        self.tracker = EpisodeTracker(system, self.system.dt, goal)
        self.model_version = 0
        self.last_error: dict[str, float] = {}
        self.node.create_subscription(RCLPY.cls(self.schema.state.msg_type), self.schema.state_topic,
                                      self._on_state, DATA_QOS.to_rclpy())
        self.node.create_subscription(JointState, MODEL_ERROR_TOPIC, self._on_error, TELEMETRY_QOS.to_rclpy())
        self.node.create_subscription(JointState, MPC_STATUS_TOPIC, self._on_status, TELEMETRY_QOS.to_rclpy())
        self.node.create_subscription(String, CHECKPOINT_TOPIC, self._on_checkpoint, CHECKPOINT_QOS.to_rclpy())

    def _on_state(self, msg: Any) -> None:
        try:
            x, stamp = self.schema.state_from_msg(msg)
        except SchemaError:
            return
        self.result.states += 1
        ep = self.tracker.add(x, stamp, self.model_version)
        if ep is not None:
            self.result.episodes.append(ep)
        self.result.sim_time = self.tracker.sim_time

    def _on_error(self, msg: Any) -> None:
        try:
            values, _ = model_error_from_msg(msg)
        except Exception:  # noqa: BLE001 - progress display only
            return
        self.last_error = values
        keys = sorted(k for k in values if k.startswith("error_in/"))
        if keys:
            self.result.constraint = keys[0].split("/", 1)[1]
            self.result.model_error.append((values.get("updates", math.nan), values[keys[0]]))

    def _on_status(self, msg: Any) -> None:
        try:
            values, stamp = mpc_status_from_msg(msg)
        except Exception:  # noqa: BLE001
            return
        self.result.add_status(stamp, values)
        version = int(values["model_version"])
        if not self.result.model_versions or self.result.model_versions[-1] != version:
            self.result.model_versions.append(version)
        self.model_version = version
        self.result.solve_ms.append(values["solve_time_ms"])
        if "step_ms" in values:
            self.result.step_ms.append(values["step_ms"])
        self.result.deadline_misses = int(values["deadline_misses"])
        self.result.checkpoints_refused = int(values.get("checkpoints_refused", 0))

    def _on_checkpoint(self, msg: Any) -> None:
        self.result.checkpoints_announced += 1

    def wait_nodes_up(self, names: Mapping[str, str], timeout: float) -> None:
        """Spin until every node name in ``names.values()`` is in the ROS graph (at most ``timeout`` s)."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            present = {n for n, _ in self.node.get_node_names_and_namespaces()}
            if set(names.values()) <= present:
                return
            self.executor.spin_once(timeout_sec=0.05)

    def subscribers(self, topic: str) -> int:
        return int(self.node.count_subscribers(f"{self.namespace}/{topic}"))

    def progress(self) -> str:
        r = self.result
        err = self.last_error
        k = r.constraint
        e_in = err.get(f"error_in/{k}", math.nan) if k else math.nan
        last_ep = r.episodes[-1] if r.episodes else None
        solve = np.median(r.solve_ms[-50:]) if r.solve_ms else math.nan
        guard = (f", fallbacks {r.guard['guard_fallbacks']:.0f}, roll backs {r.guard['guard_rollbacks']:.0f}"
                 if "guard_rollbacks" in r.guard else "")
        return (f"[bringup] t_sim {r.sim_time:7.1f} s | episodes {len(r.episodes):3d}"
                f"{f' (last error {last_ep.error:.3f} m)' if last_ep else ''} | learner updates "
                f"{err.get('updates', 0):.0f}, error_in {e_in:.4g} | MPC model v{self.model_version}, "
                f"solve {solve:.1f} ms, refused {r.checkpoints_refused}{guard}")
