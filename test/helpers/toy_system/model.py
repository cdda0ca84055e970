"""The drag cart's dynamics: x = [p (m), v (m/s)], u = [a (m/s^2)], dt = 0.1 s.

f (true): ``v' = v + dt (a - c v |v|)``, ``p' = p + dt v'``; f_hat (base): the same without the drag.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from saml_ros.core.dynamics.system import System
from saml_ros.core.layout import make_layout


class DragCart(System):
    """A cart on a line pushed by an acceleration command, slowed by quadratic drag ``drag`` (1/m)."""

    name = "toy_drag_cart"
    state = make_layout("toy_drag_cart_state", [("p", "m", "position"), ("v", "m/s", "velocity")])
    control = make_layout("toy_drag_cart_control", [("a", "m/s^2", "acceleration command")])
    target = state
    dt = 0.1
    paper_hidden = (16,)

    def __init__(self, *, drag: float = 2.0, a_max: float = 2.0) -> None:
        self.drag = float(drag)
        self.a_max = float(a_max)

    @property
    def control_low(self) -> np.ndarray:
        return np.array([-self.a_max])

    @property
    def control_high(self) -> np.ndarray:
        return np.array([self.a_max])

    def true_step(self, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        p, v = x[..., 0:1], x[..., 1:2]
        v_next = v + self.dt * (u - self.drag * v * v.abs())
        return torch.cat((p + self.dt * v_next, v_next), dim=-1)

    def base_step(self, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        p, v = x[..., 0:1], x[..., 1:2]
        v_next = v + self.dt * u
        return torch.cat((p + self.dt * v_next, v_next), dim=-1)

    def sample_inputs(self, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        x = np.column_stack((rng.uniform(-2.0, 2.0, n), rng.uniform(-1.5, 1.5, n)))
        return x, rng.uniform(-self.a_max, self.a_max, (n, 1))

    def paper_spec(self) -> dict[str, Any]:
        return {"name": "toy_drag_cart", "objective": {"loss": "l2"}}
