"""Double integrator with friction (namespace ``/friction``): a cart on a line.

* ``state`` (x = [p (m), v (m/s)]): ``sensor_msgs/JointState``, one joint ``cart``, ``position = [p]``,
  ``velocity = [v]``.
* ``cmd`` / ``applied_cmd`` (u = [u (m/s^2)], an acceleration command, i.e. force per unit mass):
  ``sensor_msgs/JointState``, joint ``cart``, ``effort = [u]``.
* target = the next ``state`` message (x_{t+1}, stamped one period later).
"""

from __future__ import annotations

from msg_schemas.base import DATA_QOS, SystemSchema, TopicSpec
from msg_schemas.codecs import JOINT_STATE, JointStateCodec

STATE = JointStateCodec(
    [("p", "m", "cart", "position"), ("v", "m/s", "cart", "velocity")],
    "JointState joint 'cart': position = p, velocity = v",
)
CONTROL = JointStateCodec(
    [("u", "m/s^2", "cart", "effort")],
    "JointState joint 'cart': effort = u (acceleration command, force per unit mass)",
)

SCHEMA = SystemSchema(
    system="friction",
    description="1-D double integrator with position-dependent friction; x = [p, v], u = [u].",
    state=STATE,
    control=CONTROL,
    target=STATE,
    topics=(
        TopicSpec("state", JOINT_STATE, DATA_QOS, "friction_sim", "learner, mpc, record",
                  "x_t, stamped with the simulated time of the sample.", codec=STATE),
        TopicSpec("cmd", JOINT_STATE, DATA_QOS, "mpc", "friction_sim, record",
                  "u_t requested by the MPC, stamped with the state it answers.", codec=CONTROL),
        TopicSpec("applied_cmd", JOINT_STATE, DATA_QOS, "friction_sim", "learner, record",
                  "u_t actually applied over [t, t + dt), stamped like x_t.", codec=CONTROL),
    ),
    target_topic="state",
    target_pairing="next",
)  # fmt: skip
