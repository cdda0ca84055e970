"""``friction_sim``: the double integrator with friction as a ROS 2 node (namespace ``/friction``).

State ``[p (m), v (m/s)]``, command ``[u (m/s^2)]``, dt = ``system.dt`` (0.1 s). Start states: the paper's MPC
starts, p ~ U[-2, 2] m, v = 0. Safe default u = 0. See docs/simulators.md for parameters and protocol.
"""

from __future__ import annotations

from saml_ros.core.params import Param
from sim_nodes.binding import SimBinding
from sim_nodes.sim_node import run

BINDING = SimBinding(
    system="friction",
    node_name="friction_sim",
    params=(Param("rate_hz", 10.0, "realtime step rate (Hz, wall clock); 1 / system.dt runs in real time"),),
    system_params=(
        ("dt", "sampling period (s); the MPC must use the same"),
        ("u_max", "control bound |u| <= u_max (m/s^2)"),
        ("mu_base", "friction deceleration everywhere (m/s^2)"),
        ("bumps", "friction bumps, flat [amplitude (m/s^2), centre (m), width (m), ...]"),
    ),
)


#: run the node (``friction_sim --ros-args ...``)
def main() -> int:
    return run(BINDING)


if __name__ == "__main__":
    raise SystemExit(main())
