"""The paddle-ball simulator core (ROS-free): the MuJoCo world as impact events for the ``paddle_ball_sim`` node.

One protocol *step* is one impact. After every impact (and at an episode start) the simulator predicts the
ball's next impact (:meth:`PaddleBallWorld.predict_impact`: ballistic flight to the impact plane) and
publishes that predicted pre-impact state on ``state``, stamped with the predicted impact time. The MPC
answers it on ``cmd`` (same stamp). When the impact has happened the simulator publishes, with the same
stamp, ``applied_cmd`` (the command the paddle realised) and ``post_impact`` (the ball velocity after the
impact) — only if the impact went as planned (``Impact.on_plan``) and happened within
``impact_time_tolerance`` of the predicted time, so the learner's triple (x, u, y) is always consistent;
other impacts are counted (``off_plan``, ``off_prediction``). ``flight`` carries the ball during flight for
viewers, at ``flight_rate_hz`` of simulated time.

* lockstep: the world is paused after publishing a predicted state until its ``cmd`` arrives (or
  ``lockstep_timeout``), then simulated to the end of the impact in one go.
* realtime: every 1 / ``rate_hz`` wall seconds the world advances 1 / ``rate_hz`` simulated seconds; commands
  are applied when they arrive (a command closer than ``min_approach_time`` to an impact applies to the one
  after it: the world counts it as late).

A lost ball (fell, out of reach, no impact for ``impact_timeout``) starts a new episode (counted
``failures/<reason>``); so do ``episode_steps`` impacts and ``~/reset``. Safe default: the system's
``safe_control()``, level paddle at rest ``u = [0, 0, 0, 0, 0, 1]``. See docs/simulators.md.
:func:`paddle_ball_simulator` builds the core from the simulator node's parameters (it imports MuJoCo).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from saml_ros.core.dynamics.system import System
from saml_ros.core.worlds.sim_core import (
    APPLIED,
    CLOCK,
    FLIGHT,
    TARGET,
    CommandRejected,
    Output,
    SimConfig,
    SimCore,
    check_initial_state,
    seconds_to_ns,
)

#: simulated time (ns) skipped at an episode restart, so stamps stay strictly increasing and visibly jump
RESTART_GAP_NS = 100_000_000


class PaddleBallSim(SimCore):
    """Impact-by-impact simulator core around a :class:`~saml_ros.systems.paddle_ball.world.PaddleBallWorld`.

    Args:
        world: the MuJoCo world (its system is the simulated :class:`PaddleBall`).
        config: shared options; ``initial_state`` is the ball ``[px, py, pz, vx, vy, vz]`` at every episode
            start (empty: :meth:`PaddleBallWorld.reset_random`), ``episode_steps`` counts impacts.
        publish_clock: emit ``/clock`` with every predicted state and flight sample (and realtime tick).
        flight_rate_hz: ``flight`` samples per simulated second (0 = none).
        tick_seconds: simulated (= wall) seconds per realtime tick.
        impact_time_tolerance: s between the predicted and the actual impact beyond which an impact is not
            published for learning.
    """

    def __init__(self, world: Any, config: SimConfig, *, publish_clock: bool = True, flight_rate_hz: float = 30.0,
                 tick_seconds: float = 0.01, impact_time_tolerance: float = 0.005) -> None:
        super().__init__(world.system, config, world.system.safe_control(), publish_clock=publish_clock)
        self.world = world
        self.flight_period_ns = seconds_to_ns(1.0 / flight_rate_hz) if flight_rate_hz > 0 else 0
        self.tick_steps = max(1, int(round(tick_seconds / world.timestep)))
        self.tolerance = impact_time_tolerance
        self.initial_state = check_initial_state(config.initial_state, 6, "initial_state (ball [p, v])")
        self.base_ns = self.t0_ns  # stamp of world time 0 in the current episode
        self.next_flight_ns = 0
        self.last_stamp = -1
        #: the published prediction the next impact is checked against: (x, stamp ns, world time s)
        self.prediction: tuple[np.ndarray, int, float] | None = None

    # -- time ---------------------------------------------------------------------------------------------
    def sim_now_ns(self) -> int:
        return self.base_ns + seconds_to_ns(self.world.time)

    # -- commands -----------------------------------------------------------------------------------------
    def validate(self, u: Any) -> np.ndarray | None:
        """Generic bounds check, then the world's own (normal norm, tilt limit), which may clip further."""
        try:
            cmd, clipped = self.validator.check(u)
            out, clipped_world = self.world.validate_command(cmd)
        except CommandRejected as exc:
            self.reject(exc.reason, str(exc))
            return None
        except ValueError as exc:  # the world's checks: normal norm not ~1 or pointing down
            self.reject("bounds", str(exc))
            return None
        self.counters["cmd_clipped"] += int(clipped or clipped_world)
        return np.asarray(out, dtype=np.float64)

    def on_cmd(self, u: Any, stamp_ns: int, now_ns: int) -> list[Output]:
        held = self.holder.u
        out = super().on_cmd(u, stamp_ns, now_ns)
        if not self.config.lockstep and self.holder.u is not held and self.holder.u is not None:
            self._set_command(self.holder.u)
        return out

    def _set_command(self, u: np.ndarray) -> None:
        try:
            self.world.set_command(u)
        except ValueError as exc:  # validated already; keep the world's command
            self.reject("bounds", str(exc))

    # -- episodes -----------------------------------------------------------------------------------------
    def _first_episode(self, now_ns: int) -> list[Output]:
        self.base_ns = self.t0_ns
        self._set_command(self.holder.safe_default)  # until a command arrives (the world keeps its last one)
        self._reset_world()
        return self._predict(now_ns)

    def _reset_world(self) -> None:
        if self.initial_state is not None:
            self.world.reset(self.initial_state[:3], self.initial_state[3:])
        else:
            self.world.reset_random(self.rng)
        self.counters["episodes"] += 1
        self.episode_step = 0
        self.next_flight_ns = self.sim_now_ns()

    def _restart(self, now_ns: int) -> list[Output]:
        """New episode; its stamps continue after everything published so far (plus a visible gap)."""
        self.pending_reset = False
        self.prediction = None
        base = max(self.sim_now_ns(), self.last_stamp) + RESTART_GAP_NS
        self._reset_world()
        self.base_ns = base
        self.next_flight_ns = base
        return self._predict(now_ns)

    def _predict(self, now_ns: int) -> list[Output]:
        """Publish the predicted next impact as the state to answer."""
        tau, x = self.world.predict_impact()
        now = self.sim_now_ns()
        stamp = max(now + seconds_to_ns(tau), self.last_stamp + 1)
        self.last_stamp = stamp
        self.prediction = (x, stamp, self.world.time + tau)
        return self._emit_state(x, stamp, now_ns, clock_ns=now)

    # -- stepping -----------------------------------------------------------------------------------------
    def _step(self, u: np.ndarray, now_ns: int) -> list[Output]:
        """Lockstep: apply ``u`` for the awaited impact and simulate until that impact has ended."""
        self._set_command(u)
        out: list[Output] = []
        while not self.done:
            impact, restarted = self._physics_step(now_ns, out)
            if impact or restarted:
                break
        return out

    def tick(self, now_ns: int) -> list[Output]:
        """Realtime: advance the world by one tick of simulated time."""
        if self.done or self.config.lockstep or not self.started:
            return []
        if self.pending_reset:
            self.counters["resets"] += 1
            return self._restart(now_ns)
        out: list[Output] = []
        for _ in range(self.tick_steps):
            self._physics_step(now_ns, out)
            if self.done:
                break
        if self.publish_clock and not self.done:
            out.append((CLOCK, None, self.sim_now_ns()))
        return out

    def _physics_step(self, now_ns: int, out: list[Output]) -> tuple[bool, bool]:
        """One physics step; appends outputs; returns ``(an impact ended, the episode restarted)``."""
        impacts = self.world.step(1)
        now = self.sim_now_ns()
        if self.flight_period_ns and now >= self.next_flight_ns:
            if self.publish_clock and self.config.lockstep:
                out.append((CLOCK, None, now))
            out.append((FLIGHT, self.world.ball_state, now))
            self.next_flight_ns = now + self.flight_period_ns
        for impact in impacts:
            out.extend(self._on_impact(impact))
        if self.world.failed():
            self.counters[f"failures/{self.world.failure_reason}"] += 1
            out.extend(self._restart(now_ns))
            return bool(impacts), True
        if impacts:
            if not self.config.lockstep:
                if self._episode_complete():
                    self.counters["episodes_completed"] += 1
                    out.extend(self._restart(now_ns))
                    return True, True
                self._refresh_command(now_ns)
            out.extend(self._predict(now_ns))
        return bool(impacts), False

    def _refresh_command(self, now_ns: int) -> None:
        """Realtime: after an impact, fall back to the safe default once the held command timed out."""
        u, fresh = self.holder.current(now_ns)
        if not fresh:
            self.counters["cmd_timeouts"] += 1
            self._set_command(u)

    def _on_impact(self, impact: Any) -> list[Output]:
        self.counters["impacts"] += 1
        self.episode_step += 1
        prediction, self.prediction = self.prediction, None
        if prediction is None:
            self.counters["off_prediction"] += 1
            return []
        _, stamp, t_pred = prediction
        if not impact.on_plan:
            self.counters["off_plan"] += 1
            return []
        if abs(impact.time - t_pred) > self.tolerance:
            self.counters["off_prediction"] += 1
            return []
        self.counters["steps"] += 1
        return [(APPLIED, np.asarray(impact.u_cmd, dtype=np.float64), stamp),
                (TARGET, np.asarray(impact.post_velocity, dtype=np.float64), stamp)]

    def diagnostics(self) -> dict[str, Any]:
        values = super().diagnostics()
        values["world_late_commands"] = self.world.n_late_commands
        return values


def paddle_ball_simulator(system: System, config: SimConfig, params: Mapping[str, Any]) -> PaddleBallSim:
    """The paddle-ball simulator core from the ``paddle_ball_sim`` node's parameter values ``params``
    (``timestep``, ``publish_clock``, ``flight_rate_hz``, ``rate_hz``, ``impact_time_tolerance``); imports MuJoCo.
    ``ValueError`` naming a bad parameter."""
    from saml_ros.systems.paddle_ball.model import PaddleBall
    from saml_ros.systems.paddle_ball.world import PaddleBallWorld

    if not isinstance(system, PaddleBall):
        raise ValueError(f"the paddle-ball simulator needs a PaddleBall system, got {system.name!r}")
    if not params["flight_rate_hz"] >= 0:
        raise ValueError(f"parameter 'flight_rate_hz' must be >= 0, got {params['flight_rate_hz']}")
    if not params["impact_time_tolerance"] > 0:
        raise ValueError(f"parameter 'impact_time_tolerance' must be > 0, got {params['impact_time_tolerance']}")
    world = PaddleBallWorld(system, timestep=params["timestep"], seed=max(config.seed, 0))
    return PaddleBallSim(world, config, publish_clock=params["publish_clock"],
                         flight_rate_hz=params["flight_rate_hz"], tick_seconds=1.0 / params["rate_hz"],
                         impact_time_tolerance=params["impact_time_tolerance"])
