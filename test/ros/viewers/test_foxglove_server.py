"""``foxglove_server`` with real processes: a WebSocket client sees the loop's channels and live CDR messages."""

from __future__ import annotations

import json
import re
import struct
import time
from typing import Any

import pytest
from helpers.ros_helpers import RosDomain, wait_for

from msg_schemas import RCLPY, get_schema

pytest.importorskip("foxglove", reason="foxglove-sdk is optional (requirements.txt installs it)")
websockets_client = pytest.importorskip("websockets.sync.client")

SUBPROTOCOL = "foxglove.sdk.v1"


def _recv_json(ws: Any, op: str, timeout: float = 20.0) -> dict[str, Any]:
    deadline = time.monotonic() + timeout
    while True:
        msg = ws.recv(timeout=max(0.1, deadline - time.monotonic()))
        if isinstance(msg, str):
            data = json.loads(msg)
            if data.get("op") == op:
                return dict(data)


def test_advertises_the_loops_channels_and_forwards_live_cdr(ros_env: RosDomain) -> None:
    from rclpy.serialization import deserialize_message

    from saml_ros.viewers.foxglove_server import ros2msg_schema, served_topics

    sim = ros_env.launch("friction_sim", "-p", "mode:=realtime", "-p", "rate_hz:=50.0", "-p", "start_delay:=0.2",
                         namespace="/friction")
    server = ros_env.launch("foxglove_server", "-p", "system:=friction", "-p", "port:=0")
    found = wait_for(lambda: re.search(r"ws://127\.0\.0\.1:(\d+)", server.output()) or not server.alive(),
                     timeout=60, what="the server to listen")
    assert server.alive(), server.output()
    port = int(found.group(1))
    with websockets_client.connect(f"ws://127.0.0.1:{port}", subprotocols=[SUBPROTOCOL], open_timeout=20) as ws:
        assert ws.subprotocol == SUBPROTOCOL
        assert _recv_json(ws, "serverInfo")["name"] == "saml_ros friction"
        channels = {c["topic"]: c for c in _recv_json(ws, "advertise")["channels"]}
        expected = served_topics("friction", "/friction")
        assert set(channels) == {t.topic for t in expected}
        assert {"/friction/state", "/friction/applied_cmd", "/friction/learner/model_error",
                "/friction/mpc/status", "/diagnostics"} <= set(channels)
        for t in expected:
            c = channels[t.topic]
            assert (c["encoding"], c["schemaName"], c["schemaEncoding"]) == ("cdr", t.msg_type, "ros2msg")
            assert c["schema"] == ros2msg_schema(t.msg_type)
        assert channels["/friction/state"]["schema"].startswith("std_msgs/Header header\nstring[] name")
        ws.send(json.dumps({"op": "subscribe", "subscriptions": [{"id": 3, "channelId": channels["/friction/state"]["id"]}]}))
        deadline = time.monotonic() + 30
        while True:
            msg = ws.recv(timeout=max(0.1, deadline - time.monotonic()))
            if isinstance(msg, bytes) and msg[0] == 1:
                break
        opcode, sub_id, log_time = struct.unpack_from("<BIQ", msg)
        assert (opcode, sub_id) == (1, 3) and abs(log_time - time.time_ns()) < 60e9
        state = deserialize_message(msg[13:], RCLPY.cls("sensor_msgs/msg/JointState"))
        x, stamp = get_schema("friction").state_from_msg(state)
        assert x.shape == (2,) and stamp > 0
    assert sim.alive() and server.alive()
    assert server.stop() == 0, server.output()


def test_serves_a_robot_of_a_system_file(ros_env: RosDomain) -> None:
    """``system_file:=`` (a robot outside the package): its own state and command topics in its namespace; with
    ``system`` beside it the server exits 2 naming both."""
    from helpers import REPO

    system_file = REPO / "examples" / "diff_drive" / "system.yaml"
    server = ros_env.launch("foxglove_server", "-p", f"system_file:={system_file}", "-p", "port:=0", namespace="/dd")
    found = wait_for(lambda: re.search(r"ws://127\.0\.0\.1:(\d+)", server.output()) or not server.alive(),
                     timeout=60, what="the server to listen")
    assert server.alive(), server.output()
    with websockets_client.connect(f"ws://127.0.0.1:{found.group(1)}", subprotocols=[SUBPROTOCOL],
                                   open_timeout=20) as ws:
        assert _recv_json(ws, "serverInfo")["name"] == "saml_ros diff_drive"
        channels = {c["topic"]: c["schemaName"] for c in _recv_json(ws, "advertise")["channels"]}
    assert channels["/dd/odom"] == "nav_msgs/msg/Odometry" and channels["/dd/cmd_vel"] == "geometry_msgs/msg/Twist"
    assert {"/dd/learner/model_error", "/dd/mpc/status", "/diagnostics"} <= set(channels), channels
    assert server.stop() == 0
    both = ros_env.launch("foxglove_server", "-p", f"system_file:={system_file}", "-p", "system:=friction",
                          "-p", "port:=0")
    assert both.wait(60) == 2 and "system_file" in both.output() and "system" in both.output(), both.output()
