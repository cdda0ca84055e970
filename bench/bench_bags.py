"""Bag benchmarks, measured in one run: recorder throughput without loss, and offline transition extraction.

    ./dev python -m bench.bench_bags                  # both (about a minute)
    ./dev python -m bench.bench_bags --rates 500 1000 2000 4000 8000 --seconds 3

1. Recorder: for each target rate, a stock rclpy publisher *process* (test/bag_publisher.py) publishes a
   friction roll-out (state + applied_cmd + cmd + /clock per step, DATA_QOS) for ``--seconds`` wall seconds
   to a ``record`` *process*; the bag's message count is compared with what was published. Reported per
   rate: achieved publish rate, recorded, lost. "Lossless throughput" is the highest achieved rate with no
   loss. The machine's other load matters (2 shared cores here): each line is one measurement.
2. Offline: a bag of ``--transitions`` friction transitions is written with BagWriter, then
   ``extract_transitions`` (decode + msg_schemas + the learner's StampPairer) is timed: transitions per second.

Uses ``ROS_DOMAIN_ID`` if set, else claims a free id in 1..100 (the lock files test/ros_helpers.py uses, so
it never shares a domain with a running test); traffic stays on this host.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from bench.ros_procs import claimed_domain, interrupt

REPO = Path(__file__).resolve().parents[1]
PUBLISHER = REPO / "test" / "bag_publisher.py"
MSGS_PER_STEP = 4  # state, applied_cmd, cmd, /clock


def _load_publisher_module() -> Any:
    import importlib.util

    spec = importlib.util.spec_from_file_location("bag_publisher", PUBLISHER)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def record_once(rate_msgs: float, seconds: float, workdir: Path, env: dict[str, str], pubmod: Any) -> dict[str, Any]:
    """One recorder + publisher run at ``rate_msgs`` messages per second (0 = as fast as possible)."""
    from saml_ros.bags.io import Bag

    steps_per_s = rate_msgs / MSGS_PER_STEP
    steps = int(max(steps_per_s, 2000 / MSGS_PER_STEP) * seconds) if rate_msgs > 0 else 20_000
    ns = f"/friction_bench_{os.getpid()}_{int(rate_msgs)}"
    events_path = workdir / f"events-{int(rate_msgs)}.npz"
    t0 = 10**9
    # the dynamics do not matter for throughput: a saw-tooth state, constant command
    events: list[dict[str, Any]] = [{"stamp": t0 + k * 100_000_000, "x": [0.1 * (k % 50), 0.0], "u": [0.5]}
                                    for k in range(steps)]
    events[-1].pop("u")
    pubmod.save_events(events_path, events)
    bag = workdir / f"bag-{int(rate_msgs)}"
    rec = subprocess.Popen([sys.executable, "-m", "saml_ros.executables", "record", "--system", "friction", "--namespace",
                            ns, "-o", str(bag)], cwd=REPO, env=env, stdout=subprocess.PIPE,
                           stderr=subprocess.STDOUT, text=True, start_new_session=True)
    try:
        pub = subprocess.run([sys.executable, str(PUBLISHER), "--events", str(events_path), "--namespace", ns,
                              "--rate", str(steps_per_s), "--cmd", "--clock", "--wait-subscribers", "1",
                              "--wait-timeout", "60"], env=env, capture_output=True, text=True, timeout=600)
        if pub.returncode != 0:
            raise RuntimeError(f"publisher failed: {pub.stderr}")
        report = json.loads(pub.stdout.strip().splitlines()[-1])
        time.sleep(1.0)  # let the recorder drain its queues
    finally:
        interrupt(rec, 30.0)
    published = {t: n for t, n in report["published"].items() if t.startswith(ns) or t == "/clock"}
    with Bag(bag) as b:
        recorded = {t: b.topics[t].message_count if t in b.topics else 0 for t in published}
    n_pub, n_rec = sum(published.values()), sum(recorded.values())
    return {"target": rate_msgs, "achieved": n_pub / report["seconds"], "published": n_pub,
            "recorded": n_rec, "lost": n_pub - n_rec}


def extraction_speed(n: int, workdir: Path) -> dict[str, float]:
    """Write ``n`` friction transitions with BagWriter and time ``extract_transitions`` on them."""
    import numpy as np

    from msg_schemas import DATA_QOS, TypestoreFactory, get_schema
    from saml_ros.bags.io import BagWriter, jazzy_typestore
    from saml_ros.bags.transitions import extract_transitions

    schema = get_schema("friction")
    factory = TypestoreFactory(jazzy_typestore())
    rng = np.random.default_rng(0)
    path = workdir / "offline"
    t_write = time.perf_counter()
    with BagWriter(path) as w:
        for topic in ("/friction/state", "/friction/applied_cmd"):
            w.add_topic(topic, "sensor_msgs/msg/JointState", DATA_QOS)
        for k in range(n + 1):
            stamp = 10**9 + k * 100_000_000
            w.write_msg("/friction/state", schema.state_to_msg(rng.normal(size=2), stamp, factory=factory), stamp)
            if k < n:
                u = schema.control_to_msg(rng.normal(size=1), stamp, factory=factory)
                w.write_msg("/friction/applied_cmd", u, stamp)
    t_write = time.perf_counter() - t_write
    t = time.perf_counter()
    out = extract_transitions([path], "friction")
    dt = time.perf_counter() - t
    assert len(out) == n, (len(out), n)
    size = (path / "offline.mcap").stat().st_size
    return {"transitions": n, "seconds": dt, "per_second": n / dt, "messages_per_second": (2 * n + 1) / dt,
            "write_messages_per_second": (2 * n + 1) / t_write, "bag_mb": size / 1e6}


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="bench_bags", description=__doc__.splitlines()[0])
    p.add_argument("--rates", type=float, nargs="+", default=[1000, 2000, 4000, 8000],
                   help="target publish rates (messages/s; 0 = as fast as the publisher can)")
    p.add_argument("--seconds", type=float, default=3.0, help="publishing time per rate (wall s)")
    p.add_argument("--transitions", type=int, default=50_000, help="transitions in the offline-extraction bag")
    p.add_argument("--skip-record", action="store_true", help="only the offline extraction")
    args = p.parse_args(argv)

    with contextlib.ExitStack() as claims:
        env = dict(os.environ)
        if "ROS_DOMAIN_ID" not in env:
            env["ROS_DOMAIN_ID"] = str(claims.enter_context(claimed_domain()))
        return run(args, env)


def run(args: argparse.Namespace, env: dict[str, str]) -> int:
    """Both measurements with the options of ``main`` in the ROS environment ``env``."""
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = env.get("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    env["PYTHONPATH"] = os.pathsep.join(x for x in (str(REPO), env.get("PYTHONPATH", "")) if x)
    with tempfile.TemporaryDirectory(prefix="bench_bags_") as tmp:
        work = Path(tmp)
        if not args.skip_record:
            pubmod = _load_publisher_module()
            print(f"recorder throughput (publisher process -> record process, ROS_DOMAIN_ID={env['ROS_DOMAIN_ID']}, "
                  f"{MSGS_PER_STEP} topics, DATA_QOS):")
            best = 0.0
            for rate in args.rates:
                r = record_once(rate, args.seconds, work, env, pubmod)
                ok = r["lost"] == 0
                if ok:
                    best = max(best, r["achieved"])
                target = f"{r['target']:8.0f}" if r["target"] > 0 else "     max"
                print(f"  target {target} msg/s: achieved {r['achieved']:8.0f} msg/s, published {r['published']:6d}, "
                      f"recorded {r['recorded']:6d}, lost {r['lost']:5d}{'' if ok else '  <- LOSS'}", flush=True)
            print(f"  => lossless recorder throughput: {best:.0f} msg/s (highest achieved rate without loss)")
        r2 = extraction_speed(args.transitions, work)
        print(f"offline extraction ({r2['transitions']} friction transitions, {r2['bag_mb']:.1f} MB bag): "
              f"{r2['per_second']:.0f} transitions/s ({r2['messages_per_second']:.0f} msg/s decoded and paired, "
              f"{r2['seconds']:.2f} s); BagWriter wrote {r2['write_messages_per_second']:.0f} msg/s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
