"""The drag cart's MPC problem: ``min sum |p_t - p_goal|  s.t. |a_t| <= a_max`` over the horizon."""

from __future__ import annotations

import numpy as np

from helpers.toy_system.model import DragCart
from saml_ros.core.mpc.shooting.tasks import ShootingTask


def drag_cart_task(system: DragCart, horizon: int = 10) -> ShootingTask:
    return ShootingTask(name="toy_drag_cart", horizon=horizon, u_low=system.control_low, u_high=system.control_high,
                        res_idx=np.array([system.state.index("p")]), target=np.zeros(1), u_default=np.zeros(1))
