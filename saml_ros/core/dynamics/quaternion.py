"""Batched torch quaternion helpers (Hamilton convention, scalar first: ``q = [w, x, y, z]``).

All functions take tensors whose last dimension is 4 (quaternions) or 3 (vectors), broadcast over the
leading dimensions, keep the input dtype, are differentiable and contain no Python branching on tensor
values. A unit quaternion ``q`` maps body-frame vectors to the world frame: ``v_w = q ⊗ [0, v_b] ⊗ q*``.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    import torch


def quat_mul(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Hamilton product ``a ⊗ b``; ``(..., 4), (..., 4) -> (..., 4)``."""
    import torch

    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack(
        (
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ),
        dim=-1,
    )


def quat_conj(q: torch.Tensor) -> torch.Tensor:
    """Conjugate ``[w, -x, -y, -z]`` (the inverse of a unit quaternion); ``(..., 4) -> (..., 4)``."""
    return q * q.new_tensor([1.0, -1.0, -1.0, -1.0])


def quat_normalize(q: torch.Tensor, eps: float = 1e-12) -> torch.Tensor:
    """``q / ||q||`` with the norm clamped below at ``eps``; ``(..., 4) -> (..., 4)``."""
    import torch

    return q / torch.linalg.vector_norm(q, dim=-1, keepdim=True).clamp_min(eps)


def pure(v: torch.Tensor) -> torch.Tensor:
    """Vector as a pure quaternion ``[0, v]``; ``(..., 3) -> (..., 4)``."""
    import torch

    return torch.cat((torch.zeros_like(v[..., :1]), v), dim=-1)


def quat_rotate(q: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """Rotate ``v`` by the unit quaternion ``q`` (``q ⊗ [0, v] ⊗ q*``); ``(..., 4), (..., 3) -> (..., 3)``.

    Uses ``v + 2 w (r × v) + 2 r × (r × v)`` with ``q = [w, r]``, exact for unit ``q``.
    """
    import torch

    w = q[..., :1]
    r = q[..., 1:]
    t = 2.0 * torch.linalg.cross(r, v, dim=-1)
    return v + w * t + torch.linalg.cross(r, t, dim=-1)


def quat_to_rotmat(q: torch.Tensor) -> torch.Tensor:
    """Rotation matrix of the unit quaternion ``q``; ``(..., 4) -> (..., 3, 3)`` with ``v_w = R @ v_b``."""
    import torch

    w, x, y, z = q.unbind(-1)
    r = torch.stack(
        (
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ),
        dim=-1,
    )  # fmt: skip
    return r.reshape(*q.shape[:-1], 3, 3)


def quat_from_axis_angle(axis: torch.Tensor, angle: torch.Tensor) -> torch.Tensor:
    """Quaternion of a rotation by ``angle`` (rad) about the unit ``axis``; ``(..., 3), (...) -> (..., 4)``."""
    import torch

    half = 0.5 * angle
    return torch.cat((torch.cos(half)[..., None], torch.sin(half)[..., None] * axis), dim=-1)


def quat_derivative_body(q: torch.Tensor, omega_body: torch.Tensor) -> torch.Tensor:
    """Kinematics ``q_dot = 1/2 q ⊗ [0, omega]`` for a body-frame angular velocity; ``-> (..., 4)``.

    (``1/2 [0, omega] ⊗ q`` is the form for a world-frame angular velocity.)
    """
    return 0.5 * quat_mul(q, pure(omega_body))


def safe_sqrt(s: torch.Tensor) -> torch.Tensor:
    """``sqrt(max(s, 0))`` whose gradient is 0 (not NaN/inf) at ``s = 0``."""
    import torch

    pos = s > 0
    return torch.where(pos, torch.sqrt(torch.where(pos, s, torch.ones_like(s))), torch.zeros_like(s))


def tilt_angle(q: torch.Tensor) -> torch.Tensor:
    """Angle (rad, in [0, pi]) between the body z axis and the world z axis; ``(..., 4) -> (...)``.

    For a unit ``q``, ``cos(theta) = 1 - 2 (x^2 + y^2)`` so ``theta = 2 atan2(|(x, y)|, |(w, z)|)``; written
    with :func:`safe_sqrt` so the gradient is finite (zero) at the level attitude, where the angle has a
    cone-shaped kink.
    """
    import torch

    w, x, y, z = q.unbind(-1)
    return 2.0 * torch.atan2(safe_sqrt(x * x + y * y), safe_sqrt(w * w + z * z))


def random_quat_np(n: int, rng: np.random.Generator, max_angle: float) -> np.ndarray:
    """``n`` unit quaternions from a uniformly random unit axis and an angle ~ U[-max_angle, max_angle].

    The paper's quadrotor sampling scheme; returns float64 ``(n, 4)`` with ``w >= cos(max_angle / 2)``.
    """
    axis = rng.normal(size=(n, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True).clip(min=1e-12)
    angle = rng.uniform(-max_angle, max_angle, size=n)
    half = 0.5 * angle
    return np.concatenate((np.cos(half)[:, None], np.sin(half)[:, None] * axis), axis=1)
