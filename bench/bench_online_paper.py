"""The online learner on a paper system, ROS-free: does a learner setting change what the paper systems reach?

    ./dev python -m bench.bench_online_paper --system friction --transitions 8000 --updates 30000 --seeds 0 1 2
    ./dev python -m bench.bench_online_paper --system friction ... --set heldout.fraction=0 --set average_updates=0 \\
        --set renormalize=false        # the learner as it was before held-out stretches, averaging and refits

A stream of ``--transitions`` true transitions from the system's paper distribution, stamped every ``dt`` of
stream time (so the learner's held-out stretches are taken as live), is fed to an
:class:`~saml_ros.core.online.OnlineLearner` with its default configuration (``--set`` any :class:`OnlineConfig`
field, ``heldout.<field>`` for the held-out split) in 50 chunks, with ``--updates / 50`` updates after each chunk
and a held-out evaluation (which picks the published weights). The model a checkpoint would hold is then judged on
200,000 fresh transitions of the same distribution: the mean in-region error of each constraint, beside f_hat's
and eps. Same seed, same stream: two settings see exactly the same transitions.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import statistics
import sys
import time
from typing import Any

import numpy as np
import torch

from bench.bench_online_replay import _settings

#: fresh transitions the model is judged on
N_EVAL = 200_000
#: chunks the stream is fed in
CHUNKS = 50


def run_one(system_name: str, n: int, updates: int, seed: int, sets: dict[str, Any]) -> dict[str, Any]:
    """One learner on one stream; returns the published model's in-region errors (and f_hat's) per constraint."""
    from saml_ros.core.online import HeldoutConfig, OnlineConfig, OnlineLearner
    from saml_ros.core.spec import ProblemSpec
    from saml_ros.core.systems import get_system
    from saml_ros.core.training import TrainConfig

    system = get_system(system_name)
    spec = ProblemSpec.for_system(system.paper_spec(), system)
    held = {k.split(".", 1)[1]: v for k, v in sets.items() if k.startswith("heldout.")}
    rest = {k: v for k, v in sets.items() if not k.startswith("heldout.")}
    config = OnlineConfig(train=TrainConfig(seed=seed), **rest)
    if held:
        config = dataclasses.replace(config, heldout=HeldoutConfig(**held))
    learner = OnlineLearner(system, spec, config)
    rng = np.random.default_rng(100 + seed)
    x, u = system.sample_inputs(n, rng)
    y = system.true_step_np(x, u)
    stamp = 100.0 + system.dt * np.arange(n)
    per = n // CHUNKS
    t0 = time.monotonic()
    for c in range(CHUNKS):
        s = slice(c * per, (c + 1) * per)
        learner.add_batch(x[s], u[s], y[s], stamp=stamp[s], source=0)
        learner.update(updates // CHUNKS)
        learner.evaluate_heldout()
    model = learner.published_model()
    xe, ue = system.sample_inputs(N_EVAL, np.random.default_rng(7))
    ye = system.true_step_np(xe, ue)
    pred = np.concatenate([model.predict_np(xe[i:i + 50_000], ue[i:i + 50_000]) for i in range(0, N_EVAL, 50_000)])
    xt, ut, yt = (torch.as_tensor(a, dtype=torch.float64) for a in (xe, ue, ye))
    errors = spec.region_errors(xt, ut, yt, torch.as_tensor(pred, dtype=torch.float64))
    base = spec.region_errors(xt, ut, yt, torch.as_tensor(system.base_step_np(xe, ue), dtype=torch.float64))
    return {"seed": seed, "updates": learner.updates, "published": learner.published,
            "seconds": round(time.monotonic() - t0, 1),
            "constraints": {c.name: {"in": float(errors[c.name]["in"]), "base_in": float(base[c.name]["in"]),
                                     "n_in": int(errors[c.name]["n_in"]), "eps": c.eps} for c in spec.constraints}}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--system", default="friction", help="a registered system: friction | quadrotor | paddle_ball")
    ap.add_argument("--transitions", type=int, default=8000, help="transitions in the stream")
    ap.add_argument("--updates", type=int, default=30000, help="updates over the whole stream")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2], help="train.seed (and the stream's seed)")
    ap.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE", help="an OnlineConfig field")
    ap.add_argument("--json", help="write the results here")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    sets = _settings(args.set)
    results = []
    for seed in args.seeds:
        r = run_one(args.system, args.transitions, args.updates, seed, sets)
        results.append(r)
        errs = ", ".join(f"{k} {v['in']:.5f} (f_hat {v['base_in']:.5f}, eps {v['eps']:g}, n={v['n_in']})"
                         for k, v in r["constraints"].items())
        print(f"seed {seed}: {r['updates']} updates, published {r['published']}, in-region {errs}; {r['seconds']} s",
              flush=True)
    for name in results[0]["constraints"]:
        vals = [r["constraints"][name]["in"] for r in results]
        print(f"{args.system} {name}: in-region error " + " / ".join(f"{v:.5f}" for v in vals)
              + f" (median {statistics.median(vals):.5f}); settings {sets or 'defaults'}")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"system": args.system, "sets": sets, "results": results}, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
