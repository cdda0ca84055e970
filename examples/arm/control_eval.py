"""Does the learned model make saml_ros's MPC reach the shelf better than the arm's own rigid-body model? A
closed-loop evaluation of ``system.yaml``'s ``mpc:`` section (docs/your_robot.md, "Control it").

    ./dev python examples/arm/control_eval.py --seeds 3 --starts 10 -o runs/arm_control

Trains ``--seeds`` residual models (the file's 32-32 network and shelf spec, one training seed and one flight
each) on transitions the arm's own controller (``controller.Reacher``: reaching moves, half of them to the shelf,
exploration noise) flies in the simulator (``sim.ArmSim``, MuJoCo, with the payload, friction and spring f_hat
lacks; 100 Hz, the torque held for each period, as the driver applies it), then flies each model from its own
``--starts`` starts (nested in the seed: at rest in random postures on or near the shelf) beside the base model
f_hat to the file's goal (the gripper at x 0.6 m, z 0) for ``--steps`` periods, the generic MPC answering every
measured (noisy) state. The error is the distance of the last state from the goal (q1, q2 in rad, dq1, dq2 in
rad/s). No oracle: the arm's true dynamics (MuJoCo) have no differentiable form here, so the headroom is not
measured (the learned model's own error shows how much f_hat leaves).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from controller import Reacher  # noqa: E402
from sim import ArmSim  # noqa: E402

DT = 0.01  # s, the file's period


class ArmEpisode:
    """``sim.ArmSim`` for ``saml_ros.experiments.robot_eval``: ``state()`` is the measured (noisy) state."""

    def __init__(self, x0: np.ndarray, seed: int = 0) -> None:
        self.sim = ArmSim(q0=(float(x0[0]), float(x0[1])), seed=seed)
        self.sim.data.qvel[:] = x0[2:4]

    def state(self) -> np.ndarray:
        return self.sim.measure()

    def step(self, u: np.ndarray, dt: float) -> None:
        self.sim.step(u, dt)


def make_arm(x0: np.ndarray) -> ArmEpisode:
    """The simulated arm at ``x0 = [q1, q2, dq1, dq2]``."""
    return ArmEpisode(x0)


def sample_starts(n: int, rng: np.random.Generator) -> np.ndarray:
    """``n`` starts at rest: postures on or near the shelf (q1 -0.3-1.6 rad, q2 -2.3 to -0.5 rad)."""
    out = np.zeros((n, 4))
    out[:, 0] = rng.uniform(-0.3, 1.6, n)
    out[:, 1] = rng.uniform(-2.3, -0.5, n)
    return out


def flight(n: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``n`` transitions of the arm under its own controller at 100 Hz (measured states, the applied torque)."""
    sim = ArmSim(seed=seed)
    reacher = Reacher(seed=seed)
    xs, us, ys = np.zeros((n, 4)), np.zeros((n, 2)), np.zeros((n, 4))
    x = sim.measure()
    for k in range(n):
        u = reacher.command(k * DT, x[:2], x[2:])
        sim.step(u, DT)
        y = sim.measure()
        xs[k], us[k], ys[k] = x, sim.applied, y
        x = y
    return xs, us, ys


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--seeds", type=int, default=3)
    p.add_argument("--starts", type=int, default=10, help="starts per seed")
    p.add_argument("--steps", type=int, default=200, help="periods of 10 ms per episode")
    p.add_argument("--transitions", type=int, default=30000)
    p.add_argument("--epochs", type=int, default=60)
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
        x, u, y = flight(args.transitions, 100 + seed)
        keep = np.all((x >= system.state_low) & (x <= system.state_high), axis=1)
        model = DynamicsModel(system, tuple(system.paper_hidden), "residual", seed=seed)
        model.fit_normalization(x[keep], u[keep], y[keep])
        trainer = PrimalDualTrainer(model, spec, TrainConfig.paper(epochs=args.epochs, batch_size=256,
                                                                   primal_lr=3e-3, seed=seed))
        trainer.fit(Transitions(model, spec, x[keep], u[keep], y[keep]))
        models[f"seed{seed}"] = model.double()
        print(f"trained seed {seed} on {int(keep.sum())} transitions ({time.perf_counter() - t0:.0f} s)", flush=True)
    ev = evaluate_nested(system, make_arm, models, sample_starts, args.starts, args.steps, seed=2000,
                         progress=lambda s: print(s, flush=True))
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "results.json").write_text(json.dumps(ev.to_json(), indent=1))
    (args.out / "results.md").write_text(ev.report() + "\n")
    print(ev.report())
    print(f"total {time.perf_counter() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
