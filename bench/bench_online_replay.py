"""Replay recorded flights into the online learner, ROS-free, and judge its model on held-out flights.

    ./dev python -m bench.bench_online_replay --system-file examples/diff_drive/system.yaml \\
        --train RUN/bag --heldout H1/bag H2/bag --rate 3800 --set updates_per_transition=3

The training recording's transitions (paired with the learner's own rule, ``extract_transitions``) are fed to an
:class:`~saml_ros.core.online.OnlineLearner` in stamp order, ``--chunk`` s of stream time at a time, with
``--rate`` updates per second of stream time in between (what the live learner managed on the same machine:
``updates / duration`` of a real run). The stamps are the recording's, so the held-out split of the stream is the
live learner's. At ``--evals`` points the published model (the trainer's weights or their average, whichever did
better on the learner's held-out stretches) is evaluated on the held-out recordings (other flights): one-step
error inside and outside each constraint's region, beside f_hat's, beside the error on the data trained on so far
and beside what the learner itself reports from its held-out stretches (value, standard error, verdict). The
learner's clock is the stream's, so its held-out evaluations (and normalisation refits) come every
``heldout_period`` s of stream time, as they come every second of wall time live.

Use it to compare online-learning settings on the same data (``--set`` any :class:`OnlineConfig` field, with
``heldout.fraction`` / ``heldout.period`` for the held-out split; ``--train-set`` any TrainConfig field): unlike live
runs, two settings see exactly the same transitions. A robot whose base model is user code needs its folder on
``PYTHONPATH`` only where the file does not say where (docs/your_robot.md).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch


def _value(text: str) -> Any:
    try:
        return json.loads(text)
    except json.JSONDecodeError:
        return text


def _settings(items: list[str]) -> dict[str, Any]:
    out = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep:
            raise SystemExit(f"--set / --train-set take NAME=VALUE, got {item!r}")
        out[key] = _value(value)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--system-file", required=True, type=Path)
    ap.add_argument("--train", nargs="+", required=True, type=Path, help="the recording(s) the learner learns from")
    ap.add_argument("--heldout", nargs="+", required=True, type=Path, help="other flights the model is judged on")
    ap.add_argument("--rate", type=float, default=2000.0, help="updates per second of stream time")
    ap.add_argument("--chunk", type=float, default=0.1, help="s of stream time between two rounds of updates")
    ap.add_argument("--evals", type=int, default=2, help="evaluations, evenly spaced over the stream")
    ap.add_argument("--seed", type=int, default=0, help="train.seed")
    ap.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE", help="an OnlineConfig field")
    ap.add_argument("--train-set", action="append", default=[], metavar="FIELD=VALUE", help="a TrainConfig field")
    ap.add_argument("--settle", type=int, nargs="*", default=[], metavar="UPDATES",
                    help="after the stream: keep training on the buffer (the robot parked) and evaluate again after "
                         "each of these cumulative update counts, e.g. --settle 2000 10000")
    ap.add_argument("--json", type=Path, help="write the evaluations here")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)

    from saml_ros.bags.transitions import extract_transitions
    from saml_ros.core.online import HeldoutConfig, OnlineConfig, OnlineLearner
    from saml_ros.core.spec import ProblemSpec
    from saml_ros.core.training import TrainConfig
    from saml_ros.user_code import load_system_file

    system = load_system_file(args.system_file)
    spec = ProblemSpec.for_system(system.paper_spec(), system)
    train = extract_transitions([str(p) for p in args.train], system)
    held = extract_transitions([str(p) for p in args.heldout], system)
    sets = _settings(args.set)
    heldout = {k.removeprefix("heldout."): sets.pop(k) for k in list(sets) if k.startswith("heldout.")}
    config = OnlineConfig(kind=system.model_kind, hidden=tuple(system.paper_hidden),
                          train=TrainConfig(**{"seed": args.seed, **_settings(args.train_set)}),
                          heldout=HeldoutConfig(**heldout), **sets)
    clock = [0.0]
    learner = OnlineLearner(system, spec, config, clock=lambda: clock[0])  # the learner's clock: stream time
    order = np.argsort(train.stamps, kind="stable")
    x, u, y, stamp = train.x[order], train.u[order], train.y[order], train.stamps[order] * 1e-9
    if len(args.train) > 1:  # recordings one after another: stamps rebased, gaps above 1 s shortened to 1 s
        stamp = 1000.0 + np.concatenate([[0.0], np.cumsum(np.clip(np.diff(stamp), 0.0, 1.0))])
    hx, hu, hy = (torch.as_tensor(a) for a in (held.x, held.u, held.y))
    base = spec.region_errors(hx, hu, hy, torch.as_tensor(system.base_step_np(held.x, held.u))[None])

    def errors(model: Any, xs: Any, us: Any, ys: Any) -> dict[str, dict[str, float]]:
        xt, ut, yt = (torch.as_tensor(a) for a in (xs, us, ys))
        with torch.no_grad():
            pred = model(xt.to(model.in_mean.dtype), ut.to(model.in_mean.dtype)).double()[:1]
        return {k: {w: float(v[w][0]) for w in ("in", "out", "n_in")}
                for k, v in spec.region_errors(xt, ut, yt, pred).items()}

    print(f"online replay: {system.name}, {len(x)} training transitions over {stamp[-1] - stamp[0]:.0f} s, "
          f"{len(held.x)} held-out transitions (other flights); {args.rate:g} updates/s of stream time; settings "
          f"{dataclasses.asdict(config.heldout)} {sets}; load average {os.getloadavg()[0]:.1f}", flush=True)
    for name, e in base.items():
        print(f"  f_hat on the held-out flights: '{name}' in {float(e['in'][0]):.5f} (n {int(e['n_in'][0])}), "
              f"out {float(e['out'][0]):.5f}", flush=True)
    rows: list[dict[str, Any]] = []
    eval_at = list(np.linspace(stamp[0], stamp[-1], args.evals + 1)[1:])
    i, now, debt, wall = 0, float(stamp[0]), 0.0, time.perf_counter()
    next_report = now
    while i < len(x):
        now += args.chunk
        clock[0] = now
        j = int(np.searchsorted(stamp, now, side="right"))
        if j > i:
            learner.add_batch(x[i:j], u[i:j], y[i:j], stamp=stamp[i:j], source=0)
            i = j
        debt += args.rate * args.chunk
        n = int(debt)
        debt -= n
        if n:
            learner.update(n)
        if now >= next_report:  # as the training process at its telemetry rate (5 Hz): held-out every heldout_period
            learner.compute_model_metrics()
            next_report = now + 0.2
        if eval_at and (now >= eval_at[0] or i >= len(x)):
            eval_at.pop(0)
            report = learner.evaluate_heldout()
            model = learner.published_model()  # what a checkpoint written now would hold
            row = {"t": now - stamp[0], "transitions": i, "updates": learner.updates, "published": learner.published,
                   "flights": errors(model, held.x, held.u, held.y),
                   "trained_on": errors(model, x[:i], u[:i], y[:i]), "stream_heldout": {},
                   "latest_on_flights": errors(learner.model, held.x, held.u, held.y)}
            for t in report.constraints if report is not None else []:
                est = t.model[0]
                row["stream_heldout"][t.name] = {"mean": est.mean, "se": est.se, "n": est.n,
                                                 "f_hat": t.base.mean, "training": t.training[0],
                                                 "verdict": t.verdicts[0]}
            rows.append(row)
            for name, e in row["flights"].items():
                s = row["stream_heldout"].get(name, {})
                own = (f"; its own held-out stretches {s['mean']:.5f} +- {s['se']:.5f} (n {s['n']}, "
                       f"{s['verdict']})" if s else "")
                print(f"  t {row['t']:6.1f} s, {i} transitions, {learner.updates} updates, published "
                      f"{learner.published}: '{name}' on the held-out flights in {e['in']:.5f} out {e['out']:.5f} "
                      f"(the trainer's weights {row['latest_on_flights'][name]['in']:.5f}); on the data trained on in "
                      f"{row['trained_on'][name]['in']:.5f}{own} [{time.perf_counter() - wall:.0f} s]", flush=True)
    done = 0
    for total in sorted(args.settle):  # the stream has paused: training goes on on the buffer
        while done < total:
            n = min(500, total - done)
            learner.update(n)
            done += n
            now += 0.2
            clock[0] = now
            learner.compute_model_metrics()
        learner.evaluate_heldout()
        model = learner.published_model()
        row = {"t": now - stamp[0], "transitions": i, "updates": learner.updates, "settled": done,
               "published": learner.published, "flights": errors(model, held.x, held.u, held.y)}
        rows.append(row)
        for name, e in row["flights"].items():
            print(f"  settled {done} updates ({done * config.train.batch_size / max(1, len(learner.buffer)):.0f} "
                  f"passes over the buffer), {learner.updates} updates, published {learner.published}: '{name}' on "
                  f"the held-out flights in {e['in']:.5f} out {e['out']:.5f} [{time.perf_counter() - wall:.0f} s]",
                  flush=True)
    if args.json:
        args.json.write_text(json.dumps({"settings": {k: str(v) for k, v in vars(args).items()}, "evaluations": rows,
                                         "f_hat": {k: {w: float(v[w][0]) for w in ("in", "out", "n_in")}
                                                   for k, v in base.items()}}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
