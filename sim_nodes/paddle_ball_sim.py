"""``paddle_ball_sim``: the MuJoCo paddle-ball world as a ROS 2 node (namespace ``/paddle_ball``).

Node wiring only: the simulator core is :class:`saml_ros.systems.paddle_ball.sim.PaddleBallSim` (its docstring
has the protocol: one step per impact, lockstep and realtime modes, episodes, the safe default), built from
these parameters by :func:`saml_ros.systems.paddle_ball.sim.paddle_ball_simulator`.
"""

from __future__ import annotations

from saml_ros.core.params import LIVE, Param
from sim_nodes.binding import SimBinding
from sim_nodes.sim_node import run

BINDING = SimBinding(
    system="paddle_ball",
    node_name="paddle_ball_sim",
    params=(
        Param("rate_hz", 100.0, "realtime: world updates per wall second (each advances 1 / rate_hz simulated s)"),
        Param("episode_steps", 0, "impacts per episode, then a new drop (0 = until the ball is lost)", when=LIVE),
        Param("initial_state", [], "ball [px, py, pz (m), vx, vy, vz (m/s)] at every episode start; empty = a "
                                   "random bounce (PaddleBallWorld.reset_random)"),
        Param("timestep", 0.002, "MuJoCo physics step (s)"),
        Param("flight_rate_hz", 30.0, "flight odometry samples per simulated second (0 = off)"),
        Param("impact_time_tolerance", 0.005, "an impact further than this (s) from its predicted time is not "
                                              "published for learning (counted off_prediction)"),
    ),
    system_params=(
        ("restitution_true", "restitution the MuJoCo contact is calibrated to"),
        ("normal_bias_y", "unobserved rotation (rad) about world y from the commanded to the real paddle normal"),
        ("g", "gravity (m/s^2)"),
        ("slow_fraction", "fraction of random episode starts that are slow (cushioned) balls"),
    ),
)


#: run the node (``paddle_ball_sim --ros-args ...``)
def main() -> int:
    return run(BINDING)


if __name__ == "__main__":
    raise SystemExit(main())
