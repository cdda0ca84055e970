"""The user's first-principles model of the example arm: rigid-body dynamics of a two-link planar arm.

This is what the arm's maker knows from the drawings and the motors' data sheets: link lengths, masses,
inertias, the motors' rotor inertia (armature), gravity. It does not know the payload in the gripper, the joint
friction or the elbow's return spring (see ``arm.xml``); the learner learns those as the residual.

* :func:`f_hat` is the base model named in ``system.yaml`` (``base_model: {function: "arm_model:f_hat"}``): batched
  torch, ``f_hat(x (B, 4), u (B, 2), *, dt, **params) -> (B, 4)``, the state ``[q1, q2, dq1, dq2]`` (rad, rad/s)
  one period ``dt`` after ``x`` under the held torque ``u = [tau1, tau2]`` (N*m). It integrates like MuJoCo's
  Euler integrator (semi-implicit: velocity first, then position) on steps of ``h`` s.
* :func:`mass_matrix`, :func:`bias`, :func:`tip`, :func:`inverse_kinematics` serve the arm's own controller
  (``controller.py``, numpy).

Angles: ``q1`` of the upper arm from the horizontal (+x), positive up; ``q2`` of the forearm relative to the upper
arm. Gravity acts along -z.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    import torch

G = 9.81  # m/s^2
#: the nominal parameters (SI): link lengths, masses, centres of mass, inertias about the centres, armatures
NOMINAL: dict[str, float] = {
    "l1": 0.45, "l2": 0.40,
    "m1": 1.6, "m2": 1.0,
    "c1": 0.225, "c2": 0.20,
    "i1": 0.027, "i2": 0.013333333,
    "a1": 0.06, "a2": 0.04,
}


def _p(params: dict[str, Any]) -> dict[str, float]:
    unknown = sorted(set(params) - set(NOMINAL) - {"h"})
    if unknown:
        raise ValueError(f"arm_model: unknown parameter(s) {unknown}; valid: {sorted(NOMINAL)} and 'h'")
    return {k: float(params.get(k, v)) for k, v in NOMINAL.items()}


def _terms(q1: Any, q2: Any, dq1: Any, dq2: Any, lib: Any, p: dict[str, float]) -> tuple[Any, ...]:
    """Entries of M(q) and of the bias b(q, dq) = C(q, dq) dq + g(q), for numpy arrays (``lib=np``) or torch
    tensors (``lib=torch``) alike: ``(m11, m12, m22, b1, b2)``."""
    l1, m1, m2, c1, c2 = p["l1"], p["m1"], p["m2"], p["c1"], p["c2"]
    cos2, sin2 = lib.cos(q2), lib.sin(q2)
    m11 = m1 * c1**2 + p["i1"] + m2 * (l1**2 + c2**2 + 2.0 * l1 * c2 * cos2) + p["i2"] + p["a1"]
    m12 = m2 * (c2**2 + l1 * c2 * cos2) + p["i2"]
    m22 = m2 * c2**2 + p["i2"] + p["a2"]
    h = m2 * l1 * c2 * sin2
    g12 = m2 * c2 * G * lib.cos(q1 + q2)
    b1 = -h * (2.0 * dq1 * dq2 + dq2 * dq2) + (m1 * c1 + m2 * l1) * G * lib.cos(q1) + g12
    b2 = h * dq1 * dq1 + g12
    return m11, m12, m22, b1, b2


def f_hat(x: torch.Tensor, u: torch.Tensor, *, dt: float, h: float = 0.002, xp: Any = None,
          **params: Any) -> torch.Tensor:
    """Next state ``(B, 4)`` after ``dt`` s of torque ``u (B, 2)`` from ``x (B, 4)``; semi-implicit Euler steps of
    at most ``h`` s. ``params`` override :data:`NOMINAL`. ``xp``: the array namespace (torch in the learner, numpy
    and CasADi in saml_ros's MPC, which then differentiates it exactly: an *array-namespace form*, docs/your_robot.md
    "Control it"); default torch."""
    batched_torch = xp is None
    if xp is None:
        import torch as xp  # here, not at the top: the arm's controller (numpy only) starts without torch
    p = _p(params)
    lib: Any = xp
    n = max(1, round(dt / h))
    step = dt / n
    q1, q2, dq1, dq2 = x[:, 0], x[:, 1], x[:, 2], x[:, 3]
    t1, t2 = u[:, 0], u[:, 1]
    for _ in range(n):
        m11, m12, m22, b1, b2 = _terms(q1, q2, dq1, dq2, lib, p)
        r1, r2 = t1 - b1, t2 - b2
        det = m11 * m22 - m12 * m12
        dq1 = dq1 + step * (m22 * r1 - m12 * r2) / det
        dq2 = dq2 + step * (m11 * r2 - m12 * r1) / det
        q1 = q1 + step * dq1
        q2 = q2 + step * dq2
    if batched_torch:
        return lib.stack([q1, q2, dq1, dq2], dim=1)
    return xp.stack([q1, q2, dq1, dq2])


# ------------------------------------------------------------------------------------ for the controller (numpy)
def mass_matrix(q: np.ndarray, params: dict[str, Any] | None = None) -> np.ndarray:
    """M(q) ``(2, 2)`` (kg m^2) at joint angles ``q (2,)``."""
    m11, m12, m22, _, _ = _terms(q[0], q[1], 0.0, 0.0, np, _p(params or {}))
    return np.array([[m11, m12], [m12, m22]])


def bias(q: np.ndarray, dq: np.ndarray, params: dict[str, Any] | None = None) -> np.ndarray:
    """C(q, dq) dq + g(q) ``(2,)`` (N*m)."""
    _, _, _, b1, b2 = _terms(q[0], q[1], dq[0], dq[1], np, _p(params or {}))
    return np.array([b1, b2])


def tip(q: np.ndarray) -> tuple[float, float]:
    """The gripper's position ``(x, z)`` (m) relative to the shoulder."""
    l1, l2 = NOMINAL["l1"], NOMINAL["l2"]
    return (l1 * math.cos(q[0]) + l2 * math.cos(q[0] + q[1]), l1 * math.sin(q[0]) + l2 * math.sin(q[0] + q[1]))


def inverse_kinematics(x: float, z: float, elbow_up: bool = True) -> np.ndarray | None:
    """Joint angles ``(2,)`` that put the gripper at ``(x, z)``; ``None`` if out of reach. ``elbow_up``: the elbow
    above the line shoulder-gripper (q2 < 0)."""
    l1, l2 = NOMINAL["l1"], NOMINAL["l2"]
    c = (x * x + z * z - l1 * l1 - l2 * l2) / (2.0 * l1 * l2)
    if not -1.0 <= c <= 1.0:
        return None
    q2 = -math.acos(c) if elbow_up else math.acos(c)
    q1 = math.atan2(z, x) - math.atan2(l2 * math.sin(q2), l1 + l2 * math.cos(q2))
    return np.array([q1, q2])
