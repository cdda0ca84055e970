"""What the MPC node does, without ROS: answer states with commands on the newest model (:class:`MPCService`).

The node decodes messages and publishes; everything in between is here and unit-testable:

* a :class:`~saml_ros.core.mpc.follower.ModelWatcher` follows the learner's checkpoints (with the
  ``gate.*`` hook, :func:`~saml_ros.core.mpc.follower.checkpoint_gate`); the model it loaded is swapped in
  right before the next solve;
* :meth:`MPCService.receive` takes a decoded state: in lockstep it is answered at once; in realtime it is kept
  until :meth:`MPCService.tick` (an older unanswered one is skipped and counted);
* the watcher's ``vet`` hook refuses a checkpoint whose model is broken or poisoned
  (:mod:`~saml_ros.core.mpc.acceptance`: non-finite weights, predictions outside the plausible range or further
  from the base model than its training data showed, on its probe set and on the recent states answered here);
* a control step resets the warm start after a stamp jump (reset, new episode, restarted simulator), solves,
  clips to the control bounds, sends the command (the node's ``send`` publishes ``cmd``) and returns the
  ``mpc/status`` values; a step (swap + solve + send) longer than the deadline is counted as a miss;
* the failure path: a state outside the system's plausible range (:mod:`~saml_ros.core.data.plausibility`; counted
  ``rejected/bounds``, never solved from), a solver that raises, a non-finite result (cost, plan or control: the
  controller fell back), a plan through predicted states outside the plausible range (the model predicts nonsense
  there, though the solver may call it a success) and, with ``safe_on_infeasible``, a plan that violates a
  constraint some command could have kept (not one the current state fixes: ``MPCResult.unavoidable``, counted
  ``solves_unavoidable`` and sent, as the safe command cannot avoid it either) are answered with the
  system's safe command (:meth:`~saml_ros.core.dynamics.system.System.safe_control`), counted
  ``safe_commands/<reason>`` (:data:`~msg_schemas.telemetry.SAFE_COMMAND_REASONS`) and flagged ``safe = 1`` on
  ``mpc/status``; a finite plan that violates a constraint is otherwise sent and counted ``solves_failed``;
* counters (``solves``, ``solves_failed``, ``solves_unavoidable``, ``solver_errors``, ``safe_commands``, ``deadline_misses``, ``swaps``,
  ``warm_start_resets``, ``skipped_states``, ``rejected/<reason>``) and :meth:`MPCService.diagnostic_values`;
* with any ``guard.*`` remedy on (``guard.rollback`` is by default), the controller is a
  :class:`~saml_ros.core.mpc.guard.GuardedController`: each control step first shows it the live transition that
  just happened (the state answered one period ``dt`` earlier, within a quarter period, the command sent for it,
  this state: a state of another stream interleaved on the topic, such as a second robot's half a period off, is
  never taken for the next state; nothing across a stamp jump; each chain of states a period apart continues its
  stream, a new chain starts the stream of its stamp's phase, in quarter periods, and the monitor keeps a window
  per stream), or, for a system whose target is not the next state
  (the paddle ball), :meth:`MPCService.receive_target` shows it the target stamped like a state it answered; a
  roll back changes the model in use (``rollbacks``, logged); its counters go on ``mpc/status`` and
  ``/diagnostics`` (``guard_*``, ``monitor_error_*``);
* the watcher knows the model in use (:meth:`~saml_ros.core.mpc.follower.ModelWatcher.set_in_use`): a checkpoint
  holding it again is a no-op (``checkpoints_reannounced``), and it is re-checked on the states flown as a new
  checkpoint is; one that fails is not used any more (``models_retired``, logged): the previous model (with the
  guard) or f_hat takes over before the next solve.
"""

from __future__ import annotations

import math
import threading
import time
from collections import Counter, OrderedDict, deque
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from msg_schemas.telemetry import SAFE_COMMAND_REASONS
from saml_ros.core.data.plausibility import Plausibility
from saml_ros.core.model.io import LoadedModel
from saml_ros.core.mpc.acceptance import AcceptanceConfig, Probe, acceptance_hook
from saml_ros.core.mpc.config import MPCConfig
from saml_ros.core.mpc.contract import Controller, MPCResult
from saml_ros.core.mpc.factory import make_controller
from saml_ros.core.mpc.follower import REFUSAL_REASONS, Logger, ModelWatcher, ReadyModel, Retired, checkpoint_gate
from saml_ros.core.mpc.generic.goals import GoalRefused, GoalTracker
from saml_ros.core.mpc.generic.section import MPCTask
from saml_ros.core.mpc.guard import GuardedController, make_guarded_controller
from saml_ros.core.mpc.shooting.native import NOT_SOLVED
from saml_ros.core.systems.registry import get_entry

#: recent (state, command) pairs kept as the acceptance check's probe rows
RECENT_PROBES = 256
#: loaded models kept by version (the model in use and those the guard may roll back to)
KEPT_MODELS = 4
#: answered (state, command) pairs kept by stamp for the live monitor (the newest; a few periods)
SENT_KEPT = 16
#: how far (fraction of dt) a state's stamp may be from one period after an answered one to be its next state
NEXT_STATE_TOLERANCE = 0.25

#: one answer: the stamp of the state it answered (ns) and the ``mpc/status`` values
Answer = tuple[int, dict[str, float]]


class MPCService:
    """The MPC node's logic for configuration ``config``; ``send(u, stamp_ns)`` delivers each command (the node
    publishes it on ``cmd``); logs through ``logger`` (info / warning)."""

    def __init__(self, config: MPCConfig, send: Callable[[np.ndarray, int], None], logger: Logger) -> None:
        self.config = config
        self.send = send
        self.logger = logger
        self.system = get_entry(config.system).make_system()
        self.guarded: GuardedController | None = None
        if config.guard.enabled:
            self.guarded = make_guarded_controller(self.system, config.solver, config.guard, member=config.member,
                                                   **config.controller_options())
            self.controller: Controller = self.guarded
        else:
            self.controller = make_controller(self.system, None, solver=config.solver, member=config.member,
                                              **config.controller_options())
        # stamp (ns) -> (state, command, stream) of the newest steps answered with a solved command (the live
        # monitor's; kept across stamp jumps: two streams interleaved on the topic jump back and forth between their
        # stamps). A stream is a chain of states a period apart (a robot among several on the topic).
        self._sent: OrderedDict[int, tuple[np.ndarray, np.ndarray, int]] = OrderedDict()
        self._target_is_state = self.system.target.names == self.system.state.names
        self._paths: dict[int, str] = {}  # checkpoint version -> path (the guard may roll back to an older one)
        self._models: OrderedDict[int, LoadedModel] = OrderedDict()  # the newest loaded ones, by version
        self.u_low = np.asarray(self.system.control_low, dtype=np.float64)
        self.u_high = np.asarray(self.system.control_high, dtype=np.float64)
        self.u_safe = np.clip(self.system.safe_control(), self.u_low, self.u_high)
        self.bounds = Plausibility.for_system(self.system, config.plausible_bounds)
        self._recent: deque[tuple[np.ndarray, np.ndarray]] = deque(maxlen=RECENT_PROBES)
        self._recent_lock = threading.Lock()
        self.deadline_s = config.deadline_s(self.system.dt)
        self.model_version = 0
        self.model_path = ""
        self.counters: Counter[str] = Counter()
        self.last_stamp: int | None = None
        self.pending: tuple[np.ndarray, int, float] | None = None  # realtime: newest unanswered state
        self.step_ms_max_swap = 0.0
        self._last_warn: dict[str, float] = {}
        #: the goal each solve plans for (``Controller.solve``'s argument): the ``goal.*`` parameters', until
        #: :meth:`set_goal` replaces it (a goal topic)
        self.goal: Any = config.goal
        #: a robot's goal / reference from its topics (its ``mpc:`` task), else None
        self.tracker: GoalTracker | None = None
        task = getattr(self.controller, "task", None)
        if isinstance(task, MPCTask):
            self.tracker = GoalTracker(task, self.system.dt, {f.name: f.unit for f in self.system.state.fields})
            self.tracker.set_goal(config.goal)
            self.goal = self.tracker
        self.last_arrival: float | None = None  # perf_counter of the newest state's arrival (the stale watchdog)
        self._stale_sent = 0.0  # perf_counter of the watchdog's last safe command
        run_dir = Path(config.run_dir) if config.run_dir else None
        vet = acceptance_hook(self.bounds, self.recent_probe, AcceptanceConfig(config.accept_residual_factor))
        self.watcher = ModelWatcher(self.system, run_dir, poll_period=config.poll_period, logger=logger,
                                    accept=checkpoint_gate(config.gate.max_constraint, config.gate.min_updates),
                                    vet=vet)

    def start(self) -> None:
        """Load the newest valid checkpoint of ``run_dir`` if there is one (before the first solve), then start
        following checkpoints on the background thread."""
        if self.config.run_dir:
            ready = self.watcher.poll_once(source="initial")
            if ready is not None:
                self.watcher.take()
                self.swap(ready)
        self.watcher.start()
        if self.model_version == 0:
            self.logger.info("no checkpoint yet: running on the base model f_hat")

    def stop(self, timeout: float = 0.5) -> None:
        """Stop the watcher's background thread, waiting at most ``timeout`` s for it: it may be loading a
        checkpoint (the first load imports torch, seconds on a loaded machine), which only reads files, and it is a
        daemon thread, so a node that shuts down does not wait for it (launch's grace period is 5 s)."""
        self.watcher.stop(timeout)

    # ------------------------------------------------------------------------------------------ input
    def notify(self, path: str, version: int, schema_hash: str) -> None:
        """A ``learner/checkpoint`` announcement."""
        self.watcher.notify(path, version, schema_hash)

    def reject(self, reason: str, text: str) -> None:
        """Count (``rejected/<reason>``) and log (throttled) a message that could not be used."""
        self.counters[f"rejected/{reason}"] += 1
        self.warn_throttled(f"rejected/{reason}", f"dropped a message ({reason}): {text}")

    def receive(self, x: np.ndarray, stamp: int, t_arrival: float, now_ns: int | None = None) -> Answer | None:
        """A decoded state (``t_arrival``: ``time.perf_counter()`` at its arrival; ``now_ns``: the node's clock, for
        ``state_timeout``): the answer in lockstep, ``None`` in realtime (answered by the next :meth:`tick`) or for
        a duplicate stamp (rejected)."""
        if self.last_stamp is not None and stamp == self.last_stamp:
            self.reject("duplicate", f"state stamped {stamp} ns was already answered")
            return None
        self.last_arrival = t_arrival
        if self.config.mode == "lockstep":
            return self.control_step(x, stamp, t_arrival, now_ns)
        if self.pending is not None:
            self.counters["skipped_states"] += 1
        self.pending = (x, stamp, t_arrival)
        return None

    def tick(self, now_ns: int | None = None) -> Answer | None:
        """Realtime timer: answer the newest state received since the last tick, if any (``now_ns``: the node's
        clock, for ``state_timeout``); without one, the stale-state watchdog (:meth:`watchdog`)."""
        if self.pending is None:
            return self.watchdog(time.perf_counter(), now_ns)
        (x, stamp, _), self.pending = self.pending, None
        return self.control_step(x, stamp, time.perf_counter(), now_ns)

    def watchdog(self, t_now: float, now_ns: int | None = None) -> Answer | None:
        """With ``state_timeout`` on: when no state has arrived for that long (``t_now``: ``time.perf_counter()``),
        send the safe command (counted ``safe_commands/stale``; at most once per ``state_timeout``) and return its
        status values; else None. The robot is never left on an old command because its state stopped."""
        timeout = self.config.state_timeout
        if timeout <= 0 or self.last_arrival is None or t_now - self.last_arrival <= timeout \
                or t_now - self._stale_sent < timeout:
            return None
        self._stale_sent = t_now
        age = t_now - self.last_arrival
        u, values = self._safe("stale", f"no state for {age:.3g} s (state_timeout {timeout:g} s)")
        stamp = int(now_ns) if now_ns is not None else (self.last_stamp or 0)
        self.send(u, stamp)
        self._sent.clear()  # the robot got the safe command: no solved command's transition to score
        values |= {"model_version": float(self.model_version), "solves": float(self.counters["solves"]),
                   "safe_commands": float(self.counters["safe_commands"]),
                   "deadline_misses": float(self.counters["deadline_misses"])}
        return stamp, values

    def set_goal(self, goal: Any) -> None:
        """Plan for ``goal`` from the next solve on (a robot's: checked here, ``GoalRefused``; others: already
        checked by the caller)."""
        if self.tracker is not None:
            self.tracker.set_goal(goal)
        else:
            self.goal = goal

    def goal_message(self, msg: Any, topic: str = "") -> bool:
        """A message of the robot's goal topic: True when it became the goal; a refused one (NaN, outside the goal
        bounds, malformed) is counted ``rejected/goal`` and logged, and the last goal is kept."""
        assert self.tracker is not None
        try:
            goal = self.tracker.goal_message(msg, topic)
        except GoalRefused as exc:
            self.reject("goal", f"goal refused, keeping {self.tracker.goal.tolist()}: {exc}")
            return False
        self.counters["goals"] += 1
        self.logger.info(f"new goal {dict(zip(self.tracker.fields, np.round(goal, 4).tolist(), strict=True))}")
        return True

    def reference_message(self, msg: Any, now_ns: int, topic: str = "") -> bool:
        """A message of the robot's reference topic (``nav_msgs/Path``): True when it is tracked; a refused one is
        counted ``rejected/reference`` (the current goal or reference kept)."""
        assert self.tracker is not None
        try:
            n = self.tracker.reference_message(msg, now_ns, topic)
        except GoalRefused as exc:
            self.reject("reference", f"reference refused: {exc}")
            return False
        self.counters["references"] += 1
        self.logger.info(f"tracking a reference of {n} pose(s)" if n else "reference cleared")
        return True

    # ------------------------------------------------------------------------------------------ control
    def control_step(self, x: np.ndarray, stamp: int, t_start: float, now_ns: int | None = None) -> Answer:
        """Swap in a ready model, solve for state ``x`` (stamp ns), send the clipped command, return the status
        values (``t_start``: ``time.perf_counter()`` when the step's clock started; ``now_ns``: the node's clock,
        a state older than ``state_timeout`` by it gets the safe command)."""
        if self.last_stamp is not None:
            dt_ns = stamp - self.last_stamp
            # a reset, a new episode or a restarted simulator: the warm start is meaningless
            if dt_ns < 0 or (self.system.dt > 0 and dt_ns > 1.5e9 * self.system.dt):
                self.controller.reset()
                self.counters["warm_start_resets"] += 1
        self.last_stamp = stamp
        if self.guarded is not None and self._target_is_state:
            previous = self._previous_step(stamp)
            if previous is not None:
                self._observe(*previous[:2], x, previous[2])
            stream = previous[2] if previous is not None else self._phase(stamp)
        else:
            stream = 0
        retired = self.watcher.take_retired()
        if retired is not None:
            self._retire(retired)
        swap_ms = 0.0
        ready = self.watcher.take()
        if ready is not None:
            t0 = time.perf_counter()
            self.swap(ready)
            swap_ms = 1e3 * (time.perf_counter() - t0)
        timeout = self.config.state_timeout
        age = None if now_ns is None or timeout <= 0 else (now_ns - stamp) * 1e-9
        if age is not None and age > timeout:
            u, values = self._safe("stale", f"state stamped {stamp * 1e-9:.3f} s is {age:.3g} s old "
                                            f"(state_timeout {timeout:g} s)")
        else:
            u, values = self._answer(x, stamp, now_ns)
        u = np.clip(u, self.u_low, self.u_high)
        self.send(u, stamp)
        # the live monitor scores transitions from solved commands only (a safe command says nothing of the model)
        if not values["safe"] and self.guarded is not None:
            self._sent[stamp] = (np.array(x, dtype=np.float64), u, stream)
            while len(self._sent) > SENT_KEPT:
                self._sent.popitem(last=False)
        if not values["safe"]:
            with self._recent_lock:
                self._recent.append((np.array(x, dtype=np.float64), u))
        step_ms = 1e3 * (time.perf_counter() - t_start)
        self.counters["solves"] += 1
        if step_ms > 1e3 * self.deadline_s:
            self.counters["deadline_misses"] += 1
        if swap_ms > 0.0:
            self.step_ms_max_swap = max(self.step_ms_max_swap, step_ms)
        stats = self.watcher.stats()
        values |= {
            "model_version": float(self.model_version),
            "deadline_misses": float(self.counters["deadline_misses"]),
            "step_ms": step_ms,
            "swap_ms": swap_ms,
            "swaps": float(self.counters["swaps"]),
            "checkpoints_refused": float(stats["refused"]),
            "checkpoints_gated": float(stats["gated"]),
            "solves": float(self.counters["solves"]),
            "safe_commands": float(self.counters["safe_commands"]),
        }
        if self.guarded is not None:
            values |= self.guarded.values()
            values["model_source"] = 1.0 if self.guarded.last_source == "learned" else 0.0
        return stamp, values

    def _phase(self, stamp: int) -> int:
        """The stream of a state that continues no chain: its stamp's phase in the period, in quarters (a robot
        whose clock is half a period off another's starts its own stream)."""
        dt_ns = int(round(self.system.dt * 1e9))
        return int(round(4 * (stamp % dt_ns) / dt_ns)) % 4 if dt_ns > 0 else 0

    def _previous_step(self, stamp: int) -> tuple[np.ndarray, np.ndarray, int] | None:
        """The (state, command, stream) answered one period before ``stamp`` (within
        :data:`NEXT_STATE_TOLERANCE` of the period), or None (a stamp jump, a safe command; a state of another
        stream in between is skipped)."""
        dt_ns = self.system.dt * 1e9
        if dt_ns <= 0:
            return None
        for t in reversed(self._sent):  # not in stamp order: interleaved streams drift apart in time
            if abs(stamp - t - dt_ns) <= NEXT_STATE_TOLERANCE * dt_ns:
                return self._sent[t]
        return None

    def receive_target(self, y: np.ndarray, stamp: int) -> None:
        """A decoded target (the paddle ball's post-impact velocity) stamped like the state whose answer it
        followed: the live monitor scores the models on that transition (ignored without ``guard.rollback``, for a
        system whose target is the next state, or when no solved command answered that stamp)."""
        if self.guarded is None or self._target_is_state:
            return
        sent = self._sent.pop(stamp, None)
        if sent is not None:
            self._observe(sent[0], sent[1], np.asarray(y, dtype=np.float64))

    def _observe(self, x: np.ndarray, u: np.ndarray, x_next: np.ndarray, stream: int = 0) -> None:
        """Show the guard the live transition ``(x, u) -> x_next``; on a roll back switch the model in use."""
        assert self.guarded is not None
        old = self.model_version
        try:
            rolled = self.guarded.observe(x, u, x_next, stream)
        except Exception as exc:  # noqa: BLE001 - the monitor must never stop the control loop
            self.counters["monitor_errors"] += 1
            self.warn_throttled("monitor", f"live monitor raised {type(exc).__name__}: {exc}")
            return
        if rolled:
            self._rolled_back(old, self.guarded.monitor.describe_verdict())

    def _rolled_back(self, old: int, why: str) -> None:
        """The guard rolled the model version ``old`` back (``why``, in words): follow it to the model it now uses."""
        assert self.guarded is not None
        self.counters["rollbacks"] += 1
        self.model_version = self.guarded.tag
        self.model_path = self._paths.get(self.model_version, "")
        self.watcher.set_in_use(self._models.get(self.model_version), self.model_version)
        self.logger.warning(f"rolled back from model version {old} to {self.model_version or 'the base model f_hat'}: "
                            f"{why}; version {old} is not used again")

    def _retire(self, retired: Retired) -> None:
        """The model in use failed the watcher's re-check on the states flown: plan without it from now on (the
        previous model with the guard, else f_hat)."""
        if retired.version != self.model_version:
            return  # swapped out meanwhile
        old = self.model_version
        if self.guarded is not None:
            self.model_version = self.guarded.retire()
        else:
            self.controller.set_model(None)
            self.model_version = 0
        self.model_path = self._paths.get(self.model_version, "") if self.model_version else ""
        self.watcher.set_in_use(self._models.get(self.model_version), self.model_version)
        self.counters["models_retired"] += 1
        self.logger.warning(f"model version {old} retired ({retired.reason} on the states flown); planning with "
                            f"{f'version {self.model_version}' if self.model_version else 'the base model f_hat'}")

    def recent_probe(self) -> Probe | None:
        """The recent states answered with a solved (not safe) command, and those commands: the acceptance
        check's probe rows ``(x (R, n_x), u (R, n_u))``, or ``None`` before the first one."""
        with self._recent_lock:
            rows = list(self._recent)
        if not rows:
            return None
        return np.stack([r[0] for r in rows]), np.stack([r[1] for r in rows])

    def _answer(self, x: np.ndarray, stamp: int, now_ns: int | None = None) -> tuple[np.ndarray, dict[str, float]]:
        """The command for state ``x`` and its status values: the solved one, or the safe command (see the module
        docstring's failure path)."""
        why = self.bounds.outside("state", x) if np.shape(x) == (self.system.state.size,) else None
        if why is not None:
            self.reject("bounds", f"state at t={stamp * 1e-9:.3f} s outside the plausible range: {why}")
            return self._safe("bounds", f"implausible state ({why})")
        try:
            goal = self.goal(x, stamp, self.controller.horizon, now_ns) if callable(self.goal) else self.goal
            task_rollbacks = self.guarded.counters["task_rollbacks"] if self.guarded is not None else 0
            res = self.controller.solve(x, goal)
            if self.guarded is not None and self.guarded.counters["task_rollbacks"] > task_rollbacks:
                self._rolled_back(self.model_version, self.guarded.task_check.describe_verdict())
        except Exception as exc:  # noqa: BLE001 - never leave the simulator without an answer
            self.counters["solver_errors"] += 1
            return self._safe("solver_error", f"solver raised {type(exc).__name__}: {exc}")
        u = np.asarray(res.u, dtype=np.float64)
        values = {"solve_time_ms": 1e3 * res.solve_time, "cost": float(res.cost),
                  "iterations": float(res.iterations), "success": float(bool(res.success)), "safe": 0.0}
        broken = _broken(res, u, self.system.control.size)
        if broken is not None:
            return self._safe("non_finite", f"{broken} ({res.message})", values)
        plan = np.asarray(res.plan_x, dtype=np.float64).reshape(-1, self.system.state.size)
        outside = ~self.bounds.state.inside(plan)
        if outside.any():
            step = int(np.argmax(outside))
            return self._safe("implausible", f"the plan predicts an implausible state at step {step}: "
                              f"{self.bounds.state.outside(plan[step])}", values)
        if not res.success and res.unavoidable:
            # no command avoids it (the safe one neither): the plan is the best effort, e.g. braking at full thrust
            self.counters["solves_unavoidable"] += 1
        elif not res.success:
            self.counters["solves_failed"] += 1
            if self.config.safe_on_infeasible:
                return self._safe("infeasible", f"plan violates a constraint: {res.message}", values)
            self.warn_throttled("fail", f"solve at t={stamp * 1e-9:.3f} s not successful: {res.message}")
        return u, values

    def _safe(self, reason: str, text: str, values: dict[str, float] | None = None) -> tuple[np.ndarray, dict[str, float]]:
        """The safe command, counted under ``reason`` (one of :data:`SAFE_COMMAND_REASONS`)."""
        assert reason in SAFE_COMMAND_REASONS
        self.counters["safe_commands"] += 1
        self.counters[f"safe_commands/{reason}"] += 1
        self.warn_throttled(f"safe_commands/{reason}", f"sent the safe command {self.u_safe.tolist()}: {text}")
        out = {"solve_time_ms": math.nan, "cost": math.nan, "iterations": 0.0, "success": 0.0}
        out.update(values or {})
        out["safe"] = 1.0
        return self.u_safe, out

    def swap(self, ready: ReadyModel) -> None:
        """Plan with the model ``ready`` from now on (with the live monitor on: unless it predicts the newest live
        transitions worse than f_hat; then it is refused, logged, and never flown)."""
        if self.guarded is not None:
            if not self.guarded.offer_model(ready.loaded.model, ready.version, ready.loaded.meta):
                self.counters["rollbacks"] += 1
                m, b, n = self.guarded.last_refusal or (math.nan, math.nan, 0)
                self.logger.warning(
                    f"refused model version {ready.version} ({ready.path.name}) before flying it: on the last {n} "
                    f"live transitions its one-step error {m:.4g} is above f_hat's {b:.4g} + margin; model version "
                    f"{self.model_version} kept, version {ready.version} is not used again")
                return
            self._paths[ready.version] = str(ready.path)
        else:
            self.controller.set_model(ready.loaded.model)
        old, self.model_version, self.model_path = self.model_version, ready.version, str(ready.path)
        self._models[ready.version] = ready.loaded
        while len(self._models) > KEPT_MODELS:
            self._models.popitem(last=False)
        self.watcher.set_in_use(ready.loaded, ready.version)
        self.counters["swaps"] += 1
        self.logger.info(f"model version {old} -> {ready.version} ({ready.path.name})")

    # ------------------------------------------------------------------------------------------ telemetry
    def warn_throttled(self, key: str, text: str, period: float = 5.0) -> None:
        """Log ``text`` as a warning at most once per ``period`` s per ``key`` (with the count so far)."""
        now = time.monotonic()
        if now - self._last_warn.get(key, -math.inf) >= period:
            self._last_warn[key] = now
            n = self.counters.get(key, 0)
            self.logger.warning(text + (f" (x{n} so far)" if n > 1 else ""))

    def diagnostic_values(self) -> dict[str, Any]:
        """Counters, the model in use and the watcher's statistics, for ``/diagnostics``."""
        stats = self.watcher.stats()
        values: dict[str, Any] = {k: v for k, v in sorted(self.counters.items())}
        values["safe_commands"] = self.counters["safe_commands"]
        values["solves_failed"] = self.counters["solves_failed"]
        values["solves_unavoidable"] = self.counters["solves_unavoidable"]
        for r in SAFE_COMMAND_REASONS:
            values[f"safe_commands/{r}"] = self.counters[f"safe_commands/{r}"]
        values["rejected/bounds"] = self.counters["rejected/bounds"]
        values["model_version"] = self.model_version
        values["model_path"] = self.model_path
        values["checkpoints_loaded"] = stats["loaded"]
        values["checkpoints_refused"] = stats["refused"]
        for r in REFUSAL_REASONS:
            values[f"checkpoints_refused/{r}"] = stats[f"refused/{r}"]
        values["last_refusal"] = stats["last_refusal"]
        values["checkpoints_gated"] = stats["gated"]
        values["last_gated"] = stats["last_gated"]
        values["checkpoints_reannounced"] = stats["reannounced"]
        values["models_retired"] = self.counters["models_retired"]
        values["max_step_ms_during_swap"] = round(self.step_ms_max_swap, 3)
        solver: Any = self.controller
        if self.guarded is not None:  # the learned model's solver once it has solved, else f_hat's
            learned = self.guarded.learned
            solver = learned if getattr(learned, "native_reason", None) != NOT_SOLVED else self.guarded.base
        describe = getattr(solver, "describe", None)
        if describe is not None:  # the generic planner: its path, solver and model
            values["planner"] = describe()
        if self.tracker is not None:
            values["goal"] = ", ".join(f"{n}={v:.4g}" for n, v in zip(self.tracker.fields, self.tracker.goal,
                                                                      strict=True))
            values["tracking_reference"] = self.tracker.tracking
            for key in ("goals", "references", "rejected/goal", "rejected/reference"):
                values[key] = self.counters[key]
        if hasattr(solver, "native_reason"):  # the fast shooting SQP: its numerics in C, or why not
            why = solver.native_reason
            values["solver_kernel"] = "C" if why is None else f"numpy ({why})"
        if self.guarded is not None:
            g = self.guarded
            values["guard_fallbacks"] = g.counters["fallbacks"]
            values["guard_base_solves"] = g.counters["solves_base"]
            values["guard_rollbacks"] = g.counters["rollbacks"]
            values["guard_refused_before_flight"] = g.counters["refused_before_flight"]
            values["guard_bounded_solves"] = g.counters["bounded"]
            values["guard_clipped_solves"] = g.counters["clipped"]
            values["guard_task_fallbacks"] = g.counters["task_fallbacks"]
            values["guard_task_rollbacks"] = g.counters["task_rollbacks"]
            values["guard_rolled_back_versions"] = ",".join(str(v) for v in sorted(g.banned))
            values["monitor_error_model"] = g.monitor.mean_model
            values["monitor_error_base"] = g.monitor.mean_base
            values["monitor_margin"] = g.monitor.margin
        return values


def _broken(res: MPCResult, u: np.ndarray, size: int) -> str | None:
    """Why ``res`` (with control ``u``) cannot be used: a wrong-sized or non-finite control, a non-finite cost or
    plan (the controller fell back); ``None`` if it can."""
    if u.shape != (size,) or not np.all(np.isfinite(u)):
        return f"invalid control {u!r}"
    if not math.isfinite(float(res.cost)):
        return f"non-finite cost {res.cost}"
    if not (np.all(np.isfinite(res.plan_x)) and np.all(np.isfinite(res.plan_u))):
        return "non-finite plan"
    return None
