"""The quadrotor's numpy twins: f_hat (vectorised and scalar, with exact Jacobians; the C kernel of the shooting SQP
rounds as the scalar one) and the true model (the MPC's oracle).
"""

from __future__ import annotations

import math

import numpy as np

from saml_ros.core.mpc.dynamics_np import Jac3
from saml_ros.systems.quadrotor.model import Quadrotor


class QuadrotorBaseNP:
    """One explicit Euler step of the rigid-body quadrotor (see :mod:`.model`)."""

    #: the shooting SQP's C kernel holds this step (``quad_step``, rounding as :meth:`step1`): see
    #: :data:`saml_ros.core.mpc.shooting.native.C_QUADROTOR`
    C_BASE = 1

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
