"""The friction system's MPC problem (paper eq. double_integrator_mpc) as a shooting task."""

from __future__ import annotations

import numpy as np

from saml_ros.core.mpc.shooting.tasks import ShootingTask, push_brake_sequences
from saml_ros.systems.friction.model import FrictionDoubleIntegrator


def friction_task(system: FrictionDoubleIntegrator, horizon: int = 10) -> ShootingTask:
    """Paper eq. double_integrator_mpc: ``min sum |p_t - p_goal|  s.t. |u_t| <= u_max`` (goal: position, m)."""
    return ShootingTask(
        name="friction",
        horizon=horizon,
        u_low=system.control_low.astype(np.float64),
        u_high=system.control_high.astype(np.float64),
        res_idx=np.array([system.state.index("p")]),
        target=np.zeros(1),
        u_default=np.zeros(1),
        # a learned model reproduces stiction (dv'/du = 0 around u = 0 at rest, flat predicted cost): a solver
        # started at rest, or from a shifted plan that rests, stays there; push-brake candidates leave it
        u_starts=push_brake_sequences(system.u_max, horizon),
        starts_every_solve=True,
    )
