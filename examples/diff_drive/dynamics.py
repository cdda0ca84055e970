"""The example robot's physics (numpy, no ROS): a differential-drive base whose wheels slip on a wet patch.

State ``[x (m), y (m), yaw (rad), v (m/s), w (rad/s)]``: pose in the odom frame, measured forward speed and yaw
rate. Command ``[v_cmd (m/s), w_cmd (rad/s)]``. The wheel controller makes the wheel speeds follow the command
with a first-order lag ``TAU``; on the floor the base moves at ``traction(x, y)`` times the wheel speeds. The wet
patch in front of the dock (at x = 1.5, y = 0) cuts the traction to about half: exactly what the unicycle base
model of ``system.yaml`` (no slip) does not know, and where the learned model has to be accurate.

saml_ros never sees this file: it learns from the topics the robot node (``robot.py``) publishes.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

TAU = 0.12  # s, wheel speed lag
WET_CENTER = (1.15, 0.0)  # m
WET_RADIUS = 0.35  # m (std-dev of the Gaussian patch)
WET_LOSS_V = 0.55  # fraction of forward traction lost at the centre of the patch
WET_LOSS_W = 0.45  # fraction of yaw traction lost at the centre
DRY_TRACTION = 0.97
V_MAX, W_MAX = 0.5, 1.5  # command limits (m/s, rad/s)
ARENA = 2.5  # m, half-width: the robot stops at a wall
#: m/s: with ``slide`` on (the evaluation's "dock on a wet ramp", docs/your_robot.md "Evaluate it"), the wet patch
#: also slopes down towards -x: the base slides that way at up to this speed whatever its wheels do
RAMP_SLIDE = 0.15


def slide_speed(x: float, y: float, slide: float) -> float:
    """m/s towards -x at (x, y): ``slide`` times the wetness."""
    return slide * wetness(x, y) if slide else 0.0


def wetness(x: float, y: float) -> float:
    """0 on dry floor, 1 at the centre of the wet patch."""
    d2 = (x - WET_CENTER[0]) ** 2 + (y - WET_CENTER[1]) ** 2
    return math.exp(-d2 / (2.0 * WET_RADIUS**2))


def traction(x: float, y: float) -> tuple[float, float]:
    """(forward, yaw) traction factors at (x, y)."""
    wet = wetness(x, y)
    return DRY_TRACTION * (1.0 - WET_LOSS_V * wet), DRY_TRACTION * (1.0 - WET_LOSS_W * wet)


class DiffDrive:
    """The simulated base: :meth:`step` advances ``dt`` seconds under a held command."""

    def __init__(self, x: float = 0.0, y: float = 0.0, yaw: float = 0.0, substeps: int = 10,
                 slide: float = 0.0) -> None:
        self.pose = np.array([x, y, yaw], dtype=np.float64)
        self.wheel = np.zeros(2)  # wheel-level forward speed and yaw rate (m/s, rad/s)
        self.substeps = substeps
        self.slide = slide  # m/s, RAMP_SLIDE for the wet ramp (0: a flat floor)

    def state(self) -> np.ndarray:
        """``[x, y, yaw, v, w]`` as measured (odometry from a ground-truth tracker; ``v`` along the base's heading)."""
        kv, kw = traction(self.pose[0], self.pose[1])
        s = slide_speed(self.pose[0], self.pose[1], self.slide)
        return np.array([*self.pose, kv * self.wheel[0] - s * math.cos(self.pose[2]), kw * self.wheel[1]])

    def step(self, cmd: np.ndarray, dt: float) -> None:
        u = np.clip(np.asarray(cmd, dtype=np.float64), [-V_MAX, -W_MAX], [V_MAX, W_MAX])
        h = dt / self.substeps
        a = 1.0 - math.exp(-h / TAU)
        for _ in range(self.substeps):
            self.wheel += a * (u - self.wheel)
            kv, kw = traction(self.pose[0], self.pose[1])
            v, w = kv * self.wheel[0], kw * self.wheel[1]
            yaw = self.pose[2]
            nx = self.pose[0] + (v * math.cos(yaw + 0.5 * w * h) - slide_speed(self.pose[0], self.pose[1], self.slide)) * h
            ny = self.pose[1] + v * math.sin(yaw + 0.5 * w * h) * h
            if abs(nx) > ARENA or abs(ny) > ARENA:  # a wall: the base stops there
                self.wheel[0] = 0.0
            else:
                self.pose[0], self.pose[1] = nx, ny
            self.pose[2] = (yaw + w * h + math.pi) % (2.0 * math.pi) - math.pi


# ------------------------------------------------------------------------------------------ evaluation hooks
# (saml_ros.experiments.robot_eval: the robot's simulator, start states and, for the headroom, its true dynamics)
def make_robot(x0: np.ndarray, slide: float = 0.0) -> DiffDrive:
    """The simulator at state ``x0 = [x, y, yaw, v, w]`` (the wheels moving at the speeds ``v, w`` imply there)."""
    r = DiffDrive(float(x0[0]), float(x0[1]), float(x0[2]), slide=slide)
    kv, kw = traction(float(x0[0]), float(x0[1]))
    s = slide_speed(float(x0[0]), float(x0[1]), slide)
    r.wheel[:] = ((float(x0[3]) + s * math.cos(float(x0[2]))) / kv, float(x0[4]) / kw)
    return r


def make_robot_on_ramp(x0: np.ndarray) -> DiffDrive:
    """:func:`make_robot` with the wet patch sloping down towards -x (``RAMP_SLIDE``)."""
    return make_robot(x0, RAMP_SLIDE)


def sample_starts(n: int, rng: np.random.Generator) -> np.ndarray:
    """``n`` starts at rest, 1-2.5 m from the dock, heading anywhere, inside the arena."""
    out = np.zeros((n, 5))
    for i in range(n):
        while True:
            r, a = rng.uniform(1.0, 2.5), rng.uniform(math.pi / 2, 3 * math.pi / 2)
            x, y = 1.5 + r * math.cos(a), r * math.sin(a)
            if abs(x) < ARENA - 0.3 and abs(y) < ARENA - 0.3:
                break
        out[i, :3] = x, y, rng.uniform(-math.pi, math.pi)
    return out


def sample_approach_starts(n: int, rng: np.random.Generator) -> np.ndarray:
    """``n`` starts at rest on the dock's approach: 0.7-1.1 m in front of it (at the wet patch's edge), within 0.1 m
    of its axis, heading within 0.2 rad of it (the docking manoeuvre's last stretch, straight through the patch)."""
    out = np.zeros((n, 5))
    out[:, 0] = rng.uniform(0.4, 0.8, n)
    out[:, 1] = rng.uniform(-0.1, 0.1, n)
    out[:, 2] = rng.uniform(-0.2, 0.2, n)
    return out


def true_step(x: Any, u: Any, *, dt: float, xp: Any, substeps: int = 10, slide: float = 0.0) -> Any:
    """The true dynamics on the measured state, ``(B, 5), (B, 2) -> (B, 5)``, written once for any array namespace
    ``xp`` (numpy, torch, CasADi: saml_ros.core.dynamics.base_forms; the walls are left out): the oracle the
    evaluation plans with, differentiated exactly by CasADi. ``slide``: as :class:`DiffDrive`'s."""

    def trac(px: Any, py: Any) -> tuple[Any, Any]:
        wet = xp.exp(-((px - WET_CENTER[0]) ** 2 + (py - WET_CENTER[1]) ** 2) / (2.0 * WET_RADIUS**2))
        return DRY_TRACTION * (1.0 - WET_LOSS_V * wet), DRY_TRACTION * (1.0 - WET_LOSS_W * wet)

    def sl(px: Any, py: Any) -> Any:
        return slide * xp.exp(-((px - WET_CENTER[0]) ** 2 + (py - WET_CENTER[1]) ** 2) / (2.0 * WET_RADIUS**2))

    px, py, yaw = x[:, 0], x[:, 1], x[:, 2]
    kv, kw = trac(px, py)
    wv, ww = (x[:, 3] + sl(px, py) * xp.cos(yaw)) / kv, x[:, 4] / kw
    uv, uw = xp.clip(u[:, 0], -V_MAX, V_MAX), xp.clip(u[:, 1], -W_MAX, W_MAX)
    h = dt / substeps
    a = 1.0 - math.exp(-h / TAU)
    for _ in range(substeps):
        wv = wv + a * (uv - wv)
        ww = ww + a * (uw - ww)
        kv, kw = trac(px, py)
        v, w = kv * wv, kw * ww
        px, py, yaw = (px + (v * xp.cos(yaw + 0.5 * w * h) - sl(px, py)) * h, py + v * xp.sin(yaw + 0.5 * w * h) * h,
                       yaw + w * h)
    kv, kw = trac(px, py)
    return xp.stack([px, py, yaw, kv * wv - sl(px, py) * xp.cos(yaw), kw * ww])


def true_step_on_ramp(x: Any, u: Any, *, dt: float, xp: Any) -> Any:
    """:func:`true_step` on the wet ramp (``RAMP_SLIDE``)."""
    return true_step(x, u, dt=dt, xp=xp, slide=RAMP_SLIDE)
