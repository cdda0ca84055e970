"""Learner ingest benchmark: lossless transitions/s of the learner node vs a bare rclpy subscriber.

``./dev python -m bench.bench_learner`` (about 4 minutes; ``--part ingest`` 1-2). In one run, on one private ROS domain:

1. a publisher process (stock rclpy, ``DATA_QOS``) sends bursts of friction transitions (``state`` + ``applied_cmd``
   per step, messages built beforehand with msg_schemas) at increasing rates;
2. two subscribers receive every burst at the same time (so both see the same stream and the same machine
   load, which on a shared machine changes from minute to minute): a bare rclpy subscriber process
   (SingleThreadedExecutor, a callback that only counts) and the real learner node
   (``python -m saml_ros.executables learner``), which trains as fast as it can (``updates_per_second: 0``) and
   publishes telemetry meanwhile;
3. a burst is *lossless* for a subscriber when every message arrived (bare: its counts; learner: the messages
   its node took from DDS, from /diagnostics) and, for the learner, every transition of the burst was then
   paired (decoding and pairing run in its training process and may finish a little after the burst; the lag
   is printed). A subscriber fails at a rate when two bursts in a row at that
   rate lose messages (one retry: the machine is shared). Its lossless ceiling is its fastest lossless burst
   below the rate it failed at (each rate is ``--step`` times the previous).

Prints both ceilings (transitions/s; 2 messages per transition) and their ratio (target >= 0.8).

Then (``--part training`` alone) the training process's own speed under its compute settings, without ROS:
primal-dual updates/s per system with subnormals kept (as before) or flushed, and with torch's default thread
count (:mod:`bench.learner_training`).
"""

from __future__ import annotations

import argparse
import contextlib
import math
import os
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import IO, Any

import numpy as np

from bench import learner_training
from bench.ros_procs import claimed_domain, friction_publisher

REPO = Path(__file__).resolve().parents[1]
NS = "/friction"
DT_NS = 100_000_000


# --------------------------------------------------------------------------------------------- children
def run_publisher() -> int:
    """Child: on stdin ``burst RATE N SEGMENT`` publish N transitions at RATE/s, then print ``done SECONDS``."""
    pub = friction_publisher("bench_publisher", NS)
    schema, system, pub_s, pub_c = pub.schema, pub.system, pub.state, pub.applied
    rng = np.random.default_rng(0)
    print("ready", flush=True)
    for line in sys.stdin:
        parts = line.split()
        if not parts:
            continue
        if parts[0] == "wait":  # wait for n matched subscriptions on both topics
            print(f"matched {pub.wait_matched(int(parts[1]), 30.0)}", flush=True)
            continue
        if parts[0] != "burst":
            break
        rate, n, segment = float(parts[1]), int(parts[2]), int(parts[3])
        t0 = (1 + segment * (n + 10) * 2) * DT_NS  # segments never share or neighbour stamps
        x, u = system.sample_inputs(1, rng)
        xs = [x[0]]
        us = rng.uniform(-5, 5, size=(n, 1))
        for k in range(n):
            xs.append(system.true_step_np(xs[-1], us[k]))
        msgs: list[tuple[Any, Any]] = []
        for k in range(n + 1):
            msgs.append((pub_s, schema.state_to_msg(xs[k], t0 + k * DT_NS)))
            if k < n:
                msgs.append((pub_c, schema.control_to_msg(us[k], t0 + k * DT_NS)))
        period = 1.0 / rate  # per transition (two messages)
        start = time.perf_counter()
        for i, (pub, msg) in enumerate(msgs):
            due = start + (i // 2) * period
            while True:
                now = time.perf_counter()
                if now >= due:
                    break
                if due - now > 0.002:
                    time.sleep(due - now - 0.001)
            pub.publish(msg)
        print(f"done {time.perf_counter() - start:.4f}", flush=True)
    pub.close()
    return 0


def run_bare() -> int:
    """Child: a bare subscriber to state and applied_cmd; on stdin ``count`` print ``states cmds``."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from sensor_msgs.msg import JointState

    from msg_schemas import DATA_QOS

    rclpy.init()
    node = rclpy.create_node("bench_bare")
    counts = {"state": 0, "applied_cmd": 0}

    def make(kind: str) -> Any:
        def cb(msg: Any) -> None:
            counts[kind] += 1

        return cb

    for kind in counts:
        node.create_subscription(JointState, f"{NS}/{kind}", make(kind), DATA_QOS.to_rclpy())

    def serve() -> None:
        for line in sys.stdin:
            if line.strip() == "count":
                print(f"{counts['state']} {counts['applied_cmd']}", flush=True)
            else:
                break
        rclpy.try_shutdown()

    threading.Thread(target=serve, daemon=True).start()
    print("ready", flush=True)
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    with contextlib.suppress(Exception):
        executor.spin()
    return 0


# --------------------------------------------------------------------------------------------- orchestrator
class Child:
    """A child process driven by lines on stdin / stdout."""

    def __init__(self, args: Sequence[str], env: dict[str, str], log: IO[bytes] | None = None) -> None:
        self.proc = subprocess.Popen(list(args), stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                     stderr=log if log is not None else subprocess.DEVNULL, env=env, cwd=REPO,
                                     text=True, bufsize=1)

    def ask(self, line: str | None = None) -> str:
        assert self.proc.stdin is not None and self.proc.stdout is not None
        if line is not None:
            self.proc.stdin.write(line + "\n")
            self.proc.stdin.flush()
        out = self.proc.stdout.readline()
        if not out:
            raise RuntimeError(f"child {self.proc.args!r} ended (rc={self.proc.poll()})")
        return out.strip()

    def close(self) -> None:
        with contextlib.suppress(Exception):
            if self.proc.stdin is not None:
                self.proc.stdin.close()
        try:
            self.proc.wait(10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait(5)


class LearnerCounts:
    """Reads the learner's /diagnostics counters (in the orchestrator)."""

    def __init__(self) -> None:
        import rclpy
        from rclpy.executors import SingleThreadedExecutor

        import msg_schemas.telemetry as tele

        self.tele = tele
        self.ctx = rclpy.Context()
        rclpy.init(context=self.ctx)
        self.node = rclpy.create_node("bench_listener", context=self.ctx)
        self.values: dict[str, str] = {}
        self.node.create_subscription(tele.RCLPY.cls(tele.DIAGNOSTIC_ARRAY), tele.DIAGNOSTICS_TOPIC, self._on,
                                      10)
        self.executor = SingleThreadedExecutor(context=self.ctx)
        self.executor.add_node(self.node)
        self.thread = threading.Thread(target=self._spin, daemon=True)
        self.thread.start()

    def _spin(self) -> None:
        with contextlib.suppress(Exception):
            self.executor.spin()

    def _on(self, msg: Any) -> None:
        entries, _ = self.tele.diagnostics_from_msg(msg)
        for e in entries:
            if e.name == f"{NS}/learner":
                self.values = dict(e.values)

    def get(self, key: str) -> int:
        return int(self.values.get(key, "-1"))

    def close(self) -> None:
        self.executor.shutdown(timeout_sec=1.0)
        self.node.destroy_node()
        self.ctx.try_shutdown()


def settle(read: Any, target: float, quiet: float = 0.6, timeout: float = 15.0) -> int:
    """Poll ``read()`` until it reaches ``target`` or stops changing for ``quiet`` s; returns the last value."""
    last, changed = read(), time.monotonic()
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if last >= target:
            return int(last)
        time.sleep(0.1)
        now = read()
        if now != last:
            last, changed = now, time.monotonic()
        elif time.monotonic() - changed > quiet:
            break
    return int(last)


class Subscriber:
    """One subscriber under test.

    Args:
        received: a counter of messages taken from DDS; a burst of n transitions is n + 1 states and n commands.
        paired: for the learner, its count of paired transitions, which must then grow by n (the pairing and
            decoding run in its training process and may finish after the burst: the lag is reported).
    """

    def __init__(self, received: Callable[[], int], paired: Callable[[], int] | None = None) -> None:
        self.received, self.paired = received, paired


def ramp(pub: Child, subscribers: dict[str, Subscriber], rates: list[float], duration: float) -> dict[str, float]:
    """Bursts at increasing rates, every subscriber receiving the same burst, until each has failed.

    A subscriber fails at a rate when two bursts in a row at that rate lose messages (one retry, because the
    machine is shared and a single loss may be another process's CPU spike); for the learner a burst also fails
    if its transitions are not all paired within 30 s. Returns each one's lossless ceiling: the achieved
    transitions/s of its fastest lossless burst below the rate it failed at.
    """
    best = dict.fromkeys(subscribers, 0.0)
    failed: set[str] = set()
    segment = 0
    for rate in rates:
        lost_once: set[str] = set()
        for attempt in range(2):
            n = max(50, int(rate * duration))
            # a failed burst's transitions may still be pairing: wait until the count is still, or they would
            # be counted in this burst (e.g. "paired 14678/7340" in a retry)
            before = {k: (sub.received(), settle(sub.paired, math.inf, quiet=2.0, timeout=30.0) if sub.paired else 0)
                      for k, sub in subscribers.items()}
            reply = pub.ask(f"burst {rate} {n} {segment}")
            segment += 1
            achieved = n / float(reply.split()[1])
            line = f"  {rate:6.0f}/s (published at {achieved:6.0f}/s){' retry' if attempt else '      '}:"
            lost_now: set[str] = set()
            for name, sub in subscribers.items():
                want = 2 * n + 1
                got = settle(lambda r=sub.received, b=before[name][0]: r() - b, want)
                ok = got == want
                note = ""
                if ok and sub.paired is not None:
                    t0 = time.monotonic()
                    paired = settle(lambda r=sub.paired, b=before[name][1]: r() - b, n, quiet=30.0, timeout=30.0)
                    ok = paired == n
                    note = f" paired {paired}/{n} (+{time.monotonic() - t0:.1f} s)"
                if ok:
                    if name not in failed:
                        best[name] = max(best[name], achieved)
                else:
                    lost_now.add(name)
                line += f"  {name} {got}/{want}{note} {'ok' if ok else 'LOSS'}"
            print(line, flush=True)
            if attempt == 0:
                lost_once = lost_now - failed
                if not lost_once:
                    break
            else:
                failed |= lost_once & lost_now
        if failed == set(subscribers):
            break
    return best


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--role", choices=["main", "publisher", "bare"], default="main", help=argparse.SUPPRESS)
    p.add_argument("--start", type=float, default=600.0, help="first rate, transitions/s")
    p.add_argument("--step", type=float, default=1.1, help="rate multiplier between bursts")
    p.add_argument("--max-rate", type=float, default=5000.0, help="last rate tried, transitions/s")
    p.add_argument("--duration", type=float, default=2.0, help="seconds per burst")
    p.add_argument("--part", choices=["all", "ingest", "training"], default="all",
                   help="the ingest ramp, the training-process speed, or both (default)")
    p.add_argument("--train-seconds", type=float, default=3.0, help="training speed: seconds per measurement")
    p.add_argument("--train-rounds", type=int, default=2, help="training speed: rounds (best one counts)")
    p.add_argument("--systems", nargs="+", default=list(learner_training.SYSTEMS), choices=learner_training.SYSTEMS,
                   help="training speed: systems to measure")
    args = p.parse_args(argv)
    if args.role == "publisher":
        return run_publisher()
    if args.role == "bare":
        return run_bare()
    if args.part in ("all", "ingest"):
        ingest(args)
    if args.part in ("all", "training"):
        learner_training.run(args.systems, args.train_seconds, args.train_rounds)
    return 0


def ingest(args: argparse.Namespace) -> None:
    """The ingest ramp (module docstring) with the options of ``main``; prints both ceilings and their ratio."""
    rates = []
    r = args.start
    while r <= args.max_rate:
        rates.append(round(r))
        r *= args.step
    with claimed_domain() as domain:
        env = dict(os.environ, ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
                   PYTHONUNBUFFERED="1")
        env["PYTHONPATH"] = os.pathsep.join(x for x in (str(REPO), env.get("PYTHONPATH", "")) if x)
        os.environ.update(ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
        me = [sys.executable, "-m", "bench.bench_learner"]
        t_start = time.monotonic()
        print(f"learner ingest benchmark (ROS_DOMAIN_ID={domain}, {os.cpu_count()} CPUs, "
              f"load {os.getloadavg()[0]:.1f}); rates in transitions/s, 2 messages each", flush=True)
        pub = Child([*me, "--role", "publisher"], env)
        assert pub.ask() == "ready"
        bare = Child([*me, "--role", "bare"], env)
        assert bare.ask() == "ready"
        listener = LearnerCounts()
        run_dir = Path(tempfile.mkdtemp(prefix="bench_learner_"))
        with open(run_dir / "learner.log", "wb") as log:
            learner = Child([sys.executable, "-m", "saml_ros.executables", "learner", "--ros-args", "-r", f"__ns:={NS}",
                             "-p", "min_transitions:=200", "-p", "updates_per_second:=0.0",
                             "-p", f"run_dir:={run_dir / 'run'}", "-p", "checkpoint_period:=5.0",
                             "-p", "telemetry_rate:=5.0", "-p", "diagnostics_rate:=10.0"], env, log)
            try:
                deadline = time.monotonic() + 90
                while listener.get(f"{NS}/publishers/state") < 1 and time.monotonic() < deadline:
                    time.sleep(0.1)
                pub.ask("wait 2")
                time.sleep(0.5)

                def bare_received() -> int:
                    return sum(int(v) for v in bare.ask("count").split())

                t_ramp = time.monotonic()
                best = ramp(pub, {
                    "bare": Subscriber(bare_received),
                    "learner": Subscriber(
                        lambda: listener.get(f"{NS}/received/state") + listener.get(f"{NS}/received/applied_cmd"),
                        lambda: listener.get(f"{NS}/paired")),
                }, rates, args.duration)
                updates = listener.get("updates")
                ramp_s = time.monotonic() - t_ramp
            finally:
                learner.proc.terminate()
                learner.close()
                listener.close()
                bare.close()
                pub.close()
    bare_best, learner_best = best["bare"], best["learner"]
    ratio = learner_best / bare_best if bare_best > 0 else float("nan")
    print(f"\nlossless ingest ceiling (both subscribed to the same bursts at the same time): bare rclpy subscriber "
          f"{bare_best:.0f} transitions/s ({2 * bare_best:.0f} msg/s), learner {learner_best:.0f} transitions/s "
          f"while training ({updates} updates in the {ramp_s:.0f} s ramp)")
    print(f"ratio learner / bare = {ratio:.2f} (target >= 0.80); {time.monotonic() - t_start:.0f} s")


if __name__ == "__main__":
    raise SystemExit(main())
