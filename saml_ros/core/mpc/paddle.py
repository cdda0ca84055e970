"""The paper's one-shot ball-bouncing controller (eq. ball_paddle_opt): choose the paddle velocity and
orientation at impact so that the ball comes back down at a target xy.

Decision variables ``theta = [pvx, pvy, pvz (m/s), roll, pitch (rad)]``; the commanded normal is
``normal_from_roll_pitch(roll, pitch)`` (unit by construction), so ``u = [pv, n]``.

    min_theta  || landing(p, v_post(x, u)) - target_xy ||_2
    s.t.       pv within the system's paddle-velocity bounds,
               roll_min <= roll <= roll_max,  pitch_min <= pitch <= pitch_max,
               v_min <= |v_ball - v_paddle| <= v_max        (relative speed at impact)

``v_post`` is the model in use (``f_hat + phi``, ``phi`` for a full model, or ``f_hat``), ``landing`` the
ballistic landing point at the impact height (:func:`~saml_ros.core.systems.paddle_ball.landing_point`).

Both solvers start from the same list (:meth:`PaddleProblem.guesses`, the previous solution first) and return the
best feasible end point. Fast solver (:class:`GaussNewtonPaddle`): projected Gauss-Newton / Newton on
``1/2 ||r||^2`` with exact first and second derivatives, in plain Python floats
(:mod:`~saml_ros.core.mpc.paddle_eval`, :mod:`~saml_ros.core.mpc.paddle_row`) and its own multi-start rule
(:mod:`~saml_ros.core.mpc.paddle_search`). Reference (:class:`SLSQPPaddle`): scipy SLSQP on the exact non-smooth
objective with finite differences, restarting until a start reaches the target or two starts agree.
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.optimize

from saml_ros.core.models import DynamicsModel
from saml_ros.core.mpc.dynamics_np import NumpyDynamics
from saml_ros.core.mpc.paddle_eval import PaddleEval
from saml_ros.core.mpc.paddle_row import PaddleRowSolver, RowResult
from saml_ros.core.mpc.paddle_search import SearchSettings, search
from saml_ros.core.mpc.types import MPCResult
from saml_ros.core.systems.base import System
from saml_ros.core.systems.paddle_ball import PaddleBall

_TILTS = ((0.0, 0.5), (0.0, -0.5), (0.5, 0.0), (-0.5, 0.0), (0.5, 0.5), (-0.5, -0.5), (0.5, -0.5), (-0.5, 0.5))
_DEFAULTS: dict[str, Any] = {"target_xy": (0.0, 0.0), "roll": (-0.4, 0.4), "pitch": (-0.4, 0.4), "v_rel": (3.0, 5.0)}


@dataclass(frozen=True)
class PaddleGoal:
    """Controller parameters of eq. ball_paddle_opt (see :func:`paddle_goal`)."""

    target_xy: np.ndarray  #: (2,) m, where the ball should come down
    roll: tuple[float, float]  #: rad, (min, max)
    pitch: tuple[float, float]  #: rad, (min, max)
    v_rel: tuple[float, float]  #: m/s, bounds of |v_ball - v_paddle| at impact


def paddle_goal(goal: PaddleGoal | Mapping[str, Any] | None = None, **fields: Any) -> PaddleGoal:
    """Validated :class:`PaddleGoal` from a goal object, a dict with (some of) the keys ``target_xy``,
    ``roll``, ``pitch``, ``v_rel``, and/or keyword overrides; missing keys take the defaults
    ``target_xy=(0, 0)``, ``roll=pitch=(-0.4, 0.4)`` rad, ``v_rel=(3, 5)`` m/s.

    Raises ``ValueError`` for an unknown key, a non-finite value, an inverted pair, an angle outside
    ``(-pi/2, pi/2)`` or a negative speed.
    """
    if isinstance(goal, PaddleGoal) and not fields:
        return goal
    values = dict(_DEFAULTS)
    if isinstance(goal, PaddleGoal):
        values.update(target_xy=goal.target_xy, roll=goal.roll, pitch=goal.pitch, v_rel=goal.v_rel)
    elif goal is not None:
        values.update(dict(goal))
    values.update({k: v for k, v in fields.items() if v is not None})
    unknown = sorted(set(values) - set(_DEFAULTS))
    if unknown:
        raise ValueError(f"paddle goal has no key(s) {unknown}; valid keys are {sorted(_DEFAULTS)}")
    target = np.asarray(values["target_xy"], dtype=np.float64).reshape(-1)
    if target.shape != (2,) or not np.all(np.isfinite(target)):
        raise ValueError(f"paddle goal: target_xy must be 2 finite numbers, got {values['target_xy']!r}")
    pairs = {}
    for key in ("roll", "pitch", "v_rel"):
        pair = np.asarray(values[key], dtype=np.float64).reshape(-1)
        if pair.shape != (2,) or not np.all(np.isfinite(pair)) or pair[0] > pair[1]:
            raise ValueError(f"paddle goal: {key} must be finite (min, max) with min <= max, got {values[key]!r}")
        pairs[key] = (float(pair[0]), float(pair[1]))
    for key in ("roll", "pitch"):
        if not (-math.pi / 2 < pairs[key][0] and pairs[key][1] < math.pi / 2):
            raise ValueError(f"paddle goal: {key} bounds must lie in (-pi/2, pi/2), got {pairs[key]}")
    if pairs["v_rel"][0] < 0.0:
        raise ValueError(f"paddle goal: v_rel bounds must be >= 0, got {pairs['v_rel']}")
    return PaddleGoal(target, pairs["roll"], pairs["pitch"], pairs["v_rel"])


class PaddleProblem:
    """Evaluation of eq. ball_paddle_opt at one pre-impact state ``x`` (6,) with the model ``dyn``."""

    def __init__(self, system: PaddleBall, dyn: NumpyDynamics, x: np.ndarray, goal: PaddleGoal) -> None:
        self.system, self.dyn, self.x, self.goal = system, dyn, x, goal
        self.lo = np.concatenate((system.control_low[:3], [goal.roll[0], goal.pitch[0]]))
        self.hi = np.concatenate((system.control_high[:3], [goal.roll[1], goal.pitch[1]]))

    def control(self, theta: np.ndarray) -> np.ndarray:
        """``u = [pv, n(roll, pitch)]`` (6,)."""
        r, p = float(theta[3]), float(theta[4])
        n = (math.cos(r) * math.sin(p), -math.sin(r), math.cos(r) * math.cos(p))
        return np.concatenate((theta[:3], n))

    def evaluate(self, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Landing residual ``r`` (2,), speed-constraint values ``c`` (2,) (``<= 0`` feasible, in (m/s)^2) and
        the post-impact velocity (3,)."""
        v_post = self.dyn.step1(self.x, self.control(theta))
        return self._residual(v_post), self._speed(theta), v_post

    def _residual(self, v_post: np.ndarray) -> np.ndarray:
        t = 2.0 * max(float(v_post[2]), 0.0) / self.system.g
        return self.x[0:2] + v_post[0:2] * t - self.goal.target_xy

    def _speed(self, theta: np.ndarray) -> np.ndarray:
        v_rel = self.x[3:6] - theta[:3]
        s2 = float(v_rel @ v_rel)
        lo, hi = self.goal.v_rel
        return np.array([lo * lo - s2, s2 - hi * hi])

    def guesses(self) -> list[np.ndarray]:
        """Start points: level paddle moving up so that |v_rel| is mid-range, then tilted variants."""
        vb = self.x[3:6].tolist()
        mid = 0.5 * sum(self.goal.v_rel)
        rest = mid * mid - vb[0] ** 2 - vb[1] ** 2
        pvz = vb[2] + math.sqrt(rest) if rest > 0.0 else 0.0
        lo, hi = self.lo.tolist(), self.hi.tolist()
        base = [min(max(c, lo[i]), hi[i]) for i, c in enumerate((0.0, 0.0, pvz, 0.0, 0.0))]
        out = np.array([base] * 9)
        for k, (fr, fp) in enumerate(_TILTS, start=1):  # roll, pitch at these fractions of their half-range
            out[k, 3] = lo[3] + (0.5 + 0.5 * fr) * (hi[3] - lo[3])
            out[k, 4] = lo[4] + (0.5 + 0.5 * fp) * (hi[4] - lo[4])
        return list(out)


class PaddleController:
    """Shared machinery of the paddle solvers (Controller protocol, horizon 1)."""

    horizon = 1

    def __init__(self, system: PaddleBall, model: DynamicsModel | None = None, member: int = 0,
                 feas_tol: float = 1e-6, tol: float = 1e-4) -> None:
        if not isinstance(system, PaddleBall):
            raise ValueError(f"the paddle controller needs a PaddleBall system, got {system.name!r}")
        self.system: System = system
        self.paddle = system
        self.member = member
        self.feas_tol = feas_tol  #: tolerance on |v_rel| bounds for success (m/s)
        self.tol = tol  #: landing error (m) below which a start is good enough (no further restarts)
        self.dyn = NumpyDynamics(system, model, member)
        self._theta: np.ndarray | None = None

    def set_model(self, model: DynamicsModel | None) -> None:
        self.dyn = NumpyDynamics(self.system, model, self.member)

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
        u = np.array([0.0, 0.0, 0.0, 0.0, 0.0, 1.0])
        if self._theta is not None:
            r, p = float(self._theta[3]), float(self._theta[4])
            n = (math.cos(r) * math.sin(p), -math.sin(r), math.cos(r) * math.cos(p))
            u = np.concatenate((self._theta[:3], n))
        u = np.clip(u, self.system.control_low, self.system.control_high)
        return MPCResult(
            u=u, plan_u=u[None].copy(), plan_x=np.full((1, 6), np.nan), cost=float("nan"),
            solve_time=time.perf_counter() - start, iterations=iters, success=False, message=why,
            constraint_violation=float("inf"), converged=False,
        )  # fmt: skip

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
        raise NotImplementedError

    def _evaluate(self, prob: PaddleProblem, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`PaddleProblem.evaluate` of the returned plan."""
        return prob.evaluate(theta)


class GaussNewtonPaddle(PaddleController):
    """The fast paddle solver: exact-derivative projected Gauss-Newton / Newton from the same starts
    (:mod:`~saml_ros.core.mpc.paddle_search`, :mod:`~saml_ros.core.mpc.paddle_row`).

    Options: ``max_iter`` (iterations of one Newton run), ``max_time`` (s, optional budget of a solve; the best
    point found by then is returned).
    """

    def __init__(self, system: PaddleBall, model: DynamicsModel | None = None, member: int = 0,
                 max_iter: int = 20, max_time: float | None = None, **kwargs: Any) -> None:
        super().__init__(system, model, member, **kwargs)
        self.max_iter, self.max_time = max_iter, max_time
        self.settings = SearchSettings(tol=self.tol, max_iter=max_iter)
        self._last: RowResult | None = None  # the end point of the last search

    def _search(self, prob: PaddleProblem, starts: list[np.ndarray]) -> tuple[np.ndarray, int, bool, str]:
        g = prob.goal
        deadline = math.inf if self.max_time is None else time.perf_counter() + self.max_time
        row = PaddleRowSolver(PaddleEval(self.dyn, prob.x, g.target_xy, self.paddle.g), prob.lo.tolist(),
                              prob.hi.tolist(), g.v_rel)
        away = (g.target_xy - prob.x[0:2]).tolist()

        def tilt(theta: list[float]) -> float:
            """how much the paddle leans towards the target: normal_xy . (target - p)"""
            return math.sin(theta[4]) * away[0] - math.sin(theta[3]) * away[1]

        best, total, msg = search(row, [s.tolist() for s in starts], tilt, self.settings, deadline)
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

    def __init__(self, system: PaddleBall, model: DynamicsModel | None = None, member: int = 0,
                 max_iter: int = 100, ftol: float = 1e-8, **kwargs: Any) -> None:
        super().__init__(system, model, member, **kwargs)
        self.max_iter, self.ftol = max_iter, ftol

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

