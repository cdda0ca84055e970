"""MuJoCo paddle-ball world: a ball bounced by a kinematic paddle with a low-level impact controller.

ROS-free (the ``paddle_ball_sim`` node, through :mod:`.sim`, and the ball experiment wrap it); sequences of
impacts and the collection of transitions are in :mod:`.bounces`. See docs/systems.md, "MuJoCo paddle-ball
scene", for the scene, the controller and measured numbers.

Frames and units: world frame, z up, SI units (m, m/s, rad, s). The *impact plane* is z = 0: the controller
meets the ball when its centre is at z = 0, so pre-impact states look like ``PaddleBall.sample_inputs``
(``pz`` about 0).

A command ``u = [pvx, pvy, pvz, nx, ny, nz]`` (the paddle-ball control layout) is for the *next* impact: the
controller predicts the ball's ballistic flight to the impact plane, moves the paddle centre under that
point, tilts it and swings it at constant velocity ``u[:3]`` through the impact point. The real paddle normal
is ``R_y(normal_bias_y) n`` (the unobserved hand-to-paddle rotation of the paper); the learner sees the
commanded ``n``. The paddle is kinematic: its five joints (x, y, z slides, pitch about y, roll about x) are
overwritten every step with the planned position *and velocity*, so contacts see the paddle's velocity
(MuJoCo gives mocap bodies zero velocity in contacts).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Any

import mujoco
import numpy as np

from saml_ros.systems.paddle_ball.model import PaddleBall

ASSET = Path(__file__).resolve().parent / "assets" / "paddle_ball.xml"

#: impact speed (m/s) at which the contact damping is calibrated to the system's restitution
CALIBRATION_SPEED = 4.0


@dataclass(frozen=True)
class SceneOptions:
    """Physical and controller options of :class:`PaddleBallWorld` (keyword ``scene_options``).

    Ball: ``ball_radius`` (m), ``ball_mass`` (kg), ``ball_inertia_factor`` (I = f m r^2; 0.19 makes a ball that
    rolls off the paddle keep about 0.8 of its tangential relative velocity, like the paper's model: the soft
    contact's point lies inside the ball, so rigid-body theory's 0.25 gives 0.75 here),
    ``spin_decay_time`` (s; time constant of a damping on the ball's spin only, so spin from one bounce
    hardly carries into the next; ``0`` = no damping).
    Paddle: ``paddle_half_size`` (m, square), ``paddle_half_thickness`` (m), ``paddle_mass`` (kg, large: kinematic).
    Contact: ``friction`` (sliding coefficient), ``contact_stiffness`` (1/s^2, mass-normalised spring of the
    normal contact; the damping is calibrated to the restitution), ``friction_timeconst`` (s, how fast
    the soft friction removes slip), ``contact_solimp`` (MuJoCo solimp of the pair).
    Controller: ``reach`` (m, paddle centre |x|, |y| limit), ``z_limits`` (m, paddle centre height limits),
    ``max_tilt`` (rad, commanded normal tilt limit), ``swing_time`` (s, half-width of the constant-velocity
    window around the planned impact), ``min_approach_time`` (s, the earliest the controller plans an impact),
    ``recover_time`` (s, deceleration after the swing).
    Tracking error of the low-level controller (the paper's "lower-level controllers that only attempt to match
    the command"): ``velocity_noise`` (m/s, std of zero-mean Gaussian noise added to each component of the paddle
    velocity the swing realises) and ``normal_noise`` (rad, std of the two small rotations, about world x and y,
    applied to the real normal), drawn once per impact from the world's own tracking generator (seeded by
    ``seed``), so the realised paddle velocity and normal differ from the command while the learner still sees
    the command. ``0`` (default) = exact tracking.
    Failure: ``fall_margin`` (m below the impact plane), ``impact_timeout`` (s without an impact).
    Reset: ``drop_height`` (m, default ball height above the impact plane).
    """

    ball_radius: float = 0.03
    ball_mass: float = 0.05
    ball_inertia_factor: float = 0.19
    spin_decay_time: float = 0.1
    paddle_half_size: float = 0.15
    paddle_half_thickness: float = 0.02
    paddle_mass: float = 100.0
    friction: float = 0.6
    contact_stiffness: float = 6.0e4
    friction_timeconst: float = 0.01
    contact_solimp: tuple[float, float, float, float, float] = (0.99, 0.99, 0.001, 0.5, 2.0)
    reach: float = 1.5
    z_limits: tuple[float, float] = (-1.0, 0.6)
    max_tilt: float = 0.6
    swing_time: float = 0.04
    min_approach_time: float = 0.12
    recover_time: float = 0.25
    velocity_noise: float = 0.0
    normal_noise: float = 0.0
    fall_margin: float = 0.3
    impact_timeout: float = 3.0
    drop_height: float = 1.0

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            values = value if isinstance(value, tuple) else (value,)
            if not all(isinstance(v, (int, float)) and math.isfinite(v) for v in values):
                raise ValueError(f"SceneOptions: {f.name} must be finite numbers, got {value!r}")
        positive = ("ball_radius", "ball_mass", "ball_inertia_factor", "paddle_half_size", "paddle_half_thickness",
                    "paddle_mass", "contact_stiffness", "friction_timeconst", "reach", "max_tilt", "swing_time",
                    "min_approach_time", "recover_time", "fall_margin", "impact_timeout", "drop_height")
        for name in positive:
            if getattr(self, name) <= 0:
                raise ValueError(f"SceneOptions: {name} must be > 0, got {getattr(self, name)}")
        if self.spin_decay_time < 0 or self.friction < 0:
            raise ValueError("SceneOptions: spin_decay_time and friction must be >= 0")
        if self.velocity_noise < 0 or not 0 <= self.normal_noise < 0.5:
            raise ValueError("SceneOptions: velocity_noise must be >= 0 and normal_noise in [0, 0.5) rad")
        if not self.z_limits[0] < self.z_limits[1]:
            raise ValueError(f"SceneOptions: z_limits must be increasing, got {self.z_limits}")
        if self.max_tilt >= math.pi / 2:
            raise ValueError(f"SceneOptions: max_tilt must be < pi/2, got {self.max_tilt}")


@dataclass(frozen=True)
class Impact:
    """One ball-paddle impact (the interval in which ball-paddle contacts exist).

    Attributes:
        time: simulation time (s) of the first step with contact.
        pre: ``(6,)`` ball ``[p (m), v (m/s)]`` at the last step before the first contact (the state x).
        u_cmd: ``(6,)`` the command the controller realised for this impact, after validation (clipped paddle
            velocity, normalised and tilt-limited normal): the control u the learner sees.
        n_real: ``(3,)`` the real paddle normal ``R_y(normal_bias_y) n_cmd`` (with the tracking error, if any).
        post_velocity: ``(3,)`` ball velocity (m/s) at the first step after the contact separated (the target y).
        paddle_velocity: ``(3,)`` the paddle velocity (m/s) at the first contact step.
        on_plan: True when the whole contact lay inside the planned constant-velocity swing window of an
            unclipped plan, i.e. the ball saw the commanded paddle velocity and orientation throughout, and the
            ball left the paddle (False: double hits, out-of-reach plans, a ball carried on the paddle, a ball
            pushed through the paddle at relative speeds above about 13 m/s).
        contact_steps: number of physics steps with contact.
    """

    time: float
    pre: np.ndarray
    u_cmd: np.ndarray
    n_real: np.ndarray
    post_velocity: np.ndarray
    paddle_velocity: np.ndarray
    on_plan: bool
    contact_steps: int

    @property
    def u_applied(self) -> np.ndarray:
        """The control of this transition for learning: the commanded ``u_cmd`` (the real normal is hidden)."""
        return self.u_cmd


@dataclass(frozen=True)
class _Segment:
    """Cubic Hermite segment of the 5 paddle coordinates ``[x, y, z, pitch, roll]`` on ``[t0, t1]``."""

    t0: float
    t1: float
    q0: np.ndarray
    v0: np.ndarray
    q1: np.ndarray
    v1: np.ndarray

    def eval(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        T = self.t1 - self.t0
        s = min(max((t - self.t0) / T, 0.0), 1.0)
        s2, s3 = s * s, s * s * s
        q = ((2 * s3 - 3 * s2 + 1) * self.q0 + (s3 - 2 * s2 + s) * T * self.v0
             + (3 * s2 - 2 * s3) * self.q1 + (s3 - s2) * T * self.v1)
        v = ((6 * s2 - 6 * s) * (self.q0 - self.q1) / T + (3 * s2 - 4 * s + 1) * self.v0
             + (3 * s2 - 2 * s) * self.v1)
        return q, v


@dataclass
class _Plan:
    """Paddle motion for the next impact: approach, constant-velocity swing, recovery, then hold."""

    segments: list[_Segment]
    u_cmd: np.ndarray
    n_real: np.ndarray
    t_impact: float
    ball: np.ndarray
    swing: tuple[float, float]
    clipped: bool
    used: bool = field(default=False)

    def eval(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        for seg in self.segments:
            if t < seg.t1:
                return seg.eval(t)
        last = self.segments[-1]
        return last.q1.copy(), np.zeros(5)


def _quat_wxyz_from_pitch_roll(pitch: float, roll: float) -> np.ndarray:
    """Quaternion of ``R_y(pitch) R_x(roll)`` (scalar first)."""
    cp, sp = math.cos(pitch / 2), math.sin(pitch / 2)
    cr, sr = math.cos(roll / 2), math.sin(roll / 2)
    return np.array([cp * cr, cp * sr, sp * cr, -sp * sr])


def _rotate_y(v: np.ndarray, angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([c * v[0] + s * v[2], v[1], -s * v[0] + c * v[2]])


def _roll_pitch(n: np.ndarray) -> tuple[float, float]:
    """Inverse of ``normal_from_roll_pitch`` (numpy, unit ``n`` with ``nz > 0``): ``(roll, pitch)`` in rad."""
    return math.atan2(-n[1], math.hypot(n[0], n[2])), math.atan2(n[0], n[2])


class PaddleBallWorld:
    """The paddle-ball MuJoCo simulation with a low-level impact controller (see module docstring).

    Args:
        system: the :class:`PaddleBall` whose ``restitution_true``, ``normal_bias_y``, ``g`` and control bounds
            the scene realises (default ``PaddleBall()``).
        timestep: physics step (s).
        seed: seeds :attr:`rng` (used by :meth:`reset_random` when no generator is passed).
        **scene_options: fields of :class:`SceneOptions`.
    """

    def __init__(self, system: PaddleBall | None = None, timestep: float = 0.002, seed: int = 0,
                 **scene_options: Any) -> None:
        self.system = system if system is not None else PaddleBall()
        if not (math.isfinite(timestep) and 0 < timestep <= 0.01):
            raise ValueError(f"PaddleBallWorld: timestep must be in (0, 0.01] s, got {timestep}")
        unknown = set(scene_options) - {f.name for f in fields(SceneOptions)}
        if unknown:
            raise ValueError(f"PaddleBallWorld: unknown scene options {sorted(unknown)}; "
                             f"valid: {[f.name for f in fields(SceneOptions)]}")
        self.options = replace(SceneOptions(), **scene_options)
        self.rng = np.random.default_rng(seed)
        #: draws the tracking error (its own stream: the same seed gives the same errors whatever else is drawn)
        self.tracking_rng = np.random.default_rng([seed, 1])
        self._tracking = (np.zeros(3), np.zeros(2))
        self.model = self._build_model(timestep)
        self.data = mujoco.MjData(self.model)
        self._ball_geom = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_GEOM, "ball")
        self._paddle_geom = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_GEOM, "paddle")
        ball_joint = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_JOINT, "ball")
        self._bq = int(self.model.jnt_qposadr[ball_joint])
        self._bv = int(self.model.jnt_dofadr[ball_joint])
        #: ball centre to paddle centre distance along the normal at first touch (m)
        self._standoff = self.options.ball_radius + self.options.paddle_half_thickness
        self.contact_damping = self._calibrate_damping(self.system.restitution_true)
        self.model.pair_solref[0] = (-self.options.contact_stiffness, -self.contact_damping)
        #: counters: clipped commands; late commands (arrived during a contact or a swing, applied one impact later)
        self.n_clipped = 0
        self.n_late_commands = 0
        self._u = np.array([0.0, 0.0, 0.0, 0.0, 0.0, 1.0])
        self._pending: np.ndarray | None = None
        # episode state, initialised by reset()
        self._plan: _Plan
        self._fresh = True
        self._in_contact = False
        self._prev_state = np.zeros(6)
        self._open: dict[str, Any] | None = None
        self._last_impact_time = 0.0
        self._failure: str | None = None
        self.reset()

    # ------------------------------------------------------------------ scene
    def _build_model(self, timestep: float) -> mujoco.MjModel:
        o = self.options
        spec = mujoco.MjSpec.from_file(str(ASSET))
        spec.option.timestep = timestep
        spec.option.gravity = [0.0, 0.0, -self.system.g]
        ball = spec.body("ball")
        ball.mass = o.ball_mass
        inertia = o.ball_inertia_factor * o.ball_mass * o.ball_radius**2
        ball.inertia = [inertia] * 3
        spec.geom("ball").size = [o.ball_radius, 0.0, 0.0]
        spec.geom("paddle").size = [o.paddle_half_size, o.paddle_half_size, o.paddle_half_thickness]
        spec.body("paddle").mass = o.paddle_mass
        pair = spec.pairs[0]
        pair.friction = [o.friction, o.friction, 0.005, 0.0001, 0.0001]
        pair.solimp = list(o.contact_solimp)
        pair.solreffriction = [o.friction_timeconst, 1.0]
        model = spec.compile()
        if o.spin_decay_time > 0:
            ball_joint = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, "ball")
            dof = int(model.jnt_dofadr[ball_joint])
            model.dof_damping[dof + 3:dof + 6] = inertia / o.spin_decay_time
        return model

    def _calibrate_damping(self, restitution: float) -> float:
        """Contact damping (1/s) giving ``restitution`` for a vertical drop at :data:`CALIBRATION_SPEED`.

        Bisection on the mean restitution over 8 sub-step phases of the first contact (the discrete contact
        makes the restitution depend on where within a step the ball first touches).
        """
        data = mujoco.MjData(self.model)
        stiffness = self.options.contact_stiffness
        dt = self.model.opt.timestep

        def measured(damping: float) -> float:
            self.model.pair_solref[0] = (-stiffness, -damping)
            out = []
            for phase in (np.arange(8) + 0.5) / 8:
                mujoco.mj_resetData(self.model, data)
                data.qpos[2] = -self._standoff
                data.qpos[self._bq:self._bq + 3] = (0.0, 0.0, phase * CALIBRATION_SPEED * dt)
                data.qpos[self._bq + 3:self._bq + 7] = (1.0, 0.0, 0.0, 0.0)
                data.qvel[self._bv + 2] = -CALIBRATION_SPEED
                v_in, touched = CALIBRATION_SPEED, False
                for _ in range(400):
                    data.qpos[:5] = (0.0, 0.0, -self._standoff, 0.0, 0.0)
                    data.qvel[:5] = 0.0
                    mujoco.mj_step1(self.model, data)
                    if data.ncon > 0 and not touched:
                        touched, v_in = True, -float(data.qvel[self._bv + 2])
                    if touched and data.ncon == 0:
                        break
                    mujoco.mj_step2(self.model, data)
                out.append(float(data.qvel[self._bv + 2]) / v_in)
            return float(np.mean(out))

        # closed form of a linear spring-damper as the upper end of the bracket
        log_e = math.log(restitution)
        zeta = -log_e / math.sqrt(math.pi**2 + log_e**2)
        lo, hi = 0.0, 4.0 * zeta * math.sqrt(stiffness) + 1.0
        if measured(lo) <= restitution:
            return lo
        for _ in range(30):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if measured(mid) > restitution else (lo, mid)
        return 0.5 * (lo + hi)

    # ------------------------------------------------------------------ state
    @property
    def time(self) -> float:
        """Simulation time (s)."""
        return float(self.data.time)

    @property
    def timestep(self) -> float:
        """Physics step (s)."""
        return float(self.model.opt.timestep)

    @property
    def ball_state(self) -> np.ndarray:
        """``(6,)`` ball ``[p (m), v (m/s)]`` in the world frame."""
        d, bq, bv = self.data, self._bq, self._bv
        return np.concatenate((d.qpos[bq:bq + 3], d.qvel[bv:bv + 3]))

    @property
    def paddle_pose(self) -> tuple[np.ndarray, np.ndarray]:
        """Paddle centre position ``(3,)`` (m) and orientation quaternion ``(4,)`` ``[w, x, y, z]`` (body->world)."""
        q = self.data.qpos
        return q[0:3].copy(), _quat_wxyz_from_pitch_roll(float(q[3]), float(q[4]))

    @property
    def paddle_velocity(self) -> np.ndarray:
        """``(3,)`` paddle linear velocity (m/s)."""
        return self.data.qvel[0:3].copy()

    @property
    def paddle_normal(self) -> np.ndarray:
        """``(3,)`` the real paddle normal (unit, world)."""
        pitch, roll = float(self.data.qpos[3]), float(self.data.qpos[4])
        return np.array([math.cos(roll) * math.sin(pitch), -math.sin(roll), math.cos(roll) * math.cos(pitch)])

    @property
    def command(self) -> np.ndarray:
        """``(6,)`` the validated command the controller uses for the next impact."""
        return (self._pending if self._pending is not None else self._u).copy()

    @property
    def failure_reason(self) -> str | None:
        """Why the ball was lost (``"fell"``, ``"out_of_reach"``, ``"timeout"``), or None."""
        return self._failure

    def failed(self) -> bool:
        """The paper's failure: the ball is not kept bouncing. Sticky until :meth:`reset`.

        Fell more than ``fall_margin`` below the impact plane, came down to the impact plane outside the
        paddle's reach, or no impact for ``impact_timeout`` seconds.
        """
        return self._failure is not None

    # ------------------------------------------------------------------ commands
    def validate_command(self, u: np.ndarray) -> tuple[np.ndarray, bool]:
        """``u`` (6,) -> (validated command, clipped?). ``ValueError`` for a wrong shape, non-finite values or a
        normal whose norm is not within [0.5, 2] (or that points straight down).

        The paddle velocity is clipped to the system's control bounds; the normal is normalised and its tilt
        from vertical limited to ``max_tilt``.
        """
        u = np.asarray(u, dtype=np.float64)
        if u.shape != (6,):
            raise ValueError(f"paddle-ball command must have shape (6,), got {u.shape}")
        if not np.all(np.isfinite(u)):
            raise ValueError(f"paddle-ball command must be finite, got {u}")
        lo, hi = self.system.control_low[:3], self.system.control_high[:3]
        v = np.clip(u[:3], lo, hi)
        clipped = bool(np.any(v != u[:3]))
        norm = float(np.linalg.norm(u[3:]))
        if not 0.5 <= norm <= 2.0:
            raise ValueError(f"paddle normal must have norm ~1, got {norm:.3g}")
        n = u[3:] / norm
        horizontal = math.hypot(n[0], n[1])
        tilt = math.atan2(horizontal, n[2])
        if tilt > self.options.max_tilt:
            if horizontal < 1e-12:
                raise ValueError("paddle normal points straight down")
            t = self.options.max_tilt
            n = np.array([n[0] / horizontal * math.sin(t), n[1] / horizontal * math.sin(t), math.cos(t)])
            clipped = True
        return np.concatenate((v, n)), clipped

    def set_command(self, u: np.ndarray) -> None:
        """Command ``u = [paddle velocity (3, m/s), paddle normal (3, unit)]`` for the next impact.

        Validated by :meth:`validate_command` (clips are counted in :attr:`n_clipped`). The command stays in
        force for later impacts until replaced. The paddle is replanned at once for the same predicted impact
        (:meth:`next_impact`); right after :meth:`reset` it is placed again as ``reset`` does. A command that
        arrives during a contact or once the planned swing has begun applies to the impact after it (counted
        in :attr:`n_late_commands`).
        """
        cmd, clipped = self.validate_command(u)
        self.n_clipped += int(clipped)
        if self._fresh:
            self._u = cmd
            self._place_paddle()
        elif self._in_contact or self.time >= self._plan.swing[0]:
            self._pending = cmd
            self.n_late_commands += 1
        else:
            self._u = cmd
            remaining = self._plan.t_impact - self.time
            self._plan = self._make_plan(self.time, t_min=min(self.options.min_approach_time, remaining))

    def next_impact(self) -> tuple[float, np.ndarray]:
        """The impact the paddle is planned for: ``(seconds from now, predicted ball state (6,) just before it)``.

        This is the state ``x`` a high-level controller chooses its command for.
        """
        return self._plan.t_impact - self.time, self._plan.ball.copy()

    # ------------------------------------------------------------------ prediction and planning
    def predict_impact(self, state: np.ndarray | None = None, t_min: float | None = None) -> tuple[float, np.ndarray]:
        """Predicted next impact of the ball in free flight: ``(seconds from now, ball state (6,) at impact)``.

        The impact is where the ball's centre descends through the impact plane z = 0, but not earlier than
        ``t_min`` (default ``min_approach_time``) from now; a ball that would cross earlier, or never, is met
        ``t_min`` from now wherever it is. The prediction matches MuJoCo's semi-implicit Euler exactly
        (``p(t) = p + v t - g/2 (t^2 + dt t)``).
        """
        s = self.ball_state if state is None else np.asarray(state, dtype=np.float64)
        t_min = self.options.min_approach_time if t_min is None else t_min
        g, dt = self.system.g, self.timestep
        # z(t) = pz + (vz - g dt / 2) t - g t^2 / 2 = 0, later root
        b = s[5] - 0.5 * g * dt
        disc = b * b + 2.0 * g * s[2]
        tau = (b + math.sqrt(disc)) / g if disc >= 0 else -math.inf
        tau = max(tau, t_min)
        p = s[:3] + s[3:] * tau
        p[2] -= 0.5 * g * (tau * tau + dt * tau)
        v = s[3:].copy()
        v[2] -= g * tau
        return tau, np.concatenate((p, v))

    def _impact_target(self, u: np.ndarray, t_min: float | None = None
                       ) -> tuple[float, np.ndarray, np.ndarray, np.ndarray, bool]:
        """Where the paddle must be for the predicted impact with command ``u``: (seconds from now, ball state
        (6,) there, paddle coordinates ``[x, y, z, pitch, roll]`` (5,), real normal (3,), clipped to the reach?)."""
        o = self.options
        tau, ball = self.predict_impact(t_min=t_min)
        n_real = _rotate_y(self._realised_normal(u[3:]), self.system.normal_bias_y)
        roll, pitch = _roll_pitch(n_real)
        centre = ball[:3] - n_real * self._standoff
        low = np.array([-o.reach, -o.reach, o.z_limits[0]])
        high = np.array([o.reach, o.reach, o.z_limits[1]])
        reachable = np.clip(centre, low, high)
        clipped = bool(np.any(reachable != centre))
        return tau, ball, np.concatenate((reachable, (pitch, roll))), n_real, clipped

    def _make_plan(self, t_now: float, start: tuple[np.ndarray, np.ndarray] | None = None,
                   t_min: float | None = None) -> _Plan:
        """Plan the paddle for the predicted impact with the current command, from ``start`` (paddle
        coordinates and their rates, default: the current plan at ``t_now``)."""
        o = self.options
        u = self._u
        q_now, v_now = start if start is not None else self._plan.eval(t_now)
        tau, ball, q_i, n_real, clipped = self._impact_target(u, t_min)
        t_i = t_now + tau
        before = min(o.swing_time, 0.25 * tau)  # constant-velocity lead-in; the follow-through is swing_time
        vel = np.concatenate((u[:3] + self._tracking[0], (0.0, 0.0)))
        q_s, q_e = q_i - vel * before, q_i + vel * o.swing_time
        q_rest = q_e + vel * (0.5 * o.recover_time)
        t_s, t_e = t_i - before, t_i + o.swing_time
        segments = [_Segment(t_now, t_s, q_now, v_now, q_s, vel)] if t_s > t_now else []
        segments += [
            _Segment(t_s, t_e, q_s, vel, q_e, vel),
            _Segment(t_e, t_e + o.recover_time, q_e, vel, q_rest, np.zeros(5)),
        ]
        return _Plan(segments, u.copy(), n_real, t_i, ball, (t_s, t_e), clipped)

    def _draw_tracking(self) -> None:
        """The tracking error of the next impact: paddle velocity offset (3,) m/s, normal rotation (x, y) rad."""
        o = self.options
        dv = self.tracking_rng.normal(0.0, o.velocity_noise, 3) if o.velocity_noise > 0 else np.zeros(3)
        dn = self.tracking_rng.normal(0.0, o.normal_noise, 2) if o.normal_noise > 0 else np.zeros(2)
        self._tracking = (dv, dn)

    def _realised_normal(self, n: np.ndarray) -> np.ndarray:
        """The commanded normal ``n`` (3,) rotated by this impact's tracking error (about world x, then y)."""
        ax, ay = self._tracking[1]
        if ax == 0.0 and ay == 0.0:
            return n
        c, s = math.cos(ax), math.sin(ax)
        n = np.array([n[0], c * n[1] - s * n[2], s * n[1] + c * n[2]])
        return _rotate_y(n, ay)

    def _apply_plan(self) -> None:
        q, v = self._plan.eval(self.time)
        self.data.qpos[:5] = q
        self.data.qvel[:5] = v

    # ------------------------------------------------------------------ episode
    def reset(self, ball_pos: np.ndarray | None = None, ball_vel: np.ndarray | None = None) -> None:
        """Restart at time 0 with the ball at ``ball_pos`` (m, default ``drop_height`` above the impact plane at
        the origin) moving with ``ball_vel`` (m/s, default 0), no spin, and the paddle at rest under the
        ball's predicted impact point with the command's orientation. The current command is kept.
        """
        pos = np.array([0.0, 0.0, self.options.drop_height]) if ball_pos is None else np.asarray(ball_pos, float)
        vel = np.zeros(3) if ball_vel is None else np.asarray(ball_vel, float)
        if pos.shape != (3,) or vel.shape != (3,) or not (np.all(np.isfinite(pos)) and np.all(np.isfinite(vel))):
            raise ValueError("reset: ball_pos and ball_vel must be finite (3,) vectors")
        mujoco.mj_resetData(self.model, self.data)
        d = self.data
        d.qpos[self._bq:self._bq + 3] = pos
        d.qpos[self._bq + 3:self._bq + 7] = (1.0, 0.0, 0.0, 0.0)
        d.qvel[self._bv:self._bv + 3] = vel
        if self._pending is not None:
            self._u, self._pending = self._pending, None
        self._draw_tracking()
        self._place_paddle()
        self._fresh = True
        self._in_contact = False
        self._prev_state = self.ball_state
        self._open = None
        self._last_impact_time = 0.0
        self._failure = None

    def _place_paddle(self) -> None:
        """After a reset: put the paddle where it will meet the ball, already tilted: at rest, or already on its
        swing line when the impact is less than ``swing_time`` away (a reset needs no approach time)."""
        tau, _, q_i = self._impact_target(self._u, t_min=0.0)[:3]
        vel = np.concatenate((self._u[:3] + self._tracking[0], (0.0, 0.0)))
        start = (q_i - vel * tau, vel) if tau <= self.options.swing_time else (q_i, np.zeros(5))
        self._plan = self._make_plan(self.time, start=start, t_min=0.0)
        self._apply_plan()
        mujoco.mj_forward(self.model, self.data)

    def reseed_tracking(self, seed: int | Sequence[int]) -> None:
        """Restart the tracking-error stream from ``seed``: the k-th impact after this call gets the same
        realised-command error whatever ran before (pairs trials across models)."""
        self.tracking_rng = np.random.default_rng(seed)

    def reset_random(self, rng: np.random.Generator | None = None) -> None:
        """Reset to a random bounce: the ball at the apex of a flight whose impact state is drawn like
        ``PaddleBall.sample_inputs``: px, py ~ U[-1, 1] m and, with probability ``1 - slow_fraction``,
        vx, vy ~ U[-1, 1], vz ~ U[-6, -2] m/s, else a slow ball vx, vy ~ U[-0.1, 0.1], vz ~ U[-0.5, -0.05] m/s.
        """
        rng = self.rng if rng is None else rng
        p = rng.uniform(-1.0, 1.0, 2)
        if rng.random() < self.system.slow_fraction:
            vh, vz = rng.uniform(-0.1, 0.1, 2), rng.uniform(-0.5, -0.05)
        else:
            vh, vz = rng.uniform(-1.0, 1.0, 2), rng.uniform(-6.0, -2.0)
        t_fall = -vz / self.system.g
        apex = np.array([*(p - vh * t_fall), vz * vz / (2 * self.system.g)])
        self.reset(apex, np.array([*vh, 0.0]))

    # ------------------------------------------------------------------ stepping
    def _ball_paddle_contact(self) -> bool:
        d = self.data
        for i in range(d.ncon):
            c = d.contact[i]
            if {int(c.geom1), int(c.geom2)} == {self._ball_geom, self._paddle_geom}:
                return True
        return False

    def step(self, n: int = 1) -> list[Impact]:
        """Advance ``n`` physics steps; return the impacts that ended (contact separated) in them."""
        impacts: list[Impact] = []
        m, d = self.model, self.data
        self._fresh = False
        for _ in range(n):
            mujoco.mj_step1(m, d)
            t = float(d.time)
            state = self.ball_state
            contact = d.ncon > 0 and self._ball_paddle_contact()
            if contact and not self._in_contact:
                plan = self._plan
                self._open = {
                    "time": t, "pre": self._prev_state, "u_cmd": plan.u_cmd.copy(), "n_real": plan.n_real.copy(),
                    "paddle_velocity": d.qvel[0:3].copy(), "steps": 0, "swing_end": plan.swing[1],
                    "on_plan": (not plan.clipped and not plan.used
                                and plan.swing[0] - 0.5 * self.timestep <= t <= plan.swing[1]),
                }
                plan.used = True
            if contact and self._open is not None:
                self._open["steps"] += 1
            if not contact and self._in_contact and self._open is not None:
                op = self._open
                # a ball still approaching the paddle at separation went through it (relative speed >~ 13 m/s)
                separating = float(np.dot(state[3:] - d.qvel[0:3], op["n_real"])) > 0.0
                on_plan = bool(op["on_plan"]) and t <= op["swing_end"] and separating
                impacts.append(Impact(op["time"], op["pre"], op["u_cmd"], op["n_real"], state[3:].copy(),
                                      op["paddle_velocity"], on_plan, int(op["steps"])))
                self._last_impact_time = t
                if self._pending is not None:
                    self._u, self._pending = self._pending, None
                self._draw_tracking()
                if self._failure is None:
                    self._plan = self._make_plan(t)
                self._open = None
            self._in_contact = contact
            self._prev_state = state
            if self._failure is None:
                self._failure = self._check_failure(state, t)
            mujoco.mj_step2(m, d)
            self._apply_plan()
        return impacts

    def _check_failure(self, state: np.ndarray, t: float) -> str | None:
        o = self.options
        if state[2] < -o.fall_margin:
            return "fell"
        if state[2] < 0.0 and max(abs(state[0]), abs(state[1])) > o.reach + o.paddle_half_size:
            return "out_of_reach"
        if t - self._last_impact_time > o.impact_timeout:
            return "timeout"
        return None

    def run_until_impact(self, max_time: float = 3.0) -> Impact | None:
        """Step until an impact ends (returned), the ball is lost (:meth:`failed`) or ``max_time`` s passed (None)."""
        n_max = int(math.ceil(max_time / self.timestep))
        for _ in range(n_max):
            impacts = self.step(1)
            if impacts:
                return impacts[0]
            if self.failed():
                return None
        return None


