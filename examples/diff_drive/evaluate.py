"""Does the learned model dock the example robot better than its base model? A closed-loop evaluation under the
generic MPC of ``system.yaml``'s ``mpc:`` section (docs/your_robot.md, "Evaluate it").

    ./dev python examples/diff_drive/evaluate.py --seeds 3 --starts 10 --steps 500 -o runs/dd_eval

The task (headroom first: on the flat floor and from anywhere in the arena the oracle does not dock better than
f_hat, see docs/your_robot.md): the last stretch of the docking, from rest 0.7-1.1 m in front of the dock, straight
through the wet patch, which here also slopes down away from the dock (``dynamics.RAMP_SLIDE``: the base slides
back at up to 0.15 m/s whatever its wheels do; f_hat knows neither the slip nor the slide). The error is the
distance of the last state from the dock (x, y, v, w; ``saml_ros.experiments.robot_eval``).

Trains ``--seeds`` residual models (the file's 32-32 network and spec, one training seed and one data set each) on
transitions of this robot's simulator (random starts, half of them in the dock approach, random commands held
0.1-1 s, a fifth of them stops; what the learner would collect while ``wander.py`` drives), then flies each
model from its own ``--starts`` starts (nested in the seed) beside the base model f_hat and the oracle (the same
planner on the true dynamics, ``dynamics.true_step_on_ramp``) for ``--steps`` steps of 20 ms, and prints the
statistics with the seed as the unit; results.md and results.json go to ``-o``.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np
import torch

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
import dynamics  # noqa: E402


def transitions(n: int, seed: int, slide: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``n`` transitions of the simulator at 20 ms (the target's yaw unwrapped relative to the state, as the learner
    pairs an angle field)."""
    rng = np.random.default_rng(seed)
    xs: list[np.ndarray] = []
    us: list[np.ndarray] = []
    ys: list[np.ndarray] = []
    while len(xs) < n:
        if rng.random() < 0.5:
            start = (rng.uniform(0.7, 1.9), rng.uniform(-0.5, 0.5))
        else:
            start = (rng.uniform(-2.0, 2.0), rng.uniform(-2.0, 2.0))
        r = dynamics.DiffDrive(*start, rng.uniform(-math.pi, math.pi), slide=slide)
        for _ in range(int(rng.integers(2, 10))):
            # a fifth of the commands stop the robot: a robot's log has it standing still too (at its dock)
            u = np.zeros(2) if rng.random() < 0.2 else rng.uniform([-0.5, -1.5], [0.5, 1.5])
            for _ in range(int(rng.integers(5, 50))):
                x = r.state()
                r.step(u, 0.02)
                y = r.state()
                y[2] = x[2] + (y[2] - x[2] + math.pi) % (2 * math.pi) - math.pi
                xs.append(x)
                us.append(u)
                ys.append(y)
    return np.array(xs[:n]), np.array(us[:n]), np.array(ys[:n])


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--seeds", type=int, default=3)
    p.add_argument("--starts", type=int, default=10, help="starts per seed")
    p.add_argument("--steps", type=int, default=500)
    p.add_argument("--transitions", type=int, default=30000)
    p.add_argument("--epochs", type=int, default=60)
    p.add_argument("--smoothing", type=float, default=0.2, help="the planner's rounding of the network's PReLU kinks "
                   "(0 = exact; without it the learned models' plans chatter at the dock)")
    p.add_argument("-o", "--out", type=Path, required=True)
    args = p.parse_args()
    torch.set_num_threads(1)
    from saml_ros.core.model.network import DynamicsModel
    from saml_ros.core.spec import ProblemSpec
    from saml_ros.core.training import PrimalDualTrainer, TrainConfig, Transitions
    from saml_ros.experiments.robot_eval import evaluate_nested
    from saml_ros.user_code import load_system_file

    t0 = time.perf_counter()
    system = load_system_file(HERE / "system.yaml")
    spec = ProblemSpec.for_system(system.paper_spec(), system)
    models = {}
    for seed in range(args.seeds):
        x, u, y = transitions(args.transitions, 100 + seed, dynamics.RAMP_SLIDE)
        model = DynamicsModel(system, tuple(system.paper_hidden), "residual", seed=seed)
        model.fit_normalization(x, u, y)
        trainer = PrimalDualTrainer(model, spec, TrainConfig.paper(epochs=args.epochs, batch_size=256,
                                                                   primal_lr=3e-3, seed=seed))
        trainer.fit(Transitions(model, spec, x, u, y))
        models[f"seed{seed}"] = model.double()
        print(f"trained seed {seed} ({time.perf_counter() - t0:.0f} s)", flush=True)
    ev = evaluate_nested(system, dynamics.make_robot_on_ramp, models, dynamics.sample_approach_starts, args.starts,
                         args.steps, seed=3000, oracle=dynamics.true_step_on_ramp, smoothing=args.smoothing,
                         progress=lambda s: print(s, flush=True))
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "results.json").write_text(json.dumps(ev.to_json(), indent=1))
    (args.out / "results.md").write_text(ev.report() + "\n")
    print(ev.report())
    print(f"total {time.perf_counter() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
