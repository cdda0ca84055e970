"""The MPC's prediction model ``f_hat + phi`` on float64 numpy arrays, with exact Jacobians.

The base models f_hat of the three systems are re-implemented here in numpy with hand-derived Jacobians
(the torch versions in ``core.systems`` stay the single source of truth: ``test/test_mpc.py`` checks values
and Jacobians against them and torch autograd). A system without a numpy twin falls back to torch autograd
(``torch.func.jacrev``), which is exact but slow.

The *oracle* is the true dynamics ``f`` as the MPC's model (``NumpyDynamics(system, "oracle")``,
``make_controller(system, "oracle")``): the best any learned model can do inside the same MPC, used to measure
how much a model can matter on a task (the headroom, docs/experiments.md). Its numpy twins
(:class:`FrictionTrueNP`, :class:`QuadrotorTrueNP`, :class:`PaddleTrueNP`) are named by the registry entry's
``true_model_np``; their Jacobians are exact wherever ``f`` is differentiable (friction: except where the
friction just holds the cart, ``|w| = b(p)``; quadrotor: at the level attitude the tilt has a cone-shaped kink and
the derivative 0 is used, as torch's ``tilt_angle``).

Shapes: ``x`` ``(B, n_x)``, ``u`` ``(B, n_u)`` -> ``y`` ``(B, n_y)``, ``A = dy/dx`` ``(B, n_y, n_x)``,
``Bu = dy/du`` ``(B, n_y, n_u)``.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Literal, Protocol

import numpy as np
import torch

from saml_ros.core.dynamics.system import System
from saml_ros.core.model.network import DynamicsModel
from saml_ros.core.mpc.mlp_np import NumpyMLP
from saml_ros.core.systems.friction import FrictionDoubleIntegrator
from saml_ros.core.systems.paddle_ball import PaddleBall
from saml_ros.core.systems.quadrotor import Quadrotor

Jac3 = tuple[np.ndarray, np.ndarray, np.ndarray]
#: :meth:`NumpyDynamics.fused_jacobians` tabulates the Jacobians of every activation pattern of up to this many
#: hidden units (2^10 = 1024 patterns; the friction model's 4-2 net has 64)
JAC_TABLE_UNITS = 10
#: one hidden layer's step of the fused rollout: (matrix, input rows, pre-activation rows, relu rows)
_FusedLayer = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]
#: the fused rollout's buffer and views (:meth:`NumpyDynamics._fused_plan`): z, per step (hidden layers, the
#: step's block, the rows of x_{t+1}), the rows of x_0, of all controls and of all states
_FusedPlan = tuple[np.ndarray, list[tuple[list[_FusedLayer], np.ndarray, np.ndarray]], np.ndarray, np.ndarray,
                   np.ndarray]

#: the model name that makes the MPC predict with the TRUE dynamics (see the module docstring)
ORACLE: Literal["oracle"] = "oracle"
#: what an MPC predicts with: a learned model (residual or full), the oracle, or None (f_hat alone)
PredictionModel = DynamicsModel | Literal["oracle"] | None


class BaseModelNP(Protocol):
    def step(self, x: np.ndarray, u: np.ndarray) -> np.ndarray: ...
    def step1(self, x: np.ndarray, u: np.ndarray) -> np.ndarray: ...
    def step_jac(self, x: np.ndarray, u: np.ndarray) -> Jac3: ...


class FrictionBaseNP:
    """Frictionless double integrator ``p' = p + dt v``, ``v' = v + dt u``."""

    def __init__(self, system: FrictionDoubleIntegrator) -> None:
        self.dt = system.dt
        self._a = np.array([[1.0, self.dt], [0.0, 1.0]])
        self._b = np.array([[0.0], [self.dt]])
        #: the model is linear, ``y = A x + B u``: (A (n, n), B (n, m)); lets ``NumpyDynamics.rollout_batch``
        #: fuse it with the network's first layer
        self.linear = (self._a, self._b)
        self._jac_cache: dict[int, tuple[np.ndarray, np.ndarray]] = {}

    def step(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        y = x @ self._a.T
        y[:, 1] += self.dt * u[:, 0]
        return y

    def step1(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        p, v = x.tolist()
        return np.array((p + self.dt * v, v + self.dt * float(u[0])))

    def step_jac(self, x: np.ndarray, u: np.ndarray) -> Jac3:
        n = x.shape[0]
        ab = self._jac_cache.get(n)
        if ab is None:  # constant: one read-only copy per batch size (np.broadcast_to costs ~3 us a call)
            ab = (np.tile(self._a, (n, 1, 1)), np.tile(self._b, (n, 1, 1)))
            for arr in ab:
                arr.flags.writeable = False
            self._jac_cache[n] = ab
        return self.step(x, u), ab[0], ab[1]


class QuadrotorBaseNP:
    """One explicit Euler step of the rigid-body quadrotor (see ``core.systems.quadrotor``)."""

    def __init__(self, system: Quadrotor) -> None:
        self.dt, self.mass, self.g = system.dt, system.mass, system.g
        self.inertia = np.asarray(system.inertia, dtype=np.float64)
        self.inv_inertia = 1.0 / self.inertia
        self._inertia_f = tuple(self.inertia.tolist())  # step1's constants as Python floats
        self._dt_inv_inertia_f = tuple((self.dt * self.inv_inertia).tolist())
        # torque = mix @ f:  [f4 - f2, f3 - f1, (f1 + f3) - (f2 + f4)]
        self.mix = np.array([[0.0, -1.0, 0.0, 1.0], [-1.0, 0.0, 1.0, 0.0], [1.0, -1.0, 1.0, -1.0]])
        self._dw_du = self.dt * self.inv_inertia[:, None] * self.mix  # (3, 4)
        self._eye4 = np.eye(4)
        # constant parts of the Jacobians
        self._a0 = np.eye(13)
        self._a0[0:3, 3:6] = self.dt * np.eye(3)
        self._b0 = np.zeros((13, 4))
        self._b0[10:13] = self._dw_du
        # linear maps: Xi(q)[i, j] = sum_k LX[k, i, j] q_k with q ⊗ [0, w] = Xi(q) w = Omega(w) q
        # Xi(q) = [[-x, -y, -z], [w, -z, y], [z, w, -x], [-y, x, w]] with q = (w, x, y, z) = indices 0..3
        lx = np.zeros((4, 4, 3))
        for k, i, j, v in ((1, 0, 0, -1), (2, 0, 1, -1), (3, 0, 2, -1), (0, 1, 0, 1), (3, 1, 1, -1), (2, 1, 2, 1),
                           (3, 2, 0, 1), (0, 2, 1, 1), (1, 2, 2, -1), (2, 3, 0, -1), (1, 3, 1, 1), (0, 3, 2, 1)):
            lx[k, i, j] = v
        self._lx = lx.reshape(4, 12)
        self._lw = lx.transpose(2, 1, 0).reshape(3, 16)  # Omega(w)[i, k] = sum_j LX[k, i, j] w_j
        # d col / d q [i, j] = sum_k LC[k, i, j] q_k,  col = R(q) e_z
        lc = np.zeros((4, 3, 4))
        for i, j, k, v in ((0, 0, 2, 2), (0, 1, 3, 2), (0, 2, 0, 2), (0, 3, 1, 2), (1, 0, 1, -2), (1, 1, 0, -2),
                           (1, 2, 3, 2), (1, 3, 2, 2), (2, 1, 1, -4), (2, 2, 2, -4)):
            lc[k, i, j] = v
        self._lc = lc.reshape(4, 12)
        # [v]x[i, j] = sum_k LS[k, i, j] v_k
        ls = np.zeros((3, 3, 3))
        for k, i, j, v in ((2, 0, 1, -1), (1, 0, 2, 1), (2, 1, 0, 1), (0, 1, 2, -1), (1, 2, 0, -1), (0, 2, 1, 1)):
            ls[k, i, j] = v
        self._ls = ls.reshape(3, 9)

    def _parts(self, x: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, ...]:
        q = x[:, 6:10]
        nq = np.sqrt(np.einsum("bi,bi->b", q, q))[:, None]
        qn = q / nq
        w = x[:, 10:13]
        qw, qx, qy, qz = qn[:, 0], qn[:, 1], qn[:, 2], qn[:, 3]
        # third column of R(qn): body z axis in the world frame
        col = np.stack((2.0 * (qx * qz + qw * qy), 2.0 * (qy * qz - qw * qx), 1.0 - 2.0 * (qx * qx + qy * qy)), 1)
        wx, wy, wz = w[:, 0], w[:, 1], w[:, 2]
        # qr = qn + dt/2 qn ⊗ [0, w]
        h = 0.5 * self.dt
        qr = qn + h * np.stack(
            (
                -qx * wx - qy * wy - qz * wz,
                qw * wx + qy * wz - qz * wy,
                qw * wy - qx * wz + qz * wx,
                qw * wz + qx * wy - qy * wx,
            ),
            1,
        )
        nr = np.sqrt(np.einsum("bi,bi->b", qr, qr))[:, None]
        return nq, qn, col, qr, nr

    def step(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        return self._step(x, u, self._parts(x, u))

    def _step(self, x: np.ndarray, u: np.ndarray, parts: tuple[np.ndarray, ...]) -> np.ndarray:
        _, _, col, qr, nr = parts
        dt = self.dt
        y = np.empty_like(x)
        y[:, 0:3] = x[:, 0:3] + dt * x[:, 3:6]
        thrust = u.sum(1, keepdims=True) * (dt / self.mass)
        y[:, 3:6] = x[:, 3:6] + thrust * col
        y[:, 5] -= dt * self.g
        y[:, 6:10] = qr / nr
        w = x[:, 10:13]
        iw = w * self.inertia
        y[:, 10:13] = w + (u @ self._dw_du.T) - dt * self.inv_inertia * _cross(w, iw)
        return y

    def step1(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """One state ``(13,), (4,) -> (13,)`` in plain Python floats (3-4x faster than numpy at B = 1)."""
        return np.array(self._step_floats(x.tolist(), u.tolist()))

    def rollout1(self, x0: np.ndarray, us: np.ndarray) -> np.ndarray:
        """States ``(T+1, 13)`` from ``x0`` ``(13,)`` under ``us`` ``(T, 4)``: :meth:`step1` T times, the states
        kept as Python floats in between (the same values, about twice as fast as T calls of :meth:`step1`)."""
        xs = [x0.tolist()]
        for u in us.tolist():
            xs.append(self._step_floats(xs[-1], u))
        return np.array(xs)

    def _step_floats(self, x: list[float], u: list[float]) -> tuple[float, ...]:
        px, py, pz, vx, vy, vz, qw, qx, qy, qz, wx, wy, wz = x
        f1, f2, f3, f4 = u
        dt, h = self.dt, 0.5 * self.dt
        nq = math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
        qw, qx, qy, qz = qw / nq, qx / nq, qy / nq, qz / nq
        a = (f1 + f2 + f3 + f4) * dt / self.mass
        rw = qw + h * (-qx * wx - qy * wy - qz * wz)
        rx = qx + h * (qw * wx + qy * wz - qz * wy)
        ry = qy + h * (qw * wy - qx * wz + qz * wx)
        rz = qz + h * (qw * wz + qx * wy - qy * wx)
        nr = math.sqrt(rw * rw + rx * rx + ry * ry + rz * rz)
        i1, i2, i3 = self._inertia_f
        j1, j2, j3 = self._dt_inv_inertia_f
        t1, t2, t3 = f4 - f2, f3 - f1, (f1 + f3) - (f2 + f4)
        return (
            px + dt * vx, py + dt * vy, pz + dt * vz,
            vx + a * 2.0 * (qx * qz + qw * qy),
            vy + a * 2.0 * (qy * qz - qw * qx),
            vz + a * (1.0 - 2.0 * (qx * qx + qy * qy)) - dt * self.g,
            rw / nr, rx / nr, ry / nr, rz / nr,
            wx + j1 * (t1 - (wy * i3 * wz - wz * i2 * wy)),
            wy + j2 * (t2 - (wz * i1 * wx - wx * i3 * wz)),
            wz + j3 * (t3 - (wx * i2 * wy - wy * i1 * wx)),
        )  # fmt: skip

    def step_jac(self, x: np.ndarray, u: np.ndarray) -> Jac3:
        y, a, b = self._step_jac(x, u, True)
        assert y is not None
        return y, a, b

    def jacobians(self, x: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`step_jac`'s Jacobians alone ``(B, 13, 13), (B, 13, 4)`` (the prediction is not computed)."""
        _, a, b = self._step_jac(x, u, False)
        return a, b

    def _step_jac(self, x: np.ndarray, u: np.ndarray, with_y: bool) -> tuple[np.ndarray | None, np.ndarray,
                                                                              np.ndarray]:
        bsz, dt, h = x.shape[0], self.dt, 0.5 * self.dt
        q, w = x[:, 6:10], x[:, 10:13]
        nq = np.sqrt(np.einsum("bi,bi->b", q, q))
        qn = q / nq[:, None]
        # every matrix below is linear in qn or w: one product with a constant tensor each
        xi = (qn @ self._lx).reshape(bsz, 4, 3)  # qn ⊗ [0, w] = xi @ w
        om = (w @ self._lw).reshape(bsz, 4, 4)  # qn ⊗ [0, w] = om @ qn
        dcol = (qn @ self._lc).reshape(bsz, 3, 4)  # d col / d qn
        col = 0.5 * np.einsum("bij,bj->bi", dcol, qn)
        col[:, 2] += 1.0
        qr = qn + h * np.einsum("bij,bj->bi", xi, w)
        nr = np.sqrt(np.einsum("bi,bi->b", qr, qr))
        qp = qr / nr[:, None]
        iw = w * self.inertia
        thrust = u.sum(1) * (dt / self.mass)
        y = None
        if with_y:
            y = np.empty_like(x)
            y[:, 0:3] = x[:, 0:3] + dt * x[:, 3:6]
            y[:, 3:6] = x[:, 3:6] + thrust[:, None] * col
            y[:, 5] -= dt * self.g
            y[:, 6:10] = qp
            y[:, 10:13] = w + u @ self._dw_du.T - dt * self.inv_inertia * _cross(w, iw)
        a = np.broadcast_to(self._a0, (bsz, 13, 13)).copy()
        b = np.broadcast_to(self._b0, (bsz, 13, 4)).copy()
        n_q = (self._eye4 - qn[:, :, None] * qn[:, None, :]) / nq[:, None, None]
        n_r = (self._eye4 - qp[:, :, None] * qp[:, None, :]) / nr[:, None, None]
        a[:, 3:6, 6:10] = thrust[:, None, None] * (dcol @ n_q)
        b[:, 3:6, :] = (dt / self.mass) * col[:, :, None]
        a[:, 6:10, 6:10] = n_r @ ((self._eye4 + h * om) @ n_q)
        a[:, 6:10, 10:13] = h * (n_r @ xi)
        # w' = w + dt I^-1 (mix f - w x I w);  d(w x Iw)/dw = [w]x diag(I) - [Iw]x
        dcross = (w @ self._ls).reshape(bsz, 3, 3) * self.inertia - (iw @ self._ls).reshape(bsz, 3, 3)
        a[:, 10:13, 10:13] -= dt * self.inv_inertia[None, :, None] * dcross
        return y, a, b


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


class FrictionTrueNP:
    """The true friction dynamics (oracle): ``p' = p + dt v``, ``v' = sign(w) max(|w| - b(p), 0)``, ``w = v + dt u``.

    Jacobians: while the cart moves (``|w| > b``) ``dv'/dv = 1``, ``dv'/du = dt``, ``dv'/dp = -sign(w) b'(p)``
    (``b'`` in closed form); while friction holds it, all three are 0.
    """

    def __init__(self, system: FrictionDoubleIntegrator) -> None:
        self.system = system
        self.dt = system.dt

    def step(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        return self.system.true_step_np(x, u)

    def step1(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        p, v = x.tolist()
        dt = self.dt
        w = v + dt * float(u[0])
        b = dt * float(self.system.friction_decel_np(p))
        mag = abs(w) - b
        return np.array((p + dt * v, math.copysign(mag, w) if mag > 0.0 else 0.0))

    def step_jac(self, x: np.ndarray, u: np.ndarray) -> Jac3:
        n, dt = x.shape[0], self.dt
        p, v = x[:, 0], x[:, 1]
        w = v + dt * u[:, 0]
        b = dt * self.system.friction_decel_np(p)
        moving = (np.abs(w) > b).astype(np.float64)
        sgn = np.sign(w)
        y = np.stack((p + dt * v, sgn * np.maximum(np.abs(w) - b, 0.0)), axis=1)
        a = np.zeros((n, 2, 2))
        a[:, 0, 0] = 1.0
        a[:, 0, 1] = dt
        a[:, 1, 0] = -sgn * dt * self.system.friction_slope_np(p) * moving
        a[:, 1, 1] = moving
        bu = np.zeros((n, 2, 1))
        bu[:, 1, 0] = dt * moving
        return y, a, bu


class QuadrotorTrueNP:
    """The true quadrotor dynamics (oracle): ``f_hat(x, u (1 + K(x)))`` with the per-motor ground-effect gain K,
    then ``v' -= dt drag v`` (the optional linear drag) and ``v' += dt a_w(p)`` (the optional wind field above the
    shelter, :meth:`Quadrotor.wind_acceleration`).

    Jacobians: ``dy/du = B_h diag(1 + K)``, ``dy/dx = A_h + B_h diag(u) dK/dx - dt drag [dv'/dv] + dt da_w/dp`` with
    ``A_h, B_h`` the base model's Jacobians at the produced forces and ``dK/dx``, ``da_w/dp`` in closed form (K
    depends on pz and the attitude only, a_w on the position only; the wind's ramp has kinks at its two ends, where
    the derivative of the clipped side is used, as torch's ``clamp``).
    """

    def __init__(self, system: Quadrotor) -> None:
        self.system = system
        self.base = QuadrotorBaseNP(system)
        self.arm, self.h_max, self.alpha = system.arm_length, system.h_max, system.alpha
        self.damp = system.dt * system.drag  # velocity lost to drag per step, per unit of velocity
        self.dt = system.dt
        self.wind, self.wind_floor, self.wind_ramp = system.wind, system.wind_floor, system.wind_ramp
        self.wind_k = 2.0 * math.pi / system.wind_length

    def wind_dv(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The wind's velocity change per step ``dt a_w`` ``(B, 2)`` (x and y) and its derivative by the position
        ``(B, 2, 3)`` at states ``x`` ``(B, 13)`` (the same operations as ``Quadrotor.wind_acceleration``)."""
        s = (x[:, 2] - self.wind_floor) / self.wind_ramp
        ramp = np.clip(s, 0.0, 1.0) * self.wind
        dramp = np.where((s > 0.0) & (s < 1.0), self.wind / self.wind_ramp, 0.0)
        k = self.wind_k
        sy, sx = np.sin(k * x[:, 1]), np.sin(k * x[:, 0])
        dv = np.stack((self.dt * (ramp * sy), self.dt * (ramp * sx)), axis=1)
        d = np.zeros((x.shape[0], 2, 3))
        d[:, 0, 1] = self.dt * ramp * k * np.cos(k * x[:, 1])
        d[:, 0, 2] = self.dt * dramp * sy
        d[:, 1, 0] = self.dt * ramp * k * np.cos(k * x[:, 0])
        d[:, 1, 2] = self.dt * dramp * sx
        return dv, d

    def gain(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """K ``(B, 4)`` and dK/dx ``(B, 4, 13)`` at states ``x`` ``(B, 13)``."""
        bsz = x.shape[0]
        q = x[:, 6:10]
        qw, qx, qy, qz = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
        nn = np.einsum("bi,bi->b", q, q)
        # propeller height offsets: rzx = 2 (qx qz - qw qy) / |q|^2, rzy = 2 (qy qz + qw qx) / |q|^2
        sx, sy = qx * qz - qw * qy, qy * qz + qw * qx
        rzx, rzy = 2.0 * sx / nn, 2.0 * sy / nn
        dsx = np.stack((-qy, qz, -qw, qx), axis=1)
        dsy = np.stack((qx, qw, qz, qy), axis=1)
        drzx = 2.0 * dsx / nn[:, None] - (4.0 * sx / nn**2)[:, None] * q
        drzy = 2.0 * dsy / nn[:, None] - (4.0 * sy / nn**2)[:, None] * q
        sign = np.array([[1.0, 0.0], [0.0, -1.0], [-1.0, 0.0], [0.0, 1.0]])  # offset_i = L (s_x rzx + s_y rzy)
        off = self.arm * (rzx[:, None] * sign[:, 0] + rzy[:, None] * sign[:, 1])  # (B, 4)
        doff = self.arm * (sign[None, :, 0, None] * drzx[:, None, :] + sign[None, :, 1, None] * drzy[:, None, :])
        h = x[:, 2:3] + off
        hf = 1.0 - h / self.h_max
        height = np.clip(hf, 0.0, 1.0)
        inside = ((hf > 0.0) & (hf < 1.0)).astype(np.float64)
        # tilt theta = 2 atan2(|(qx, qy)|, |(qw, qz)|); derivative 0 at the level attitude (cone kink)
        ra, rb = np.sqrt(qx * qx + qy * qy), np.sqrt(qw * qw + qz * qz)
        theta = 2.0 * np.arctan2(ra, rb)
        rr = ra * ra + rb * rb
        inv_a = np.divide(1.0, ra, out=np.zeros_like(ra), where=ra > 0.0)
        inv_b = np.divide(1.0, rb, out=np.zeros_like(rb), where=rb > 0.0)
        dtheta = (2.0 / rr)[:, None] * np.stack(
            (-ra * qw * inv_b, rb * qx * inv_a, rb * qy * inv_a, -ra * qz * inv_b), axis=1)
        slack = np.maximum(0.5 * math.pi - theta, 0.0)
        tilt = (4.0 / math.pi**2) * slack**2
        dtilt = -(8.0 / math.pi**2) * slack  # d tilt / d theta
        k = self.alpha * height * tilt[:, None]
        dk = np.zeros((bsz, 4, 13))
        dh = -(inside / self.h_max)  # d height / d h, (B, 4)
        dk[:, :, 2] = self.alpha * dh * tilt[:, None]
        dk[:, :, 6:10] = self.alpha * (dh[:, :, None] * doff * tilt[:, None, None]
                                       + height[:, :, None] * (dtilt[:, None] * dtheta)[:, None, :])
        return k, dk

    def step(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        y = self.base.step(x, u * (1.0 + self.gain(x)[0]))
        if self.damp:
            y[:, 3:6] -= self.damp * x[:, 3:6]
        if self.wind:
            y[:, 3:5] += self.wind_dv(x)[0]
        return y

    def step1(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """One state in plain Python floats (the rollout's hot path; 4-5x faster than the batched :meth:`step`)."""
        pz, qw, qx, qy, qz = float(x[2]), float(x[6]), float(x[7]), float(x[8]), float(x[9])
        nn = qw * qw + qx * qx + qy * qy + qz * qz
        rzx, rzy = 2.0 * (qx * qz - qw * qy) / nn, 2.0 * (qy * qz + qw * qx) / nn
        theta = 2.0 * math.atan2(math.sqrt(qx * qx + qy * qy), math.sqrt(qw * qw + qz * qz))
        slack = max(0.5 * math.pi - theta, 0.0)
        tilt = self.alpha * (4.0 / math.pi**2) * slack * slack
        f = u.tolist()
        for i, off in enumerate((rzx, -rzy, -rzx, rzy)):
            height = min(max(1.0 - (pz + self.arm * off) / self.h_max, 0.0), 1.0)
            f[i] *= 1.0 + height * tilt
        y = self.base.step1(x, np.array(f))
        if self.damp:
            y[3:6] -= self.damp * x[3:6]
        if self.wind:
            ramp = min(max((pz - self.wind_floor) / self.wind_ramp, 0.0), 1.0) * self.wind
            k = self.wind_k
            y[3] += self.dt * (ramp * math.sin(k * float(x[1])))
            y[4] += self.dt * (ramp * math.sin(k * float(x[0])))
        return y

    def step_jac(self, x: np.ndarray, u: np.ndarray) -> Jac3:
        k, dk = self.gain(x)
        y, a, b = self.base.step_jac(x, u * (1.0 + k))
        a = a + np.einsum("bij,bj,bjk->bik", b, u, dk)
        if self.damp:
            y[:, 3:6] -= self.damp * x[:, 3:6]
            a[:, 3:6, 3:6] -= self.damp * np.eye(3)
        if self.wind:
            dv, dw = self.wind_dv(x)
            y[:, 3:5] += dv
            a[:, 3:5, 0:3] += dw
        return y, a, b * (1.0 + k)[:, None, :]


class TorchBaseNP:
    """Any system's ``base_step`` through torch autograd (exact but slow: the fallback for unknown systems)."""

    def __init__(self, system: System) -> None:
        self.system = system

    def step(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        with torch.no_grad():
            return self.system.base_step(torch.from_numpy(x), torch.from_numpy(u)).numpy()

    def step1(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        return self.step(x[None], u[None])[0]

    def step_jac(self, x: np.ndarray, u: np.ndarray) -> Jac3:
        def one(xi: torch.Tensor, ui: torch.Tensor) -> torch.Tensor:
            return self.system.base_step(xi[None], ui[None])[0]

        xt, ut = torch.from_numpy(np.ascontiguousarray(x)), torch.from_numpy(np.ascontiguousarray(u))
        ja, jb = torch.func.vmap(torch.func.jacrev(one, argnums=(0, 1)))(xt, ut)
        return self.step(x, u), ja.numpy(), jb.numpy()


class TorchTrueNP(TorchBaseNP):
    """Any system's ``true_step`` through torch autograd (the oracle's fallback for systems without a twin)."""

    def step(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        with torch.no_grad():
            return self.system.true_step(torch.from_numpy(x), torch.from_numpy(u)).numpy()

    def step_jac(self, x: np.ndarray, u: np.ndarray) -> Jac3:
        def one(xi: torch.Tensor, ui: torch.Tensor) -> torch.Tensor:
            return self.system.true_step(xi[None], ui[None])[0]

        xt, ut = torch.from_numpy(np.ascontiguousarray(x)), torch.from_numpy(np.ascontiguousarray(u))
        ja, jb = torch.func.vmap(torch.func.jacrev(one, argnums=(0, 1)))(xt, ut)
        return self.step(x, u), ja.numpy(), jb.numpy()


class NumpyDynamics:
    """The model the MPC predicts with: ``f_hat + phi`` (residual), ``phi`` (full), ``f_hat`` (no model) or the
    true dynamics ``f`` (``model = "oracle"``, :data:`ORACLE`).

    The learned part is a frozen copy of ensemble member ``member`` taken when this object is built. ``base`` is
    the numpy twin of ``system.base_step`` (:func:`saml_ros.core.mpc.factory.base_model_np` finds the system's
    own); without one, the exact but slower autograd :class:`TorchBaseNP` serves. ``true`` is the twin of
    ``system.true_step`` the oracle uses (:func:`saml_ros.core.mpc.factory.true_model_np`; fallback
    :class:`TorchTrueNP`).
    """

    def __init__(self, system: System, model: PredictionModel = None, member: int = 0,
                 base: BaseModelNP | None = None, true: BaseModelNP | None = None) -> None:
        self.system = system
        self.base: BaseModelNP | None = None
        self.mlp: NumpyMLP | None = None
        #: "residual", "full", "base" (f_hat alone) or "oracle"
        self.kind: str
        #: rollout_batch's stacked weights, row blocks and rows of ones (:meth:`_fused_layout`), made on first use
        self._fused: tuple[list[np.ndarray], list[tuple[int, int, int, int, int]], list[int]] | None = None
        #: per (batch size, horizon): the buffer and row views of :meth:`_rollout_fused` (:meth:`_fused_plan`)
        self._fused_plans: dict[tuple[int, int], _FusedPlan] = {}
        #: fused rollouts made so far; :attr:`_fused_stamps` holds, per buffer, the count at its last fill
        self.fused_calls = 0
        self._fused_stamps: dict[tuple[int, int], int] = {}
        #: :meth:`rollout_batch` is fused (one product per layer and step for all K sequences): K sequences cost
        #: about as much as one, so callers may batch what they would otherwise roll out one by one
        self.fused_rollout = False
        #: :meth:`fused_jacobians`' code weights and tables (:meth:`_jac_table`), False if too wide; made on first use
        self._jac_tab: tuple[np.ndarray, np.ndarray, np.ndarray] | Literal[False] | None = None
        if isinstance(model, str):
            if model != ORACLE:
                raise ValueError(f"unknown prediction model {model!r}; a DynamicsModel, None or {ORACLE!r}")
            self.kind = ORACLE
            self.base = true if true is not None else TorchTrueNP(system)
            return
        self.kind = "base" if model is None else model.kind
        if model is None or model.kind == "residual":
            self.base = base if base is not None else TorchBaseNP(system)
        if model is not None:
            if model.system.schema_hash() != system.schema_hash():
                raise ValueError(
                    f"model is for system {model.system.name!r} (schema {model.system.schema_hash()}), "
                    f"not {system.name!r} (schema {system.schema_hash()})"
                )
            self.mlp = NumpyMLP(model, member)
        self.fused_rollout = self.mlp is not None and (self.base is None or getattr(self.base, "linear", None)
                                                       is not None)

    def step(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """Predicted target ``(B, n_y)``."""
        return self._plus_phi(None if self.base is None else self.base.step(x, u), x, u)

    def step1(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """Prediction for one sample ``(n_x,), (n_u,) -> (n_y,)`` (the rollout's hot path)."""
        return self._plus_phi(None if self.base is None else self.base.step1(x, u), x, u)

    def rollout(self, x0: np.ndarray, us: np.ndarray) -> np.ndarray:
        """Predicted states ``(T+1, n)`` from ``x0`` ``(n,)`` under ``us`` ``(T, m)``: :meth:`step1` T times (by the
        base model's own ``rollout1`` when it has one and there is no network: the same values, faster)."""
        roll = getattr(self.base, "rollout1", None) if self.mlp is None else None
        if roll is not None:
            return np.asarray(roll(x0, us))
        return rollout_steps(self.step1, x0, us)

    def _plus_phi(self, y: np.ndarray | None, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """The base prediction ``y`` plus phi (in place), phi alone for a full model (``y`` None), or ``y``."""
        if y is None:
            assert self.mlp is not None
            return self.mlp.forward(x, u)
        if self.mlp is not None:
            y += self.mlp.forward(x, u)
        return y

    def rollout_batch(self, x0: np.ndarray, us: np.ndarray) -> np.ndarray:
        """Predicted states ``(K, T+1, n)`` of control sequences ``us`` ``(K, T, m)`` from ``x0`` ``(n,)``, batched
        over the K sequences (the start scoring of the shooting MPC: ~40 sequences at every friction solve).

        With a linear base model (``base.linear``) or none (a full model) and a network, the rollout is fused:
        states are kept as columns ``(n, K)``, the controls' share of the first layer and of the base model is
        computed for all steps at once, and the base model's ``A x`` comes out of the same product as the first
        layer's ``W_x x``: about 10 numpy calls per step instead of about 20. Otherwise: T calls of :meth:`step`.
        """
        k, horizon = us.shape[0], us.shape[1]
        if self.fused_rollout:
            return self._rollout_fused(x0, us, None if self.base is None else getattr(self.base, "linear", None))
        xs = np.empty((k, horizon + 1, x0.shape[0]))
        xs[:, 0] = x0
        x = xs[:, 0]
        for t in range(horizon):
            x = self.step(x, us[:, t])
            xs[:, t + 1] = x
        return xs

    def _rollout_fused(self, x0: np.ndarray, us: np.ndarray, lin: tuple[np.ndarray, np.ndarray] | None) -> np.ndarray:
        """:meth:`rollout_batch` for ``y = A x + B u + phi(x, u)`` (``lin`` = (A, B), or None for ``y = phi``).

        Layout: one buffer ``z`` ``(T+1, R, K)`` whose step-t block holds the columns
        ``[x_t; u_t; 1 | h_1; relu(h_1); 1 | ... | h_L; relu(h_L); 1]`` (controls and ones filled in before the
        loop). Since ``PReLU_a(h) = a h + (1 - a) relu(h)`` for every slope a, the next layer's pre-activation is
        ONE product of ``[a W, (1 - a) W, b]`` with the previous block; the last product also carries the base
        model ``A x + B u`` (zero weights elsewhere) and writes ``x_{t+1}`` in place. Per step: one product and
        one ``maximum`` per hidden layer, one final product (5 numpy calls for two hidden layers, was 8)."""
        k, horizon, n = us.shape[0], us.shape[1], x0.shape[0]
        m = us.shape[2]
        if self._fused is None:
            self._fused = self._fused_layout(lin, n, m)
        plan = self._fused_plans.get((k, horizon))
        if plan is None:
            plan = self._fused_plans[(k, horizon)] = self._fused_plan(k, horizon, n, m)
        self.fused_calls += 1
        self._fused_stamps[(k, horizon)] = self.fused_calls
        z, steps, x_first, u_all, x_all = plan
        x_first[...] = x0[:, None]
        u_all[...] = us.transpose(1, 2, 0)
        last = self._fused[0][-1]
        # np.dot into a C-contiguous row block: ~1 us a call here; np.matmul with out= checks the overlap of
        # out and input (same buffer) and costs ~3.5 us. The row blocks are views made once per batch size
        # (numpy 2.4: ~0.2 us per slice, as much as the products themselves on these sizes)
        dot, maximum = np.dot, np.maximum
        for layers, zt, x_next in steps:
            for mat, z_in, h, relu in layers:
                dot(mat, z_in, out=h)
                maximum(h, 0.0, out=relu)
            dot(last, zt, out=x_next)
        return x_all.transpose(2, 0, 1).copy()

    def _fused_plan(self, k: int, horizon: int, n: int, m: int) -> _FusedPlan:
        """:meth:`_rollout_fused`'s buffer ``z`` ``(T+1, R, K)`` (rows of ones filled in) and its views: per step
        t the hidden layers' ``(matrix, input rows, h rows, relu(h) rows)``, the whole block and the rows of
        ``x_{t+1}``; then the rows of ``x_0``, of all controls ``(T, m, K)`` and of all states ``(T+1, n, K)``."""
        assert self._fused is not None
        mats, blocks, ones = self._fused
        z = np.empty((horizon + 1, mats[-1].shape[1], k))
        z[:, ones] = 1.0
        steps: list[tuple[list[_FusedLayer], np.ndarray, np.ndarray]] = []
        for t in range(horizon):
            zt = z[t]
            layers: list[_FusedLayer] = [(mat, zt[i0:i1], zt[o0:o1], zt[o1:r1])
                                         for mat, (i0, i1, o0, o1, r1) in zip(mats, blocks, strict=False)]
            steps.append((layers, zt, z[t + 1, :n]))
        return z, steps, z[0, :n], z[:horizon, n : n + m], z[:, :n]

    def _fused_layout(self, lin: tuple[np.ndarray, np.ndarray] | None, n: int,
                      m: int) -> tuple[list[np.ndarray], list[tuple[int, int, int, int, int]], list[int]]:
        """:meth:`_rollout_fused`'s matrices (one per hidden layer, then the output one over the whole block),
        each hidden layer's ``(input start, input end, h start, h end = relu start, relu end)`` rows, and the
        rows that hold ones."""
        mlp = self.mlp
        assert mlp is not None
        w, b, slopes = mlp.weights, mlp.biases, mlp.slopes
        a_mat, b_mat = lin if lin is not None else (np.zeros((n, n)), np.zeros((n, m)))
        ones = [n + m]
        if len(w) == 1:  # no hidden layer: phi is affine, fold it into the base rows
            last = np.hstack((a_mat + mlp.w_x.T, b_mat + mlp.w_u.T, (b[0])[:, None]))
            return [np.ascontiguousarray(last)], [], ones
        mats: list[np.ndarray] = []
        blocks: list[tuple[int, int, int, int, int]] = []
        i0, i1 = 0, n + m + 1
        prev: np.ndarray | None = None  # the previous hidden layer's slope-split weights [a W; (1 - a) W]
        for i in range(len(w) - 1):
            d = w[i].shape[1]
            if i == 0:
                mat = np.hstack((mlp.w_x.T, mlp.w_u.T, b[0][:, None]))
            else:
                assert prev is not None
                mat = np.hstack((prev, b[i][:, None]))
            o0 = i1
            blocks.append((i0, i1, o0, o0 + d, o0 + 2 * d))
            mats.append(np.ascontiguousarray(mat))
            a = slopes[i]
            nxt = w[i + 1].T
            prev = np.hstack((a * nxt, (1.0 - a) * nxt))
            i0, i1 = o0, o0 + 2 * d
            if i < len(w) - 2:  # a ones row for the next hidden layer's bias
                ones.append(i1)
                i1 += 1
        assert prev is not None
        last = np.zeros((n, i1))
        last[:, :n], last[:, n : n + m], last[:, n + m] = a_mat, b_mat, b[-1]
        last[:, i0:i1] = prev
        mats.append(np.ascontiguousarray(last))
        return mats, blocks, ones

    def fused_jacobians(self, k: int, horizon: int, i: int, stamp: int) -> tuple[np.ndarray, np.ndarray] | None:
        """The Jacobians ``A (T, n, n)``, ``B (T, n, m)`` along sequence ``i`` of the fused :meth:`rollout_batch` of
        ``k`` sequences over ``horizon`` steps that was call number ``stamp`` (:attr:`fused_calls` right after it),
        read from the activation pattern its pre-activations left in the fused buffer (:meth:`_jac_table`): 5 numpy
        calls instead of the ~20 of :meth:`jacobians` (a forward pass and the reverse products). The values are
        :meth:`jacobians`' at that sequence's states and controls (a pre-activation within rounding of 0 may fall on
        the other side of the kink). None when that buffer has been refilled since (or never filled), or the
        network has more than :data:`JAC_TABLE_UNITS` hidden units."""
        plan = self._fused_plans.get((k, horizon))
        if plan is None or self._fused_stamps.get((k, horizon)) != stamp:
            return None
        if self._jac_tab is None:
            self._jac_tab = self._jac_table()
        if self._jac_tab is False:
            return None
        weights, tab_a, tab_b = self._jac_tab
        codes = np.dot(plan[0][:horizon, :, i] >= 0.0, weights).astype(np.intp)
        return tab_a[codes], tab_b[codes]

    def _jac_table(self) -> tuple[np.ndarray, np.ndarray, np.ndarray] | Literal[False]:
        """For :meth:`fused_jacobians`: the code weights over the fused buffer's rows ``(R,)`` (``2^j`` on hidden
        unit j's pre-activation row, 0 elsewhere: the dot with ``h >= 0`` numbers the activation pattern), and the
        Jacobians of ``f_hat + phi`` of every pattern, ``A (2^H, n, n)`` and ``B (2^H, n, m)`` (a PReLU unit with
        ``h >= 0`` passes its input, otherwise scales it by its slope, as :meth:`NumpyMLP.forward_jac`). False when
        the H hidden units exceed :data:`JAC_TABLE_UNITS`."""
        mlp = self.mlp
        assert mlp is not None and self._fused is not None
        mats, blocks, _ = self._fused
        widths = [o1 - o0 for _, _, o0, o1, _ in blocks]
        units = sum(widths)
        if units > JAC_TABLE_UNITS:
            return False
        n, m = mlp.n_x, mlp.n_u
        weights = np.zeros(mats[-1].shape[1])
        bits = (np.arange(2**units)[:, None] >> np.arange(units)) & 1  # (2^H, H): pattern c's unit j is on
        masks, j = [], 0
        for (_, _, o0, o1, _), width, slope in zip(blocks, widths, mlp.slopes, strict=False):
            weights[o0:o1] = 2.0 ** np.arange(j, j + width)
            masks.append(np.where(bits[:, j : j + width] == 1, 1.0, slope))
            j += width
        # reverse mode, as NumpyMLP._jac: W_L' M_{L-1} ... W_1' M_0 W_0' for every pattern at once
        w = mlp.weights
        g = np.broadcast_to(w[-1].T, (2**units, *w[-1].T.shape)).copy()
        for layer in range(len(w) - 2, -1, -1):
            g = (g * masks[layer][:, None, :]) @ w[layer].T
        lin = None if self.base is None else getattr(self.base, "linear", None)
        if lin is not None:
            g[:, :, :n] += lin[0]
            g[:, :, n:] += lin[1]
        return weights, np.ascontiguousarray(g[:, :, :n]), np.ascontiguousarray(g[:, :, n : n + m])

    def jacobians(self, x: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The Jacobians of :meth:`step_jac` alone (the SQP has the prediction from its rollout): with a linear
        base model (``base.linear``) neither the base step nor the network's output is computed."""
        lin = None if self.base is None else getattr(self.base, "linear", None)
        base_jac = None if self.base is None else getattr(self.base, "jacobians", None)
        if self.base is not None and lin is None and base_jac is not None:
            a, b = base_jac(x, u)
            if self.mlp is not None:
                ap, bp = self.mlp.jacobians(x, u)
                a += ap
                b += bp
            return a, b
        if self.mlp is None or (self.base is not None and lin is None):
            _, a, b = self.step_jac(x, u)
            return a, b
        ap, bp = self.mlp.jacobians(x, u)
        if lin is not None:
            ap += lin[0]
            bp += lin[1]
        return ap, bp

    def step_jac(self, x: np.ndarray, u: np.ndarray) -> Jac3:
        """Prediction and its Jacobians ``(B, n_y)``, ``(B, n_y, n_x)``, ``(B, n_y, n_u)``."""
        if self.base is None:
            assert self.mlp is not None
            return self.mlp.forward_jac(x, u)
        y, a, b = self.base.step_jac(x, u)
        if self.mlp is not None:
            yp, ap, bp = self.mlp.forward_jac(x, u)
            yp += y
            ap += a
            bp += b
            return yp, ap, bp
        return y, a, b


def rollout_steps(step1: Callable[[np.ndarray, np.ndarray], np.ndarray], x0: np.ndarray,
                  us: np.ndarray) -> np.ndarray:
    """States ``(T+1, n)`` from ``x0`` ``(n,)`` under ``us`` ``(T, m)`` by T calls of a one-sample ``step1``."""
    xs = np.empty((us.shape[0] + 1, x0.shape[0]))
    xs[0] = x0
    for t in range(us.shape[0]):
        xs[t + 1] = step1(xs[t], us[t])
    return xs


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise cross product of ``(B, 3)`` arrays (``np.cross`` is several times slower for small B)."""
    return np.stack(
        (
            a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1],
            a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2],
            a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0],
        ),
        1,
    )

