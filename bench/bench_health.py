"""What the training-health guard costs (saml_ros.core.training.health), measured in one run.

``./dev bench health`` (about a minute). For the paper's friction (4-2) and quadrotor (16-8) networks at batch 128:

1. the plain step (``primal_dual_step``, what online learning takes) against the same step without the guard (the
   unguarded step is written out here, as it was before the guard existed);
2. the fast engine's ``fit`` with the default block check (every ``check_every = 10`` steps) against checks only
   at the log points and epoch ends (``check_every`` = 10^9).

Rounds alternate between the variants; each variant's best round counts (load only slows a round down).
"""

from __future__ import annotations

import argparse
import logging
import time
from collections.abc import Callable, Mapping, Sequence

import numpy as np
import torch

from saml_ros.core.model.network import DynamicsModel
from saml_ros.core.spec import ProblemSpec, SpecValues
from saml_ros.core.systems import get_system
from saml_ros.core.training import PrimalDualTrainer, TrainConfig, Transitions
from saml_ros.core.training.health import HealthConfig


def unguarded_step(run: PrimalDualTrainer, x: torch.Tensor, u: torch.Tensor, y: torch.Tensor) -> SpecValues:
    """``primal_dual_step`` without the health checks (the reference)."""
    pred = run.model(x, u)
    vals = run.spec.evaluate_with_masks(y, pred, run.spec.masks(x, u, y))
    loss = run.dual.lagrangian(vals).sum()
    run.primal_opt.zero_grad(set_to_none=True)
    loss.backward()
    run.primal_opt.step()
    run.dual.step(vals.constraints.detach())
    run.steps += 1
    out = SpecValues(vals.objective.detach(), vals.constraints.detach(), vals.region_fraction.detach())
    run.log.add(out)
    return out


def _trainer(name: str, health: HealthConfig | None = None, **cfg: object) -> tuple[PrimalDualTrainer, Transitions]:
    system = get_system(name)
    spec = ProblemSpec.for_system(system.paper_spec(), system)
    x, u, y = system.make_dataset(10_000, np.random.default_rng(0))
    model = DynamicsModel(system, seed=0)
    model.fit_normalization(x, u, y)
    tr = PrimalDualTrainer(model, spec, TrainConfig(batch_size=128, **cfg), health)  # type: ignore[arg-type]
    return tr, Transitions(model, spec, x, u, y)


def best_of(variants: Mapping[str, Callable[[], float]], rounds: int) -> dict[str, float]:
    """Alternate the variants for ``rounds`` rounds; each one's smallest time per step (s)."""
    best = dict.fromkeys(variants, float("inf"))
    for _ in range(rounds):
        for name, run in variants.items():
            best[name] = min(best[name], run())
    return best


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--steps", type=int, default=300, help="plain steps per round")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    logging.getLogger("saml_ros.trainer").setLevel(logging.ERROR)  # the short fits' verdicts are not the point here
    import os

    print(f"training-health overhead (load {os.getloadavg()[0]:.1f}); times per step, best of {args.rounds} rounds")
    for name in ("friction", "quadrotor"):
        tr, data = _trainer(name)
        rng = torch.Generator().manual_seed(0)
        batches = [data.take(torch.randint(0, len(data), (1, 128), generator=rng))[:3] for _ in range(16)]

        def plain(step: Callable[..., SpecValues], tr: PrimalDualTrainer = tr,
                  batches: list[tuple[torch.Tensor, ...]] = batches) -> float:
            t0 = time.perf_counter()
            for i in range(args.steps):
                x, u, y = batches[i % len(batches)]
                step(tr, x[0], u[0], y[0])
            tr.log.take_pending()
            return (time.perf_counter() - t0) / args.steps

        plain(unguarded_step)
        res = best_of({"guarded": lambda: plain(PrimalDualTrainer.step),
                       "unguarded": lambda: plain(unguarded_step)}, args.rounds)
        print(f"{name:10s} plain step: guarded {1e6 * res['guarded']:7.1f} us, unguarded "
              f"{1e6 * res['unguarded']:7.1f} us: overhead {100 * (res['guarded'] / res['unguarded'] - 1):+.1f} %")
        fast: dict[str, Callable[[], float]] = {}
        for label, every in (("checks every 10 steps", 10), ("checks at log points only", 10**9)):
            ftr, fdata = _trainer(name, HealthConfig(check_every=every), epochs=1)
            ftr.fit(fdata, epochs=1)
            steps = len(fdata) // 128

            def fit(ftr: PrimalDualTrainer = ftr, fdata: Transitions = fdata, steps: int = steps) -> float:
                t0 = time.perf_counter()
                ftr.fit(fdata, epochs=3)
                return (time.perf_counter() - t0) / (3 * steps)

            fast[label] = fit
        res = best_of(fast, args.rounds)
        a, b = res["checks every 10 steps"], res["checks at log points only"]
        print(f"{name:10s} fast engine: every 10 steps {1e6 * a:7.1f} us, at log points only {1e6 * b:7.1f} us: "
              f"overhead {100 * (a / b - 1):+.1f} %")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
