"""A second robot publishing into another robot's namespace, its command wired wrong (the misconfigured-robot
benchmark and test: bench/bench_misconfig.py, test/test_misconfig_loop.py).

    python -m bench.miswired_robot --system friction --namespace /friction --node-name robot_b

A real rclpy node around the system's simulator core (the same physics and episodes as its simulator node) in
lockstep with whatever answers ``cmd``: it publishes ``state`` and ``applied_cmd`` into ``--namespace`` as the
simulator there does, stamped half a period later (``--offset``: its clock is offset, so no stamp of the two
robots collides and nothing is a duplicate), answers to its own stamps only, and applies each command through a
wrong wiring (``--wiring``: ``reversed`` = the command's sign flipped, as motor leads swapped; ``swapped`` = the
actuators in reverse order) while reporting on ``applied_cmd`` the command it was sent. Without ``/clock`` (the
simulator beside it publishes that). It starts once ``cmd`` has a publisher, ``state`` another publisher (the
robot it shares the namespace with) and ``--min-subscribers`` subscriptions, and ends after ``--max-sim-time`` s of its own simulated time (0 = at SIGINT / SIGTERM).
"""

from __future__ import annotations

import argparse
import importlib
import sys
import time
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

#: how a command reaches the actuators: a miswiring (its own inverse: the robot reports what it was sent)
WIRINGS: dict[str, Callable[[np.ndarray], np.ndarray]] = {
    "reversed": lambda u: -u,
    "swapped": lambda u: u[::-1].copy(),
}


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(prog="miswired_robot", description=__doc__.split("\n\n")[0])
    ap.add_argument("--system", default="friction", help="a registered time-stepped system (default friction)")
    ap.add_argument("--namespace", default=None, help="namespace it publishes into (default /<system>)")
    ap.add_argument("--node-name", default="robot_b")
    ap.add_argument("--wiring", choices=sorted(WIRINGS), default="reversed")
    ap.add_argument("--offset", type=float, default=0.5, help="stamp offset from the simulator's, in periods")
    ap.add_argument("--episode-steps", type=int, default=0, help="0 = the simulator node's bringup default")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--min-subscribers", type=int, default=1, help="state subscriptions to wait for")
    ap.add_argument("--max-sim-time", type=float, default=0.0)
    ap.add_argument("--lockstep-timeout", type=float, default=5.0)
    return ap.parse_args(argv)


def main(argv: Sequence[str] | None = None) -> int:
    import rclpy
    from rclpy.executors import SingleThreadedExecutor

    from msg_schemas import DATA_QOS, RCLPY, SchemaError
    from msg_schemas.cdr import CdrCodec
    from saml_ros.core.systems import get_entry
    from saml_ros.core.worlds.sim_core import APPLIED, LOCKSTEP_T0_NS
    from saml_ros.nodes.runtime import catch_stop_signals, init_rclpy
    from sim_nodes.binding import config_from_params
    from sim_nodes.emitters import make_emitters

    args = parse_args(argv)
    stop = catch_stop_signals()
    entry = get_entry(args.system)
    binding = importlib.import_module(f"sim_nodes.{entry.sim_node}").BINDING
    params: dict[str, Any] = {p.name: p.default for p in binding.param_table()}
    params.update(mode="lockstep", seed=args.seed, publish_clock=False, max_sim_time=args.max_sim_time,
                  lockstep_timeout=args.lockstep_timeout,
                  episode_steps=args.episode_steps or entry.bringup["sim"].get("episode_steps", 0))
    system = entry.make_system()
    dt_ns = int(round(system.dt * 1e9))
    t0 = LOCKSTEP_T0_NS + int(round(args.offset * dt_ns))
    core = entry.simulator(system, config_from_params(params, t0), params)
    wire = WIRINGS[args.wiring]
    schema = entry.schema()

    init_rclpy([sys.argv[0]])
    node = rclpy.create_node(args.node_name, namespace=args.namespace or f"/{args.system}")
    emit = make_emitters(node, schema, publish_clock=False)
    cmd_cdr = CdrCodec(schema.control)

    def publish(outputs: list[Any]) -> None:
        for kind, vec, stamp in outputs:
            if kind == APPLIED:  # the driver reports the command it was sent, not what the actuators did
                vec = wire(np.asarray(vec, dtype=np.float64))
            emit.emit[kind](vec, stamp)  # CLOCK: nothing (publish_clock off)

    def on_cmd(msg: Any) -> None:
        try:
            u, stamp = cmd_cdr.decode(msg, "cmd")
        except SchemaError:
            return
        if stamp == core.awaiting:  # the other robot's answers are not for it
            publish(core.on_cmd(wire(np.asarray(u, dtype=np.float64)), stamp, time.monotonic_ns()))

    cmd_sub = node.create_subscription(RCLPY.cls(schema.control.msg_type), schema.cmd_topic, on_cmd,
                                       DATA_QOS.to_rclpy(), raw=True)

    def housekeeping() -> None:
        if not core.started:
            # once the robot it shares the namespace with is running (a second publisher on state) and answered
            if node.count_publishers(cmd_sub.topic_name) >= 1 and node.count_publishers(emit.state_pub.topic_name) >= 2 \
                    and emit.state_pub.get_subscription_count() >= args.min_subscribers:
                print(f"miswired_robot: {args.wiring} wiring, stamps from {t0} ns, publishing into "
                      f"{node.get_namespace()}", flush=True)
                publish(core.begin(time.monotonic_ns(), t0))
            return
        publish(core.poll(time.monotonic_ns()))

    node.create_timer(0.05, housekeeping)
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    try:
        while not stop["signal"] and not core.done:
            executor.spin_once(timeout_sec=0.1)
    finally:
        print(f"miswired_robot: stopped; {core.diagnostics()}", flush=True)
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
