"""What the ROS benchmarks share: a private ROS domain id, stopping a node process they started, and the friction
transition publisher of their publisher children."""

from __future__ import annotations

import contextlib
import fcntl
import os
import signal
import subprocess
import tempfile
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

#: the same claim files as test/ros_helpers.py, so a benchmark never shares a ROS domain with a test run
CLAIM_DIR = Path(tempfile.gettempdir()) / "saml_ros_ros_domains"


@contextlib.contextmanager
def claimed_domain() -> Iterator[int]:
    """A ROS_DOMAIN_ID in 1..100 that no other claiming process uses (an flock per id, held while inside)."""
    CLAIM_DIR.mkdir(parents=True, exist_ok=True)
    start = os.getpid() % 100
    for i in range(100):
        domain = 1 + (start + i) % 100
        fd = os.open(CLAIM_DIR / f"{domain}.lock", os.O_CREAT | os.O_RDWR, 0o666)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            os.close(fd)
            continue
        try:
            yield domain
        finally:
            os.close(fd)
        return
    raise RuntimeError("every ROS domain id 1..100 is claimed")


def interrupt(proc: subprocess.Popen[Any], timeout: float = 10.0) -> None:
    """SIGINT ``proc`` (a node's clean shutdown) and wait up to ``timeout`` s for it; then SIGKILL its process
    group (``proc`` must have been started with ``start_new_session=True``)."""
    proc.send_signal(signal.SIGINT)
    try:
        proc.wait(timeout)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(10)


@dataclass
class FrictionPublisher:
    """A spinning rclpy node publishing friction ``state`` and ``applied_cmd`` under a namespace (DATA_QOS)."""

    node: Any
    executor: Any
    schema: Any
    system: Any
    state: Any
    applied: Any

    def close(self) -> None:
        """Stop spinning, destroy the node, shut rclpy down."""
        import rclpy

        self.executor.shutdown()
        self.node.destroy_node()
        rclpy.try_shutdown()

    def wait_matched(self, want: int, timeout: float) -> int:
        """Wait until both topics have ``want`` matched subscriptions (or ``timeout`` s); returns the state
        topic's count."""
        deadline = time.monotonic() + timeout
        while min(self.state.get_subscription_count(), self.applied.get_subscription_count()) < want and \
                time.monotonic() < deadline:
            time.sleep(0.05)
        return int(self.state.get_subscription_count())


def friction_publisher(node_name: str, namespace: str) -> FrictionPublisher:
    """``rclpy.init()``, a node ``node_name`` with the two friction publishers under ``namespace``, spun by a
    SingleThreadedExecutor in a daemon thread (the publisher children of bench_learner and bench_soak)."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor

    from msg_schemas import DATA_QOS, get_schema
    from saml_ros.core.systems import get_system

    schema = get_schema("friction")
    rclpy.init()
    node = rclpy.create_node(node_name)
    qos = DATA_QOS.to_rclpy()
    jt = type(schema.state_to_msg(np.zeros(2), 0))
    executor = SingleThreadedExecutor()
    out = FrictionPublisher(node, executor, schema, get_system("friction"),
                            node.create_publisher(jt, f"{namespace}/state", qos),
                            node.create_publisher(jt, f"{namespace}/applied_cmd", qos))
    executor.add_node(node)
    threading.Thread(target=executor.spin, daemon=True).start()
    return out
