"""Closed-loop plans of every built-in system, saved or compared: a change that must not change what the MPC does
(a restructure) shows ``identical`` for all of them.

    ./dev python -m scripts.system_plans --save before.npz     # on the old tree
    ./dev python -m scripts.system_plans --against before.npz  # on the new tree: exit 1 unless identical

Friction and paddle ball with both solvers, the quadrotor with the fast one, each with f_hat and with the oracle
(the true model: the systems' numpy twins of both), from fixed starts, a few steps each (about 30 s); states,
commands, stage costs and the paddle ball's landing points are compared bit for bit. ``bench loop_parts
--against`` checks the quadrotor's lockstep loop the same way.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from saml_ros.core.mpc import closed_loop, make_controller
from saml_ros.core.systems import get_entry, get_system

STARTS: dict[str, list[list[float]]] = {
    "friction": [[1.5, 0.0], [-1.0, 0.3]],
    "quadrotor": [[1.0, -0.5, 2.0, 0, 0, 0, 1, 0, 0, 0, 0, 0, 0.0]],
    "paddle_ball": [[0.05, -0.02, 0.5, 0.1, 0.0, -3.0]],
}


def plans() -> dict[str, np.ndarray]:
    """``{"<system>_<model>_<solver>_<start>_<what>": array}`` of every run."""
    out: dict[str, np.ndarray] = {}
    for name, starts in STARTS.items():
        system = get_system(name)
        goal = get_entry(name).make_goal({})
        horizon = {} if name == "paddle_ball" else {"horizon": 10}
        for model in (None, "oracle"):
            for solver in ("fast",) if name == "quadrotor" else ("fast", "slsqp"):
                ctrl = make_controller(system, model, solver, **horizon)
                for i, x0 in enumerate(starts):
                    run = closed_loop(system, ctrl, np.array(x0), 15 if name == "quadrotor" else 8, goal=goal)
                    key = f"{name}_{model}_{solver}_{i}"
                    out |= {f"{key}_xs": run.xs, f"{key}_us": run.us, f"{key}_stage": run.stage_costs}
                    if run.landing is not None:
                        out[f"{key}_landing"] = run.landing
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--save", type=Path, metavar="NPZ", help="save the plans")
    ap.add_argument("--against", type=Path, metavar="NPZ", help="compare with saved plans (exit 1 unless identical)")
    args = ap.parse_args(argv)
    now = plans()
    if args.save is not None:
        np.savez(args.save, **now)  # type: ignore[arg-type]
        print(f"saved {len(now)} arrays to {args.save}")
    if args.against is None:
        return 0
    ref = np.load(args.against)
    different = sorted(k for k in set(ref.files) | set(now)
                       if k not in ref.files or k not in now or not np.array_equal(ref[k], now[k]))
    print(f"against {args.against}: {len(now)} arrays, " + (f"DIFFERENT: {different}" if different else "identical"))
    return 1 if different else 0


if __name__ == "__main__":
    sys.exit(main())
