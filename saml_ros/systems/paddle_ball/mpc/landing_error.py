"""The paddle-ball landing error (eq. ball_paddle_opt) and its exact derivatives at one point, in plain Python floats.

For one pre-impact state ``x`` (6,) and a decision vector ``theta`` = ``[pvx, pvy, pvz (m/s), roll, pitch (rad)]``
with ``u = [pv, n(roll, pitch)]``, ``n = (cos(roll) sin(pitch), -sin(roll), cos(roll) cos(pitch))``:

    v = v_post(x, u)                                  (3,) m/s: f_hat + phi, phi, or f_hat
    r = p_xy + v_xy * 2 max(v_z, 0) / g - target_xy   (2,) m: the landing error

:meth:`LandingError.value` gives ``r`` and ``v``; :meth:`LandingError.derivatives` the Jacobians ``dv/dtheta`` (3 x 5),
``J = dr/dtheta`` (2 x 5) and, on request, the Hessian ``H = J^T J + C`` of ``1/2 ||r||^2`` with the residual
curvature ``C = sum_i r_i d^2 r_i / dtheta^2`` (the term Gauss-Newton drops), all in closed form: the base impact
map ``a (w - 2 n (n . w)) + pv`` (``w = v_ball - pv``) is differentiated by hand, and phi is a PReLU network,
piecewise linear in ``u``, so its only curvature in ``theta`` comes through ``n(roll, pitch)``
(``d^2 phi / du^2 = 0`` between the kinks). The network runs in numpy (:meth:`NumpyMLP.forward_pre1`, its
Jacobian in reverse mode by :meth:`NumpyMLP.jac_u1`: 3 output rows instead of 12 input columns); the rest is a few
hundred float operations, several times cheaper than numpy calls on arrays this small.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from saml_ros.core.mpc.dynamics_np import NumpyDynamics
from saml_ros.systems.paddle_ball.dynamics_np import PaddleBaseNP


@dataclass(slots=True)
class Point:
    """:meth:`LandingError.value` at one ``theta``, with what :meth:`LandingError.derivatives` reuses."""

    theta: list[float]  #: [pv (m/s), roll, pitch (rad)]
    r: tuple[float, float]  #: landing error (m)
    v: tuple[float, float, float]  #: post-impact velocity (m/s)
    f: float  #: 1/2 ||r||^2 (m^2)
    up: bool  #: the ball leaves upwards (v_z > 0)
    trig: tuple[float, float, float, float]  #: cos, sin of roll, cos, sin of pitch
    n: tuple[float, float, float]  #: paddle normal
    w: tuple[float, float, float]  #: relative velocity v_ball - pv (m/s)
    nw: float  #: n . w
    pre: list[np.ndarray] | None  #: the network's hidden pre-activations at this input
    dv: list[list[float]] | None = None  #: d v / d theta (3 x 5), set by :meth:`LandingError.derivatives`
    jac: list[list[float]] | None = None  #: J (2 x 5), cached by :meth:`LandingError.derivatives`
    hess: list[list[float]] | None = None  #: H (5 x 5), cached by :meth:`LandingError.derivatives`


class LandingError:
    """The landing residual at one state ``x`` (6,) and target ``target_xy`` (2,) m under the model ``dyn``."""

    def __init__(self, dyn: NumpyDynamics, x: np.ndarray, target_xy: np.ndarray, g: float) -> None:
        if dyn.base is not None and not isinstance(dyn.base, PaddleBaseNP):
            raise TypeError(f"LandingError needs the paddle-ball base model, got {type(dyn.base).__name__}")
        self.mlp = dyn.mlp
        self.a = dyn.base.a if dyn.base is not None else None  # base restitution, None for a full model
        # the oracle's real normal is the commanded one pitched by this angle (rad); never with a network
        self.pitch_offset = dyn.base.pitch_offset if dyn.base is not None else 0.0
        if self.pitch_offset and self.mlp is not None:
            raise TypeError("LandingError: a pitch offset of the impact map cannot be combined with a network")
        self.x = np.asarray(x, dtype=np.float64)
        self.vb = self.x[3:6]
        self.offset = self.x[0:2] - np.asarray(target_xy, dtype=np.float64)  # r at zero flight time (m)
        self.k = 2.0 / g  # flight time per unit of upward speed (s^2/m)
        self._vb = [float(c) for c in self.vb]
        self._off = [float(c) for c in self.offset]
        self._x_part = None if self.mlp is None else self.mlp.state_part(self.x)

    def value(self, theta: list[float]) -> Point:
        """``r`` and ``v`` at one ``theta`` (5 floats); :meth:`derivatives` adds the derivatives."""
        p0, p1, p2, roll, pitch = theta
        pitch += self.pitch_offset  # the normal the impact map sees; d/dpitch is unchanged
        cr, sr, cp, sp = math.cos(roll), math.sin(roll), math.cos(pitch), math.sin(pitch)
        n = (cr * sp, -sr, cr * cp)
        w = (self._vb[0] - p0, self._vb[1] - p1, self._vb[2] - p2)
        a = self.a
        pre = None
        if self.mlp is not None:
            phi_np, pre = self.mlp.forward_pre1(self.x, np.array((p0, p1, p2, n[0], n[1], n[2])), self._x_part)
            phi = phi_np.tolist()
        else:
            phi = [0.0, 0.0, 0.0]
        nw = n[0] * w[0] + n[1] * w[1] + n[2] * w[2]
        if a is not None:
            v0 = a * (w[0] - 2.0 * n[0] * nw) + p0 + phi[0]
            v1 = a * (w[1] - 2.0 * n[1] * nw) + p1 + phi[1]
            v2 = a * (w[2] - 2.0 * n[2] * nw) + p2 + phi[2]
        else:
            v0, v1, v2 = phi
        t = self.k * v2 if v2 > 0.0 else 0.0
        r0, r1 = self._off[0] + v0 * t, self._off[1] + v1 * t
        return Point(theta, (r0, r1), (v0, v1, v2), 0.5 * (r0 * r0 + r1 * r1), v2 > 0.0, (cr, sr, cp, sp), n, w, nw,
                     pre)

    def derivatives(self, pt: Point, curvature: bool) -> tuple[list[list[float]], list[list[float]] | None]:
        """``J`` (2 x 5) and, if ``curvature``, the Hessian ``H = J^T J + C`` (5 x 5) of ``1/2 ||r||^2`` at ``pt``
        (lists of floats, read-only: cached on ``pt`` for later calls; zero where the ball would not leave upwards).
        Also sets ``pt.dv``."""
        if pt.jac is not None and (pt.hess is not None or not curvature):
            return pt.jac, (pt.hess if curvature else None)
        if not pt.up:
            return [[0.0] * 5, [0.0] * 5], ([[0.0] * 5 for _ in range(5)] if curvature else None)
        jp = None if pt.pre is None or self.mlp is None else self.mlp.jac_u1(pt.pre).tolist()
        dn = _normal_derivatives(pt)
        jac = self._jacobians(pt, jp, dn)
        if not curvature:
            return jac, None
        pt.hess = self._hessian(pt, jp, dn, jac)
        return jac, pt.hess

    def _jacobians(self, pt: Point, jp: list[list[float]] | None, dn: _NormalDerivatives) -> list[list[float]]:
        """``dv/dtheta`` (3 x 5, set as ``pt.dv``) and ``J = dr/dtheta`` (2 x 5, set as ``pt.jac`` and returned):
        the base impact map by hand, the network (``jp = d phi / du``, 3 x 6) through ``u = [pv, n(roll, pitch)]``."""
        n, nw = pt.n, pt.nw
        v0, v1, v2 = pt.v
        a, k = self.a, self.k
        nr, npi, nrw, npw = dn
        n0, n1, n2 = n
        if a is not None:
            a2, b = 2.0 * a, 1.0 - a
            x0, x1, x2 = a2 * n0, a2 * n1, a2 * n2
            dv = [[b + x0 * n0, x0 * n1, x0 * n2, -a2 * nr[0] * nw - x0 * nrw, -a2 * npi[0] * nw - x0 * npw],
                  [x1 * n0, b + x1 * n1, x1 * n2, -a2 * nr[1] * nw - x1 * nrw, -x1 * npw],
                  [x2 * n0, x2 * n1, b + x2 * n2, -a2 * nr[2] * nw - x2 * nrw, -a2 * npi[2] * nw - x2 * npw]]
        else:
            dv = [[0.0] * 5 for _ in range(3)]
        if jp is not None:
            for row, jo in zip(dv, jp):
                row[0] += jo[0]
                row[1] += jo[1]
                row[2] += jo[2]
                row[3] += jo[3] * nr[0] + jo[4] * nr[1] + jo[5] * nr[2]
                row[4] += jo[3] * npi[0] + jo[5] * npi[2]
        pt.dv = dv
        d0, d1, dz = dv
        kz, kx, ky = k * v2, k * v0, k * v1
        jac = [[kz * d0[0] + kx * dz[0], kz * d0[1] + kx * dz[1], kz * d0[2] + kx * dz[2], kz * d0[3] + kx * dz[3],
                kz * d0[4] + kx * dz[4]],
               [kz * d1[0] + ky * dz[0], kz * d1[1] + ky * dz[1], kz * d1[2] + ky * dz[2], kz * d1[3] + ky * dz[3],
                kz * d1[4] + ky * dz[4]]]
        pt.jac = jac
        return jac

    def _hessian(self, pt: Point, jp: list[list[float]] | None, dn: _NormalDerivatives,
                 jac: list[list[float]]) -> list[list[float]]:
        """``H = J^T J + C`` (5 x 5) at ``pt``, with ``pt.dv`` and ``jac`` from :meth:`_jacobians`."""
        # C = sum_i r_i d2 r_i, r_i = p_i + k v_i v_z - target_i (i = x, y):
        # d2 r_i = k (dv_i dv_z^T + dv_z dv_i^T + v_z d2 v_i + v_i d2 v_z), d2 v from n(roll, pitch) only
        cr, sr, cp, sp = pt.trig
        n, w, nw = pt.n, pt.w, pt.nw
        v0, v1, v2 = pt.v
        r0, r1 = pt.r
        a, k = self.a, self.k
        nr, npi, nrw, npw = dn
        dv = pt.dv
        assert dv is not None
        dz = dv[2]
        s = [r0 * dv[0][j] + r1 * dv[1][j] for j in range(5)]
        j0, j1 = jac
        ks = [k * c for c in s]
        curv = [[ks[i] * dz[j] + dz[i] * ks[j] + j0[i] * j0[j] + j1[i] * j1[j] for j in range(5)] for i in range(5)]
        q0, q1, q2 = k * r0 * v2, k * r1 * v2, k * (r0 * v0 + r1 * v1)  # weights of the Hessians of v
        nrr = (-n[0], -n[1], -n[2])
        nrp = (-sr * cp, 0.0, sr * sp)
        npp = (-cr * sp, 0.0, -cr * cp)
        ang_rr = ang_rp = ang_pp = 0.0
        if jp is not None:  # q^T (d phi / d n) d2 n
            e0 = q0 * jp[0][3] + q1 * jp[1][3] + q2 * jp[2][3]
            e1 = q0 * jp[0][4] + q1 * jp[1][4] + q2 * jp[2][4]
            e2 = q0 * jp[0][5] + q1 * jp[1][5] + q2 * jp[2][5]
            ang_rr = e0 * nrr[0] + e1 * nrr[1] + e2 * nrr[2]
            ang_rp = e0 * nrp[0] + e2 * nrp[2]
            ang_pp = e0 * npp[0] + e2 * npp[2]
        if a is not None:  # the base map: -2 a d2[n (n . w)] (angles), 2 a d[n n^T] (pv x angle)
            a2 = 2.0 * a
            qn = q0 * n[0] + q1 * n[1] + q2 * n[2]
            qr = q0 * nr[0] + q1 * nr[1] + q2 * nr[2]
            qp = q0 * npi[0] + q2 * npi[2]
            q_rr = q0 * nrr[0] + q1 * nrr[1] + q2 * nrr[2]
            q_rp = q0 * nrp[0] + q2 * nrp[2]
            q_pp = q0 * npp[0] + q2 * npp[2]
            wrr = nrr[0] * w[0] + nrr[1] * w[1] + nrr[2] * w[2]
            wrp = nrp[0] * w[0] + nrp[2] * w[2]
            wpp = npp[0] * w[0] + npp[2] * w[2]
            ang_rr -= a2 * (q_rr * nw + qn * wrr + 2.0 * qr * nrw)
            ang_rp -= a2 * (q_rp * nw + qn * wrp + qr * npw + qp * nrw)
            ang_pp -= a2 * (q_pp * nw + qn * wpp + 2.0 * qp * npw)
            for i in range(3):
                m_r = a2 * (n[i] * qr + qn * nr[i])
                m_p = a2 * (n[i] * qp + qn * npi[i])
                curv[i][3] += m_r
                curv[3][i] += m_r
                curv[i][4] += m_p
                curv[4][i] += m_p
        curv[3][3] += ang_rr
        curv[3][4] += ang_rp
        curv[4][3] += ang_rp
        curv[4][4] += ang_pp
        return curv


#: ``dn/droll`` (3,), ``dn/dpitch`` (3,), and their products with ``w``
_NormalDerivatives = tuple[tuple[float, float, float], tuple[float, float, float], float, float]


def _normal_derivatives(pt: Point) -> _NormalDerivatives:
    """``(dn/droll, dn/dpitch, dn/droll . w, dn/dpitch . w)`` at ``pt``."""
    cr, sr, cp, sp = pt.trig
    w = pt.w
    nr = (-sr * sp, -cr, -sr * cp)
    npi = (cr * cp, 0.0, -cr * sp)
    return nr, npi, nr[0] * w[0] + nr[1] * w[1] + nr[2] * w[2], npi[0] * w[0] + npi[2] * w[2]
