"""The friction system's simulator world: episode starts and the safe command of a stepped simulator."""

from __future__ import annotations

import numpy as np

from saml_ros.core.worlds.sim_core import SteppedModel
from saml_ros.systems.friction.model import FrictionDoubleIntegrator


def friction_start(rng: np.random.Generator) -> np.ndarray:
    """The paper's MPC starts: p ~ U[-2, 2] m, v = 0."""
    return np.array([rng.uniform(-2.0, 2.0), 0.0])


def friction_model(system: FrictionDoubleIntegrator) -> SteppedModel:
    """Double integrator: safe default u = 0 (``system.safe_control()``), starts from :func:`friction_start`,
    stepped by the numpy true dynamics (``true_step_np``)."""
    return SteppedModel(system, system.safe_control(), friction_start, step=system.true_step_np)
