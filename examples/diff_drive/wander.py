"""A stand-in for the operator or the robot's own planner: drives the example base around its arena, often
through the dock approach, publishing unstamped ``cmd_vel`` (geometry_msgs/Twist) at 10 Hz.

    python examples/diff_drive/wander.py --ros-args -r __ns:=/dd -p seed:=1

It follows random waypoints (the first and ``dock_fraction`` of the others in the dock approach, the rest anywhere
in the arena)
with a proportional heading controller, random speed and command noise, so the data covers the workspace and
the commands. Nothing here uses saml_ros.
"""

from __future__ import annotations

import math
import signal
import sys
from typing import Any

import numpy as np
import rclpy
from geometry_msgs.msg import Twist
from nav_msgs.msg import Odometry
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rclpy.signals import SignalHandlerOptions

DOCK_BOX = ((0.8, 1.8), (-0.4, 0.4))
ARENA = 2.0


class Wander(Node):
    def __init__(self) -> None:
        super().__init__("wander")
        self.rng = np.random.default_rng(int(self.declare_parameter("seed", 0).value))
        self.dock_fraction = float(self.declare_parameter("dock_fraction", 0.5).value)
        rate = float(self.declare_parameter("rate", 10.0).value)
        qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
        self.pub = self.create_publisher(Twist, "cmd_vel", qos)
        self.create_subscription(Odometry, "odom", self.on_odom, qos)
        self.pose: tuple[float, float, float] | None = None
        (x0, x1), (y0, y1) = DOCK_BOX
        self.goal = (float(self.rng.uniform(x0, x1)), float(self.rng.uniform(y0, y1)))  # it starts by docking
        self.speed = 0.3
        self.create_timer(1.0 / rate, self.tick)

    def new_goal(self) -> tuple[float, float]:
        if self.rng.random() < self.dock_fraction:
            (x0, x1), (y0, y1) = DOCK_BOX
            return float(self.rng.uniform(x0, x1)), float(self.rng.uniform(y0, y1))
        return float(self.rng.uniform(-ARENA, ARENA)), float(self.rng.uniform(-ARENA, ARENA))

    def on_odom(self, msg: Odometry) -> None:
        q = msg.pose.pose.orientation
        yaw = math.atan2(2 * (q.w * q.z + q.x * q.y), 1 - 2 * (q.y * q.y + q.z * q.z))
        self.pose = (msg.pose.pose.position.x, msg.pose.pose.position.y, yaw)

    def tick(self) -> None:
        cmd = Twist()
        if self.pose is not None:
            x, y, yaw = self.pose
            dx, dy = self.goal[0] - x, self.goal[1] - y
            if math.hypot(dx, dy) < 0.15:
                self.goal = self.new_goal()
                self.speed = float(self.rng.uniform(0.1, 0.5))
            err = (math.atan2(dy, dx) - yaw + math.pi) % (2 * math.pi) - math.pi
            v = self.speed * max(0.0, math.cos(err)) + self.rng.normal(0.0, 0.05)
            w = 2.0 * err + self.rng.normal(0.0, 0.2)
            cmd.linear.x = float(np.clip(v, -0.5, 0.5))
            cmd.angular.z = float(np.clip(w, -1.5, 1.5))
        self.pub.publish(cmd)


def main(argv: Any = None) -> int:
    rclpy.init(args=sys.argv, signal_handler_options=SignalHandlerOptions.NO)
    node = Wander()
    done = [False]
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: done.__setitem__(0, True))
    ex = SingleThreadedExecutor()
    ex.add_node(node)
    try:
        while not done[0]:
            ex.spin_once(timeout_sec=0.05)
    except ExternalShutdownException:
        pass
    node.destroy_node()
    rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
