"""The example robot as its own small ROS 2 node: publishes ``odom`` (nav_msgs/Odometry) at 50 Hz and takes
unstamped ``cmd_vel`` (geometry_msgs/Twist), like a real differential-drive base driver.

    python examples/diff_drive/robot.py --ros-args -r __ns:=/dd -p rate:=50.0

Odometry is stamped with the time of its measurement (a fixed 50 Hz schedule on the ROS clock); the twist is in
``base_link`` (REP 105). A command takes effect at the first control step after it was received and is held; after
``cmd_timeout`` s without one the base stops. Nothing here uses saml_ros.
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
from geometry_msgs.msg import Twist
from nav_msgs.msg import Odometry
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rclpy.signals import SignalHandlerOptions

sys.path.insert(0, str(Path(__file__).resolve().parent))
from dynamics import DiffDrive  # noqa: E402


class Robot(Node):
    def __init__(self) -> None:
        super().__init__("diff_drive_robot")
        self.rate = float(self.declare_parameter("rate", 50.0).value)
        self.cmd_timeout = float(self.declare_parameter("cmd_timeout", 0.5).value)
        x0 = float(self.declare_parameter("x0", 0.0).value)
        self.base = DiffDrive(x=x0)
        qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
        self.pub = self.create_publisher(Odometry, "odom", qos)
        self.create_subscription(Twist, "cmd_vel", self.on_cmd, qos)
        self.lock = threading.Lock()
        self.cmds: list[tuple[int, np.ndarray]] = []  # (receipt time ns, command), oldest first
        self.stop = threading.Event()
        self.steps = 0

    def on_cmd(self, msg: Twist, info: Any) -> None:
        t = int(info["received_timestamp"]) if info else self.get_clock().now().nanoseconds
        with self.lock:
            self.cmds.append((t, np.array([msg.linear.x, msg.angular.z])))

    def command_at(self, t_ns: int) -> np.ndarray:
        """The last command received at or before ``t_ns`` (zero after ``cmd_timeout`` without one)."""
        with self.lock:
            while len(self.cmds) > 1 and self.cmds[1][0] <= t_ns:
                self.cmds.pop(0)
            if not self.cmds or self.cmds[0][0] > t_ns or t_ns - self.cmds[0][0] > self.cmd_timeout * 1e9:
                return np.zeros(2)
            return self.cmds[0][1]

    def publish(self, t_ns: int) -> None:
        x, y, yaw, v, w = self.base.state()
        m = Odometry()
        m.header.stamp.sec, m.header.stamp.nanosec = divmod(t_ns, 1_000_000_000)
        m.header.frame_id, m.child_frame_id = "odom", "base_link"
        m.pose.pose.position.x, m.pose.pose.position.y = float(x), float(y)
        m.pose.pose.orientation.z, m.pose.pose.orientation.w = math.sin(yaw / 2), math.cos(yaw / 2)
        m.twist.twist.linear.x, m.twist.twist.angular.z = float(v), float(w)
        self.pub.publish(m)

    def run(self) -> None:
        """Fixed-rate control loop: measure and publish at t_k, apply the command held at t_k until t_k+1."""
        period = int(1e9 / self.rate)
        t_k = self.get_clock().now().nanoseconds
        while not self.stop.is_set():
            self.publish(t_k)
            self.base.step(self.command_at(t_k), period / 1e9)
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
