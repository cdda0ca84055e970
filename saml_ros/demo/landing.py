"""The demo's task, start states and metrics (ROS-free): a precise landing on a pad inside the ground effect.

**Task** (:class:`LandingTask`): land the quadrotor on a pad at ``(0, 0, 0.2)`` m, which is also the lowest
height the MPC allows (``min_height``): the best reachable point. Inside the ground effect (below 1.5 m) the
motors give up to 50 % more thrust than f_hat predicts, so an MPC planning with f_hat alone settles above the
pad (or bounces), one planning with the true dynamics (the oracle) lands on it. The MPC also keeps the tilt
``|qx_t|, |qy_t| <= tilt_max`` on every predicted step (``task.tilt_max``, docs/mpc.md): without it plans from
far or fast starts bank steeply and some episodes ended metres off target, whatever the model.

**Starts**: ``standard`` = the simulator's own sampler (x, y ~ U[-2, 2] m, z ~ U[1, 3] m, level, at rest; what
the live loop trains on) and ``aggressive`` = large offsets and high descent rates, outside the training data
(x, y ~ U[-4, 4] m, z ~ U[0.5, 4] m, vz ~ U[-3, 0] m/s).

**Metrics** (:func:`episode_metrics`, per episode of ``steps`` control steps on the TRUE system with the
simulator's ground contact), all "lower is better":

* ``landing_error``: distance from the pad at the end (m) -- the task metric;
* ``height_error``: mean |pz - pad z| over the last second (m): the height error above the reachable floor;
* ``horizontal_error``: mean horizontal distance from the pad over the last second (m);
* ``settling_time``: time after which the vehicle stays within ``settle_tol`` of the pad (s; an episode that
  never settles counts as its length plus one step);
* ``overshoot``: the largest height above the pad after the vehicle first came within 5 cm of the pad's height
  (m; the bounce of a base-model landing);
* ``cost``: the MPC's objective on the flown trajectory, ``sum_t ||p_t - pad||`` (m, steps 1..steps);
* ``failed_solves``: fraction of solves whose plan violated a constraint some control could have kept (the
  demo's evaluation passes ``MPCResult.success or unavoidable`` as ``success``); ``solve_ms``: mean solve time.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from saml_ros.systems.quadrotor.model import Quadrotor

#: metric name -> (label, unit); the order of the tables
METRICS: dict[str, tuple[str, str]] = {
    "landing_error": ("landing error |p_T - pad|", "m"),
    "height_error": ("height error above the floor, last 1 s", "m"),
    "horizontal_error": ("horizontal error, last 1 s", "m"),
    "settling_time": ("settling time (within 3 cm)", "s"),
    "overshoot": ("overshoot above the pad", "m"),
    "cost": ("MPC cost sum_t |p_t - pad|", "m"),
    "failed_solves": ("solves violating an avoidable constraint", "1"),
    "solve_ms": ("solve time (mean)", "ms"),
}
#: the task metric: the gain, its CI and the captured headroom are reported on it
TASK_METRIC = "landing_error"
#: an episode ending farther than this from the pad (m) "flew away"
FAR = 1.0
#: the demo's worlds (``demo --world``): ``Quadrotor`` constructor overrides, handed to the simulator as its
#: ``system.*`` parameters and to the evaluation (base, oracle, learned arms) as :attr:`LandingTask.world`. ``paper``:
#: the ground effect alone (the paper's); ``wind``: plus a wind field of 3 m/s^2, wavelength 8 m, above the pad's
#: shelter (1.5 m; docs/systems.md), so a model must share its capacity between the pad and the approach (the
#: capacity sweep's world, :attr:`saml_ros.experiments.capacity.CapacitySettings.world`)
WORLDS: dict[str, dict[str, float]] = {"paper": {}, "wind": {"wind": 3.0, "wind_length": 8.0}}


@dataclass(frozen=True)
class LandingTask:
    """The demo task (see the module docstring); lengths in m, times in control steps of ``dt`` = 0.1 s."""

    pad: tuple[float, float, float] = (0.0, 0.0, 0.2)
    min_height: float = 0.2
    tilt_max: float = 0.2
    horizon: int = 10
    steps: int = 50
    settle_tol: float = 0.03
    landing_height: float = 0.1  #: the simulator's ground contact (centre of mass), m
    #: the world's physical parameters (``Quadrotor`` constructor overrides, e.g. the wind; ``(name, value)``
    #: pairs): the simulator, the oracle and the evaluation's plant are all built from :meth:`system`
    world: tuple[tuple[str, float], ...] = ()

    def system(self) -> Quadrotor:
        """The quadrotor of this task's world (``get_system("quadrotor", **world)``)."""
        from saml_ros.core.systems import get_system

        system = get_system("quadrotor", **dict(self.world))
        assert isinstance(system, Quadrotor)
        return system

    @property
    def goal(self) -> np.ndarray:
        return np.asarray(self.pad, dtype=np.float64)

    @property
    def reachable(self) -> np.ndarray:
        """The best point the height bound allows: the pad, raised to ``min_height`` if it is below."""
        g = self.goal.copy()
        g[2] = max(g[2], self.min_height)
        return g

    def mpc_options(self) -> dict[str, Any]:
        """``make_controller`` options of this task."""
        return {"horizon": self.horizon, "min_height": self.min_height, "tilt_max": self.tilt_max}

    @classmethod
    def from_mpc_params(cls, mpc: dict[str, Any], steps: int, landing_height: float,
                        world: dict[str, float] | None = None) -> LandingTask:
        """The task a bringup configuration's ``mpc`` section (ROS parameters) sets up, in the world ``world``
        (the simulator's ``system.*`` parameters, :func:`world_params`)."""
        pad = tuple(float(v) for v in mpc.get("goal.position", (0.0, 0.0, 0.2)))
        return cls(pad=pad, min_height=float(mpc.get("task.min_height", 0.2)),  # type: ignore[arg-type]
                   tilt_max=float(mpc.get("task.tilt_max", math.inf)), horizon=int(mpc.get("horizon", 10)),
                   steps=steps, landing_height=landing_height, world=tuple(sorted((world or {}).items())))


def world_params(sim: dict[str, Any]) -> dict[str, float]:
    """The world's physical parameters a bringup configuration's ``sim`` section gives the simulator (its
    ``system.<name>`` ROS parameters): ``{name: value}``."""
    return {k[len("system."):]: v for k, v in sim.items() if k.startswith("system.")}


# ------------------------------------------------------------------------------------------ starts
def standard_starts(system: Quadrotor, n: int, seed: int) -> np.ndarray:
    """``(n, 13)`` starts from the simulator's sampler (x, y ~ U[-2, 2] m, z ~ U[1, 3] m, level, at rest)."""
    from saml_ros.systems.quadrotor.world import quadrotor_start

    rng = np.random.default_rng(seed)
    return np.stack([quadrotor_start(system, rng) for _ in range(n)]) if n else np.zeros((0, 13))


def aggressive_starts(system: Quadrotor, n: int, seed: int) -> np.ndarray:
    """``(n, 13)`` starts far and fast: x, y ~ U[-4, 4] m, z ~ U[0.5, 4] m, vz ~ U[-3, 0] m/s, level."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        x = system.hover_state((rng.uniform(-4, 4), rng.uniform(-4, 4), rng.uniform(0.5, 4.0)))
        x[5] = rng.uniform(-3.0, 0.0)
        out.append(x)
    return np.stack(out) if out else np.zeros((0, 13))


def plant(system: Quadrotor, landing_height: float) -> Callable[[np.ndarray, np.ndarray], np.ndarray]:
    """The simulated true system: ``true_step`` then the simulator's ground contact; ``(13,), (4,) -> (13,)``."""
    from saml_ros.core.worlds.sim_core import FastStep
    from saml_ros.systems.quadrotor.world import quadrotor_model

    step = FastStep(system)
    constrain = quadrotor_model(system, landing_height).constrain
    assert constrain is not None

    def f(x: np.ndarray, u: np.ndarray) -> np.ndarray:
        return constrain(step(x, u))[0]

    return f


# ------------------------------------------------------------------------------------------ metrics
def episode_metrics(xs: np.ndarray, success: np.ndarray, solve_times: np.ndarray, task: LandingTask,
                    dt: float = 0.1) -> dict[str, float]:
    """The metrics of one episode (see the module docstring): ``xs`` ``(steps + 1, 13)`` true states from the
    start, ``success`` ``(steps,)`` per solve, ``solve_times`` ``(steps,)`` s."""
    p = np.asarray(xs, dtype=np.float64)[1:, 0:3]
    pad = task.reachable
    dist = np.linalg.norm(p - pad, axis=1)
    last = max(1, int(round(1.0 / dt)))
    inside = dist <= task.settle_tol
    if inside.all():
        settle = dt
    elif not inside[-1]:
        settle = (len(dist) + 1) * dt
    else:
        settle = (int(np.flatnonzero(~inside)[-1]) + 2) * dt
    z = p[:, 2]
    near = np.flatnonzero(np.abs(z - pad[2]) <= 0.05)
    overshoot = float(max(0.0, z[near[0]:].max() - pad[2])) if near.size else math.nan
    return {
        "landing_error": float(dist[-1]),
        "height_error": float(np.mean(np.abs(z[-last:] - pad[2]))),
        "horizontal_error": float(np.mean(np.linalg.norm(p[-last:, :2] - pad[:2], axis=1))),
        "settling_time": float(settle),
        "overshoot": overshoot,
        "cost": float(np.linalg.norm(p - task.goal, axis=1).sum()),
        "failed_solves": float(np.mean(~np.asarray(success, dtype=bool))),
        "solve_ms": float(1e3 * np.mean(solve_times)),
        "max_distance": float(dist.max()),
    }
