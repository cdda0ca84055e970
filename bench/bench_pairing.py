"""Pairing for controllers at the state's rate: ``./dev bench pairing [--part sim|ros|all] [--seeds 6] [--seconds 20]``.

``sim`` (no ROS, seconds): the timing simulator of :mod:`bench.pairing_timing` over several seeds (random delays,
stalls, timer phases); for each timing and robot, each pairing rule's share of intervals paired, lost
(``ambiguous_cmd``, ``no_answer``) and **mis-paired** against the command the simulated robot applied.

``ros`` (real processes, about 2 x ``--seconds``): a zero-order-hold robot node (100 Hz ``nav_msgs/Odometry``,
applies at each step the last ``geometry_msgs/Twist`` it received, and logs it), a controller (first triggered
by each state, then on its own 100 Hz timer) and a listener standing for the learner (stamps each command on
receipt, as the learner does). Prints how far apart the robot's and the listener's receive times of one
command are (what ``command_guard`` must cover), the controller's answer latency, and the pairing of the
listener's stamps by each rule against the robot's own log (paired, lost, mis-paired). Results depend on the
machine's load: run ``uptime`` beside it.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from bench.pairing_timing import DT, MS, T0, N, config, mispaired, run, state, timer, triggered
from saml_ros.core.data.resampling import ResamplingPairer

REPO = Path(__file__).resolve().parents[1]


def _row(name: str, rule: str, counts: list[dict[str, int]], bad: int) -> str:
    n = sum(c["intervals"] for c in counts)

    def pct(key: str) -> str:
        return f"{100.0 * sum(c[key] for c in counts) / max(n, 1):6.1f}"

    return f"{name:<44} {rule:<17} {n:>7} {pct('paired')} {pct('ambiguous_cmd')} {pct('no_answer')} {bad:>10}"


def part_sim(seeds: int) -> None:
    print(f"timing simulator: {seeds} runs of {N} steps at 100 Hz per row (bench/pairing_timing.py)")
    print(f"{'timing / robot':<44} {'rule':<17} {'intervals':>7} {'paired%':>6} {'ambig%':>6} {'no_ans%':>6} "
          f"{'mis-paired':>10}")
    cases: list[tuple[str, dict[str, Any], str, tuple[str, ...]]] = [
        ("state-triggered, answers within the period", {}, "answer", ("hold", "answer")),
        ("state-triggered, stalls over a period", {"stalls": 12, "max_stall": 35 * MS, "cap": None}, "answer",
         ("answer",)),
        ("state-triggered, robot applies at next step", {"stalls": 6, "cap": None}, "next_step",
         ("hold", "answer_next_step")),
    ]
    for name, kw, truth_name, rules in cases:
        sims = [triggered(100 + s, **kw) for s in range(seeds)]
        for rule in rules:
            counts, bad = [], 0
            for sim in sims:
                p = ResamplingPairer(config(cmd_rule=rule, stamped_cmd=False))
                trs = run(p, sim.events)
                truth: dict[int, float | None] = dict(sim.answer if truth_name == "answer" else sim.next_step)
                bad += mispaired(trs, truth)
                counts.append(dict(p.counts))
            print(_row(name, rule, counts, bad))
    rng = np.random.default_rng(0)
    phases = rng.integers(0, DT, seeds)
    counts, bad, racing = [], 0, 0
    for s, phase in enumerate(phases):
        events, truth, _ = timer(200 + s, int(phase))
        p = ResamplingPairer(config(stamped_cmd=False))
        bad += mispaired(run(p, events), truth)
        counts.append(dict(p.counts))
        racing += p.counts["ambiguous_cmd"] > 0
    print(_row("own timer at the state's rate (random phase)", "hold", counts, bad))
    shares = ", ".join(f"{100 * c['paired'] / c['intervals']:.0f}%" for c in counts)
    print(f"  timer phases (ms after the robot's step): {', '.join(f'{p / MS:.1f}' for p in phases)}; "
          f"{racing} of {seeds} lost intervals (commands within command_guard of the robot's step); paired per run: "
          f"{shares}")


# ------------------------------------------------------------------------------------------ real processes
def role_main(role: str, out: str, seconds: float) -> int:
    """One process of the ``ros`` part: ``robot``, ``trigger``, ``timer`` or ``listener``."""
    import rclpy
    from geometry_msgs.msg import Twist
    from nav_msgs.msg import Odometry
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import QoSProfile, ReliabilityPolicy

    rclpy.init()
    node = rclpy.create_node(f"pairing_{role}")
    qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
    lock = threading.Lock()
    log = open(out, "w")  # noqa: SIM115 - closed below

    def write(rec: dict[str, Any]) -> None:
        with lock:
            log.write(json.dumps(rec) + "\n")

    stop = threading.Event()
    if role == "robot":
        pub = node.create_publisher(Odometry, "odom", qos)
        cmds: list[tuple[int, float]] = []

        def on_cmd(msg: Twist, info: Any) -> None:
            t = int(info["received_timestamp"])
            with lock:
                cmds.append((t, float(msg.linear.x)))
            write({"rx": t, "v": float(msg.linear.x)})

        node.create_subscription(Twist, "cmd_vel", on_cmd, qos)  # type: ignore[arg-type]  # (msg, info) form

        def loop() -> None:  # a free-running zero-order-hold loop: publish x_k at t_k, apply the last command
            t = node.get_clock().now().nanoseconds
            k = 0
            while not stop.is_set():
                with lock:
                    got = [v for r, v in cmds if r <= t]
                m = Odometry()
                m.header.stamp.sec, m.header.stamp.nanosec = divmod(t, 1_000_000_000)
                m.pose.pose.position.x = float(k)
                pub.publish(m)
                write({"k": k, "t": t, "applied": got[-1] if got else None})
                k += 1
                t += DT
                delay = (t - node.get_clock().now().nanoseconds) / 1e9
                if delay > 0:
                    stop.wait(delay)

        threading.Thread(target=loop, daemon=True).start()
    elif role in ("trigger", "timer"):
        cpub = node.create_publisher(Twist, "cmd_vel", qos)
        count = [0]

        def send(answers: float) -> None:
            m = Twist()
            m.linear.x = float(count[0])
            count[0] += 1
            cpub.publish(m)
            write({"v": m.linear.x, "answers": answers})

        if role == "trigger":
            node.create_subscription(Odometry, "odom", lambda msg: send(msg.pose.pose.position.x),  # type: ignore[attr-defined]
                                     qos)
        else:
            node.create_timer(DT / 1e9, lambda: send(-1.0))
    else:
        def on(kind: str) -> Any:
            def cb(msg: Any, info: Any) -> None:
                rec: dict[str, Any] = {"kind": kind, "rx": int(info["received_timestamp"])}
                if kind == "cmd":
                    rec["v"] = float(msg.linear.x)
                else:
                    rec["stamp"] = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
                write(rec)
            return cb

        node.create_subscription(Twist, "cmd_vel", on("cmd"), qos)
        node.create_subscription(Odometry, "odom", on("state"), qos)
    ex = SingleThreadedExecutor()
    ex.add_node(node)
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        ex.spin_once(timeout_sec=0.05)
    stop.set()
    time.sleep(0.05)
    with lock:
        log.close()
    node.destroy_node()
    rclpy.try_shutdown()
    return 0


def _read(path: Path) -> list[dict[str, Any]]:
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def _pct(a: np.ndarray, qs: tuple[float, ...]) -> str:
    return ", ".join(f"p{q:g} {v / 1e3:.0f}" for q, v in zip(qs, np.percentile(a, qs), strict=True))


def part_ros(seconds: float, keep: str | None = None) -> None:
    from bench.ros_procs import claimed_domain

    with claimed_domain() as domain, tempfile.TemporaryDirectory(prefix="bench_pairing_") as tmp_dir:
        tmp = keep or tmp_dir
        Path(tmp).mkdir(parents=True, exist_ok=True)
        env = dict(os.environ, ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
                   PYTHONPATH=str(REPO))
        for controller in ("trigger", "timer"):
            d = Path(tmp) / controller
            d.mkdir(exist_ok=True)

            def start(role: str, secs: float, d: Path = d) -> subprocess.Popen[bytes]:
                return subprocess.Popen([sys.executable, "-m", "bench.bench_pairing", "--role", role, "--out",
                                         str(d / f"{role}.jl"), "--seconds", str(secs)], env=env, cwd=REPO)

            procs = [start("robot", seconds + 4), start("listener", seconds + 4)]
            time.sleep(2.0)
            procs.append(start(controller, seconds))
            for proc in procs:
                proc.wait(seconds + 60)
            robot, listener = _read(d / "robot.jl"), _read(d / "listener.jl")
            steps = {r["k"]: r for r in robot if "k" in r}
            robot_rx = {r["v"]: r["rx"] for r in robot if "rx" in r}
            cmds = [r for r in listener if r["kind"] == "cmd"]
            skew = np.array([c["rx"] - robot_rx[c["v"]] for c in cmds if c["v"] in robot_rx], dtype=float)
            print(f"\n{controller} controller, {len(steps)} robot steps, {len(cmds)} commands:")
            print(f"  listener minus robot receive time (us): {_pct(skew, (0.1, 1, 50, 99, 99.9))}, "
                  f"max |.| {np.abs(skew).max() / 1e3:.0f}")
            if controller == "trigger":
                ctrl = {r["v"]: r["answers"] for r in _read(d / "trigger.jl")}
                lat = np.array([c["rx"] - steps[int(ctrl[c["v"]])]["t"] for c in cmds
                                if c["v"] in ctrl and int(ctrl[c["v"]]) in steps], dtype=float)
                print(f"  state stamp to the answer's receipt (us): {_pct(lat, (1, 50, 99, 99.9))}; "
                      f"{100 * np.mean(lat >= DT):.2f}% later than the 10 ms period")
            # pair the listener's stamps as the learner would, against what the robot applied
            t0 = min(r["t"] for r in steps.values())
            truth = {(r["t"] - t0) // DT: r["applied"] for r in steps.values()}
            rules = ("hold", "answer_next_step") if controller == "trigger" else ("hold",)
            for rule in rules:
                events = [(r["rx"], "state", r["stamp"], np.array([(r["stamp"] - t0) / 1e9, 0.0]))
                          for r in listener if r["kind"] == "state"]
                events += [(c["rx"], "applied_cmd", c["rx"], np.array([c["v"]])) for c in cmds]
                pairer = ResamplingPairer(config(cmd_rule=rule, stamped_cmd=False))
                trs = []
                for _, kind, stamp, vec in sorted(events, key=lambda e: (e[0], e[1])):
                    trs += pairer.add(kind, stamp, vec).transitions
                bad = sum(1 for tr in trs if truth.get((tr.stamp_ns - t0) // DT) != tr.u[0])
                c = pairer.counts
                print(f"  pairing '{rule}' (command_guard 2 ms): {c['intervals']} intervals, "
                      f"{100 * c['paired'] / max(c['intervals'], 1):.1f}% paired, "
                      f"{100 * c['ambiguous_cmd'] / max(c['intervals'], 1):.1f}% ambiguous_cmd, mis-paired {bad}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="bench pairing", description=__doc__.split("\n\n")[0])
    ap.add_argument("--part", choices=("sim", "ros", "all"), default="all")
    ap.add_argument("--seeds", type=int, default=6, help="simulated runs per row")
    ap.add_argument("--seconds", type=float, default=20.0, help="length of each real-process run")
    ap.add_argument("--keep", help="keep the real-process logs in this directory")
    ap.add_argument("--role", help=argparse.SUPPRESS)
    ap.add_argument("--out", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.role:
        return role_main(args.role, args.out, args.seconds)
    print(f"load average {os.getloadavg()[0]:.1f} (1 min) on {os.cpu_count()} CPUs")
    if args.part in ("sim", "all"):
        part_sim(args.seeds)
    if args.part in ("ros", "all"):
        part_ros(args.seconds, args.keep)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())


__all__ = ["main", "part_ros", "part_sim", "state", "T0"]
