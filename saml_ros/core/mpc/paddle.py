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

Fast solver: Gauss-Newton on ``1/2 ||r||^2`` with exact Jacobians (model and landing point), the speed
bounds linearised as elastic rows (as ``|v_rel|^2``), a Levenberg-Marquardt term and a backtracking line
search on ``1/2 ||r||^2 + penalty * violation``; restarts from a few tilted guesses when a start ends short
of the target. Reference: scipy SLSQP on the exact non-smooth objective with finite differences.
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
from saml_ros.core.mpc.qp import solve_box_qp, solve_qp
from saml_ros.core.mpc.types import MPCResult
from saml_ros.core.systems.base import System
from saml_ros.core.systems.paddle_ball import PaddleBall

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

    def residual_jac(self, thetas: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Landing residuals ``(B, 2)`` and their exact Jacobians ``d r / d theta`` ``(B, 2, 5)`` at ``(B, 5)``."""
        bsz = thetas.shape[0]
        r, p = thetas[:, 3], thetas[:, 4]
        cr, sr, cp, sp = np.cos(r), np.sin(r), np.cos(p), np.sin(p)
        u = np.concatenate((thetas[:, :3], np.stack((cr * sp, -sr, cr * cp), 1)), 1)
        v_post, _, du = self.dyn.step_jac(np.broadcast_to(self.x, (bsz, 6)), u)
        du_dth = np.zeros((bsz, 6, 5))
        du_dth[:, 0:3, 0:3] = np.eye(3)
        du_dth[:, 3:6, 3] = np.stack((-sr * sp, -cr, -sr * cp), 1)
        du_dth[:, 3:6, 4] = np.stack((cr * cp, np.zeros(bsz), -cr * sp), 1)
        g = self.system.g
        up = v_post[:, 2] > 0.0
        t = 2.0 * np.maximum(v_post[:, 2], 0.0) / g
        dland = np.zeros((bsz, 2, 3))
        dland[:, 0, 0] = dland[:, 1, 1] = t
        dland[:, :, 2] = np.where(up[:, None], 2.0 * v_post[:, 0:2] / g, 0.0)
        res = self.x[0:2] + v_post[:, 0:2] * t[:, None] - self.goal.target_xy
        return res, dland @ du @ du_dth

    def jacobians(self, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``r``, ``dr/dtheta`` (2, 5), ``c``, ``dc/dtheta`` (2, 5)."""
        res, jac = self.residual_jac(theta[None])
        v_rel = self.x[3:6] - theta[:3]
        dc = np.zeros((2, 5))
        dc[0, 0:3] = 2.0 * v_rel
        dc[1, 0:3] = -2.0 * v_rel
        return res[0], jac[0], self._speed(theta), dc

    def residual_curvature(self, theta: np.ndarray, r: np.ndarray, jac: np.ndarray, h: float = 1e-6) -> np.ndarray:
        """``sum_i r_i d^2 r_i / d theta^2`` ``(5, 5)``: forward differences of the exact Jacobian (one batched
        evaluation), the term Gauss-Newton drops; it matters when the target cannot be reached (r != 0)."""
        _, jacs = self.residual_jac(theta[None] + h * np.eye(5))
        s = np.einsum("i,bij->bj", r, jacs - jac[None]) / h
        return 0.5 * (s + s.T)

    def project(self, theta: np.ndarray) -> np.ndarray:
        """Nearly the closest point satisfying every constraint: the relative velocity scaled radially into
        ``[v_min, v_max]``, then everything clipped to the box (which can only undo the first step at a corner
        of the paddle-velocity box)."""
        theta = np.clip(theta, self.lo, self.hi)
        v_rel = self.x[3:6] - theta[:3]
        speed = math.sqrt(float(v_rel @ v_rel))
        lo, hi = self.goal.v_rel
        if speed > hi or 0.0 < speed < lo:
            theta = theta.copy()
            theta[:3] = self.x[3:6] - v_rel * (min(max(speed, lo), hi) / speed)
            theta = np.clip(theta, self.lo, self.hi)
        return theta

    def guesses(self) -> list[np.ndarray]:
        """Start points: level paddle moving up so that |v_rel| is mid-range, then tilted variants."""
        vb = self.x[3:6]
        mid = 0.5 * sum(self.goal.v_rel)
        rest = mid * mid - vb[0] ** 2 - vb[1] ** 2
        pvz = vb[2] + math.sqrt(rest) if rest > 0.0 else 0.0
        base = np.clip(np.array([0.0, 0.0, pvz, 0.0, 0.0]), self.lo, self.hi)
        out = [base]
        for fr, fp in ((0.0, 0.5), (0.0, -0.5), (0.5, 0.0), (-0.5, 0.0), (0.5, 0.5), (-0.5, -0.5), (0.5, -0.5),
                       (-0.5, 0.5)):
            g = base.copy()
            g[3] = self.lo[3] + (0.5 + 0.5 * fr) * (self.hi[3] - self.lo[3])
            g[4] = self.lo[4] + (0.5 + 0.5 * fp) * (self.hi[4] - self.lo[4])
            out.append(g)
        return out


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
        best: tuple[tuple[bool, float], np.ndarray, bool, str] | None = None
        total = 0
        try:
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
        except Exception as exc:  # numerical breakdown: the safe default
            return self._fallback(start, f"solver failure: {type(exc).__name__}: {exc}")
        assert best is not None
        _, theta, conv, msg = best
        theta = np.clip(theta, prob.lo, prob.hi)
        u = np.clip(prob.control(theta), self.system.control_low, self.system.control_high)
        r, c, v_post = prob.evaluate(theta)
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

    def _optimize(self, prob: PaddleProblem, theta0: np.ndarray) -> tuple[np.ndarray, int, bool, str]:
        raise NotImplementedError


class GaussNewtonPaddle(PaddleController):
    """The fast paddle solver (module docstring). Options: ``max_iter`` per start, ``penalty``."""

    def __init__(self, system: PaddleBall, model: DynamicsModel | None = None, member: int = 0,
                 max_iter: int = 30, penalty: float = 10.0, rtol: float = 1e-9, **kwargs: Any) -> None:
        super().__init__(system, model, member, **kwargs)
        self.max_iter, self.penalty, self.rtol = max_iter, penalty, rtol
        self.gn_iters = 4  # plain Gauss-Newton iterations before the residual curvature is added

    def _merit(self, r: np.ndarray, c: np.ndarray) -> float:
        m = 0.5 * float(r @ r) + self.penalty * float(np.maximum(c, 0.0).sum())
        return m if math.isfinite(m) else math.inf

    def _optimize(self, prob: PaddleProblem, theta0: np.ndarray) -> tuple[np.ndarray, int, bool, str]:
        theta = prob.project(theta0)
        r, jr, c, jc = prob.jacobians(theta)
        merit = self._merit(r, c)
        rho = 1e-3
        eye = np.eye(5)
        lam = np.zeros(2)  # multipliers of the speed rows (last QP)
        it = 0
        for it in range(1, self.max_iter + 1):  # noqa: B007
            if float(np.linalg.norm(r)) <= 0.1 * self.tol and c.max() <= 0.0:
                return theta, it, True, "converged"
            hess, grad = jr.T @ jr, jr.T @ r
            if it > self.gn_iters and float(r @ r) > (10.0 * self.tol) ** 2:
                # still far from the target after a few Gauss-Newton steps (probably unreachable): full Newton (Gauss-Newton + residual curvature), made positive definite
                evals, evecs = np.linalg.eigh(hess + prob.residual_curvature(theta, r, jr))
                hess = (evecs * np.maximum(evals, 1e-9 * max(float(evals.max()), 1e-12))) @ evecs.T
            # curvature of the active upper speed bound (|v_rel|^2 is convex): lam * 2 I on the paddle velocity
            hess[:3, :3] += 2.0 * max(float(lam[1] - lam[0]), 0.0) * np.eye(3)
            scale = float(np.trace(hess)) / 5.0 + 1e-9
            viol0 = float(np.maximum(c, 0.0).sum())
            accepted = False
            while not accepted:
                h_lm = hess + rho * scale * eye
                lo, hi = prob.lo - theta, prob.hi - theta
                box = solve_box_qp(h_lm, grad, lo, hi)
                if box.converged and float((c + jc @ box.d).max()) <= 0.0:
                    d, lam = box.d, np.zeros(2)
                else:
                    qp = solve_qp(h_lm, grad, lo, hi, jc, -c, self.penalty)
                    d, lam = qp.d, qp.mult
                pred = -(grad @ d + 0.5 * d @ hess @ d) + self.penalty * (
                    viol0 - float(np.maximum(c + jc @ d, 0.0).sum()))
                if pred <= self.rtol * (1.0 + merit):
                    return theta, it, True, "converged"
                for alpha in (1.0, 0.5, 0.25, 0.125):
                    # stepping along the curved speed bound: put the trial point back on it
                    cand = prob.project(theta + alpha * d)
                    rn, cn, _ = prob.evaluate(cand)
                    mn = self._merit(rn, cn)
                    if mn <= merit - 1e-4 * alpha * pred:
                        accepted = True
                        break
                if accepted:
                    rho = max(rho / 4.0, 1e-9) if alpha == 1.0 else rho * 2.0
                else:
                    rho = max(rho, 1e-3) * 10.0
                    if rho > 1e6:
                        return theta, it, False, "line search failed"
            theta = cand
            r, jr, c, jc = prob.jacobians(theta)
            merit = self._merit(r, c)
        return theta, it, False, "max_iter"


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
