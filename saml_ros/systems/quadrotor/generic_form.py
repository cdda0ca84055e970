"""The quadrotor's f_hat as an array-namespace form (:mod:`saml_ros.core.dynamics.base_forms`), for the generic
planner: the same explicit Euler step as :meth:`saml_ros.systems.quadrotor.model.Quadrotor.euler_step` (torch),
written once for numpy, torch and CasADi, so the generic SQP differentiates it symbolically (CasADi) instead of by
torch autograd. Equal to the torch f_hat to rounding (``test/unit/core/mpc/test_quadrotor_form.py``).

State ``[px, py, pz, vx, vy, vz, qw, qx, qy, qz, wx, wy, wz]``, control the four motor forces (N); see the system's
module docstring for the frame and the torques.
"""

from __future__ import annotations

from typing import Any

from saml_ros.core.mpc.generic.dynamics import SymbolicBase


def quadrotor_f_hat(x: Any, u: Any, *, dt: float, xp: Any, mass: float, inertia: tuple[float, float, float],
                    g: float) -> Any:
    """One Euler step of the rigid body under the motor forces ``u (B, 4)`` from ``x (B, 13)``; ``-> (B, 13)``
    (the quaternion renormalised before and after, as the torch f_hat does)."""
    px, py, pz, vx, vy, vz = (x[:, i] for i in range(6))
    qn = xp.clip(xp.sqrt(x[:, 6] ** 2 + x[:, 7] ** 2 + x[:, 8] ** 2 + x[:, 9] ** 2), 1e-12, 1e300)
    qw, qx, qy, qz = x[:, 6] / qn, x[:, 7] / qn, x[:, 8] / qn, x[:, 9] / qn
    wx, wy, wz = x[:, 10], x[:, 11], x[:, 12]
    f1, f2, f3, f4 = u[:, 0], u[:, 1], u[:, 2], u[:, 3]
    a = (f1 + f2 + f3 + f4) / mass  # body z acceleration
    # R(q) [0, 0, a]: the third column of the rotation matrix times a
    ax = 2.0 * (qx * qz + qw * qy) * a
    ay = 2.0 * (qy * qz - qw * qx) * a
    az = (1.0 - 2.0 * (qx * qx + qy * qy)) * a - g
    ix, iy, iz = inertia
    tx, ty, tz = f4 - f2, f3 - f1, (f1 + f3) - (f2 + f4)
    # omega x (I omega)
    cx = wy * (iz * wz) - wz * (iy * wy)
    cy = wz * (ix * wx) - wx * (iz * wz)
    cz = wx * (iy * wy) - wy * (ix * wx)
    # q_dot = 1/2 q (x) [0, omega]
    dw = 0.5 * (-qx * wx - qy * wy - qz * wz)
    dx = 0.5 * (qw * wx + qy * wz - qz * wy)
    dy = 0.5 * (qw * wy - qx * wz + qz * wx)
    dz = 0.5 * (qw * wz + qx * wy - qy * wx)
    nw, nx, ny, nz = qw + dt * dw, qx + dt * dx, qy + dt * dy, qz + dt * dz
    nn = xp.clip(xp.sqrt(nw * nw + nx * nx + ny * ny + nz * nz), 1e-12, 1e300)
    return xp.stack([px + dt * vx, py + dt * vy, pz + dt * vz, vx + dt * ax, vy + dt * ay, vz + dt * az,
                     nw / nn, nx / nn, ny / nn, nz / nn,
                     wx + dt * (tx - cx) / ix, wy + dt * (ty - cy) / iy, wz + dt * (tz - cz) / iz])


def quadrotor_params(system: Any) -> dict[str, Any]:
    """The form's parameters of a :class:`~saml_ros.systems.quadrotor.model.Quadrotor` instance."""
    return {"mass": float(system.mass), "inertia": tuple(float(v) for v in system.inertia), "g": float(system.g)}


def quadrotor_base(system: Any) -> SymbolicBase:
    """f_hat of the quadrotor for :class:`~saml_ros.core.mpc.generic.GenericSQP` (numpy values, CasADi
    Jacobians): assign it to the planner's ``_base`` and rebuild its ``dyn``, as the evaluation's oracle does."""
    return SymbolicBase(quadrotor_f_hat, quadrotor_params(system), 13, 4, system.dt, "quadrotor Euler step (xp form)")


#: the generic SQP's options equal to the hand-written SQP's defaults (:class:`~saml_ros.core.mpc.shooting.sqp.
#: SQPShootingMPC`): the same stopping test, Levenberg-Marquardt start and floor, violation price schedule (10, x10 up
#: to 1e4 while a movable constraint is violated) and feasibility tolerance, so both take the same steps
HAND_WRITTEN_OPTIONS = {"max_iter": 20, "tol": 3e-4, "rho0": 1e-3, "lm_floor": 1e-3, "feas_tol": 1e-4,
                        "penalty_max": 1e4, "undamped_check": False, "compile": True}


def quadrotor_generic_task(system: Any, horizon: int = 10, min_height: float = 0.2, qw_tol: float = 0.05,
                           tilt_max: float = 0.2) -> Any:
    """The quadrotor demo's landing task (:func:`saml_ros.systems.quadrotor.task.quadrotor_task`) as a generic
    :class:`~saml_ros.core.mpc.generic.section.MPCTask`: the unsquared distance of ``(px, py, pz)`` from the goal at
    every step (``norm_cost``, smoothed by 1e-3 as the hand-written SQP's ``eps``), ``pz >= min_height`` and
    ``|qx|, |qy| <= tilt_max`` at every step, and the final attitude bound ``|qw_T - 1| <= qw_tol`` in the form the
    hand-written planner linearises, ``||(qx, qy, qz)_T|| <= sqrt(1 - (1 - qw_tol)^2)`` (``at: terminal``); motor
    forces in ``[0, f_max]``, hover thrust as the safe command; the hand-written SQP's solver options
    (:data:`HAND_WRITTEN_OPTIONS`, violation price 10 raised to 1e4)."""
    import math

    import numpy as np

    from saml_ros.core.mpc.generic.section import MPCTask, StateConstraint

    names = tuple(system.state.names)
    ix = tuple(names.index(n) for n in ("px", "py", "pz"))
    cons = [StateConstraint("height", "box", (names.index("pz"),), low=(float(min_height),), high=(math.inf,))]
    if math.isfinite(tilt_max):
        cons.append(StateConstraint("tilt", "box", (names.index("qx"), names.index("qy")),
                                    low=(-tilt_max, -tilt_max), high=(tilt_max, tilt_max)))
    cons.append(StateConstraint("attitude", "norm", tuple(names.index(n) for n in ("qx", "qy", "qz")),
                                max=math.sqrt(1.0 - (1.0 - qw_tol) ** 2), terminal=True))
    return MPCTask(horizon=int(horizon), rate=0.0, state_timeout=0.0, goal_idx=ix, goal_default=np.zeros(3),
                   goal_low=np.full(3, -1e3), goal_high=np.full(3, 1e3), goal_angle=(False, False, False),
                   w_stage=np.ones(3), w_terminal=np.ones(3), w_effort=np.zeros(4), w_rate=np.zeros(4),
                   u_low=np.asarray(system.control_low, dtype=np.float64),
                   u_high=np.asarray(system.control_high, dtype=np.float64),
                   u_safe=np.asarray(system.hover_thrust(), dtype=np.float64), constraints=tuple(cons),
                   state_names=names, control_names=tuple(system.control.names), norm_cost=True, norm_eps=1e-3,
                   penalty=10.0, solver_options=dict(HAND_WRITTEN_OPTIONS))
