"""Ball bouncing on a paddle: the impact map (paper section "Ball Bouncing").

State (6): the ball just before impact ``[px, py, pz (m), vx, vy, vz (m/s)]`` (world frame, z up).
Control (6): ``[pvx, pvy, pvz (m/s)]`` paddle velocity at impact and ``[nx, ny, nz]`` the commanded paddle
normal (unit, world; normalised inside the dynamics). Target (3): the ball velocity just after impact,
layout ``post_impact_velocity`` with fields ``[vx, vy, vz]``. Event based: ``dt = 0``.

Impact model, exactly as printed in the paper (eq. ball_base_model):

    v_rel = v_ball - v_paddle
    v_ball+ = a (v_rel - 2 n (n . v_rel)) + v_paddle

i.e. the relative velocity is mirrored in the paddle plane and *both* its normal and tangential parts are
scaled by the restitution ``a``. True model: ``a = restitution_true`` and the real paddle normal is
``R_y(normal_bias_y) n`` (an unobserved hand-to-paddle rotation). Base model f_hat: ``a = restitution_base``
and ``n`` as commanded.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

import numpy as np

from saml_ros.core.dynamics import checks as _checks
from saml_ros.core.dynamics.system import System
from saml_ros.core.layout import make_layout

if TYPE_CHECKING:
    import torch

_STATE = [
    ("px", "m", "ball position x before impact"), ("py", "m", "ball position y before impact"),
    ("pz", "m", "ball position z before impact"), ("vx", "m/s", "ball velocity x before impact"),
    ("vy", "m/s", "ball velocity y before impact"), ("vz", "m/s", "ball velocity z before impact"),
]  # fmt: skip
_CONTROL = [
    ("pvx", "m/s", "paddle velocity x at impact"), ("pvy", "m/s", "paddle velocity y at impact"),
    ("pvz", "m/s", "paddle velocity z at impact"), ("nx", "1", "commanded paddle normal x (world)"),
    ("ny", "1", "commanded paddle normal y (world)"), ("nz", "1", "commanded paddle normal z (world)"),
]  # fmt: skip
_TARGET = [
    ("vx", "m/s", "ball velocity x after impact"), ("vy", "m/s", "ball velocity y after impact"),
    ("vz", "m/s", "ball velocity z after impact"),
]  # fmt: skip


def impact(v_ball: torch.Tensor, v_paddle: torch.Tensor, normal: torch.Tensor, restitution: float) -> torch.Tensor:
    """The paper's impact map; ``(B, 3) x 3 -> (B, 3)`` post-impact ball velocity (m/s).

    ``normal`` is normalised here (commanded normals may be slightly off unit length).
    """
    import torch

    n = normal / torch.linalg.vector_norm(normal, dim=-1, keepdim=True).clamp_min(1e-12)
    v_rel = v_ball - v_paddle
    mirrored = v_rel - 2.0 * n * (n * v_rel).sum(-1, keepdim=True)
    return restitution * mirrored + v_paddle


def rotate_y(v: torch.Tensor, angle: float) -> torch.Tensor:
    """Rotate vectors ``(..., 3)`` by ``angle`` (rad) about the world y axis."""
    import torch

    c, s = math.cos(angle), math.sin(angle)
    x, y, z = v.unbind(-1)
    return torch.stack((c * x + s * z, y, -s * x + c * z), dim=-1)


def normal_from_roll_pitch(roll: torch.Tensor, pitch: torch.Tensor) -> torch.Tensor:
    """Paddle normal ``R_y(pitch) R_x(roll) e_z = [cos r sin p, -sin r, cos r cos p]``; ``(...) -> (..., 3)``.

    Roll and pitch (rad) as in ROS RPY with zero yaw. A rotation about y adds to the pitch, so the true
    model's normal bias is ``pitch + normal_bias_y``.
    """
    import torch

    cr = torch.cos(roll)
    return torch.stack((cr * torch.sin(pitch), -torch.sin(roll), cr * torch.cos(pitch)), dim=-1)


def roll_pitch_from_normal(n: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Inverse of :func:`normal_from_roll_pitch` for ``nz > 0`` (any length); ``(..., 3) -> (...), (...)``."""
    import torch

    nx, ny, nz = n.unbind(-1)
    roll = torch.atan2(-ny, torch.sqrt(nx * nx + nz * nz))
    pitch = torch.atan2(nx, nz)
    return roll, pitch


def landing_point(p: torch.Tensor, v_post: torch.Tensor, g: float = 9.81) -> torch.Tensor:
    """Where (xy, m) a ball leaving ``p`` (m, ``(B, 3)``) with velocity ``v_post`` (m/s, ``(B, 3)``) is back at
    its current height: ballistic flight of ``2 vz / g`` seconds; ``p``'s xy when ``vz <= 0``. ``-> (B, 2)``.

    Differentiable (the flight time's gradient is 0 for ``vz <= 0``).
    """
    import torch

    t = 2.0 * torch.clamp(v_post[..., 2:3], min=0.0) / g
    return p[..., 0:2] + v_post[..., 0:2] * t


class PaddleBall(System):
    """Paddle-ball impact map; the base model has the wrong restitution and misses a paddle-normal bias.

    Args:
        restitution_true: restitution of the true model (simulator), in (0, 1].
        restitution_base: restitution assumed by the base model f_hat, in (0, 1].
        normal_bias_y: unobserved rotation (rad) about world y from the commanded to the real paddle normal.
        g: gravity (m/s^2), used by :meth:`landing_point`.
        slow_fraction: fraction of :meth:`sample_inputs` drawn as cushioned catches (slow post-impact balls).
    """

    name = "paddle_ball"
    state = make_layout("paddle_ball_state", _STATE)
    control = make_layout("paddle_ball_control", _CONTROL)
    target = make_layout("post_impact_velocity", _TARGET)
    dt = 0.0
    paper_hidden = (128, 128)

    def __init__(
        self,
        *,
        restitution_true: float = 0.8,
        restitution_base: float = 0.6,
        normal_bias_y: float = 0.2,
        g: float = 9.81,
        slow_fraction: float = 0.1,
    ) -> None:
        own = type(self).__name__
        self.restitution_true = _checks.real(own, "restitution_true", restitution_true, lo=0.0, hi=1.0, lo_open=True)
        self.restitution_base = _checks.real(own, "restitution_base", restitution_base, lo=0.0, hi=1.0, lo_open=True)
        self.normal_bias_y = _checks.real(own, "normal_bias_y", normal_bias_y, lo=-math.pi / 2, hi=math.pi / 2)
        self.g = _checks.positive(own, "g", g)
        self.slow_fraction = _checks.real(own, "slow_fraction", slow_fraction, lo=0.0, hi=1.0)

    def params(self) -> dict[str, Any]:
        """Constructor parameters of this instance (``type(self)(**self.params())`` rebuilds it)."""
        return {"restitution_true": self.restitution_true, "restitution_base": self.restitution_base,
                "normal_bias_y": self.normal_bias_y, "g": self.g, "slow_fraction": self.slow_fraction}

    @property
    def control_low(self) -> np.ndarray:
        """Paddle velocity bounds (m/s), then normal components (tilt limits belong to the controller)."""
        return np.array([-1.0, -1.0, -3.0, -1.0, -1.0, 0.0])

    @property
    def control_high(self) -> np.ndarray:
        return np.array([1.0, 1.0, 4.0, 1.0, 1.0, 1.0])

    def plausible_state(self) -> dict[str, tuple[float, float]]:
        """Ball before impact within 10 m of the paddle's workspace horizontally, -5 .. 10 m high, speeds <= 30 m/s
        per axis (a ball dropped from 45 m); the paper's data spans +-1 m, +-0.05 m, 6 m/s."""
        out = {f: (-10.0, 10.0) for f in ("px", "py")}
        out["pz"] = (-5.0, 10.0)
        out.update({f: (-30.0, 30.0) for f in ("vx", "vy", "vz")})
        return out

    def plausible_target(self) -> dict[str, tuple[float, float]]:
        """Post-impact ball velocity <= 30 m/s per axis."""
        return {f: (-30.0, 30.0) for f in self.target.names}

    def safe_control(self) -> np.ndarray:
        """Level paddle at rest: ``[pvx, pvy, pvz] = 0``, normal ``[0, 0, 1]``."""
        return np.array([0.0, 0.0, 0.0, 0.0, 0.0, 1.0])

    def base_step(self, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        return impact(x[:, 3:6], u[:, 0:3], u[:, 3:6], self.restitution_base)

    def true_step(self, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        return impact(x[:, 3:6], u[:, 0:3], rotate_y(u[:, 3:6], self.normal_bias_y), self.restitution_true)

    def landing_point(self, p: torch.Tensor, v_post: torch.Tensor) -> torch.Tensor:
        """:func:`landing_point` with this system's gravity; ``(B, 3), (B, 3) -> (B, 2)`` (m)."""
        return landing_point(p, v_post, self.g)

    def sample_inputs(self, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """Impacts of a ball bounced on a paddle around the origin (see docs/systems.md).

        Bounces (fraction ``1 - slow_fraction``): ball at px, py ~ U[-1, 1] m, pz ~ U[-0.05, 0.05] m;
        falling with vx, vy ~ U[-1, 1] and vz ~ U[-6, -2] m/s; paddle velocity pvx, pvy ~ U[-0.5, 0.5] and
        pvz ~ U[0, 2] m/s (|v_rel| spans about [2, 8] m/s, covering the controller's [3, 6]).
        Cushioned catches (fraction ``slow_fraction``): ball falling slowly, vx, vy ~ U[-0.1, 0.1],
        vz ~ U[-0.5, -0.05] m/s; the paddle moves with it at k * v_ball, k ~ U[0.3, 0.6], so the ball still
        approaches the paddle but leaves slowly: about half of them end below 0.1 m/s (the "slow balls").
        Normals: uniform on the cap within 0.35 rad of vertical.
        """
        slow = rng.random(n) < self.slow_fraction
        p = np.stack((rng.uniform(-1, 1, n), rng.uniform(-1, 1, n), rng.uniform(-0.05, 0.05, n)), axis=1)
        v_fast = np.stack((rng.uniform(-1, 1, n), rng.uniform(-1, 1, n), rng.uniform(-6, -2, n)), axis=1)
        v_slow = np.stack(
            (rng.uniform(-0.1, 0.1, n), rng.uniform(-0.1, 0.1, n), rng.uniform(-0.5, -0.05, n)), axis=1
        )
        v = np.where(slow[:, None], v_slow, v_fast)
        pv_fast = np.stack((rng.uniform(-0.5, 0.5, n), rng.uniform(-0.5, 0.5, n), rng.uniform(0, 2, n)), axis=1)
        pv_slow = rng.uniform(0.3, 0.6, size=(n, 1)) * v
        pv = np.where(slow[:, None], pv_slow, pv_fast)
        cos_tilt = rng.uniform(math.cos(0.35), 1.0, n)
        sin_tilt = np.sqrt(1.0 - cos_tilt**2)
        phi = rng.uniform(0.0, 2 * math.pi, n)
        normal = np.stack((sin_tilt * np.cos(phi), sin_tilt * np.sin(phi), cos_tilt), axis=1)
        return np.concatenate((p, v), axis=1), np.concatenate((pv, normal), axis=1)

    def paper_spec(self) -> dict[str, Any]:
        """Normalized objective: E[||e|| / ||y|| ; ||y|| >= 0.1] (unconditional), s.t. E[||e|| | ||y|| < 0.1] <= 0.1."""
        fast = {"norm": {"fields": ["next.vx", "next.vy", "next.vz"], "ord": 2, "min": 0.1}}
        return {
            "name": "normalized_objective",
            "objective": {"loss": "normalized", "fields": ["vx", "vy", "vz"], "region": fast,
                          "mean": "unconditional"},
            "constraints": [
                {
                    "name": "slow_balls",
                    "loss": "l2",
                    "fields": ["vx", "vy", "vz"],
                    "region": {"not": fast},
                    "eps": 0.1,
                    "mean": "conditional",
                }
            ],
        }
