"""A learner node process and the test's side of it (stock rclpy publishers of the friction system's topics, the
learner's telemetry and /diagnostics), shared by the learner node and disk fault tests."""

from __future__ import annotations

import signal
import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest

from helpers import ros_helpers

DT_NS = 100_000_000  # friction dt = 0.1 s
SYSTEM = "friction"

rclpy = pytest.importorskip("rclpy")


class Learner:
    """One learner process (``python -m saml_ros.executables learner --ros-args -r __ns:=... -p ...``)."""

    def __init__(self, dom: ros_helpers.RosDomain, params: dict[str, Any], ns: str = "/friction",
                 env: dict[str, str] | None = None) -> None:
        self.domain = dom.domain_id
        args: list[str] = []
        for k, v in params.items():
            args += ["-p", f"{k}:={_param(v)}"]
        self.proc = dom.launch("learner", *args, namespace=ns, env=env)

    def log(self) -> str:
        return self.proc.output()

    def wait_log(self, text: str, timeout: float = 90.0) -> None:
        deadline = time.monotonic() + timeout
        while text not in self.log():
            if not self.proc.alive() or time.monotonic() > deadline:
                raise AssertionError(f"{text!r} not in the learner log (rc={self.proc.popen.poll()}):\n{self.log()}")
            time.sleep(0.05)

    def stop(self, sig: int = signal.SIGTERM, timeout: float = 30.0) -> int:
        """Send ``sig`` and return the exit status (negative: killed by a signal)."""
        self.proc.signal(sig)
        rc = self.proc.wait(timeout)
        if rc is None:
            self.proc.stop(1.0)
            raise AssertionError(f"learner ignored signal {sig}:\n{self.log()}")
        return rc


def _param(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, list | tuple):
        return "[" + ", ".join(_param(x) for x in v) + "]"
    return str(v)


class RosSide:
    """The test side: an rclpy context on the learner's domain, publishers per namespace, telemetry log."""

    def __init__(self, domain: int, learner_ns: str = "/friction") -> None:
        from rclpy.executors import SingleThreadedExecutor

        import msg_schemas.telemetry as tele
        from msg_schemas import DATA_QOS, TELEMETRY_QOS, get_schema

        self.tele = tele
        self.schema = get_schema(SYSTEM)
        self.ctx = rclpy.Context()
        rclpy.init(context=self.ctx, domain_id=domain)
        self.node = rclpy.create_node("tester", context=self.ctx)
        self.qos = DATA_QOS.to_rclpy()
        self.pubs: dict[str, tuple[Any, Any]] = {}
        self.lock = threading.Lock()
        self.telemetry: list[dict[str, float]] = []
        self.diag: dict[str, str] = {}
        self.diag_level = -1
        self.diag_message = ""
        self.diag_levels: set[int] = set()
        self.error_messages: list[str] = []
        self.checkpoints: list[Any] = []
        jt = tele.RCLPY.cls(tele.JOINT_STATE)
        self.node.create_subscription(jt, f"{learner_ns}/{tele.MODEL_ERROR_TOPIC}", self._on_error,
                                      TELEMETRY_QOS.to_rclpy())
        self.node.create_subscription(tele.RCLPY.cls(tele.DIAGNOSTIC_ARRAY), tele.DIAGNOSTICS_TOPIC, self._on_diag,
                                      TELEMETRY_QOS.to_rclpy())
        from msg_schemas import CHECKPOINT_QOS

        self.node.create_subscription(tele.RCLPY.cls(tele.STRING), f"{learner_ns}/{tele.CHECKPOINT_TOPIC}",
                                      self._on_ckpt, CHECKPOINT_QOS.to_rclpy())
        self.executor = SingleThreadedExecutor(context=self.ctx)
        self.executor.add_node(self.node)
        self.thread = threading.Thread(target=self._spin, daemon=True)
        self.thread.start()
        self.sent: dict[tuple[str, str], int] = {}

    def _spin(self) -> None:
        try:
            self.executor.spin()
        except Exception:  # noqa: BLE001 - context shut down at close()
            pass

    def _on_error(self, msg: Any) -> None:
        values, _ = self.tele.model_error_from_msg(msg)
        with self.lock:
            self.telemetry.append(values)

    def _on_diag(self, msg: Any) -> None:
        entries, _ = self.tele.diagnostics_from_msg(msg)
        for e in entries:
            if e.name.endswith("/learner"):
                with self.lock:
                    self.diag = dict(e.values)
                    self.diag_level = e.level
                    self.diag_message = e.message
                    self.diag_levels.add(e.level)
                    if e.level == 2:
                        self.error_messages.append(e.message)

    def _on_ckpt(self, msg: Any) -> None:
        with self.lock:
            self.checkpoints.append(self.tele.checkpoint_from_msg(msg))

    def close(self) -> None:
        self.executor.shutdown(timeout_sec=1.0)
        self.node.destroy_node()
        self.ctx.try_shutdown()
        self.thread.join(2.0)

    # -------------------------------------------------------------------------------------- reading
    def last(self) -> dict[str, float]:
        with self.lock:
            return dict(self.telemetry[-1]) if self.telemetry else {}

    def counter(self, key: str) -> int:
        with self.lock:
            return int(self.diag.get(key, "-1"))

    def wait(self, pred: Callable[[], bool], timeout: float, what: str) -> None:
        deadline = time.monotonic() + timeout
        while not pred():
            if time.monotonic() > deadline:
                raise AssertionError(f"timed out waiting for {what}; last telemetry {self.last()}, diag {self.diag}")
            time.sleep(0.02)

    # -------------------------------------------------------------------------------------- sending
    def reset(self) -> None:
        """Forget what the previous learner reported (before talking to a restarted one)."""
        with self.lock:
            self.telemetry.clear()
            self.diag = {}
            self.checkpoints.clear()
        self.sent.clear()

    def connect(self, ns: str, timeout: float = 15.0) -> None:
        """Publishers for ``ns``, once the learner reports (on /diagnostics) that it has matched them: a
        killed learner's subscriptions linger in discovery, so our own publisher's match count is not enough."""
        from sensor_msgs.msg import JointState

        if ns not in self.pubs:
            st = self.node.create_publisher(JointState, f"{ns}/state", self.qos)
            cmd = self.node.create_publisher(JointState, f"{ns}/applied_cmd", self.qos)
            self.pubs[ns] = (st, cmd)
        self.wait(lambda: self.counter(f"{ns}/publishers/state") > 0 and self.counter(f"{ns}/publishers/applied_cmd") > 0,
                  timeout, f"the learner to match our publishers on {ns}")

    def publish(self, ns: str, kind: str, msg: Any, max_outstanding: int = 40) -> None:
        """Publish with flow control: at most ``max_outstanding`` messages per topic not yet counted as received
        by the learner (its /diagnostics counters), so the learner's reader queue (depth 100) never overflows."""
        key = (ns, kind)
        n = self.sent.get(key, 0)
        recv_key = f"{ns}/received/{kind}"
        self.wait(lambda: n - self.counter(recv_key) < max_outstanding, 20.0, f"the learner to receive {key}")
        self.pubs[ns][0 if kind == "state" else 1].publish(msg)
        self.sent[key] = n + 1

    def send(self, ns: str, events: list[tuple[str, int, np.ndarray]]) -> None:
        sc = self.schema
        for kind, stamp, vec in events:
            msg = sc.state_to_msg(vec, stamp) if kind == "state" else sc.control_to_msg(vec, stamp)
            self.publish(ns, kind, msg)

    def wait_received(self, ns: str, timeout: float = 20.0) -> None:
        for kind in ("state", "applied_cmd"):
            n = self.sent.get((ns, kind), 0)
            self.wait(lambda k=kind, n=n: self.counter(f"{ns}/received/{k}") >= n, timeout,  # type: ignore[misc]
                      f"{ns} to receive {n} {kind}")


def episodes(n_transitions: int, rng: np.random.Generator, t0: int, ep_len: int = 6,
             interleave: bool = True) -> list[tuple[str, int, np.ndarray]]:
    """Friction episodes from the paper's input distribution, in a publish order with interleavings.

    Follows the simulator contract: the last state of an episode has no applied_cmd and the next episode starts
    3 dt later. With ``interleave`` some commands go before their state and some after the next state.
    """
    from saml_ros.core.systems import get_system

    system = get_system(SYSTEM)
    events: list[tuple[str, int, np.ndarray]] = []
    t, done = t0, 0
    while done < n_transitions:
        x, _ = system.sample_inputs(1, rng)
        xk = x[0]
        steps = min(ep_len, n_transitions - done)
        ep: list[tuple[str, int, np.ndarray]] = []
        for _ in range(steps):
            _, u = system.sample_inputs(1, rng)
            ep += [("state", t, xk), ("applied_cmd", t, u[0])]
            xk = system.true_step_np(xk, u[0])
            t += DT_NS
            done += 1
        ep.append(("state", t, xk))
        if interleave:  # reorder across the two topics only: each topic stays in stamp order, as DDS keeps it
            keys, last_cmd = [], -1.0
            for i, (kind, _, _) in enumerate(ep):
                k = i // 2
                if kind == "state":
                    keys.append(10.0 * k)
                else:
                    key = 10.0 * k + float(rng.choice([-1.0, 1.0, 11.0]))  # before, after its state, after the next
                    last_cmd = max(key, last_cmd + 0.1)
                    keys.append(last_cmd)
            ep = [e for _, e in sorted(zip(keys, ep), key=lambda p: p[0])]
        events += ep
        t += 3 * DT_NS
    return events

BASE_PARAMS: dict[str, Any] = {
    "telemetry_rate": 20.0,
    "diagnostics_rate": 20.0,
    "checkpoint_period": 1.0,
    "train.batch_size": 128,
    "train.primal_lr": 0.003,
    "train.dual_lr": 0.01,
}
