"""``quadrotor_sim``: the quadrotor with ground effect as a ROS 2 node (namespace ``/quadrotor``).

State: 13-d rigid body (``state`` is a ``nav_msgs/Odometry``, so 3D viewers show the vehicle); command: four
motor forces (N). Start states like the paper's landing task: x, y ~ U[-2, 2] m, z ~ U[1, 3] m, level, at
rest. Safe default: hover thrust. Ground: the centre of mass stays at or above ``landing_height``
(:func:`saml_ros.systems.quadrotor.world.ground_contact`); a step changed by the ground publishes no ``applied_cmd``.
See docs/simulators.md.
"""

from __future__ import annotations

from saml_ros.core.params import Param
from sim_nodes.binding import SimBinding
from sim_nodes.sim_node import run

BINDING = SimBinding(
    system="quadrotor",
    node_name="quadrotor_sim",
    params=(
        Param("rate_hz", 10.0, "realtime step rate (Hz, wall clock); 1 / system.dt runs in real time"),
        Param("landing_height", 0.1, "height (m) of the centre of mass when the quadrotor stands on the ground; "
                                     "it never goes lower"),
    ),
    system_params=(
        ("dt", "Euler step (s); the MPC must use the same"),
        ("mass", "mass (kg)"),
        ("inertia", "principal moments of inertia [Ixx, Iyy, Izz] (kg m^2)"),
        ("g", "gravity (m/s^2)"),
        ("f_max", "upper motor force bound (N); the lower bound is 0"),
        ("arm_length", "centre-to-motor distance (m), for the propeller heights of the ground effect"),
        ("h_max", "ground-effect ceiling (m): no ground effect above it"),
        ("alpha", "maximum ground-effect fraction in [0, 1] (level, at the ground)"),
        ("drag", "linear air drag (1/s) f_hat does not know: v' -= dt drag v; 0 = none (the paper)"),
        ("wind", "amplitude (m/s^2) of the horizontal wind field above the shelter f_hat does not know; 0 = none"),
        ("wind_length", "wavelength (m) of the wind field in x and y"),
        ("wind_floor", "height (m) below which the air is still (the pad's shelter)"),
        ("wind_ramp", "height (m) over which the wind grows to its full amplitude above wind_floor"),
    ),
)


#: run the node (``quadrotor_sim --ros-args ...``)
def main() -> int:
    return run(BINDING)


if __name__ == "__main__":
    raise SystemExit(main())
