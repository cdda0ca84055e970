"""Lockstep simulator speed: ``./dev python -m bench.bench_sim [--system quadrotor] [--steps 3000]``.

Prints three numbers measured in one run, each as steps per second and as a multiple of real time
(steps/s * dt):

1. ``core``: the ROS-free :class:`~saml_ros.core.worlds.sim_core.SteppedSim` answered in a Python loop (the simulator's
   own cost: validation, ``true_step``, ground contact, stamping);
2. ``core + messages`` (message objects) and ``core + CDR messages`` (the CDR bytes of :mod:`msg_schemas.cdr`,
   what the node writes and reads now): the same plus every message conversion a lockstep step makes (``msg_schemas``:
   decode ``cmd``, encode ``applied_cmd``, ``/clock`` and ``state``), still without DDS;
3. ``node``: the real simulator node (``<system>_sim`` in lockstep, its own process) answered by a minimal
   responder node in this process that replies to each state with the safe default (hover thrust for the
   quadrotor), stamped with the state's stamp: the loop a lockstep MPC closes, with an instant MPC.

``--executors single events --rounds N`` measures the node with rclpy's SingleThreadedExecutor and the
experimental EventsExecutor (node and responder alike, ``SAML_EXECUTOR``) alternately, N runs each (best counts).

Runs in a private ROS domain (ROS_DOMAIN_ID from the pid, LOCALHOST discovery) and stops the node it started.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from pathlib import Path

from bench.ros_procs import interrupt

REPO = Path(__file__).resolve().parents[1]
#: the measured runs' start state per system (a data table: hover at 2 m; the cart at rest at p = 1 m)
STARTS: dict[str, tuple[float, ...]] = {
    "quadrotor": (0.0, 0.0, 2.0) + (0.0,) * 3 + (1.0, 0.0, 0.0, 0.0) + (0.0,) * 3,
    "friction": (1.0, 0.0),
}


def bench_core(system_name: str, steps: int, with_messages: bool, cdr: bool = False) -> float:
    """Steps per second of the lockstep core answered in-process (optionally with message conversions: message
    objects, or with ``cdr`` the CDR bytes the node writes and reads for state, applied_cmd and cmd)."""
    from msg_schemas import get_schema
    from msg_schemas.cdr import CdrCodec
    from msg_schemas.telemetry import clock_to_msg
    from saml_ros.core.systems import get_system
    from saml_ros.core.worlds.sim_core import APPLIED, CLOCK, STATE, SimConfig, build_stepped_sim

    system = get_system(system_name)
    schema = get_schema(system_name)
    sim = build_stepped_sim(system, SimConfig(mode="lockstep", initial_state=STARTS[system_name]))
    answer = system.safe_control()
    encode = {
        STATE: lambda v, t: schema.state_to_msg(v, t),
        APPLIED: lambda v, t: schema.control_to_msg(v, t),
        CLOCK: lambda v, t: clock_to_msg(t),
    }
    state_cdr, control_cdr = CdrCodec(schema.state), CdrCodec(schema.control)
    if cdr:
        encode[STATE] = state_cdr.encode
        encode[APPLIED] = control_cdr.encode
    outputs = sim.begin(time.monotonic_ns())
    t0 = time.perf_counter()
    for _ in range(steps):
        stamp = outputs[-1][2]
        if with_messages:
            for kind, vec, t in outputs:
                encode[kind](vec, t)
            if cdr:
                u, stamp = control_cdr.decode(control_cdr.encode(answer, stamp))
            else:
                u, stamp = schema.control_from_msg(schema.control_to_msg(answer, stamp))
        else:
            u = answer
        outputs = sim.on_cmd(u, stamp, time.monotonic_ns())
    return steps / (time.perf_counter() - t0)


def bench_node(system_name: str, steps: int, warmup: int, timeout: float,
               publish_clock: bool = True) -> tuple[float, dict[str, str]]:
    """Steps per second of the lockstep simulator node answered by a responder node in this process."""
    import rclpy
    from rclpy.event_handler import PublisherEventCallbacks, SubscriptionEventCallbacks

    from msg_schemas import DATA_QOS, RCLPY, get_schema
    from msg_schemas.telemetry import DIAGNOSTICS_TOPIC, TELEMETRY_QOS, diagnostics_from_msg
    from saml_ros.core.systems import get_entry, get_system
    from saml_ros.nodes.runtime import make_executor

    system = get_system(system_name)
    schema = get_schema(system_name)
    answer = system.safe_control()
    start = "[" + ", ".join(str(float(v)) for v in STARTS[system_name]) + "]"
    cmd = [sys.executable, "-m", "saml_ros.executables", get_entry(system_name).sim_node, "--ros-args",
           "-p", "mode:=lockstep", "-p", f"initial_state:={start}", "-p", "start_delay:=0.2",
           "-p", "lockstep_timeout:=2.0", "-p", "diagnostics_period:=0.5",
           "-p", f"publish_clock:={str(publish_clock).lower()}"]
    env = dict(os.environ, PYTHONPATH=str(REPO))
    sim = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, start_new_session=True)

    rclpy.init()
    node = rclpy.create_node("bench_responder", namespace=f"/{system_name}", start_parameter_services=False,
                             enable_rosout=False)
    qos = DATA_QOS.to_rclpy()
    pub = node.create_publisher(RCLPY.cls(schema.control.msg_type), schema.cmd_topic, qos,
                                event_callbacks=PublisherEventCallbacks(use_default_callbacks=False))
    times: list[float] = []
    diag: dict[str, str] = {}

    def on_state(msg: object) -> None:
        _, stamp = schema.state_from_msg(msg)
        pub.publish(schema.control_to_msg(answer, stamp))
        times.append(time.perf_counter())

    def on_diag(msg: object) -> None:
        entries, _ = diagnostics_from_msg(msg)
        for e in entries:
            if e.name.endswith(get_entry(system_name).sim_node):
                diag.update(e.values)

    node.create_subscription(RCLPY.cls(schema.state.msg_type), schema.state_topic, on_state, qos,
                             event_callbacks=SubscriptionEventCallbacks(use_default_callbacks=False))
    node.create_subscription(RCLPY.cls("diagnostic_msgs/msg/DiagnosticArray"), DIAGNOSTICS_TOPIC, on_diag,
                             TELEMETRY_QOS.to_rclpy())
    executor = make_executor()
    executor.add_node(node)
    try:
        deadline = time.monotonic() + timeout
        while len(times) < warmup + steps and time.monotonic() < deadline and sim.poll() is None:
            executor.spin_once(timeout_sec=0.1)
        if len(times) < warmup + steps:
            err = sim.stderr.read().decode(errors="replace")[-2000:] if sim.poll() is not None and sim.stderr else ""
            raise RuntimeError(f"only {len(times)} states within {timeout} s {err}")
        rate = steps / (times[warmup + steps - 1] - times[warmup - 1])
        end = time.monotonic() + 1.5  # one more diagnostics message
        while time.monotonic() < end:
            executor.spin_once(timeout_sec=0.1)
    finally:
        interrupt(sim, 10.0)
        node.destroy_node()
        rclpy.try_shutdown()
    return rate, diag


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--system", default="quadrotor", choices=list(STARTS))
    parser.add_argument("--steps", type=int, default=3000, help="measured lockstep steps through ROS")
    parser.add_argument("--warmup", type=int, default=200)
    parser.add_argument("--timeout", type=float, default=120.0, help="s before giving up on the node")
    parser.add_argument("--no-clock", action="store_true", help="run the node with publish_clock:=false")
    parser.add_argument("--executors", nargs="+", default=["single"], choices=["single", "events"],
                        help="executors of the node and the responder (SAML_EXECUTOR), measured alternately")
    parser.add_argument("--rounds", type=int, default=1, help="node runs per executor (alternating; best counts)")
    args = parser.parse_args(argv)
    os.environ.setdefault("ROS_DOMAIN_ID", str(1 + os.getpid() % 100))
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"

    import torch

    torch.set_num_threads(1)
    from saml_ros.core.systems import get_system

    dt = get_system(args.system).dt
    core = bench_core(args.system, 5 * args.steps, with_messages=False)
    core_msgs = bench_core(args.system, args.steps, with_messages=True)
    core_cdr = bench_core(args.system, args.steps, with_messages=True, cdr=True)
    node_rates: dict[str, list[float]] = {ex: [] for ex in args.executors}
    diag: dict[str, str] = {}
    for r in range(args.rounds):
        for ex in args.executors if r % 2 == 0 else list(reversed(args.executors)):
            os.environ["SAML_EXECUTOR"] = ex
            rate, diag = bench_node(args.system, args.steps, args.warmup, args.timeout,
                                    publish_clock=not args.no_clock)
            node_rates[ex].append(rate)
    print(f"{args.system} lockstep (dt = {dt} s), {os.cpu_count()} CPUs, load average "
          f"{', '.join(f'{x:.2f}' for x in os.getloadavg())}")
    rows = [("core", core), ("core + messages", core_msgs), ("core + CDR messages", core_cdr)]
    clock = "" if args.no_clock else " + /clock"
    rows += [(f"node{clock} + responder, {ex}", max(v)) for ex, v in node_rates.items()]
    for label, rate in rows:
        print(f"  {label:<36} {rate:9.0f} steps/s = {rate * dt:8.0f} x real time")
    if len(node_rates) > 1 or args.rounds > 1:
        for ex, v in node_rates.items():
            print(f"  {ex} executor, every round (steps/s): {', '.join(f'{x:.0f}' for x in v)}")
    misses = {k: v for k, v in diag.items() if k.startswith(("rejected/", "lockstep_misses", "cmd_timeouts"))}
    print(f"  node counters: steps {diag.get('steps', '?')}, misses/rejections/timeouts {misses or 'none'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
