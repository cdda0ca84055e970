"""An MPC node process and the test's side of it (a stock rclpy node that sends states, collects the stamped
commands, ``mpc/status`` and ``/diagnostics``), shared by the MPC node tests."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from helpers import REPO
from helpers.ros_helpers import dying_with_test

rclpy = pytest.importorskip("rclpy")


# --------------------------------------------------------------------------------------- node (ROS)
DT_NS = 100_000_000  # quadrotor dt = 0.1 s
T0_NS = 1_000_000_000


class MPCProcess:
    """``python -m saml_ros.executables mpc --ros-args ...`` in its own process group, log in a file."""

    def __init__(self, tmp: Path, domain: int, params: dict[str, Any], ns: str = "/quadrotor") -> None:
        self.log_path = tmp / f"mpc-{time.monotonic_ns()}.log"
        args = [sys.executable, "-m", "saml_ros.executables", "mpc", "--ros-args", "-r", f"__ns:={ns}"]
        for k, v in params.items():
            args += ["-p", f"{k}:={v}"]
        env = dict(os.environ, ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
                   PYTHONUNBUFFERED="1")
        env["PYTHONPATH"] = str(REPO) + os.pathsep + env.get("PYTHONPATH", "")
        self._log = open(self.log_path, "wb")  # noqa: SIM115 - closed in stop()
        self.proc = subprocess.Popen(dying_with_test(args), cwd=tmp, env=env, stdout=self._log,
                                     stderr=subprocess.STDOUT,
                                     process_group=0)

    def log(self) -> str:
        return self.log_path.read_text(errors="replace")

    def stop(self, sig: int = signal.SIGINT, timeout: float = 20.0) -> int:
        try:
            if self.proc.poll() is None:
                os.killpg(self.proc.pid, sig)
            return self.proc.wait(timeout)
        except subprocess.TimeoutExpired:
            os.killpg(self.proc.pid, signal.SIGKILL)
            self.proc.wait(5)
            raise AssertionError(f"mpc ignored {sig}:\n{self.log()}") from None
        finally:
            self._log.close()


class Probe:
    """The test's own rclpy node in the quadrotor namespace: publishes states, collects cmd / status / diagnostics."""

    def __init__(self, domain: int) -> None:
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.executors import SingleThreadedExecutor
        from sensor_msgs.msg import JointState
        from std_msgs.msg import String

        from msg_schemas import CHECKPOINT_QOS, DATA_QOS, RCLPY, TELEMETRY_QOS, get_schema

        os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
        self.ctx = rclpy.Context()
        rclpy.init(context=self.ctx, domain_id=domain)
        self.schema = get_schema("quadrotor")
        self.node = rclpy.create_node("probe", namespace="/quadrotor", context=self.ctx)
        self.executor = SingleThreadedExecutor(context=self.ctx)
        self.executor.add_node(self.node)
        self.cmds: dict[int, np.ndarray] = {}
        self.status: list[dict[str, float]] = []
        self.diag: dict[str, str] = {}
        self.state_pub = self.node.create_publisher(RCLPY.cls(self.schema.state.msg_type), "state",
                                                    DATA_QOS.to_rclpy())
        self.ckpt_pub = self.node.create_publisher(String, "learner/checkpoint", CHECKPOINT_QOS.to_rclpy())
        self.cmd_sub = self.node.create_subscription(JointState, "cmd", self._on_cmd, DATA_QOS.to_rclpy())
        self.node.create_subscription(JointState, "mpc/status", self._on_status, TELEMETRY_QOS.to_rclpy())
        self.node.create_subscription(DiagnosticArray, "/diagnostics", self._on_diag, TELEMETRY_QOS.to_rclpy())

    def _on_cmd(self, msg: Any) -> None:
        u, stamp = self.schema.control_from_msg(msg)
        assert stamp not in self.cmds, f"two commands for the state stamped {stamp}"
        self.cmds[stamp] = u

    def _on_status(self, msg: Any) -> None:
        from msg_schemas.telemetry import mpc_status_from_msg

        self.status.append(mpc_status_from_msg(msg)[0])

    def _on_diag(self, msg: Any) -> None:
        from msg_schemas.telemetry import diagnostics_from_msg

        for entry in diagnostics_from_msg(msg)[0]:
            if entry.name == "/quadrotor/mpc":
                self.diag = dict(entry.values)

    def spin_until(self, pred: Any, timeout: float, what: str | Callable[[], str],
                   proc: MPCProcess | None = None) -> None:
        deadline = time.monotonic() + timeout
        while not pred():
            if time.monotonic() > deadline:
                what = what() if callable(what) else what
                raise AssertionError(f"timed out waiting for {what}" + (f"\n{proc.log()}" if proc else ""))
            if proc is not None and proc.proc.poll() is not None:
                what = what() if callable(what) else what
                raise AssertionError(f"mpc exited ({proc.proc.returncode}) while waiting for {what}\n{proc.log()}")
            self.executor.spin_once(timeout_sec=0.02)

    def wait_connected(self, proc: MPCProcess, timeout: float = 60.0) -> None:
        """Until both sides of both directions matched: the probe's state writer and cmd reader (seen here), and
        the node's state reader (its ``state_publishers`` on /diagnostics). A loaded suite run lost the first
        state to a node whose reader had not matched the probe yet, though the probe's writer had."""
        self.spin_until(lambda: self.state_pub.get_subscription_count() > 0 and self.cmd_sub.get_publisher_count() > 0,
                        timeout, lambda: (f"the MPC node (state subscribers {self.state_pub.get_subscription_count()}"
                                          f", cmd publishers {self.cmd_sub.get_publisher_count()})"), proc)
        # the node's side, from its 1 Hz /diagnostics: a loaded run once saw none from it for 60 s with both
        # directions matched here, so wait for it a while, then let the first step tell
        deadline = time.monotonic() + 15.0
        while float(self.diag.get("state_publishers", 0)) < 1 and time.monotonic() < deadline:
            self.executor.spin_once(timeout_sec=0.05)

    def step(self, x: np.ndarray, stamp: int, proc: MPCProcess, timeout: float = 10.0) -> np.ndarray:
        """Publish state ``x`` stamped ``stamp`` and wait for the answer (like a lockstep simulator)."""
        self.state_pub.publish(self.schema.state_to_msg(x, stamp))
        self.spin_until(lambda: stamp in self.cmds, timeout, f"the cmd stamped {stamp}", proc)
        return self.cmds[stamp]

    def close(self) -> None:
        self.node.destroy_node()
        rclpy.shutdown(context=self.ctx)
