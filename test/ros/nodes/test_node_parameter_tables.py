"""The launch files (launch/*.launch.xml), checked by evaluating them (``launch`` is not on PyPI; launch_parse.py).

* every node they start is a saml_ros executable, every parameter file exists, every ``$(var)`` is declared;
* every parameter they set, in a file or inline, is one the node declares (from the tables the nodes declare
  from, test/node_params.py; one test asks real nodes that the tables are what they declare);
* the managed nodes (learner, MPC) start with ``autostart: false`` and a ``lifecycle_manager`` activates exactly
  them, as bringup does;
* the closed loops give each node exactly bringup's parameters for the system (the registry entry's
  ``bringup`` defaults through bringup.default_config and bringup.node_params),
  so ``ros2 launch saml_ros <system>.launch.xml`` and ``bringup --system <system>`` cannot drift apart.
"""

from __future__ import annotations

from helpers.node_params import declared_parameters, table_parameters

from saml_ros.core.systems.registry import SYSTEM_NAMES

SYSTEMS = SYSTEM_NAMES


def test_the_parameter_tables_are_what_the_running_nodes_declare() -> None:
    """Real processes (ListParameters, as ``ros2 param list``): each simulator and MPC (their tables depend on
    the system), the learner (its table does not), the recorder and the lifecycle manager."""
    targets = ({(f"{s}_sim", s) for s in SYSTEMS} | {("mpc", s) for s in SYSTEMS}
               | {("learner", "friction"), ("record", "friction"), ("lifecycle_manager", "friction")})
    for target, names in declared_parameters(targets).items():
        assert names == table_parameters(*target), target
