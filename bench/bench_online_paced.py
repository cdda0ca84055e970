"""The training loop on a busy CPU, paced evaluations against wall-clock ones, side by side (ROS-free):

    ./dev python -m bench.bench_online_paced --system-file examples/diff_drive/system.yaml \\
        --train RUN/bag --heldout OTHER/bag --seconds 120 --niceness 10

Two training loops (:func:`~saml_ros.core.online.loop.run_loop`, the training process's own loop, each in its own
process at ``--niceness``, one torch thread) get the same recorded transitions at the recording's own pace (the
stream replayed in real time, in batches of 0.1 s of stream time). ``paced`` runs the loop as it is (the held-out
evaluation and the model metrics yield to the updates, :data:`~saml_ros.core.online.learner.EVAL_SHARE`); ``wall
clock`` evaluates every ``heldout.eval_period`` and every telemetry period whatever the updates cost (the loop
before). Both start together and share whatever CPU the machine leaves them, so the load is the same for both.
Printed per loop: updates, updates in the last quarter of the stream, the CPU time it got and the share of it spent
in updates, and the published model's in-region error on the held-out recording (other flights) at the stop,
beside f_hat's. The numbers depend on the
machine's load (printed).
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np


def _loop(mode: str, system_file: str, train: list[str], heldout: list[str], niceness: int, conn: Any,
          out: Any) -> None:
    """One training loop fed by ``conn``; puts ``(mode, result)`` on ``out`` after the stop."""
    os.nice(niceness)
    import torch

    torch.set_num_threads(1)
    from saml_ros.bags.transitions import extract_transitions
    from saml_ros.core.online import OnlineConfig, OnlineLearner
    from saml_ros.core.online.loop import LoopConfig, run_loop
    from saml_ros.core.spec import ProblemSpec
    from saml_ros.user_code import load_system_file

    system = load_system_file(Path(system_file))
    spec = ProblemSpec.for_system(system.paper_spec(), system)
    learner = OnlineLearner(system, spec, OnlineConfig(kind=system.model_kind, hidden=tuple(system.paper_hidden)))
    if mode != "paced":  # every evaluation when its period has passed
        plain = OnlineLearner.compute_model_metrics

        def unpaced(self: OnlineLearner, paced: bool = False) -> dict[str, float]:
            return plain(self, False)

        OnlineLearner.compute_model_metrics = unpaced  # type: ignore[method-assign]
    counts: list[tuple[float, int]] = []

    def send(msg: Any) -> None:  # tuples ("status", status, ...) or typed messages (Status(status, ...))
        status = msg[1] if isinstance(msg, tuple) and msg[0] == "status" else getattr(msg, "status", None)
        if isinstance(status, dict):
            counts.append((time.monotonic(), int(status.get("updates", 0))))

    cpu0 = time.process_time()
    run_loop(learner, LoopConfig(), conn, send)
    cpu = time.process_time() - cpu0
    held = extract_transitions(heldout, system)
    model = learner.published_model()
    xt, ut, yt = (torch.as_tensor(a) for a in (held.x, held.u, held.y))
    with torch.no_grad():
        pred = model(xt.to(model.in_mean.dtype), ut.to(model.in_mean.dtype)).double()[:1]
    err = spec.region_errors(xt, ut, yt, pred)
    base = spec.region_errors(xt, ut, yt, torch.as_tensor(system.base_step_np(held.x, held.u))[None])
    out.put((mode, {"updates": learner.updates, "counts": counts, "cpu": cpu, "update_cpu": learner._update_cpu,
                    "in": {k: float(v["in"][0]) for k, v in err.items()},
                    "f_hat": {k: float(v["in"][0]) for k, v in base.items()}}))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--system-file", required=True, type=Path)
    ap.add_argument("--train", nargs="+", required=True, type=Path, help="the recording streamed to both loops")
    ap.add_argument("--heldout", nargs="+", required=True, type=Path, help="other flights the models are judged on")
    ap.add_argument("--seconds", type=float, default=0.0, help="stream seconds to replay (0: the whole recording)")
    ap.add_argument("--niceness", type=int, default=10, help="nice increment of both loops (the learner's default)")
    args = ap.parse_args(argv)

    from saml_ros.bags.transitions import extract_transitions
    from saml_ros.user_code import load_system_file

    system = load_system_file(args.system_file)
    tr = extract_transitions([str(p) for p in args.train], system)
    order = np.argsort(tr.stamps, kind="stable")
    x, u, y, stamp = tr.x[order], tr.u[order], tr.y[order], tr.stamps[order] * 1e-9
    end = stamp[0] + (args.seconds or (stamp[-1] - stamp[0]))
    try:  # the training loop's inbox messages: typed where they are, tuples before
        from saml_ros.core.online import messages  # type: ignore[attr-defined,unused-ignore]

        def batch(*fields: Any) -> Any:
            return messages.Batch(*fields)

        stop: Any = messages.Stop()
    except ImportError:
        def batch(*fields: Any) -> Any:
            return ("batch", *fields)

        stop = ("stop",)
    ctx = mp.get_context("spawn")
    out = ctx.Queue()
    modes = ("paced", "wall clock")
    pipes, procs = [], []
    for mode in modes:
        parent, child = ctx.Pipe()
        p = ctx.Process(target=_loop, args=(mode, str(args.system_file), [str(t) for t in args.train],
                                            [str(h) for h in args.heldout], args.niceness, child, out))
        p.start()
        pipes.append(parent)
        procs.append(p)
    time.sleep(20.0)  # both import torch and build their learners before the stream starts
    print(f"bench_online_paced: {len(x)} transitions over {end - stamp[0]:.0f} s of stream, niceness {args.niceness}; "
          f"load average {os.getloadavg()[0]:.1f}", flush=True)
    t0, i = time.monotonic(), 0
    while i < len(x) and stamp[i] <= end:
        now = stamp[0] + time.monotonic() - t0
        j = int(np.searchsorted(stamp, min(now, end), side="right"))
        if j > i:
            for c in pipes:
                c.send(batch(x[i:j], u[i:j], y[i:j], stamp[i:j], np.zeros(j - i, dtype=np.int64)))
            i = j
        time.sleep(0.1)
    stopped = time.monotonic()
    for c in pipes:
        c.send(stop)
    results = dict(out.get() for _ in modes)
    for p in procs:
        p.join(60)
    for mode in modes:
        r = results[mode]
        last = [n for t, n in r["counts"] if t <= stopped - 0.25 * (stopped - t0)]
        late = r["updates"] - (last[-1] if last else 0)
        errs = ", ".join(f"'{k}' in-region {v:.5f} (f_hat {r['f_hat'][k]:.5f})" for k, v in r["in"].items())
        print(f"  {mode:10s}: {r['updates']} updates, {late} in the last quarter of the stream; {r['cpu']:.1f} CPU s, "
              f"{100 * r['update_cpu'] / max(r['cpu'], 1e-9):.0f} % of it in updates; {errs}", flush=True)
    print(f"bench_online_paced: load average {os.getloadavg()[0]:.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
