"""The paper's one-shot ball-bouncing controllers (eq. ball_paddle_opt, :mod:`~saml_ros.systems.paddle_ball.mpc.problem`):
choose the paddle velocity and orientation at impact so that the ball comes back down at a target xy.

Both solvers start from the same list (:meth:`PaddleProblem.guesses`, the previous solution first) and return the
best feasible end point. Fast solver (:class:`GaussNewtonPaddle`): projected Gauss-Newton / Newton on
``1/2 ||r||^2`` with exact first and second derivatives, in plain Python floats
(:mod:`~saml_ros.systems.paddle_ball.mpc.landing_error`, :mod:`~saml_ros.systems.paddle_ball.mpc.projected_newton`,
:mod:`~saml_ros.systems.paddle_ball.mpc.feasible_set`) and its own multi-start rule
(:mod:`~saml_ros.systems.paddle_ball.mpc.multistart`). Reference (:class:`SLSQPPaddle`): scipy SLSQP on the exact non-smooth
objective with finite differences, restarting until a start reaches the target or two starts agree.
"""

from __future__ import annotations

import math
import time
from typing import Any

import numpy as np
import scipy.optimize

from saml_ros.core.dynamics.system import System
from saml_ros.core.mpc.contract import MPCResult
from saml_ros.core.mpc.dynamics_np import BaseModelNP, NumpyDynamics, PredictionModel
from saml_ros.systems.paddle_ball.model import PaddleBall
from saml_ros.systems.paddle_ball.mpc.multistart import SearchSettings, search
from saml_ros.systems.paddle_ball.mpc.problem import PaddleGoal, PaddleProblem, control_from_theta, paddle_goal
from saml_ros.systems.paddle_ball.mpc.projected_newton import ProjectedNewton, RunResult


class PaddleController:
    """Shared machinery of the paddle solvers (Controller protocol, horizon 1)."""

    horizon = 1

    def __init__(self, system: PaddleBall, model: PredictionModel = None, member: int = 0,
                 feas_tol: float = 1e-6, tol: float = 1e-4, base: BaseModelNP | None = None,
                 true: BaseModelNP | None = None) -> None:
        if not isinstance(system, PaddleBall):
            raise ValueError(f"the paddle controller needs a PaddleBall system, got {system.name!r}")
        self.system: System = system
        self.paddle = system
        self.member = member
        self.feas_tol = feas_tol  #: tolerance on |v_rel| bounds for success (m/s)
        self.tol = tol  #: landing error (m) below which a start is good enough (no further restarts)
        self.base_np, self.true_np = base, true
        self.dyn = NumpyDynamics(system, model, member, base, true)
        self._theta: np.ndarray | None = None

    def set_model(self, model: PredictionModel) -> None:
        self.dyn = NumpyDynamics(self.system, model, self.member, self.base_np, self.true_np)

    def reset(self) -> None:
        self._theta = None

    def solve(self, x0: np.ndarray, goal: Any | None = None) -> MPCResult:
        start = time.perf_counter()
        x0 = np.asarray(x0, dtype=np.float64)
        if x0.shape != (6,):
            raise ValueError(f"paddle_ball MPC: x0 must have shape (6,), got {x0.shape}")
        g = paddle_goal(goal)
        if not np.all(np.isfinite(x0)):
            return self._fallback(start, "non-finite state")
        prob = PaddleProblem(self.paddle, self.dyn, x0, g)
        starts = prob.guesses()
        if self._theta is not None:
            starts.insert(0, np.clip(self._theta, prob.lo, prob.hi))
        try:
            theta, total, conv, msg = self._search(prob, starts)
        except Exception as exc:  # numerical breakdown: the safe default
            return self._fallback(start, f"solver failure: {type(exc).__name__}: {exc}")
        theta = np.clip(theta, prob.lo, prob.hi)
        u = np.clip(prob.control(theta), self.system.control_low, self.system.control_high)
        r, c, v_post = self._evaluate(prob, theta)
        if not (np.all(np.isfinite(v_post)) and np.all(np.isfinite(u))):
            return self._fallback(start, f"non-finite plan ({msg})", total)
        viol = self._violation(c, g)
        ok = viol <= self.feas_tol and v_post[2] > 0.0
        if viol > self.feas_tol:
            msg += f"; |v_rel| outside [{g.v_rel[0]}, {g.v_rel[1]}] by {viol:.3g} m/s"
        if v_post[2] <= 0.0:
            msg += "; the ball would not leave the paddle upwards"
        self._theta = theta
        return MPCResult(
            u=u, plan_u=u[None].copy(), plan_x=np.concatenate((x0[:3], v_post))[None],
            cost=float(np.linalg.norm(r)), solve_time=time.perf_counter() - start, iterations=total,
            success=bool(ok), message=msg, constraint_violation=viol, converged=conv,
        )  # fmt: skip

    @staticmethod
    def _violation(c: np.ndarray, g: PaddleGoal) -> float:
        """Largest |v_rel| bound violation in m/s from the squared-speed constraint values."""
        s2 = g.v_rel[0] ** 2 - c[0]
        s = math.sqrt(max(s2, 0.0))
        return max(0.0, g.v_rel[0] - s, s - g.v_rel[1])

    def _fallback(self, start: float, why: str, iters: int = 0) -> MPCResult:
        u = np.array([0.0, 0.0, 0.0, 0.0, 0.0, 1.0]) if self._theta is None else control_from_theta(self._theta)
        u = np.clip(u, self.system.control_low, self.system.control_high)
        return MPCResult(
            u=u, plan_u=u[None].copy(), plan_x=np.full((1, 6), np.nan), cost=float("nan"),
            solve_time=time.perf_counter() - start, iterations=iters, success=False, message=why,
            constraint_violation=float("inf"), converged=False,
        )  # fmt: skip

    def _search(self, prob: PaddleProblem, starts: list[np.ndarray]) -> tuple[np.ndarray, int, bool, str]:
        """Best end point over the starts: ``(theta (5,), iterations, converged, message)``."""
        raise NotImplementedError

    def _evaluate(self, prob: PaddleProblem, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`PaddleProblem.evaluate` of the returned plan."""
        return prob.evaluate(theta)


class GaussNewtonPaddle(PaddleController):
    """The fast paddle solver: exact-derivative projected Gauss-Newton / Newton from the same starts
    (:mod:`~saml_ros.systems.paddle_ball.mpc.multistart`, :mod:`~saml_ros.systems.paddle_ball.mpc.projected_newton`).

    Options: ``max_iter`` (iterations of one Newton run), ``max_time`` (s, optional budget of a solve; the best
    point found by then is returned).
    """

    def __init__(self, system: PaddleBall, model: PredictionModel = None, member: int = 0,
                 max_iter: int = 20, max_time: float | None = None, **kwargs: Any) -> None:
        super().__init__(system, model, member, **kwargs)
        self.max_iter, self.max_time = max_iter, max_time
        self.settings = SearchSettings(tol=self.tol, max_iter=max_iter)
        self._last: RunResult | None = None  # the end point of the last search

    def _search(self, prob: PaddleProblem, starts: list[np.ndarray]) -> tuple[np.ndarray, int, bool, str]:
        g = prob.goal
        deadline = math.inf if self.max_time is None else time.perf_counter() + self.max_time
        newton = ProjectedNewton(prob.landing_error(), prob.feasible_set())
        away = (g.target_xy - prob.x[0:2]).tolist()

        def tilt(theta: list[float]) -> float:
            """how much the paddle leans towards the target: normal_xy . (target - p)"""
            return math.sin(theta[4]) * away[0] - math.sin(theta[3]) * away[1]

        best, total, msg = search(newton, [s.tolist() for s in starts], tilt, self.settings, deadline)
        self._last = best
        return np.array(best.theta), total, best.converged, msg

    def _evaluate(self, prob: PaddleProblem, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The search's own evaluation of the plan (the same model, in floats) when it returned this point."""
        last, self._last = self._last, None
        th = theta.tolist()
        if last is None or last.point is None or last.point.theta != th:
            return prob.evaluate(theta)
        w = [c - p for c, p in zip(prob.x[3:6].tolist(), th[:3])]
        s2 = w[0] * w[0] + w[1] * w[1] + w[2] * w[2]
        lo, hi = prob.goal.v_rel
        return np.array(last.point.r), np.array([lo * lo - s2, s2 - hi * hi]), np.array(last.point.v)


class SLSQPPaddle(PaddleController):
    """The reference: scipy SLSQP on ``||landing - target||`` with finite differences, from the same starts."""

    def __init__(self, system: PaddleBall, model: PredictionModel = None, member: int = 0,
                 max_iter: int = 100, ftol: float = 1e-8, **kwargs: Any) -> None:
        super().__init__(system, model, member, **kwargs)
        self.max_iter, self.ftol = max_iter, ftol

    def _search(self, prob: PaddleProblem, starts: list[np.ndarray]) -> tuple[np.ndarray, int, bool, str]:
        """Best end point over the starts: ``(theta, iterations, converged, message)``.

        Runs :meth:`_optimize` from each start in turn and stops when a start reaches the target within
        ``tol`` or a second start ends at the best (feasible) cost found so far (within 1 %).
        """
        g = prob.goal
        best: tuple[tuple[bool, float], np.ndarray, bool, str] | None = None
        total = 0
        for guess in starts:
            theta, iters, conv, msg = self._optimize(prob, guess)
            total += iters
            r, c, v_post = prob.evaluate(theta)
            bad = self._violation(c, g) > self.feas_tol or v_post[2] <= 0.0
            key = (bad, float(np.linalg.norm(r)))
            if best is None or key < best[0]:
                best = (key, theta, conv, msg)
            if not best[0][0] and best[0][1] <= self.tol:
                break
            # a second start ending at the best (feasible) cost found so far: take it as the minimum
            if key is not best[0] and not bad and abs(key[1] - best[0][1]) <= max(self.tol, 1e-2 * best[0][1]):
                break
        assert best is not None
        return best[1], total, best[2], best[3]

    def _optimize(self, prob: PaddleProblem, theta0: np.ndarray) -> tuple[np.ndarray, int, bool, str]:
        lo, hi = prob.goal.v_rel

        def speed(th: np.ndarray) -> float:
            return float(np.linalg.norm(prob.x[3:6] - th[:3]))

        res = scipy.optimize.minimize(
            lambda th: float(np.linalg.norm(prob.evaluate(th)[0])),
            theta0,
            method="SLSQP",
            bounds=scipy.optimize.Bounds(prob.lo, prob.hi),
            constraints=[{"type": "ineq", "fun": lambda th: np.array([speed(th) - lo, hi - speed(th)])}],
            options={"maxiter": self.max_iter, "ftol": self.ftol},
        )
        return np.clip(res.x, prob.lo, prob.hi), int(res.nit), bool(res.success), str(res.message)

