"""The quadrotor's simulator world: episode starts, the ground (landing height), the safe command."""

from __future__ import annotations

import math

import numpy as np

from saml_ros.core.worlds.sim_core import SteppedModel
from saml_ros.systems.quadrotor.dynamics_np import QuadrotorTrueNP
from saml_ros.systems.quadrotor.model import Quadrotor


def quadrotor_start(system: Quadrotor, rng: np.random.Generator) -> np.ndarray:
    """Landing-task starts: x, y ~ U[-2, 2] m, z ~ U[1, 3] m, level, at rest (v = 0, omega = 0)."""
    return system.hover_state((rng.uniform(-2.0, 2.0), rng.uniform(-2.0, 2.0), rng.uniform(1.0, 3.0)))


def ground_contact(x: np.ndarray, landing_height: float) -> tuple[np.ndarray, bool]:
    """The quadrotor's ground: the centre of mass cannot go below ``landing_height`` (m).

    Contact happens when the integrated state is below the landing height, or at it while still moving
    down. Then ``pz = landing_height``, a downward ``vz`` becomes 0 and the body rates become 0 (the body
    rests on its legs); horizontal velocity and attitude are kept (frictionless, no tipping).
    Returns ``(state, touched)``; ``x`` is not modified.
    """
    pz, vz = x[2], x[5]
    if pz > landing_height or (pz == landing_height and vz >= 0.0):
        return x, False
    out = x.copy()
    out[2] = landing_height
    out[5] = max(vz, 0.0)
    out[10:13] = 0.0
    return out, True


def _normalize_quaternion(x: np.ndarray) -> np.ndarray:
    out = np.asarray(x, dtype=np.float64).copy()
    norm = float(np.linalg.norm(out[6:10]))
    if not norm > 1e-9:
        raise ValueError(f"initial_state: the quaternion [qw, qx, qy, qz] = {out[6:10]} has no direction")
    out[6:10] /= norm
    return out


def quadrotor_model(system: Quadrotor, landing_height: float = 0.1) -> SteppedModel:
    """Quadrotor: safe default = hover thrust (``system.safe_control()``), starts from :func:`quadrotor_start`,
    :func:`ground_contact`, stepped by the numpy true dynamics (the oracle's :class:`QuadrotorTrueNP`)."""
    if not (math.isfinite(landing_height) and landing_height >= 0):
        raise ValueError(f"landing_height must be a finite number >= 0 m, got {landing_height}")
    return SteppedModel(
        system,
        system.safe_control(),
        lambda rng: quadrotor_start(system, rng),
        lambda x: ground_contact(x, landing_height),
        _normalize_quaternion,
        step=QuadrotorTrueNP(system).step1,
    )
