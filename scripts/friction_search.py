"""The search for a friction profile on which a model can matter (issue #11; docs/systems.md has the table).

``./dev python -m scripts.friction_search [--out FILE.jsonl] [--names NAME ...] [--seeds 0 1 2]
[--starts 200]``: for each candidate profile mu(p), the base model's held-out error, the Uniformly Accurate 4-2
net's held-out error overall / inside / outside the region (the paper's training, one model per seed), and the
MPC cost of the base model and of the oracle (the true dynamics) from the experiment's starts, i.e. the headroom.
A candidate fits the paper when UA's errors are about 0.110 / 0.083 / 0.113 (inside / outside about 0.75, inside
2-3 eps) and the headroom is at least 15 %; one line per candidate is appended to the JSON-lines file (done names
are skipped) and the markdown table printed.

Candidate notation: ``const<m>`` constant mu = m; ``default_x<k>`` the sticky_patch profile scaled by k;
``g1_b<m>_a<a>_c<c>_w<w>`` = m + a exp(-((p - c) / w)^2); ``cos_b<m>_a<a>_L<L>[_c<c>]`` = m + a/2 (1 + cos(2 pi (p - c)
/ L)) (peak at c); ``tanh_b<m>_a<a>_s<s>`` = m + a/2 (1 + tanh(p / s)); ``_tilt1`` adds 0.5 (1 + tanh(p));
``gauss3`` bumps at 0 and +-2 m. ``cos_b0.5_a4_L2`` is the ``periodic`` profile.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from saml_ros.core.mpc.dynamics_np import ORACLE
from saml_ros.systems.friction.model import DEFAULT_BUMPS, FrictionDoubleIntegrator

#: one candidate: (name, mu_base, bumps (a, c, w), waves (A, L, phase), tanh steps (a, c, s) a/2 (1 + tanh((p-c)/s)))
Candidate = tuple[str, float, tuple[tuple[float, float, float], ...], tuple[tuple[float, float, float], ...],
                  tuple[tuple[float, float, float], ...]]


class SteppedFriction(FrictionDoubleIntegrator):
    """A friction profile with smooth steps ``a/2 (1 + tanh((p - c) / s))`` added (search candidates only)."""

    def __init__(self, steps: tuple[tuple[float, float, float], ...], **params: Any) -> None:
        super().__init__(**params)
        self.steps = steps

    def friction_decel(self, p: torch.Tensor) -> torch.Tensor:
        mu = super().friction_decel(p)
        for a, c, s in self.steps:
            mu = mu + 0.5 * a * (1.0 + torch.tanh((p - c) / s))
        return mu

    def friction_decel_np(self, p: np.ndarray | float) -> np.ndarray:
        mu = super().friction_decel_np(p)
        for a, c, s in self.steps:
            mu = mu + 0.5 * a * (1.0 + np.tanh((np.asarray(p, dtype=np.float64) - c) / s))
        return mu

    def friction_slope_np(self, p: np.ndarray | float) -> np.ndarray:
        slope = super().friction_slope_np(p)
        for a, c, s in self.steps:
            slope = slope + 0.5 * a / s / np.cosh((np.asarray(p, dtype=np.float64) - c) / s) ** 2
        return slope


def _cos(m: float, a: float, period: float, c: float = 0.0) -> tuple[float, tuple[tuple[float, float, float], ...]]:
    """``m + a/2 (1 + cos(2 pi (p - c) / L))`` as (mu_base, waves)."""
    return m + 0.5 * a, ((0.5 * a, period, -2.0 * math.pi * c / period),)


def candidates() -> list[Candidate]:
    """The candidates of docs/systems.md's search table, in its order."""
    out: list[Candidate] = []
    for m in (1.0, 3.0, 5.0, 7.0):
        out.append((f"const{m:g}", m, (), (), ()))
    for k in (2.0, 3.0):
        out.append((f"default_x{k:g}", k, tuple((k * a, c, w) for a, c, w in DEFAULT_BUMPS), (), ()))
    for a in (3.0, 6.0):
        for c in (0.0, 0.3):
            out.append((f"g1_b2_a{a:g}_c{c:g}_w0.3", 2.0, ((a, c, 0.3),), (), ()))
    out.append(("gauss1_b0.5_a4_w0.6", 0.5, ((4.0, 0.0, 0.6),), (), ()))
    out.append(("gauss3_b0.5_a4_w0.6", 0.5, ((4.0, 0.0, 0.6), (4.0, 2.0, 0.6), (4.0, -2.0, 0.6)), (), ()))
    for a in (4.0, 6.0):
        out.append((f"tanh_b1_a{a:g}_s0.3", 1.0, (), (), ((a, 0.0, 0.3),)))
    grid = [(1.0, 4.0, 0.5), (1.0, 6.0, 0.5)]
    grid += [(b, a, 1.0) for b, a in ((1.0, 3.0), (1.0, 4.0), (1.0, 5.0), (1.0, 6.0), (0.5, 4.0), (2.0, 4.0))]
    grid += [(b, a, 1.5) for b, a in ((1.0, 3.0), (1.0, 4.0), (1.0, 5.0), (0.5, 4.0), (2.0, 4.0))]
    grid += [(0.5, 4.0, 1.75)]
    grid += [(b, a, 2.0) for b, a in ((1.0, 3.0), (1.0, 4.0), (1.0, 5.0), (1.0, 6.0), (0.25, 4.0), (0.5, 4.0),
                                      (0.75, 4.0), (0.5, 3.5), (0.5, 4.5), (0.5, 5.0))]
    for b, a, period in grid:
        mu, waves = _cos(b, a, period)
        out.append((f"cos_b{b:g}_a{a:g}_L{period:g}", mu, (), waves, ()))
    for c in (0.2, 0.4):
        mu, waves = _cos(0.5, 4.0, 2.0, c)
        out.append((f"cos_b0.5_a4_L2_c{c:g}", mu, (), waves, ()))
    mu, waves = _cos(0.5, 4.0, 2.0)
    out.append(("cos_b0.5_a4_L2_tilt1", mu, (), waves, ((1.0, 0.0, 1.0),)))
    mu, waves = _cos(0.5, 4.0, 2.5)
    out.append(("cos_b0.5_a4_L2.5", mu, (), waves, ()))
    return out


def build(c: Candidate) -> FrictionDoubleIntegrator:
    """The system of candidate ``c``."""
    _, mu, bumps, waves, steps = c
    params: dict[str, Any] = {"mu_base": mu, "bumps": [list(b) for b in bumps], "waves": [list(w) for w in waves]}
    return SteppedFriction(steps, **params) if steps else FrictionDoubleIntegrator(**params)


def evaluate(c: Candidate, seeds: list[int], n_starts: int) -> dict[str, Any]:
    """One row of the search table (see the module docstring)."""
    from saml_ros.core.spec import ProblemSpec
    from saml_ros.core.training import TrainConfig
    from saml_ros.experiments.common import quiet_trainer_warnings
    from saml_ros.experiments.friction import FrictionSettings, evaluate_controller, starts
    from saml_ros.offline.pipelines import evaluate_models, generate_datasets, train_models

    t0 = time.process_time()
    s = FrictionSettings()
    system = build(c)
    grid = np.linspace(-2.0, 2.0, 4001)
    mu = system.friction_decel_np(grid)
    xt, ut, yt = system.make_dataset(s.n_test, np.random.default_rng(10_000))
    inside = np.max(np.abs(xt), axis=1) <= 0.5
    base_err = np.linalg.norm(system.base_step_np(xt, ut) - yt, axis=1)
    x0s = starts(s.n_starts if n_starts <= 0 else n_starts, s.start_seed)
    ends = {"base": evaluate_controller(system, None, "fast", x0s, s.steps, s.horizon),
            "oracle": evaluate_controller(system, ORACLE, "fast", x0s, s.steps, s.horizon)}
    spec = ProblemSpec.for_system(system.paper_spec(), system)
    x, u, y = generate_datasets(system, s.n_train, seeds)
    config = TrainConfig.paper(epochs=s.epochs, batch_size=128, primal_lr=1e-3, dual_lr=1e-4)
    with quiet_trainer_warnings():
        ua = train_models(system, spec.uniform(), x, u, y, config, seeds, s.hidden, "residual")
    region = evaluate_models(ua.model, spec, xt, ut, yt).regions[0]
    eps = float(system.paper_spec()["constraints"][0]["eps"])
    rec: dict[str, Any] = {
        "name": c[0], "mu_min": float(mu.min()), "mu_max": float(mu.max()),
        "base_err": {"overall": float(base_err.mean()), "inside": float(base_err[inside].mean()),
                     "outside": float(base_err[~inside].mean())},
        "ua": {"overall": float(region.overall.mean()), "inside": float(region.inside.mean()),
               "outside": float(region.outside.mean())},
        "seeds": seeds, "n_starts": len(x0s)}
    rec["ua"]["in_out"] = rec["ua"]["inside"] / rec["ua"]["outside"] if rec["ua"]["outside"] > 1e-6 else math.nan
    rec["ua"]["inside_over_eps"] = rec["ua"]["inside"] / eps
    for label, r in ends.items():
        rec[label] = {"raw": float(r["raw"].mean()), "norm": float(r["norm"].mean()),
                      "stuck": float(np.mean(r["stuck"]))}
    rec["headroom_raw"] = 1.0 - rec["oracle"]["raw"] / rec["base"]["raw"]
    rec["headroom_norm"] = 1.0 - rec["oracle"]["norm"] / rec["base"]["norm"]
    rec["cpu_seconds"] = time.process_time() - t0
    return rec


def table(rows: list[dict[str, Any]]) -> str:
    head = ("| candidate | mu range (m/s²) | base err | UA overall | UA inside | UA outside | in/out | inside/eps | "
            "base cost | oracle cost | headroom Σ\\|p\\| | headroom Σ\\|p\\|/\\|p0\\| |\n" + "|---" * 12 + "|")
    lines = [head]
    for r in rows:
        ua = r["ua"]
        # a net that fits the profile exactly (constant friction: UA error ~0) has no meaningful in/out ratio
        ratio = "–" if not math.isfinite(ua["in_out"]) or ua["outside"] < 5e-3 else f"{ua['in_out']:.2f}"
        lines.append(f"| {r['name']} | {r['mu_min']:.1f}–{r['mu_max']:.1f} | {r['base_err']['overall']:.3f} | "
                     f"{ua['overall']:.3f} | {ua['inside']:.3f} | {ua['outside']:.3f} | {ratio} | "
                     f"{ua['inside_over_eps']:.1f} | {r['base']['raw']:.2f} | {r['oracle']['raw']:.2f} | "
                     f"{100 * r['headroom_raw']:.1f}% | {100 * r['headroom_norm']:.1f}% |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    ap.add_argument("--out", type=Path, default=Path("results/friction_search.jsonl"))
    ap.add_argument("--names", nargs="*", help="only these candidates (default: all)")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--starts", type=int, default=200)
    args = ap.parse_args(argv)
    from saml_ros.experiments.common import compute_settings

    cands = [c for c in candidates() if not args.names or c[0] in args.names]
    args.out.parent.mkdir(parents=True, exist_ok=True)
    done = {json.loads(line)["name"]: json.loads(line) for line in args.out.read_text().splitlines()} \
        if args.out.exists() else {}
    with compute_settings():
        for c in cands:
            if c[0] in done:
                continue
            rec = evaluate(c, list(args.seeds), args.starts)
            done[c[0]] = rec
            with args.out.open("a") as f:
                f.write(json.dumps(rec) + "\n")
            print(table([rec]).splitlines()[-1], f"[{rec['cpu_seconds']:.0f} s CPU]", flush=True)
    print(table([done[c[0]] for c in cands if c[0] in done]))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
