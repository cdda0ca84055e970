"""The paddle ball's numpy twins: the impact map of f_hat and of the true model with exact Jacobians."""

from __future__ import annotations

import math

import numpy as np

from saml_ros.core.mpc.dynamics_np import Jac3
from saml_ros.systems.paddle_ball.model import PaddleBall


class PaddleBaseNP:
    """The paper's impact map with the base restitution: ``v+ = a (v_rel - 2 n (n . v_rel)) + v_paddle``."""

    #: rotation (rad) about world y from the commanded to the real normal (0: the base model has no bias)
    pitch_offset = 0.0

    def __init__(self, system: PaddleBall) -> None:
        self.a = system.restitution_base

    def step(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        return self.step_jac(x, u)[0]

    def step1(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        n = u[3:6] / math.sqrt(max(float(u[3:6] @ u[3:6]), 1e-24))
        vrel = x[3:6] - u[0:3]
        return self.a * (vrel - 2.0 * n * float(n @ vrel)) + u[0:3]

    def step_jac(self, x: np.ndarray, u: np.ndarray) -> Jac3:
        bsz = x.shape[0]
        pv, nraw = u[:, 0:3], u[:, 3:6]
        nn = np.sqrt(np.einsum("bi,bi->b", nraw, nraw))[:, None].clip(min=1e-12)
        n = nraw / nn
        vrel = x[:, 3:6] - pv
        dot = np.einsum("bi,bi->b", n, vrel)[:, None]
        y = self.a * (vrel - 2.0 * n * dot) + pv
        eye = np.eye(3)
        refl = eye - 2.0 * n[:, :, None] * n[:, None, :]  # (B, 3, 3)
        a = np.zeros((bsz, 3, 6))
        a[:, :, 3:6] = self.a * refl
        b = np.empty((bsz, 3, 6))
        b[:, :, 0:3] = eye - self.a * refl
        dn = -2.0 * self.a * (dot[:, :, None] * eye + n[:, :, None] * vrel[:, None, :])
        proj = (eye - n[:, :, None] * n[:, None, :]) / nn[:, :, None]
        b[:, :, 3:6] = dn @ proj
        return y, a, b


class PaddleTrueNP(PaddleBaseNP):
    """The true impact map (oracle): restitution ``restitution_true`` and the real normal ``R_y(normal_bias_y) n``.

    A rotation about y adds to the pitch, so the fast paddle solver treats it as a pitch offset
    (:attr:`pitch_offset`); ``dn_real/dn = R_y`` in the Jacobian.
    """

    def __init__(self, system: PaddleBall) -> None:
        self.a = system.restitution_true
        self.pitch_offset = system.normal_bias_y
        c, s = math.cos(self.pitch_offset), math.sin(self.pitch_offset)
        self._rot = np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])

    def _rotated(self, u: np.ndarray) -> np.ndarray:
        ur = np.array(u, dtype=np.float64, copy=True)
        ur[..., 3:6] = u[..., 3:6] @ self._rot.T
        return ur

    def step1(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        return super().step1(x, self._rotated(u))

    def step_jac(self, x: np.ndarray, u: np.ndarray) -> Jac3:
        y, a, b = super().step_jac(x, self._rotated(u))
        b[:, :, 3:6] = b[:, :, 3:6] @ self._rot
        return y, a, b
