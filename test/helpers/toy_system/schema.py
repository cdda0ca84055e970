"""The drag cart's topics: ``state`` (JointState joint ``cart``: position, velocity), ``cmd`` / ``applied_cmd``
(its effort = the acceleration command); the target is the next ``state``."""

from __future__ import annotations

from msg_schemas.base import DATA_QOS, SystemSchema, TopicSpec
from msg_schemas.codecs import JOINT_STATE, JointStateCodec

STATE = JointStateCodec([("p", "m", "cart", "position"), ("v", "m/s", "cart", "velocity")], "cart position, velocity")
CONTROL = JointStateCodec([("a", "m/s^2", "cart", "effort")], "cart acceleration command")
SCHEMA = SystemSchema(
    system="toy_drag_cart", description="A toy cart with drag (test tree).", state=STATE, control=CONTROL,
    target=STATE, target_topic="state", target_pairing="next",
    topics=(TopicSpec("state", JOINT_STATE, DATA_QOS, "sim", "learner, mpc", "x", codec=STATE),
            TopicSpec("cmd", JOINT_STATE, DATA_QOS, "mpc", "sim", "u", codec=CONTROL),
            TopicSpec("applied_cmd", JOINT_STATE, DATA_QOS, "sim", "learner", "u", codec=CONTROL)),
)
