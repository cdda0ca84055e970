"""The example arm as its own small ROS 2 node, like a real arm's driver: publishes ``joint_states``
(sensor_msgs/JointState: position, velocity and the applied effort of ``shoulder`` and ``elbow``) at 100 Hz and
takes ``effort_controller/commands`` (std_msgs/Float64MultiArray, ``[tau_shoulder, tau_elbow]`` in N*m; the topic and
type of ros2_control's effort ``forward_command_controller``).

    python examples/arm/robot.py --ros-args -r __ns:=/arm -p rate:=100.0 -p seed:=0

Joint states are stamped with the time of their measurement t_k (a fixed-rate schedule on the ROS clock). The
torque applied over [t_k, t_k+1) is the last command received (middleware receipt time) at or before t_k, held;
after ``cmd_timeout`` s without one the motors are switched off (zero torque). The effort reported in the state
message of t_k+1 is that torque. A real driver's command callback runs within microseconds of receipt; this one
runs in Python beside the simulation, so the step waits ``settle`` s after t_k for the callbacks of commands
received before t_k (the simulated physics of the interval does not depend on when it is computed). The physics is
MuJoCo (``sim.py``, ``arm.xml``). Nothing here uses saml_ros.
"""

from __future__ import annotations

import math
import signal
import sys
import threading
from pathlib import Path
from typing import Any

import numpy as np
import rclpy
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rclpy.signals import SignalHandlerOptions
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray

sys.path.insert(0, str(Path(__file__).resolve().parent))
from sim import JOINTS, ArmSim  # noqa: E402


class Robot(Node):
    def __init__(self) -> None:
        super().__init__("arm_robot")
        number = ParameterDescriptor(dynamic_typing=True)  # -p rate:=100 as well as rate:=100.0

        def param(name: str, default: float) -> float:
            value = self.declare_parameter(name, default, number).value
            if isinstance(value, bool) or not isinstance(value, int | float):
                raise SystemExit(f"arm_robot: parameter {name!r} must be a number, got {value!r}")
            return float(value)

        self.rate = param("rate", 100.0)
        self.cmd_timeout = param("cmd_timeout", 0.2)
        seed = int(self.declare_parameter("seed", 0).value)
        noise = param("noise", 1.0)
        self.settle = param("settle", 0.004)
        if not (math.isfinite(self.rate) and self.rate > 0 and math.isfinite(self.cmd_timeout)
                and self.cmd_timeout > 0 and math.isfinite(noise) and noise >= 0
                and math.isfinite(self.settle) and 0 <= self.settle < 0.9 / self.rate):
            raise SystemExit(f"arm_robot: bad parameters rate={self.rate} cmd_timeout={self.cmd_timeout} "
                             f"noise={noise} settle={self.settle} (rate and cmd_timeout must be > 0, noise >= 0, "
                             "0 <= settle < 0.9 / rate)")
        self.arm = ArmSim(seed=seed, noise=noise)
        qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
        self.pub = self.create_publisher(JointState, "joint_states", qos)
        self.create_subscription(Float64MultiArray, "effort_controller/commands", self.on_cmd, qos)
        self.lock = threading.Lock()
        self.cmds: list[tuple[int, np.ndarray]] = []  # (receipt time ns, command), oldest first
        self.stop = threading.Event()
        self.steps = 0
        self.rejected = 0

    def on_cmd(self, msg: Float64MultiArray, info: Any) -> None:
        data = np.asarray(msg.data, dtype=np.float64)
        if data.shape != (2,) or not np.all(np.isfinite(data)):
            self.rejected += 1
            self.get_logger().warning(f"ignored a command of {data.size} values (expected 2 finite torques); "
                                      f"{self.rejected} so far", throttle_duration_sec=5.0)
            return
        t = int(info["received_timestamp"]) if info else self.get_clock().now().nanoseconds
        with self.lock:
            self.cmds.append((t, data))

    def command_at(self, t_ns: int) -> np.ndarray:
        """The last command received at or before ``t_ns`` (zero after ``cmd_timeout`` without one)."""
        with self.lock:
            while len(self.cmds) > 1 and self.cmds[1][0] <= t_ns:
                self.cmds.pop(0)
            if not self.cmds or self.cmds[0][0] > t_ns or t_ns - self.cmds[0][0] > self.cmd_timeout * 1e9:
                return np.zeros(2)
            return self.cmds[0][1]

    def publish(self, t_ns: int) -> None:
        x = self.arm.measure()
        m = JointState()
        m.header.stamp.sec, m.header.stamp.nanosec = divmod(t_ns, 1_000_000_000)
        m.name = list(JOINTS)
        m.position = [float(x[0]), float(x[1])]
        m.velocity = [float(x[2]), float(x[3])]
        m.effort = [float(v) for v in self.arm.applied]
        self.pub.publish(m)

    def run(self) -> None:
        """Fixed-rate loop: measure and publish at t_k, apply the command held at t_k until t_k+1."""
        period = int(1e9 / self.rate)
        settle = int(self.settle * 1e9)
        t_k = self.get_clock().now().nanoseconds
        while not self.stop.is_set():
            self.publish(t_k)
            wait = (t_k + settle - self.get_clock().now().nanoseconds) / 1e9
            if wait > 0:
                self.stop.wait(wait)
            self.arm.step(self.command_at(t_k), period / 1e9)
            self.steps += 1
            t_k += period
            delay = (t_k - self.get_clock().now().nanoseconds) / 1e9
            if delay > 0:
                self.stop.wait(delay)
            elif delay < -1.0:  # fell far behind (machine suspended): skip ahead, do not burst
                t_k = self.get_clock().now().nanoseconds


def main() -> int:
    rclpy.init(args=sys.argv, signal_handler_options=SignalHandlerOptions.NO)
    node = Robot()
    done = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: done.set())
    loop = threading.Thread(target=node.run, daemon=True)
    loop.start()
    ex = SingleThreadedExecutor()
    ex.add_node(node)
    try:
        while not done.is_set():
            ex.spin_once(timeout_sec=0.05)
    except ExternalShutdownException:
        pass
    node.stop.set()
    loop.join(2.0)
    node.get_logger().info(f"stopped after {node.steps} steps")
    node.destroy_node()
    rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
