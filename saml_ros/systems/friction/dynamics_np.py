"""The friction system's numpy twins: f_hat and the true model on float64 arrays with exact Jacobians (the MPC's
prediction model, :class:`saml_ros.core.mpc.dynamics_np.NumpyDynamics`).
"""

from __future__ import annotations

import math

import numpy as np

from saml_ros.core.mpc.dynamics_np import Jac3
from saml_ros.systems.friction.model import FrictionDoubleIntegrator


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
