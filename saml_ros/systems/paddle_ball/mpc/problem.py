"""The paper's one-shot ball-bouncing problem (eq. ball_paddle_opt) at one pre-impact state: its goal parameters
(:class:`PaddleGoal`, :func:`paddle_goal`), decision box, numpy evaluation and start points (:class:`PaddleProblem`).

Decision variables ``theta = [pvx, pvy, pvz (m/s), roll, pitch (rad)]``; the commanded normal is
``normal_from_roll_pitch(roll, pitch)`` (unit by construction), so ``u = [pv, n]`` (:func:`control_from_theta`).

    min_theta  || landing(p, v_post(x, u)) - target_xy ||_2
    s.t.       pv within the system's paddle-velocity bounds,
               roll_min <= roll <= roll_max,  pitch_min <= pitch <= pitch_max,
               v_min <= |v_ball - v_paddle| <= v_max        (relative speed at impact)

``v_post`` is the model in use (``f_hat + phi``, ``phi`` for a full model, or ``f_hat``), ``landing`` the
ballistic landing point at the impact height (:func:`~saml_ros.systems.paddle_ball.model.landing_point`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from saml_ros.core.mpc.dynamics_np import NumpyDynamics
from saml_ros.systems.paddle_ball.model import PaddleBall
from saml_ros.systems.paddle_ball.mpc.feasible_set import FeasibleSet
from saml_ros.systems.paddle_ball.mpc.landing_error import LandingError

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

    @staticmethod
    def control(theta: np.ndarray) -> np.ndarray:
        """:func:`control_from_theta`."""
        return control_from_theta(theta)

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

    def landing_error(self) -> LandingError:
        """The landing error and its exact derivatives in plain floats (for the fast solver)."""
        return LandingError(self.dyn, self.x, self.goal.target_xy, self.system.g)

    def feasible_set(self) -> FeasibleSet:
        """The box ``[lo, hi]`` and the speed bounds around the ball's velocity, in plain floats (for the fast
        solver)."""
        return FeasibleSet(self.lo.tolist(), self.hi.tolist(), self.x[3:6].tolist(), self.goal.v_rel)

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


def control_from_theta(theta: np.ndarray) -> np.ndarray:
    """``u = [pv, n(roll, pitch)]`` (6,) from ``theta = [pv (3) m/s, roll, pitch (rad)]`` (5,)."""
    r, p = float(theta[3]), float(theta[4])
    n = (math.cos(r) * math.sin(p), -math.sin(r), math.cos(r) * math.cos(p))
    return np.concatenate((theta[:3], n))


def loop_bounce(system: PaddleBall, x: np.ndarray, v_post: np.ndarray,
                goal: PaddleGoal | Mapping[str, Any] | None) -> tuple[np.ndarray, np.ndarray, float, bool]:
    """One step of :func:`saml_ros.core.mpc.loop.closed_loop` for the paddle ball (its entry's ``loop_event``):
    the ball leaves pre-impact state ``x`` (6,) with ``v_post`` (3,) and flies ballistically back to its impact
    height. Returns the landing point (2,) m, the next pre-impact state (6,) there, the stage cost
    ``||landing - target_xy||_2`` (m) and whether the ball was dropped (it did not leave the paddle upwards)."""
    vz = float(v_post[2])
    flight = 2.0 * max(vz, 0.0) / system.g
    land = x[0:2] + v_post[0:2] * flight
    x_next = np.array([land[0], land[1], x[2], v_post[0], v_post[1], -max(vz, 0.0)])
    return land, x_next, float(np.linalg.norm(land - paddle_goal(goal).target_xy)), float(v_post[2]) <= 0.0
