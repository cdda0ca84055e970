"""Messages the msg_schemas tests share: the rosbags typestore, random vectors of each system and one message of
every type saml_ros publishes."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
from rosbags.typesys import Stores, get_typestore

from msg_schemas import TypestoreFactory, get_schema
from msg_schemas import telemetry as tm

TS = get_typestore(Stores.ROS2_JAZZY)

BAGS = TypestoreFactory(TS)


def unit_quat(rng: np.random.Generator) -> np.ndarray:
    """A random unit quaternion ``(4,)``."""
    q = rng.normal(size=4)
    return q / np.linalg.norm(q)


def random_vector(system: str, role: str, rng: np.random.Generator) -> np.ndarray:
    """A random ``role`` vector (state, control, target) of ``system`` (the quadrotor's quaternion a unit one)."""
    codec = getattr(get_schema(system), role)
    x = rng.normal(scale=3.0, size=codec.size)
    if system == "quadrotor" and role in ("state", "target"):
        x[6:10] = unit_quat(rng)
    return x


def one_message_per_type() -> list[tuple[str, Callable[[Any], Any]]]:
    """(type name, build(factory)) for one message of every type saml_ros publishes."""
    rng = np.random.default_rng(7)
    friction_x = random_vector("friction", "state", rng)
    quad_x = random_vector("quadrotor", "state", rng)
    quad_u = random_vector("quadrotor", "control", rng)
    ball_y = random_vector("paddle_ball", "target", rng)
    metrics = {n: 0.5 * i for i, n in enumerate(tm.model_error_names(["near_origin"]))}
    stamp = 1_234_567_890_123
    entry = tm.DiagnosticEntry("/quadrotor/learner", tm.WARN, "dropping", {"rejected/nan": 3})
    info = tm.CheckpointInfo("/tmp/run/ckpt-000003.saml", 3, "0123456789abcdef", 12.5)
    return [
        ("sensor_msgs/msg/JointState", lambda f: get_schema("friction").state_to_msg(friction_x, stamp, factory=f)),
        ("sensor_msgs/msg/JointState", lambda f: get_schema("quadrotor").control_to_msg(quad_u, stamp, factory=f)),
        ("sensor_msgs/msg/JointState", lambda f: tm.model_error_to_msg(metrics, stamp, factory=f)),
        ("nav_msgs/msg/Odometry", lambda f: get_schema("quadrotor").state_to_msg(quad_x, stamp, factory=f)),
        ("geometry_msgs/msg/TwistStamped", lambda f: get_schema("paddle_ball").target_to_msg(ball_y, stamp, factory=f)),
        ("std_msgs/msg/String", lambda f: tm.checkpoint_to_msg(info, factory=f)),
        ("diagnostic_msgs/msg/DiagnosticArray", lambda f: tm.diagnostics_to_msg([entry], stamp, factory=f)),
        ("rosgraph_msgs/msg/Clock", lambda f: tm.clock_to_msg(stamp, factory=f)),
    ]
