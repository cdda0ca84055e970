"""Ball bouncing on a paddle (namespace ``/paddle_ball``); event based: one transition per impact.

* ``state`` (x = [px, py, pz, vx, vy, vz], the ball just before the next impact): ``nav_msgs/Odometry``,
  ``frame_id = "world"``, ``child_frame_id = "ball"``, orientation identity, so ``twist.linear`` is the
  world velocity. One message per impact, stamped with the impact time; the MPC answers it.
* ``cmd`` / ``applied_cmd`` (u = [pvx, pvy, pvz, nx, ny, nz]: paddle velocity at impact (m/s) and paddle
  normal): ``sensor_msgs/JointState`` used as a stamped named vector: names ``paddle_vx, paddle_vy,
  paddle_vz, normal_x, normal_y, normal_z``, values in ``position``.
* ``post_impact`` (target y = [vx, vy, vz], the ball velocity just after the impact):
  ``geometry_msgs/TwistStamped``, ``frame_id = "world"``, ``twist.linear``. Stamped exactly like the
  ``state`` and ``applied_cmd`` of the same impact: the learner pairs the three by identical stamp.
* ``flight`` (optional): continuous ball odometry during flight for 3D viewers, same layout as ``state``;
  not used for learning.
"""

from __future__ import annotations

from msg_schemas.base import DATA_QOS, TELEMETRY_QOS, SystemSchema, TopicSpec
from msg_schemas.codecs import JOINT_STATE, ODOMETRY, TWIST_STAMPED, JointStateCodec, LinearVelocityCodec, OdometryCodec

STATE = OdometryCodec(rigid_body=False, frame_id="world", child_frame_id="ball", units=("m",) * 3 + ("m/s",) * 3)
_CONTROL_FIELDS = [
    ("pvx", "m/s", "paddle_vx"), ("pvy", "m/s", "paddle_vy"), ("pvz", "m/s", "paddle_vz"),
    ("nx", "1", "normal_x"), ("ny", "1", "normal_y"), ("nz", "1", "normal_z"),
]  # fmt: skip
CONTROL = JointStateCodec(
    [(f, u, joint, "position") for f, u, joint in _CONTROL_FIELDS],
    "JointState as a stamped named vector: paddle velocity and paddle normal in position",
)
TARGET = LinearVelocityCodec(frame_id="world")

SCHEMA = SystemSchema(
    system="paddle_ball",
    description="Ball bouncing on a paddle; x = ball just before impact, u = paddle velocity + normal, "
    "y = ball velocity just after impact.",
    state=STATE,
    control=CONTROL,
    target=TARGET,
    topics=(
        TopicSpec("state", ODOMETRY, DATA_QOS, "paddle_ball_sim", "learner, mpc, record",
                  "x_t: the ball just before the next impact, one message per impact, stamped with the impact "
                  "time.", codec=STATE),
        TopicSpec("cmd", JOINT_STATE, DATA_QOS, "mpc", "paddle_ball_sim, record",
                  "u_t: the impact command the MPC chose, stamped with the state it answers.", codec=CONTROL),
        TopicSpec("applied_cmd", JOINT_STATE, DATA_QOS, "paddle_ball_sim", "learner, record",
                  "u_t actually applied at the impact, stamped like x_t.", codec=CONTROL),
        TopicSpec("post_impact", TWIST_STAMPED, DATA_QOS, "paddle_ball_sim", "learner, mpc (guard.rollback), record",
                  "y_t: the ball velocity just after the impact (world frame), stamped like x_t.", codec=TARGET),
        TopicSpec("flight", ODOMETRY, TELEMETRY_QOS, "paddle_ball_sim", "3D viewers",
                  "Ball odometry during flight (same layout as state) for visualisation; not used for "
                  "learning.", codec=STATE, required=False),
    ),
    target_topic="post_impact",
    target_pairing="same",
)  # fmt: skip
