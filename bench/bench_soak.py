"""Learner soak benchmark: transitions streamed at 1 kHz for 10 minutes into a real learner node.

``./dev bench soak`` (10 minutes of streaming plus about 30 s of start-up) or
``./dev python -m bench.bench_soak --minutes 1`` (the short run). In one private ROS domain:

1. the learner node (``python -m saml_ros.executables learner``, friction, training as fast as it can:
   ``updates_per_second: 0``, a checkpoint every 10 s) runs with its training process;
2. a publisher process (stock rclpy, ``DATA_QOS``) streams friction episodes (100 steps each, true dynamics, random
   commands; the simulator contract: no ``applied_cmd`` for an episode's last state, the next episode 2 dt later)
   at ``--rate`` transitions per second, paced by the wall clock, for ``--minutes``;
3. every ``--sample`` seconds the resident memory (VmRSS) of the node and of its training process are read from
   /proc, and the learner's /diagnostics counters (messages taken from DDS, transitions paired, rejections,
   training-process queue and drops, updates).

Reported: transitions published and paired (``lost`` = published - paired, after the learner has drained), the
publisher's achieved rate, the learner's updates, and the resident memory of both processes from the first sample
after streaming started (the buffer starts filling then) to the end, with the growth over the second half (a leak
shows there; filling the fixed-size replay buffer does not). Targets: 0 lost, growth < 50 MB.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import re
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from bench.bench_learner import Child, LearnerCounts, settle
from bench.ros_procs import claimed_domain, friction_publisher, interrupt
from msg_schemas import DATA_QOS

REPO = Path(__file__).resolve().parents[1]
NS = "/friction"
DT_NS = 100_000_000
EPISODE = 100


# --------------------------------------------------------------------------------------------- publisher
def run_publisher() -> int:
    """Child: on stdin ``stream RATE SECONDS`` publish friction episodes at RATE transitions/s for SECONDS, then
    print ``done TRANSITIONS MESSAGES SECONDS``; ``wait N`` waits for N matched subscriptions per topic."""
    pub = friction_publisher("soak_publisher", NS)
    schema, system, pub_s, pub_c = pub.schema, pub.system, pub.state, pub.applied
    rng = np.random.default_rng(0)
    print("ready", flush=True)
    for line in sys.stdin:
        parts = line.split()
        if parts and parts[0] == "wait":
            print(f"matched {pub.wait_matched(int(parts[1]), 60.0)}", flush=True)
            continue
        if not parts or parts[0] != "stream":
            break
        rate, seconds = float(parts[1]), float(parts[2])
        period = 1.0 / rate
        t_ns, n_tr, n_msg = DT_NS, 0, 0
        start = time.perf_counter()
        while time.perf_counter() - start < seconds:
            x = np.array([rng.uniform(-2.0, 2.0), 0.0])
            us = rng.uniform(-10.0, 10.0, size=(EPISODE, 1))
            for k in range(EPISODE + 1):
                pub_s.publish(schema.state_to_msg(x, t_ns))
                n_msg += 1
                if k < EPISODE:
                    pub_c.publish(schema.control_to_msg(us[k], t_ns))
                    n_msg += 1
                    n_tr += 1
                    x = system.true_step_np(x, us[k])
                    t_ns += DT_NS
                    due = start + n_tr * period  # pace by transitions (two messages each)
                    while (now := time.perf_counter()) < due:
                        time.sleep(min(due - now, 0.002))
            t_ns += 2 * DT_NS  # the next episode starts 2 dt after the last state
        print(f"done {n_tr} {n_msg} {time.perf_counter() - start:.3f}", flush=True)
    pub.close()
    return 0


# --------------------------------------------------------------------------------------------- measuring
def rss_mb(pid: int | None) -> float:
    """Resident memory of process ``pid`` in MB (NaN if it is gone)."""
    if pid is None:
        return float("nan")
    try:
        text = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return float("nan")
    m = re.search(r"VmRSS:\s+(\d+) kB", text)
    return int(m.group(1)) / 1024.0 if m else float("nan")


def sampler(samples: list[dict[str, Any]], pids: dict[str, int | None], listener: LearnerCounts, period: float,
            stop: threading.Event) -> None:
    t0 = time.monotonic()
    while not stop.wait(period if samples else 0.0):
        row: dict[str, Any] = {"t": time.monotonic() - t0}
        row.update({f"rss_{k}": rss_mb(p) for k, p in pids.items()})
        for key in ("paired", "updates", "queued", "dropped", "buffer_size", f"{NS}/received/state",
                    f"{NS}/received/applied_cmd"):
            row[key] = listener.get(key)
        samples.append(row)


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--role", choices=["main", "publisher"], default="main", help=argparse.SUPPRESS)
    p.add_argument("--minutes", type=float, default=10.0, help="streaming time (default 10; 1 for a short run)")
    p.add_argument("--rate", type=float, default=1000.0, help="transitions per second (default 1000)")
    p.add_argument("--sample", type=float, default=10.0, help="seconds between memory / counter samples")
    p.add_argument("--niceness", type=int, default=10,
                   help="the learner's training_niceness (default 10, the learner's own default; its training "
                        "process also decodes and pairs, so on a busy machine it is what starves first)")
    p.add_argument("--warmup", type=float, default=60.0,
                   help="seconds of streaming before the memory baseline (torch's first training steps allocate "
                        "their working memory; default 60)")
    args = p.parse_args(argv)
    if args.role == "publisher":
        return run_publisher()
    return soak(args.minutes * 60.0, args.rate, args.sample, args.warmup, args.niceness)


def soak(seconds: float, rate: float, sample_s: float, warmup: float, niceness: int = 10) -> int:
    """The soak run (module docstring); returns 0 when nothing was lost and memory grew less than 50 MB."""
    with claimed_domain() as domain:
        env = dict(os.environ, ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
                   PYTHONUNBUFFERED="1")
        env["PYTHONPATH"] = os.pathsep.join(x for x in (str(REPO), env.get("PYTHONPATH", "")) if x)
        os.environ.update(ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
        print(f"learner soak: {rate:.0f} transitions/s for {seconds:.0f} s, training_niceness {niceness} "
              f"(ROS_DOMAIN_ID={domain}, {os.cpu_count()} CPUs, load {os.getloadavg()[0]:.1f}, this process's "
              f"niceness {os.nice(0)})", flush=True)
        run_dir = Path(tempfile.mkdtemp(prefix="bench_soak_"))
        listener = LearnerCounts()
        pub = Child([sys.executable, "-m", "bench.bench_soak", "--role", "publisher"], env)
        assert pub.ask() == "ready"
        log_path = run_dir / "learner.log"
        with open(log_path, "wb") as log:
            learner = subprocess.Popen(
                [sys.executable, "-m", "saml_ros.executables", "learner", "--ros-args", "-r", f"__ns:={NS}",
                 "-p", "min_transitions:=1000", "-p", "updates_per_second:=0.0", "-p", f"run_dir:={run_dir / 'run'}",
                 "-p", "checkpoint_period:=10.0", "-p", "telemetry_rate:=5.0", "-p", "diagnostics_rate:=2.0",
                 "-p", f"training_niceness:={niceness}"],
                env=env, cwd=REPO, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
            stop = threading.Event()
            samples: list[dict[str, Any]] = []
            try:
                deadline = time.monotonic() + 120
                while listener.get(f"{NS}/publishers/state") < 1 and time.monotonic() < deadline:
                    time.sleep(0.2)
                pub.ask("wait 1")
                found = None
                while found is None and time.monotonic() < deadline:
                    found = re.search(r"training process pid (\d+)", log_path.read_text(errors="replace"))
                    time.sleep(0.2)
                child = int(found.group(1)) if found else None
                pids = {"node": learner.pid, "training": child}
                thread = threading.Thread(target=sampler, args=(samples, pids, listener, sample_s, stop), daemon=True)
                thread.start()
                t_stream = time.monotonic()
                reply = pub.ask(f"stream {rate} {seconds}").split()
                n_tr, n_msg, took = int(reply[1]), int(reply[2]), float(reply[3])
                stream_s = time.monotonic() - t_stream
                paired = settle(lambda: listener.get("paired"), n_tr, quiet=10.0, timeout=120.0)
                received = listener.get(f"{NS}/received/state") + listener.get(f"{NS}/received/applied_cmd")
                stop.set()
                thread.join(5.0)
                final_load = os.getloadavg()
                final = {k: listener.get(k) for k in ("updates", "dropped", "queued", "train_errors", "rejected/late",
                                                      "rejected/out_of_order", "rejected/duplicate", "expired",
                                                      "model_version", "train_health/skipped")}
            finally:
                stop.set()
                interrupt(learner, 60.0)
                listener.close()
                pub.close()
    print(f"load average at the end: {final_load[0]:.1f} (1 min), {final_load[1]:.1f} (5 min), "
          f"{final_load[2]:.1f} (15 min)")
    return report(samples, n_tr, n_msg, took, stream_s, paired, received, final, log_path, warmup)


def report(samples: list[dict[str, Any]], n_tr: int, n_msg: int, took: float, stream_s: float, paired: int,
           received: int, final: dict[str, int], log_path: Path, warmup: float) -> int:
    """Print the soak's numbers; 0 when nothing was lost and resident memory grew by less than 50 MB."""
    lost = n_tr - paired
    print(f"\npublished {n_tr} transitions ({n_msg} messages) in {took:.1f} s: {n_tr / took:.0f} transitions/s")
    print(f"learner: took {received}/{n_msg} messages from DDS ({n_msg - received} never taken: the node was not "
          f"scheduled in time and the writer's history of {DATA_QOS.depth} overflowed), paired {paired}/{n_tr} "
          f"transitions -> lost {lost}; "
          f"{final['updates']} updates, model version {final['model_version']}, dropped {final['dropped']}, "
          f"rejected late/out_of_order/duplicate {final['rejected/late']}/{final['rejected/out_of_order']}/"
          f"{final['rejected/duplicate']}, expired {final['expired']}, train errors {final['train_errors']}, "
          f"training steps skipped {final['train_health/skipped']}")
    streaming = [s for s in samples if s["t"] <= stream_s + 1.0]
    if len(streaming) < 2:
        print("too few memory samples")
        return 1
    growth = {}
    print(f"\n{'t (s)':>7} {'node RSS':>9} {'train RSS':>9} {'paired':>8} {'updates':>8} {'buffer':>7} {'queued':>7}")
    for s in streaming:
        print(f"{s['t']:7.0f} {s['rss_node']:9.1f} {s['rss_training']:9.1f} {s['paired']:8d} {s['updates']:8d} "
              f"{s['buffer_size']:7d} {s['queued']:7d}")
    steady = [s for s in streaming if s["t"] >= min(warmup, streaming[-1]["t"] / 2)]
    first, mid, last = steady[0], steady[len(steady) // 2], steady[-1]
    print(f"(memory growth from t = {first['t']:.0f} s, after the warm-up; before it: node "
          f"{streaming[0]['rss_node']:.1f} MB, training {streaming[0]['rss_training']:.1f} MB)")
    for key in ("node", "training"):
        a, m, b = first[f"rss_{key}"], mid[f"rss_{key}"], last[f"rss_{key}"]
        growth[key] = b - a
        print(f"resident memory, {key:8s}: {a:.1f} -> {b:.1f} MB (growth {b - a:+.1f} MB; second half {b - m:+.1f} MB)")
    total = growth["node"] + growth["training"]
    ok = lost == 0 and total < 50.0
    print(f"\nsoak: lost {lost} (target 0), resident memory growth {total:+.1f} MB in all (target < 50 MB): "
          f"{'met' if ok else 'NOT met'}; learner log {log_path}")
    return 0 if ok else 1


if __name__ == "__main__":
    with contextlib.suppress(KeyboardInterrupt):
        raise SystemExit(main())
