"""Double integrator with position-varying kinetic friction (paper section "Double Integrator with Friction").

State ``x = [p (m), v (m/s)]``, control ``u = [u (m/s^2)]`` (acceleration command), target = next state.

* Base model f_hat (frictionless): ``p' = p + dt v``, ``v' = v + dt u``.
* True model: ``p' = p + dt v``; ``w = v + dt u``; ``b(p) = dt mu(p)``;
  ``v' = 0`` if ``|w| <= b(p)`` else ``w - b(p) sign(w)``, i.e. ``v' = sign(w) max(|w| - b(p), 0)``:
  friction opposes the motion and never reverses the velocity within one step.
* Friction deceleration magnitude (m/s^2):
  ``mu(p) = mu_base + sum_k a_k exp(-((p - c_k) / w_k)^2)`` with ``bumps = ((a_k, c_k, w_k), ...)``.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import torch

from saml_ros.core.layout import make_layout
from saml_ros.core.systems import _checks
from saml_ros.core.systems.base import System

#: default friction bumps (amplitude m/s^2, centre m, width m): a sticky patch just right of the origin
#: (inside the |p| <= 0.5 accuracy region) and a broad one at p = -1.2
DEFAULT_BUMPS: tuple[tuple[float, float, float], ...] = ((2.0, 0.3, 0.25), (1.5, -1.2, 0.4))


class FrictionDoubleIntegrator(System):
    """1-D double integrator; the true model adds position-varying kinetic friction.

    Args:
        dt: sampling period (s), paper: 0.1.
        u_max: control bound (m/s^2), ``|u| <= u_max``, paper: 10.
        mu_base: friction deceleration everywhere (m/s^2), > 0.
        bumps: Gaussian bumps ``(amplitude >= 0 m/s^2, centre m, width > 0 m)`` added to ``mu_base``; also
            accepted flat (``[a1, c1, w1, a2, ...]``, e.g. from a ROS double-array parameter).
    """

    name = "friction"
    state = make_layout("friction_state", [("p", "m", "position"), ("v", "m/s", "velocity")])
    control = make_layout("friction_control", [("u", "m/s^2", "commanded acceleration")])
    target = state
    paper_hidden = (4, 2)

    def __init__(
        self,
        *,
        dt: float = 0.1,
        u_max: float = 10.0,
        mu_base: float = 1.0,
        bumps: Sequence[Sequence[float]] = DEFAULT_BUMPS,
    ) -> None:
        own = type(self).__name__
        self.dt = _checks.positive(own, "dt", dt)
        self.u_max = _checks.positive(own, "u_max", u_max)
        self.mu_base = _checks.positive(own, "mu_base", mu_base)
        if isinstance(bumps, (str, bytes)) or not isinstance(bumps, Sequence):
            raise ValueError(f"{own}: parameter 'bumps' must be a list of [amplitude, centre, width], got {bumps!r}")
        if bumps and all(isinstance(b, (int, float)) for b in bumps):
            if len(bumps) % 3:
                raise ValueError(f"{own}: flat parameter 'bumps' needs 3 numbers per bump, got {len(bumps)}")
            flat: list[Any] = list(bumps)
            bumps = [flat[i : i + 3] for i in range(0, len(flat), 3)]
        checked = []
        for k, bump in enumerate(bumps):
            a, c, w = _checks.real_vector(own, f"bumps[{k}]", bump, 3)
            _checks.real(own, f"bumps[{k}].amplitude", a, lo=0.0)
            _checks.positive(own, f"bumps[{k}].width", w)
            checked.append((a, c, w))
        self.bumps: tuple[tuple[float, float, float], ...] = tuple(checked)

    def params(self) -> dict[str, Any]:
        """Constructor parameters of this instance (``type(self)(**self.params())`` rebuilds it)."""
        return {"dt": self.dt, "u_max": self.u_max, "mu_base": self.mu_base,
                "bumps": [list(b) for b in self.bumps]}

    @property
    def control_low(self) -> np.ndarray:
        return np.array([-self.u_max])

    @property
    def control_high(self) -> np.ndarray:
        return np.array([self.u_max])

    def plausible_state(self) -> dict[str, tuple[float, float]]:
        """|p| <= 1000 m (a long track), |v| <= 100 m/s (10 s at the full 10 m/s^2); the paper's data spans
        |p| <= 2 m, |v| <= 2.5 m/s, and a random-input roll-out of 3000 steps drifts about 100 m."""
        return {"p": (-1000.0, 1000.0), "v": (-100.0, 100.0)}

    def friction_decel(self, p: torch.Tensor) -> torch.Tensor:
        """mu(p): friction deceleration magnitude (m/s^2) at positions ``p`` (any shape, m), > 0."""
        mu = torch.full_like(p, self.mu_base)
        for a, c, w in self.bumps:
            mu = mu + a * torch.exp(-(((p - c) / w) ** 2))
        return mu

    def friction_decrement(self, p: torch.Tensor) -> torch.Tensor:
        """b(p) = dt mu(p): the velocity (m/s) friction removes in one step at positions ``p``."""
        return self.dt * self.friction_decel(p)

    def base_step(self, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        p, v = x[:, 0], x[:, 1]
        return torch.stack((p + self.dt * v, v + self.dt * u[:, 0]), dim=-1)

    def true_step(self, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        p, v = x[:, 0], x[:, 1]
        w = v + self.dt * u[:, 0]
        # Soft-thresholding: 0 when |w| <= b(p), else w - b(p) sign(w).
        v_next = torch.sign(w) * torch.clamp(w.abs() - self.friction_decrement(p), min=0.0)
        return torch.stack((p + self.dt * v, v_next), dim=-1)

    def sample_inputs(self, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """p ~ U[-2, 2] m, v ~ U[-2.5, 2.5] m/s, u ~ U[-u_max, u_max] m/s^2 (paper: u_max = 10)."""
        x = np.stack((rng.uniform(-2.0, 2.0, n), rng.uniform(-2.5, 2.5, n)), axis=1)
        u = rng.uniform(-self.u_max, self.u_max, size=(n, 1))
        return x, u

    def paper_spec(self) -> dict[str, Any]:
        """Selective accuracy: mean l2 error overall, mean l2 error <= 0.035 where ||[p, v]||_inf <= 0.5.

        The constraint is the conditional mean (E[l | region] <= eps): the region holds about 5 % of the
        paper's training distribution, so the unconditional E[l I] <= 0.035 would never be active.
        """
        return {
            "name": "selective_accuracy",
            "objective": {"loss": "l2", "fields": ["p", "v"], "region": None, "mean": "unconditional"},
            "constraints": [
                {
                    "name": "near_origin",
                    "loss": "l2",
                    "fields": ["p", "v"],
                    "region": {"norm": {"fields": ["x.p", "x.v"], "ord": "inf", "max": 0.5}},
                    "eps": 0.035,
                    "mean": "conditional",
                }
            ],
        }
