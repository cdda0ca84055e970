"""msg_schemas: vector <-> stock message round trips (rclpy and rosbags), wire bytes, validation, docs."""

from __future__ import annotations

import os
import subprocess
import sys
import time

from helpers.messages import BAGS, TS, one_message_per_type

from msg_schemas import RCLPY
from msg_schemas.base import DATA_QOS


def test_import_is_light() -> None:
    code = "import sys, msg_schemas.docs; print(sorted({m.split('.')[0] for m in sys.modules} & {'rclpy', 'rosbags', 'torch'}))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=True)
    assert out.stdout.strip() == "[]"


def test_bytes_on_the_wire_equal_rosbags_bytes() -> None:
    """What a node publishes is byte-identical to what the bag tools write for the same vector."""
    import rclpy
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node

    cases = one_message_per_type()
    ctx = Context()
    rclpy.init(context=ctx, domain_id=60 + os.getpid() % 40)
    node = Node("msg_schemas_wire_test", context=ctx)
    try:
        received: list[list[bytes]] = [[] for _ in cases]
        pubs = []
        for i, (_, build) in enumerate(cases):
            cls = type(build(RCLPY))
            topic = f"/msg_schemas_test_{os.getpid()}/t{i}"
            node.create_subscription(cls, topic, received[i].append, DATA_QOS.to_rclpy(), raw=True)
            pubs.append(node.create_publisher(cls, topic, DATA_QOS.to_rclpy()))
        executor = SingleThreadedExecutor(context=ctx)
        executor.add_node(node)
        deadline = time.monotonic() + 15
        while not all(received) and time.monotonic() < deadline:
            for pub, got, (_, build) in zip(pubs, received, cases, strict=True):
                if not got:
                    pub.publish(build(RCLPY))
            executor.spin_once(timeout_sec=0.05)
        assert all(received), "no message received within 15 s"
        for (type_name, build), got in zip(cases, received, strict=True):
            assert got[0] == bytes(TS.serialize_cdr(build(BAGS), type_name)), type_name
    finally:
        node.destroy_node()
        ctx.try_shutdown()
