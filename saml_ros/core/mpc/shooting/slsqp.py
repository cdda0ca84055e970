"""The paper's reference single-shooting solver (:class:`SLSQPShootingMPC`): scipy SLSQP with finite differences."""

from __future__ import annotations

from collections import OrderedDict
from typing import Any

import numpy as np
import scipy.optimize

from saml_ros.core.dynamics.system import System
from saml_ros.core.mpc.dynamics_np import PredictionModel
from saml_ros.core.mpc.shooting.controller import ShootingMPC
from saml_ros.core.mpc.shooting.tasks import ShootingTask


class SLSQPShootingMPC(ShootingMPC):
    """The paper's reference: scipy SLSQP over the flattened controls, single shooting through the model,
    gradients by scipy's default 2-point finite differences, the exact (non-smooth) objective.

    Rollouts are memoised (LRU) so the objective and the constraints never roll out the same U twice.

    Args (beyond :class:`ShootingMPC`'s): ``max_iter`` (SLSQP ``maxiter``), ``ftol`` (SLSQP ``ftol``).
    """

    def __init__(
        self,
        system: System,
        model: PredictionModel = None,
        horizon: int = 10,
        max_iter: int = 100,
        ftol: float = 1e-6,
        **kwargs: Any,
    ) -> None:
        super().__init__(system, model, horizon, **kwargs)
        self.max_iter, self.ftol = max_iter, ftol

    def _optimize(
        self, x0: np.ndarray, u0: np.ndarray, task: ShootingTask, xs0: np.ndarray | None = None
    ) -> tuple[np.ndarray, int, bool, str, np.ndarray | None]:
        T, m = self.horizon, self.m
        cache: OrderedDict[bytes, np.ndarray] = OrderedDict()

        def traj(flat: np.ndarray) -> np.ndarray:
            key = flat.tobytes()
            xs = cache.get(key)
            if xs is None:
                xs = self.rollout(x0, flat.reshape(T, m))
                cache[key] = xs
                if len(cache) > 4 * T * m + 8:
                    cache.popitem(last=False)
            return xs

        constraints = []
        if task.n_cons:
            constraints.append({"type": "ineq", "fun": lambda f: -task.violations(traj(f))})
        res = scipy.optimize.minimize(
            lambda f: task.cost(traj(f)),
            u0.reshape(-1),
            method="SLSQP",
            bounds=scipy.optimize.Bounds(self._u_lo, self._u_hi),
            constraints=constraints,
            options={"maxiter": self.max_iter, "ftol": self.ftol},
        )
        return res.x.reshape(T, m), int(res.nit), bool(res.success), str(res.message), None
