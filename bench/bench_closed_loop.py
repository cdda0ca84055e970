"""Closed-loop latency: quadrotor simulator (lockstep) + MPC node (+ learner), state -> command.

    ./dev python -m bench.bench_closed_loop                # 60 s of simulated time, learner running
    ./dev python -m bench.bench_closed_loop --no-learner --sim-time 20
    ./dev bench closed_loop --no-learner --compare --rounds 2          # before / numpy SQP / after (issue #15)
    ./dev bench closed_loop --no-learner --sim-time 40 --numpy-sqp     # the SQP's numpy path, not its C kernel
    ./dev bench closed_loop --no-learner --mpc demo                    # the demo's MPC settings

Starts the nodes as separate processes (the bringup machinery, private ROS_DOMAIN_ID unless one is set) and
subscribes to ``state`` and ``cmd`` itself: the latency of a step is the arrival time of the ``cmd`` stamped
t_k minus the arrival time of the ``state`` stamped t_k, both in this process (so it includes the MPC's
receive, solve and publish, and one extra DDS hop of the state, which the MPC receives at about the same
time). Also reports the MPC's own control-step time (``mpc/status`` ``step_ms``), its solve time, the lockstep
rate and the steps in which a new model was swapped in. Target: median state -> cmd latency < 10 ms.
"""

from __future__ import annotations

import argparse
import os
import random
import struct
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from saml_ros.bringup import ProcessGroup, child_env, node_argv, ros_params_file

TARGET_MEDIAN_MS = 10.0


def _percentiles(values: Sequence[float]) -> str:
    if not values:
        return "n/a"
    v = np.asarray(values)
    return f"median {np.median(v):6.2f} ms  p99 {np.percentile(v, 99):6.2f} ms  max {v.max():7.2f} ms  (n={v.size})"


def run(sim_time: float, learner: bool, domain_id: int, solver: str, workdir: Path,
        sim_executor: str = "events", mpc_executor: str = "events", cdr: bool = True,
        mpc_extra: dict[str, Any] | None = None, native: bool = True) -> dict[str, Any]:
    """Run the loop for ``sim_time`` simulated seconds; returns the measurements (ms). One function on purpose
    (longer than 80 lines): the probe node's callbacks close over the measurement lists it returns."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from rclpy.signals import SignalHandlerOptions
    from sensor_msgs.msg import JointState

    from msg_schemas import DATA_QOS, RCLPY, TELEMETRY_QOS, get_schema
    from msg_schemas.telemetry import mpc_status_from_msg

    env = child_env(domain_id)
    env["SAML_CDR"] = "1" if cdr else "0"
    env["SAML_MPC_NATIVE"] = "1" if native else "0"
    os.environ["ROS_DOMAIN_ID"] = env["ROS_DOMAIN_ID"]
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = env["ROS_AUTOMATIC_DISCOVERY_RANGE"]
    schema = get_schema("quadrotor")
    ckpt_dir = workdir / "checkpoints"
    params = {
        "sim": {"mode": "lockstep", "episode_steps": 50, "seed": 0, "lockstep_timeout": 5.0,
                "max_sim_time": 0.0, "executor": sim_executor},
        "mpc": {"system": "quadrotor", "solver": solver, "run_dir": str(ckpt_dir), "use_sim_time": True,
                "executor": mpc_executor, **(mpc_extra or {})},
        "learner": {"system": "quadrotor", "run_dir": str(ckpt_dir), "use_sim_time": True, "min_transitions": 200,
                    "checkpoint_period": 1.0},
    }
    files = {}
    for name, values in params.items():
        files[name] = workdir / f"{name}.yaml"
        files[name].write_text(ros_params_file(values))
    procs = ProcessGroup()
    state_t: dict[int, int] = {}
    lat: list[float] = []
    sim_side: list[float] = []  # cmd arrival -> the next state's arrival (ms): the simulator's part of a step
    last_cmd = [0]
    step_ms: list[float] = []
    solve_ms: list[float] = []
    swap_steps: list[float] = []
    swap_ms: list[float] = []
    swap_solve: list[float] = []
    versions: set[int] = set()
    rclpy.init(args=["bench"], signal_handler_options=SignalHandlerOptions.NO)
    node = Node("bench_closed_loop", namespace="/quadrotor")
    first: list[int] = []
    last = [0]

    # state and cmd are taken raw and only their stamps read (the CDR header: sec, nanosec after the 4-byte
    # encapsulation), so this probe's own decoding does not delay its arrival times
    def stamp_of(data: bytes) -> int:
        sec, nanosec = struct.unpack_from("<iI", data, 4)
        return int(sec) * 1_000_000_000 + int(nanosec)

    def on_state(msg: Any) -> None:
        now = time.perf_counter_ns()
        stamp = stamp_of(msg)
        state_t[stamp] = now
        if last_cmd[0]:
            sim_side.append((now - last_cmd[0]) * 1e-6)
            last_cmd[0] = 0
        if not first:
            first.append(stamp)
        last[0] = stamp

    def on_cmd(msg: Any) -> None:
        now = time.perf_counter_ns()
        stamp = stamp_of(msg)
        t = state_t.pop(stamp, None)
        if t is not None:
            lat.append((now - t) * 1e-6)
            last_cmd[0] = now

    def on_status(msg: Any) -> None:
        values, _ = mpc_status_from_msg(msg)
        step_ms.append(values.get("step_ms", float("nan")))
        solve_ms.append(values["solve_time_ms"])
        versions.add(int(values["model_version"]))
        if values.get("swap_ms", 0.0) > 0:
            swap_steps.append(values["step_ms"])
            swap_ms.append(values["swap_ms"])
            swap_solve.append(values["solve_time_ms"])

    node.create_subscription(RCLPY.cls(schema.state.msg_type), "state", on_state, DATA_QOS.to_rclpy(), raw=True)
    node.create_subscription(JointState, "cmd", on_cmd, DATA_QOS.to_rclpy(), raw=True)
    node.create_subscription(JointState, "mpc/status", on_status, TELEMETRY_QOS.to_rclpy())
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    logs = workdir / "logs"
    phases: dict[str, float] = {}
    t_start = time.monotonic()
    try:
        if learner:
            procs.start("learner", node_argv("learner", "/quadrotor", files["learner"]), env, logs / "learner.log")
        procs.start("mpc", node_argv("mpc", "/quadrotor", files["mpc"]), env, logs / "mpc.log")
        want = 2 + int(learner)
        deadline = time.monotonic() + 90
        while node.count_subscribers("/quadrotor/state") < want:
            executor.spin_once(timeout_sec=0.1)
            if time.monotonic() > deadline or procs.exited():
                raise RuntimeError("nodes did not come up; see " + str(logs))
        phases["nodes up"] = time.monotonic() - t_start
        procs.start("sim", node_argv("quadrotor_sim", "/quadrotor", files["sim"]), env, logs / "sim.log")
        t0 = None
        while not first or (last[0] - first[0]) * 1e-9 < sim_time:
            executor.spin_once(timeout_sec=0.05)
            if first and t0 is None:
                t0 = time.monotonic()
                phases["first state"] = t0 - t_start
            if procs.exited():
                raise RuntimeError(f"a node exited early; see {logs}")
        wall = time.monotonic() - (t0 or time.monotonic())
    finally:
        t_stop = time.monotonic()
        codes = procs.stop()
        phases["shutdown"] = time.monotonic() - t_stop
        node.destroy_node()
        rclpy.try_shutdown()
    steps = len(lat)
    return {"latency": lat, "sim_side": sim_side, "step_ms": step_ms, "solve_ms": solve_ms, "swap_steps": swap_steps, "swap_ms": swap_ms,
            "swap_solve": swap_solve,
            "versions": sorted(versions), "wall": wall, "steps": steps, "codes": codes, "phases": phases}


#: the loop's configurations ``--compare`` measures: (simulator executor, MPC executor, CDR fast path, the SQP's C
#: kernel); "before" is the loop before issue #15's second item (MPC on SingleThreadedExecutor, message objects,
#: the numpy SQP), "numpy SQP" today's loop with the SQP's numpy path (SAML_MPC_NATIVE=0)
CONFIGS = {"before": ("events", "single", False, False), "numpy SQP": ("events", "events", True, False),
           "after": ("events", "events", True, True)}


def _report(label: str, r: dict[str, Any], args: argparse.Namespace) -> dict[str, float]:
    """Print one run's measurements; returns the summary numbers."""
    from saml_ros.core.systems import get_system

    lat = r["latency"][5:]  # the first solves include import / allocation warm-up
    speed = r["steps"] * get_system("quadrotor").dt / max(r["wall"], 1e-9)
    med = float(np.median(lat)) if lat else float("nan")
    print(f"[{label}] closed loop: quadrotor_sim (lockstep) + mpc ({args.solver}, {args.mpc} settings)"
          f"{' + learner' if not args.no_learner else ''}; {r['steps']} steps in {r['wall']:.1f} s wall "
          f"({r['steps'] / max(r['wall'], 1e-9):.0f} steps/s); model versions used {r['versions']}; "
          f"load average {', '.join(f'{x:.2f}' for x in os.getloadavg())}")
    print(f"  simulated / wall time: {speed:.1f}x real time ({'meets' if speed >= 30 else 'misses'} the target of "
          f">= 30x on an idle machine)")
    print(f"  state -> cmd latency (this process):  {_percentiles(lat)}")
    print(f"  cmd -> next state (simulator side):    {_percentiles(r['sim_side'][5:])}")
    print(f"  MPC control step (mpc/status step_ms): {_percentiles(r['step_ms'][5:])}")
    print(f"  MPC solve time:                       {_percentiles(r['solve_ms'][5:])}")
    print(f"  MPC step that swapped a model in:      {_percentiles(r['swap_steps'])}")
    print(f"    of which the swap itself:            {_percentiles(r['swap_ms'])}")
    print(f"    and the solve:                       {_percentiles(r['swap_solve'])}")
    verdict = "meets" if med < TARGET_MEDIAN_MS else "MISSES"
    print(f"  median latency {med:.2f} ms {verdict} the target of < {TARGET_MEDIAN_MS:g} ms")
    print("  set-up and shutdown (s): " + ", ".join(f"{k} {v:.1f}" for k, v in r["phases"].items()))
    bad = {k: v for k, v in r["codes"].items() if v != 0}
    if bad:
        print(f"  warning: non-zero exit codes {bad}", file=sys.stderr)
    step = r["step_ms"][5:]
    solve = r["solve_ms"][5:]
    sim_side = r["sim_side"][5:]
    return {"speed": speed, "latency": med, "sim_side": float(np.median(sim_side)) if sim_side else float("nan"), "solve": float(np.median(solve)) if solve else float("nan"),
            "overhead": float(np.median(lat)) - float(np.median(solve)) if lat and solve else float("nan"),
            "step": float(np.median(step)) if step else float("nan"), "load": os.getloadavg()[0]}


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="bench_closed_loop", description=__doc__.splitlines()[0])
    p.add_argument("--sim-time", type=float, default=60.0, help="simulated seconds (dt = 0.1 s per step)")
    p.add_argument("--no-learner", action="store_true", help="simulator + MPC only")
    p.add_argument("--solver", default="fast", choices=("fast", "slsqp"))
    p.add_argument("--mpc", default="plain", choices=("plain", "demo"),
                   help="plain: the MPC node's defaults (goal at the origin) | demo: the demo's MPC section of "
                        "config/bringup_quadrotor.yaml (pad at 0.2 m, tilt bound, guard; f_hat until a model)")
    p.add_argument("--solver-options", default="", help="the MPC's solver_options, e.g. '{max_iter: 3}'")
    p.add_argument("--executor", default="events", choices=("events", "single"), help="the simulator's executor")
    p.add_argument("--mpc-executor", default="events", choices=("events", "single"), help="the MPC's executor")
    p.add_argument("--objects", action="store_true",
                   help="state and cmd as message objects (SAML_CDR=0), not the CDR fast path")
    p.add_argument("--numpy-sqp", action="store_true",
                   help="the fast SQP on its numpy path (SAML_MPC_NATIVE=0), not its C kernel")
    p.add_argument("--compare", action="store_true",
                   help=f"run the configurations {list(CONFIGS)} alternately (--rounds each) and print them side "
                        "by side: before = MPC on SingleThreadedExecutor, message objects and the numpy SQP; numpy "
                        "SQP = today's loop with the SQP's numpy path; after = today's loop")
    p.add_argument("--rounds", type=int, default=2, help="with --compare: runs of each configuration")
    p.add_argument("--domain-id", type=int, default=None, help="ROS_DOMAIN_ID (default: env or random 30..90)")
    args = p.parse_args(argv)
    domain = args.domain_id
    if domain is None:
        domain = int(os.environ["ROS_DOMAIN_ID"]) if "ROS_DOMAIN_ID" in os.environ else random.randint(30, 90)
    mpc_extra: dict[str, Any] = {}
    if args.mpc == "demo":
        from saml_ros.bringup.config import default_config

        mpc_extra = {k: v for k, v in default_config("quadrotor")["mpc"].items() if k != "solver"}
    if args.solver_options:
        mpc_extra["solver_options"] = args.solver_options
    if args.compare:
        plan = [name for _ in range(args.rounds) for name in CONFIGS]
    else:
        CONFIGS["this run"] = (args.executor, args.mpc_executor, not args.objects, not args.numpy_sqp)
        plan = ["this run"]
    rows: list[tuple[str, dict[str, float]]] = []
    for i, name in enumerate(plan):
        sim_ex, mpc_ex, cdr, native = CONFIGS[name]
        label = (f"{name} (sim {sim_ex}, mpc {mpc_ex}, {'CDR' if cdr else 'message objects'}, SQP "
                 f"{'C kernel' if native else 'numpy'})")
        with tempfile.TemporaryDirectory(prefix="bench_closed_loop_") as tmp:
            r = run(args.sim_time, not args.no_learner, domain, args.solver, Path(tmp), sim_ex, mpc_ex, cdr,
                    mpc_extra, native)
        rows.append((name, _report(f"{i + 1}/{len(plan)} {label}", r, args)))
    if args.compare:
        print("\nside by side (medians; overhead = median latency - median solve: transport, decoding, scheduling)")
        print(f"  {'run':<10} {'x real time':>11} {'latency ms':>10} {'solve ms':>8} {'overhead ms':>11} "
              f"{'MPC step ms':>11} {'sim side ms':>11} {'load':>5}")
        for name, v in rows:
            print(f"  {name:<10} {v['speed']:>11.1f} {v['latency']:>10.2f} {v['solve']:>8.2f} {v['overhead']:>11.2f} "
                  f"{v['step']:>11.2f} {v['sim_side']:>11.2f} {v['load']:>5.2f}")
        for name in CONFIGS:
            mine = [v for n, v in rows if n == name]
            print(f"  {name:<10} mean {np.mean([v['speed'] for v in mine]):.1f}x real time, latency "
                  f"{np.mean([v['latency'] for v in mine]):.2f} ms, overhead {np.mean([v['overhead'] for v in mine]):.2f} ms")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
