"""The arm's own controller: reaches through random targets, half of them on the shelf in front of the arm (the
reaching task), the others anywhere in the workspace, publishing joint torques at 100 Hz on its own timer.

    python examples/arm/controller.py --ros-args -r __ns:=/arm -p seed:=1

It reads ``joint_states`` (sensor_msgs/JointState) and publishes ``effort_controller/commands``
(std_msgs/Float64MultiArray, ``[tau_shoulder, tau_elbow]`` in N*m; the topic and type of ros2_control's
effort ``forward_command_controller``). Each move is a minimum-jerk joint trajectory to the target, tracked by
computed torque with the *nominal* model (``arm_model.py``: no payload, friction or spring, so it tracks
imperfectly, as a real arm's controller does), then a hold; random gains per move and coloured noise on the
torque explore the states and commands, so the data covers the workspace. The timer is not synchronised with
the joint states: each tick uses the newest one; when that is older than 50 ms (the arm's driver stalled) it
holds the arm against gravity instead of tracking, and starts the move again from the next fresh state. Nothing
here uses saml_ros.
"""

from __future__ import annotations

import math
import signal
import sys
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from arm_model import bias, inverse_kinematics, mass_matrix  # noqa: E402

#: the shelf: the gripper targets of the reaching task, ``x`` and ``z`` ranges (m) relative to the shoulder
SHELF = ((0.45, 0.75), (-0.20, 0.20))
#: joint-space targets elsewhere stay this far inside these ranges (rad); the joint limits are in arm.xml
Q_RANGE = ((-2.2, 1.7), (-2.3, 2.3))
TAU_MAX = np.array([30.0, 15.0])  # N*m, the motors' ranges


class Reacher:
    """The controller without ROS: :meth:`command` maps the time and the measured state to a torque.

    Args:
        seed: targets, gains and exploration noise.
        task_fraction: share of the targets on the shelf.
        noise: torque noise std (N*m) per joint (Ornstein-Uhlenbeck, correlation time ``noise_tau`` s).
        stale_after: a measured state older than this (s) is stale (see :meth:`command`).
        homing: seconds of a start-up routine first (0: none): slow small moves around the rest pose (hanging
            down), as a real arm's homing or calibration does before it starts its task.
    """

    def __init__(self, seed: int = 0, task_fraction: float = 0.5, noise: tuple[float, float] = (1.5, 0.6),
                 noise_tau: float = 0.15, stale_after: float = 0.05, homing: float = 0.0) -> None:
        self.rng = np.random.default_rng(seed)
        self.homing = homing
        self.t_start: float | None = None
        self.stale_after = stale_after
        self.stale = 0  # commands computed from a stale state
        self.task_fraction = task_fraction
        self.noise_std = np.asarray(noise, dtype=np.float64)
        self.noise_tau = noise_tau
        self.ou = np.zeros(2)
        self.t_last: float | None = None
        self.segment: dict[str, Any] | None = None
        self.targets = 0

    def new_target(self) -> np.ndarray:
        """A shelf target (elbow up) with probability ``task_fraction``, else a random reachable posture."""
        if self.rng.random() < self.task_fraction:
            (x0, x1), (z0, z1) = SHELF
            q = inverse_kinematics(float(self.rng.uniform(x0, x1)), float(self.rng.uniform(z0, z1)))
            if q is not None:
                return q
        return np.array([self.rng.uniform(*Q_RANGE[0]), self.rng.uniform(*Q_RANGE[1])])

    def plan(self, t: float, q: np.ndarray) -> None:
        if self.t_start is None:
            self.t_start = t
        if t - self.t_start < self.homing:  # start-up: slow, small moves around the rest pose
            goal = np.array([-np.pi / 2, 0.0]) + self.rng.uniform(-0.3, 0.3, 2)
            speed = float(self.rng.uniform(0.2, 0.5))
        else:
            goal = self.new_target()
            speed = float(self.rng.uniform(0.8, 2.5))  # rad/s, mean joint speed of the move
        duration = float(np.clip(np.max(np.abs(goal - q)) / speed, 0.4, 3.0))
        omega = float(self.rng.uniform(6.0, 14.0))  # rad/s, closed-loop bandwidth of this move
        self.segment = {"t0": t, "q0": q.copy(), "goal": goal, "T": duration,
                        "hold": float(self.rng.uniform(0.2, 1.0)), "kp": omega**2, "kd": 2.0 * 0.8 * omega}
        self.targets += 1

    def reference(self, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Minimum-jerk position, velocity, acceleration of the current move at time ``t``."""
        s = self.segment
        assert s is not None
        tau = min(max((t - s["t0"]) / s["T"], 0.0), 1.0)
        d = s["goal"] - s["q0"]
        p = 10 * tau**3 - 15 * tau**4 + 6 * tau**5
        v = (30 * tau**2 - 60 * tau**3 + 30 * tau**4) / s["T"]
        a = (60 * tau - 180 * tau**2 + 120 * tau**3) / s["T"] ** 2
        if tau >= 1.0:
            v = a = 0.0
        return s["q0"] + p * d, v * d, a * d

    def command(self, t: float, q: np.ndarray, dq: np.ndarray, age: float = 0.0) -> np.ndarray:
        """Torque ``(2,)`` (N*m) at time ``t`` (s) for the measured angles ``q`` (rad) and rates ``dq`` (rad/s),
        measured ``age`` s ago. A state older than ``stale_after`` gets the nominal gravity hold at ``q`` (tracking a
        reference that moves on while the measurements stand still would wind the arm up), and the move restarts
        from the next fresh state."""
        if age > self.stale_after:
            self.segment = None
            self.stale += 1
            return np.clip(bias(q, np.zeros(2)), -TAU_MAX, TAU_MAX)
        if self.segment is None or t > self.segment["t0"] + self.segment["T"] + self.segment["hold"]:
            self.plan(t, q)
        s = self.segment
        assert s is not None
        q_ref, dq_ref, ddq_ref = self.reference(t)
        acc = ddq_ref + s["kp"] * (q_ref - q) + s["kd"] * (dq_ref - dq)
        tau = mass_matrix(q) @ acc + bias(q, dq)
        h = 0.0 if self.t_last is None else min(max(t - self.t_last, 0.0), 0.1)
        self.t_last = t
        a = math.exp(-h / self.noise_tau)
        self.ou = a * self.ou + math.sqrt(1.0 - a * a) * self.noise_std * self.rng.normal(size=2)
        return np.clip(tau + self.ou, -TAU_MAX, TAU_MAX)


def main() -> int:
    import rclpy
    from rcl_interfaces.msg import ParameterDescriptor
    from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
    from rclpy.node import Node
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from rclpy.signals import SignalHandlerOptions
    from sensor_msgs.msg import JointState
    from std_msgs.msg import Float64MultiArray

    class ControllerNode(Node):
        def __init__(self) -> None:
            super().__init__("arm_controller")
            number = ParameterDescriptor(dynamic_typing=True)  # -p homing:=20 as well as homing:=20.0

            def param(name: str, default: float, ok: Any, what: str) -> float:
                value = self.declare_parameter(name, default, number).value
                if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value) \
                        or not ok(value):
                    raise SystemExit(f"arm_controller: parameter {name!r} must be {what}, got {value!r}")
                return float(value)

            seed = int(self.declare_parameter("seed", 0).value)
            rate = param("rate", 100.0, lambda v: v > 0, "a rate > 0 (Hz)")
            fraction = param("task_fraction", 0.5, lambda v: 0 <= v <= 1, "in [0, 1]")
            homing = param("homing", 0.0, lambda v: v >= 0, "a duration >= 0 (s)")
            self.reacher = Reacher(seed=seed, task_fraction=fraction, homing=homing)
            qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
            self.pub = self.create_publisher(Float64MultiArray, "effort_controller/commands", qos)
            self.create_subscription(JointState, "joint_states", self.on_state, qos)
            self.state: tuple[np.ndarray, np.ndarray, int] | None = None
            self.create_timer(1.0 / rate, self.tick)

        def on_state(self, msg: JointState) -> None:
            try:
                i, j = msg.name.index("shoulder"), msg.name.index("elbow")
                self.state = (np.array([msg.position[i], msg.position[j]]),
                              np.array([msg.velocity[i], msg.velocity[j]]),
                              msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec)
            except (ValueError, IndexError):
                self.get_logger().warning("joint_states without shoulder / elbow position and velocity", once=True)

        def tick(self) -> None:
            if self.state is None:
                return
            now = self.get_clock().now().nanoseconds
            q, dq, stamp = self.state
            tau = self.reacher.command(now / 1e9, q, dq, age=(now - stamp) / 1e9)
            self.pub.publish(Float64MultiArray(data=[float(v) for v in tau]))

    rclpy.init(args=sys.argv, signal_handler_options=SignalHandlerOptions.NO)
    node = ControllerNode()
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
    node.get_logger().info(f"stopped after {node.reacher.targets} targets ({node.reacher.stale} commands held on a "
                           "stale state)")
    node.destroy_node()
    rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
