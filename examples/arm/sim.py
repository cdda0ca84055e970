"""The example arm's physics (MuJoCo, no ROS): ``arm.xml`` stepped under a held joint torque.

State ``[q1, q2, dq1, dq2]``: shoulder and elbow angles (rad) and rates (rad/s), as the joint encoders report them
(with a little measurement noise). Command ``[tau1, tau2]`` (N*m), clipped to the motors' ranges and held for a
control period. The payload, the joint friction and the elbow spring of ``arm.xml`` are what the user's base
model does not know.

saml_ros never sees this file: it learns from the topics the robot node (``robot.py``) publishes.
"""

from __future__ import annotations

from pathlib import Path

import mujoco
import numpy as np

MJCF = Path(__file__).resolve().parent / "arm.xml"
JOINTS = ("shoulder", "elbow")
#: measurement noise (std) of the encoders' angle (rad) and rate (rad/s)
NOISE_Q, NOISE_DQ = 1e-4, 2e-3


class ArmSim:
    """The simulated arm; :meth:`step` advances ``dt`` seconds under a held torque command.

    Args:
        q0: initial joint angles (rad), default hanging straight down.
        seed: seed of the measurement noise.
        noise: scale of the measurement noise (0 = exact readings).
        unknown_effects: False removes the payload, the joint friction and the elbow spring (the model the base
            model describes exactly; for checking it).
    """

    def __init__(self, q0: tuple[float, float] = (-np.pi / 2, 0.0), seed: int = 0, noise: float = 1.0,
                 unknown_effects: bool = True) -> None:
        self.model = mujoco.MjModel.from_xml_path(str(MJCF))
        if not unknown_effects:
            self.model.body_mass[self.model.body("payload").id] = 0.0
            self.model.body_inertia[self.model.body("payload").id] = 0.0
            self.model.dof_damping[:] = 0.0
            self.model.dof_frictionloss[:] = 0.0
            self.model.tendon_stiffness[:] = 0.0
        self.data = mujoco.MjData(self.model)
        self.data.qpos[:] = q0
        mujoco.mj_forward(self.model, self.data)
        self.rng = np.random.default_rng(seed)
        self.noise = float(noise)
        self.ctrl_low = self.model.actuator_ctrlrange[:, 0].copy()
        self.ctrl_high = self.model.actuator_ctrlrange[:, 1].copy()
        self.applied = np.zeros(2)

    @property
    def timestep(self) -> float:
        """MuJoCo's integration step (s)."""
        return float(self.model.opt.timestep)

    def true_state(self) -> np.ndarray:
        """``[q1, q2, dq1, dq2]`` exactly."""
        return np.concatenate([self.data.qpos, self.data.qvel]).astype(np.float64)

    def measure(self) -> np.ndarray:
        """``[q1, q2, dq1, dq2]`` as the encoders report it (with noise)."""
        noise = self.rng.normal(0.0, 1.0, 4) * np.array([NOISE_Q, NOISE_Q, NOISE_DQ, NOISE_DQ]) * self.noise
        return self.true_state() + noise

    def step(self, tau: np.ndarray, dt: float) -> None:
        """Hold torque ``tau`` (N*m, clipped to the motors' ranges) for ``dt`` s."""
        tau = np.asarray(tau, dtype=np.float64)
        self.applied = np.clip(np.where(np.isfinite(tau), tau, 0.0), self.ctrl_low, self.ctrl_high)
        self.data.ctrl[:] = self.applied
        n = max(1, round(dt / self.timestep))
        for _ in range(n):
            mujoco.mj_step(self.model, self.data)
