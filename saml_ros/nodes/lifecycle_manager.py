"""``lifecycle_manager``: brings managed nodes up through their lifecycle services, then exits.

The launch files start the learner and the MPC with ``autostart: false`` and this node beside them (Jazzy's XML
launch front end has no ``<lifecycle_node>``; launch_ros exposes it, with ``autostart``, only in later
distributions): it requests ``transitions`` (default configure, then activate) of every node in ``node_names``
(default ``[learner, mpc]``, relative to its namespace) and exits 0 when all made them, 1 otherwise (the failing
node logs why and stays where it was, e.g. unconfigured). Usage::

    ros2 run saml_ros lifecycle_manager --ros-args -r __ns:=/friction -p node_names:="[learner, mpc]"
"""

from __future__ import annotations

from collections.abc import Sequence

from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node

from msg_schemas.names import join_topic
from saml_ros.core.errors import SamlError
from saml_ros.core.runtime.lifecycle import MANAGER_PARAMS, check_manager_params
from saml_ros.nodes.lifecycle_client import drive
from saml_ros.nodes.ros_params import ParamGuard, start_params
from saml_ros.nodes.runtime import catch_stop_signals, full_argv, init_rclpy, process_main, shutdown, wants_help

#: exit code for invalid parameters
USAGE_ERROR = 2


@process_main
def main(argv: Sequence[str] | None = None) -> int:
    """``lifecycle_manager [--ros-args ...]``: 0 when every node made every transition, 1 otherwise."""
    stop = catch_stop_signals()
    args = full_argv("lifecycle_manager", argv)
    if wants_help(args):
        print(__doc__)
        return 0
    init_rclpy(args)
    node = Node("lifecycle_manager")
    try:
        try:
            p = start_params(node, MANAGER_PARAMS, check_manager_params)
            transitions = check_manager_params(p)
        except SamlError as exc:
            node.get_logger().fatal(f"configuration error: {exc}")
            return USAGE_ERROR
        ParamGuard(node, MANAGER_PARAMS, check_manager_params)  # every parameter is read at start-up
        fqns = [join_topic(node.get_namespace(), n) for n in p["node_names"]]
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        node.get_logger().info(f"requesting {' -> '.join(transitions)} of {', '.join(fqns)}")
        errors = drive(node, lambda t: executor.spin_once(timeout_sec=t), fqns, transitions, float(p["timeout"]),
                       cancelled=lambda: bool(stop["signal"]))
        for error in errors:
            node.get_logger().error(error)
        if not errors:
            node.get_logger().info(f"{', '.join(fqns)}: {transitions[-1] if transitions else 'nothing'} done")
        return 1 if errors else 0
    finally:
        shutdown(node)


if __name__ == "__main__":
    raise SystemExit(main())
