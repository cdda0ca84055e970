"""A stock rclpy publisher process that plays a simulator's part for bag tests and benchmarks.

    python test/bag_publisher.py --system friction --steps 200 --rate 500 --episode-steps 50 --wait-subscribers 1

Rolls out ``system.true_step_np`` with random controls (from the paper's sampling distribution), builds the
messages with ``msg_schemas`` and publishes them stamped per docs/architecture.md "Time, stamps and pairing":
x_k on ``state`` stamped t_k = t_0 + k dt, u_k on ``applied_cmd`` (and ``cmd``) stamped t_k iff x_{k+1} is
its integration; an episode restart skips that applied_cmd and stamps the next state 3 dt later. For the
paddle ball (event based) each impact publishes ``state``, ``applied_cmd`` and ``post_impact`` with one stamp.
``--clock`` also publishes ``/clock`` = t_k. The trajectory is computed before publishing, so ``--rate``
(steps per wall second, 0 = as fast as possible) is not limited by torch.

``--events FILE`` publishes a roll-out saved by :func:`save_events` (the test computes it; this process then
starts without importing torch). Prints one JSON line at the end: ``{"published": {topic: count}, "transitions": n, "seconds": s}`` where
``transitions`` is the number of transitions a correct learner pairs from what was published.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from msg_schemas import get_schema  # noqa: E402
from msg_schemas.names import join_topic  # noqa: E402
from msg_schemas.telemetry import clock_to_msg, model_error_to_msg  # noqa: E402


def rollout(system_name: str, steps: int, episode_steps: int, seed: int, t0_ns: int) -> list[dict]:
    """The events to publish, in order: dicts with ``stamp`` (ns) and ``x`` / ``u`` / ``y`` vectors.

    ``u`` is present iff the next state continues the same episode (time-stepped) and ``y`` for event systems.
    """
    from saml_ros.core.systems import get_system  # torch: only when rolling out here

    system = get_system(system_name)
    rng = np.random.default_rng(seed)
    schema = get_schema(system_name)
    if schema.target_pairing == "same":
        x, u = system.sample_inputs(steps, rng)
        y = system.true_step_np(x, u)
        return [{"stamp": t0_ns + k * 500_000_000, "x": x[k], "u": u[k], "y": y[k]} for k in range(steps)]
    dt_ns = int(round(system.dt * 1e9))
    events: list[dict] = []
    t = t0_ns
    xs, _ = system.sample_inputs(max(1, steps // max(1, episode_steps) + 2), rng)
    episode = 0
    x = xs[0]
    for k in range(steps):
        end_of_episode = episode_steps > 0 and (k + 1) % episode_steps == 0
        last = k == steps - 1
        if last or end_of_episode:
            events.append({"stamp": t, "x": x})
            episode += 1
            x = xs[episode % len(xs)]
            t += 3 * dt_ns
            continue
        _, u = system.sample_inputs(1, rng)
        events.append({"stamp": t, "x": x, "u": u[0]})
        x = system.true_step_np(x, u[0])
        t += dt_ns
    return events


def save_events(path: Path, events: list[dict]) -> None:
    """Store a roll-out for ``--events`` (so the publisher process need not import torch)."""
    arrays: dict[str, np.ndarray] = {"stamp": np.array([e["stamp"] for e in events], dtype=np.int64)}
    for key in ("x", "u", "y"):
        rows = [e.get(key) for e in events]
        width = next((len(r) for r in rows if r is not None), 0)
        arrays[key] = np.array([r if r is not None else np.full(width, np.nan) for r in rows]).reshape(len(rows), width)
        arrays["has_" + key] = np.array([r is not None for r in rows])
    np.savez(path, **arrays)  # type: ignore[arg-type]


def load_events(path: Path) -> list[dict]:
    data = np.load(path)
    events = []
    for k, stamp in enumerate(data["stamp"]):
        ev: dict = {"stamp": int(stamp)}
        for key in ("x", "u", "y"):
            if data["has_" + key][k]:
                ev[key] = data[key][k]
        events.append(ev)
    return events


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--system", default="friction")
    p.add_argument("--namespace", default=None)
    p.add_argument("--steps", type=int, default=100)
    p.add_argument("--rate", type=float, default=200.0, help="steps per wall second (0 = as fast as possible)")
    p.add_argument("--episode-steps", type=int, default=0)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--t0", type=float, default=1.0, help="first stamp (s)")
    p.add_argument("--clock", action="store_true", help="also publish /clock")
    p.add_argument("--cmd", action="store_true", help="also publish cmd (like an MPC) with each applied_cmd")
    p.add_argument("--model-error-every", type=int, default=0, help="publish learner/model_error every N steps")
    p.add_argument("--wait-subscribers", type=int, default=0,
                   help="before publishing, wait until the pairing topics (state, applied_cmd, target) have this "
                        "many subscribers and every other topic one")
    p.add_argument("--wait-timeout", type=float, default=20.0)
    p.add_argument("--go-file", type=Path,
                   help="after the subscribers matched, write the published topics (JSON) to GO_FILE.ready and "
                        "publish only once GO_FILE exists (the test saw the subscriber side match too)")
    p.add_argument("--events", type=Path, help="publish this saved roll-out (save_events) instead of rolling out")
    args = p.parse_args()

    import rclpy
    from rclpy.node import Node
    from rosgraph_msgs.msg import Clock

    from msg_schemas.base import CLOCK_QOS, TELEMETRY_QOS

    schema = get_schema(args.system)
    ns = args.namespace or f"/{args.system}"
    if args.events:
        events = load_events(args.events)
    else:
        events = rollout(args.system, args.steps, args.episode_steps, args.seed, int(args.t0 * 1e9))

    rclpy.init()
    node = Node("bag_publisher")
    pubs = {}
    for spec in schema.topics:
        if spec.required:
            pubs[spec.name] = node.create_publisher(schema_cls(spec.msg_type), join_topic(ns, spec.name),
                                                    spec.qos.to_rclpy())
    if not args.cmd:
        node.destroy_publisher(pubs.pop(schema.cmd_topic))
    if args.clock:
        pubs["/clock"] = node.create_publisher(Clock, "/clock", CLOCK_QOS.to_rclpy())
    if args.model_error_every:
        from sensor_msgs.msg import JointState

        pubs["learner/model_error"] = node.create_publisher(JointState, join_topic(ns, "learner/model_error"),
                                                            TELEMETRY_QOS.to_rclpy())
    counts = {join_topic(ns, name): 0 for name in pubs}

    if args.wait_subscribers:
        deadline = time.monotonic() + args.wait_timeout
        pairing = {schema.state_topic, schema.applied_cmd_topic, schema.target_topic}

        def enough(name: str) -> bool:
            return pubs[name].get_subscription_count() >= (args.wait_subscribers if name in pairing else 1)

        while not all(enough(name) for name in pubs):
            if time.monotonic() > deadline:
                print("bag_publisher: timed out waiting for subscribers", file=sys.stderr)
                return 1
            time.sleep(0.02)
        if not args.go_file:
            time.sleep(0.2)  # let the subscriber side finish matching too
    if args.go_file:
        ready = args.go_file.with_name(args.go_file.name + ".ready")
        ready.write_text(json.dumps(sorted(counts)))
        deadline = time.monotonic() + args.wait_timeout
        while not args.go_file.exists():
            if time.monotonic() > deadline:
                print("bag_publisher: timed out waiting for the go file", file=sys.stderr)
                return 1
            time.sleep(0.01)

    def send(name: str, msg: object) -> None:
        pubs[name].publish(msg)
        counts[join_topic(ns, name)] += 1

    start = time.monotonic()
    transitions = 0
    for k, ev in enumerate(events):
        if args.rate > 0:
            delay = start + k / args.rate - time.monotonic()
            if delay > 0:
                time.sleep(delay)
        stamp = ev["stamp"]
        if args.clock:
            send("/clock", clock_to_msg(stamp))
        send(schema.state_topic, schema.state_to_msg(ev["x"], stamp))
        if "u" in ev:
            if args.cmd:
                send(schema.cmd_topic, schema.control_to_msg(ev["u"], stamp))
            send(schema.applied_cmd_topic, schema.control_to_msg(ev["u"], stamp))
            transitions += 1
        if "y" in ev:
            send(schema.target_topic, schema.target_to_msg(ev["y"], stamp))
        if args.model_error_every and k % args.model_error_every == 0:
            metrics = {"objective": 1.0 / (k + 1), "buffer_size": float(k), "updates": float(2 * k)}
            send("learner/model_error", model_error_to_msg(metrics, stamp))
    seconds = time.monotonic() - start
    for pub in pubs.values():
        pub.wait_for_all_acked(rclpy.duration.Duration(seconds=10.0))
    print(json.dumps({"published": counts, "transitions": transitions, "seconds": seconds}), flush=True)
    node.destroy_node()
    rclpy.shutdown()
    return 0


def schema_cls(msg_type: str) -> type:
    from msg_schemas import RCLPY

    cls: type = RCLPY.cls(msg_type)
    return cls


if __name__ == "__main__":
    raise SystemExit(main())
