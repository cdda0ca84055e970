"""The quadrotor's MPC problem (paper eq. quad3d_mpc: landing at a target) as a shooting task."""

from __future__ import annotations

import math

import numpy as np

from saml_ros.core.mpc.shooting.tasks import ShootingTask
from saml_ros.systems.quadrotor.model import Quadrotor


def quadrotor_task(
    system: Quadrotor, horizon: int = 10, min_height: float = 0.2, qw_tol: float = 0.05,
    tilt_max: float = math.inf,
) -> ShootingTask:
    """Paper eq. quad3d_mpc: ``min sum ||p_t - p_goal||_2  s.t. 0 <= u <= f_max, pz_t >= min_height (all t),
    |qw_T - 1| <= qw_tol`` (only ``qw_T >= 1 - qw_tol`` can bind: a unit quaternion has ``qw <= 1``).

    ``tilt_max`` (finite, in (0, 1)): also ``|qx_t| <= tilt_max`` and ``|qy_t| <= tilt_max`` at every step
    t = 1..T (linear rows; 0.2 is a tilt of about 23 degrees about a horizontal axis). Not in the paper: it keeps
    a plan from buying a fast horizontal dash with a steep bank, which the height bound alone allows (from far
    or fast starts such plans ended metres off target even with the exact model, docs/mpc.md)."""
    if not 0.0 < qw_tol < 1.0:
        raise ValueError(f"quadrotor MPC: qw_tol must be in (0, 1), got {qw_tol}")
    if not (math.isinf(tilt_max) and tilt_max > 0) and not 0.0 < tilt_max < 1.0:
        raise ValueError(f"quadrotor MPC: tilt_max must be in (0, 1) or inf, got {tilt_max}")
    t = np.arange(1, horizon + 1)
    iz, iqw = system.state.index("pz"), system.state.index("qw")
    cons_t, cons_idx = [t], [np.full(horizon, iz)]
    cons_sign, cons_bound = [np.full(horizon, -1.0)], [np.full(horizon, -min_height)]
    names = [f"height pz_{i}" for i in t]
    if math.isfinite(tilt_max):
        for name in ("qx", "qy"):
            for sign in (1.0, -1.0):
                cons_t.append(t)
                cons_idx.append(np.full(horizon, system.state.index(name)))
                cons_sign.append(np.full(horizon, sign))
                cons_bound.append(np.full(horizon, tilt_max))
                names += [f"tilt {'+' if sign > 0 else '-'}{name}_{i}" for i in t]
    return ShootingTask(
        name="quadrotor",
        horizon=horizon,
        u_low=system.control_low.astype(np.float64),
        u_high=system.control_high.astype(np.float64),
        res_idx=np.array([system.state.index(n) for n in ("px", "py", "pz")]),
        target=np.zeros(3),
        u_default=system.hover_thrust(),
        u_starts=np.tile(system.hover_thrust(), (1, horizon, 1)),  # cold start only: keeps the solve fast
        cons_t=np.concatenate(cons_t),
        cons_idx=np.concatenate(cons_idx),
        cons_sign=np.concatenate(cons_sign),
        cons_bound=np.concatenate(cons_bound),
        cons_name=tuple(names),
        att_tol=qw_tol,
        att_qw=iqw,
        att_qv=(iqw + 1, iqw + 2, iqw + 3),
    )
