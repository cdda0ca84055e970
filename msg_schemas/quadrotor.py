"""Quadrotor with ground effect (namespace ``/quadrotor``).

* ``state`` (x = [px, py, pz, vx, vy, vz, qw, qx, qy, qz, wx, wy, wz]): ``nav_msgs/Odometry`` with
  ``frame_id = "world"``, ``child_frame_id = "base_link"``; pose = position + orientation; per REP 105 the
  twist is in the child (body) frame: ``twist.linear = R(q)^T [vx, vy, vz]`` (the state's velocity is in the
  world frame, the conversion is exact both ways) and ``twist.angular`` = the body rates ``[wx, wy, wz]``.
  Any 3D viewer shows the body from this message.
* ``cmd`` / ``applied_cmd`` (u = [f1, f2, f3, f4] (N)): ``sensor_msgs/JointState`` joints
  ``rotor1 .. rotor4`` with ``effort`` = motor forces.
* target = the next ``state`` message.
"""

from __future__ import annotations

from msg_schemas.base import DATA_QOS, SystemSchema, TopicSpec
from msg_schemas.codecs import JOINT_STATE, ODOMETRY, JointStateCodec, OdometryCodec

STATE = OdometryCodec(
    rigid_body=True,
    frame_id="world",
    child_frame_id="base_link",
    units=("m",) * 3 + ("m/s",) * 3 + ("1",) * 4 + ("rad/s",) * 3,
)
CONTROL = JointStateCodec(
    [(f"f{i}", "N", f"rotor{i}", "effort") for i in range(1, 5)],
    "JointState joints rotor1..rotor4: effort = motor force",
)

SCHEMA = SystemSchema(
    system="quadrotor",
    description="Quadrotor landing with ground effect; 13-d rigid-body state, 4 motor forces.",
    state=STATE,
    control=CONTROL,
    target=STATE,
    topics=(
        TopicSpec("state", ODOMETRY, DATA_QOS, "quadrotor_sim", "learner, mpc, record",
                  "x_t (pose in world, twist in base_link), stamped with the simulated time.", codec=STATE),
        TopicSpec("cmd", JOINT_STATE, DATA_QOS, "mpc", "quadrotor_sim, record",
                  "u_t requested by the MPC, stamped with the state it answers.", codec=CONTROL),
        TopicSpec("applied_cmd", JOINT_STATE, DATA_QOS, "quadrotor_sim", "learner, record",
                  "u_t actually applied over [t, t + dt) (after clipping to [0, f_max]), stamped like x_t.",
                  codec=CONTROL),
    ),
    target_topic="state",
    target_pairing="next",
)  # fmt: skip
