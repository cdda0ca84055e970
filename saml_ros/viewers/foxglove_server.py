"""``foxglove_server``: one system's loop topics on a Foxglove WebSocket, for set-ups without ``foxglove_bridge``.

    foxglove_server --ros-args -p system:=quadrotor [-p port:=8765] [-p host:=127.0.0.1] [-r __ns:=/robot1]
    foxglove_server --ros-args -p system_file:=examples/diff_drive/system.yaml -r __ns:=/dd

Then open ``ws://HOST:PORT`` in Foxglove (*Open connection* > *Foxglove WebSocket*) and import
``layouts/<system>.foxglove.json``. On a ROS machine with apt, ``ros2 launch foxglove_bridge
foxglove_bridge_launch.xml`` does the same for every topic; this node needs only the ``foxglove-sdk`` package
(PyPI) and serves exactly the loop's topics:

* every topic of the system's schema (``state``, ``cmd``, ``applied_cmd``, ...; a system file's ``state`` and
  ``control`` topics), ``learner/model_error``, ``learner/checkpoint``, ``mpc/status`` in the namespace
  (``/<system>`` unless ``__ns`` is remapped) and ``/diagnostics``;
* each one a channel with encoding ``cdr`` and its ``ros2msg`` schema (the message definition with its
  dependencies, as rosbag2 writes it into MCAP); messages are forwarded as received (serialized, ``raw=True``)
  with the receive time as log time.

SIGINT / SIGTERM stop the server and exit 0; a missing ``foxglove-sdk`` or bad parameters exit 2.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from saml_ros.core.params import Param, Problems, read_params
from saml_ros.nodes.runtime import catch_stop_signals, full_argv, init_rclpy, process_main, shutdown, spin_until_stopped

NODE_NAME = "foxglove_server"
USAGE_ERROR = 2
#: the server's parameters (all read at start-up)
PARAMS: tuple[Param, ...] = (
    Param("system", "friction", "system whose loop topics are served: friction | quadrotor | paddle_ball"),
    Param("system_file", "", "a robot described by a system file (docs/your_robot.md): its own topics are served "
                             "(replaces system)"),
    Param("host", "127.0.0.1", "address the WebSocket server listens on"),
    Param("port", 8765, "TCP port of the WebSocket server (0 = any free port)"),
)

#: parameters that cannot be given together
EXCLUSIVE = (("system", "system_file"),)


def check_params(values: dict[str, Any]) -> dict[str, Any]:
    """The server's parameter values (by name) converted and checked; ``ParamErrors`` naming every bad one."""
    from msg_schemas import get_schema

    problems = Problems()
    p = read_params(PARAMS, values, problems)
    if p.get("system_file"):
        from saml_ros.user_code import load_robot_param

        with problems.capture("system_file"):
            p["system"] = load_robot_param(p["system_file"]).name  # registers the robot's schema by its name
    with problems.capture("system", prefix="parameter 'system': "):
        get_schema(p["system"])
    problems.check(0 <= p["port"] <= 65535, "port", "in 0..65535", p["port"])
    problems.raise_if_any()
    return p


@dataclass(frozen=True)
class ServedTopic:
    """One forwarded topic: absolute name, full message type and the msg_schemas QoS it is read with."""

    topic: str
    msg_type: str
    qos: Any


def served_topics(system: str, namespace: str) -> list[ServedTopic]:
    """What the server forwards for ``system`` in ``namespace`` (ROS-free)."""
    from msg_schemas import get_schema
    from msg_schemas.base import full_topic
    from msg_schemas.telemetry import GLOBAL_TOPICS, TELEMETRY_TOPICS

    ns = namespace.rstrip("/")
    out = [ServedTopic(full_topic(ns, t.name), t.msg_type, t.qos)
           for t in get_schema(system).topics]  # a system file's topic may be absolute
    out += [ServedTopic(f"{ns}/{t.name}", t.msg_type, t.qos) for t in TELEMETRY_TOPICS]
    out += [ServedTopic(t.name, t.msg_type, t.qos) for t in GLOBAL_TOPICS if t.name == "/diagnostics"]
    return out


def ros2msg_schema(msg_type: str) -> str:
    """The ``ros2msg`` schema text of ``msg_type`` (its definition, then each dependency after a ``MSG:`` line)."""
    from saml_ros.bags.io import jazzy_typestore

    text, _ = jazzy_typestore().generate_msgdef(msg_type, ros_version=2)
    return str(text)


def _run(argv: Sequence[str] | None) -> int:
    args = full_argv(NODE_NAME, argv)
    if any(a in ("-h", "--help") for a in args[1:]) and "--ros-args" not in args:
        print(__doc__)
        return 0
    stop = catch_stop_signals()
    try:
        import foxglove
    except ImportError:
        print("foxglove_server: the foxglove-sdk package is not installed (pip install foxglove-sdk)", file=sys.stderr)
        return USAGE_ERROR
    from rclpy.node import Node

    from msg_schemas import RCLPY
    from saml_ros.nodes.ros_params import ParamGuard, start_params

    init_rclpy(args)
    node = None
    server = None
    try:
        node = Node(NODE_NAME)
        try:
            p = check_params(start_params(node, PARAMS, check_params, exclusive=EXCLUSIVE))
        except ValueError as exc:
            node.get_logger().fatal(f"configuration error: {exc}")
            return USAGE_ERROR
        ParamGuard(node, PARAMS, check_params, exclusive=EXCLUSIVE)  # every parameter is read at start-up
        system, host, port = p["system"], p["host"], p["port"]
        namespace = node.get_namespace() if node.get_namespace() != "/" else f"/{system}"
        try:
            server = foxglove.start_server(name=f"saml_ros {system}", host=host, port=port)
        except Exception as exc:  # noqa: BLE001 - e.g. the port is taken: a clear message, not a traceback
            node.get_logger().fatal(f"cannot serve on {host}:{port}: {exc}")
            return USAGE_ERROR
        topics = served_topics(system, namespace)
        received = {t.topic: 0 for t in topics}
        for t in topics:
            schema = foxglove.Schema(name=t.msg_type, encoding="ros2msg", data=ros2msg_schema(t.msg_type).encode())
            channel = foxglove.Channel(t.topic, message_encoding="cdr", schema=schema)

            def forward(data: bytes, channel: Any = channel, topic: str = t.topic) -> None:
                received[topic] += 1
                channel.log(data, log_time=time.time_ns())

            node.create_subscription(RCLPY.cls(t.msg_type), t.topic, forward, t.qos.to_rclpy(), raw=True)
        node.get_logger().info(f"Foxglove WebSocket on ws://{host}:{server.port}: {len(topics)} topics of "
                               f"{system} in {namespace}")
        spin_until_stopped(node, stop)
        node.get_logger().info("forwarded " + ", ".join(f"{k} {v}" for k, v in received.items() if v))
        return 0
    finally:
        if server is not None:
            server.stop()
        shutdown(node)


@process_main
def main(argv: Sequence[str] | None = None) -> int:
    """``foxglove_server [--ros-args ...]``: serve until SIGINT / SIGTERM (exit 0)."""
    return _run(argv)


if __name__ == "__main__":
    raise SystemExit(main())
