"""The MPC node's configuration without ROS: its parameter table and the validated :class:`MPCConfig`.

The node declares :meth:`MPCConfig.params` (names, defaults, descriptions; ``goal.*`` and ``task.*`` come from
the system's registry entry) and builds the configuration from the declared values with
:meth:`MPCConfig.from_params`, which raises ``ValueError`` naming the bad parameter. See docs/nodes.md.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, replace
from typing import Any

import yaml

from saml_ros.core.data.plausibility import parse_overrides
from saml_ros.core.mpc.factory import SOLVERS
from saml_ros.core.mpc.guard import GuardConfig
from saml_ros.core.mpc.monitor import MonitorConfig
from saml_ros.core.mpc.task_check import TaskCheckConfig
from saml_ros.core.params import LIVE, START, Param, ParamErrors, Problems, memory_problems, read_params
from saml_ros.core.systems.registry import get_entry

#: how the node answers states
MODES = ("lockstep", "realtime")
#: rclpy executors the node can spin on (saml_ros.nodes.runtime.EXECUTORS)
EXECUTORS = ("events", "single")
#: what the ``executor`` parameter accepts: an executor, or ``auto`` (:func:`choose_executor`)
EXECUTOR_CHOICES = ("auto", *EXECUTORS)


def choose_executor(executor: str, mode: str) -> str:
    """The executor the ``executor`` parameter means: ``auto`` is ``events`` in lockstep (simulation: the shorter
    round trip is the loop's speed, and a simulator that gets no answer falls back after ``lockstep_timeout``) and
    ``single`` in realtime (beside a robot: the long-established executor)."""
    if executor == "auto":
        return "events" if mode == "lockstep" else "single"
    return executor


#: the parameters of every MPC node (``system``'s default is the node's own system)
PARAMS: tuple[Param, ...] = (
    Param("system", "friction", "system name: friction | quadrotor | paddle_ball (read before the node starts)",
          when=START),
    Param("system_file", "", "a robot described by a system file with an 'mpc:' section (docs/your_robot.md, "
                             "'Control it'): planned by the generic planner, commanded on its own topic and type; "
                             "the system is the file's name (read before the node starts)", when=START),
    Param("solver", "fast", "MPC solver: fast (SQP, warm-started) | slsqp (scipy reference, slow)"),
    Param("horizon", 10, "planning horizon T (steps; ignored by the one-shot paddle problem)"),
    Param("member", 0, "ensemble member of the checkpoint's model used for planning"),
    Param("solver_options", "", "extra solver options as a YAML mapping, e.g. '{max_iter: 20}'"),
    Param("mode", "lockstep", "lockstep: answer every state at once | realtime: answer the newest state at rate_hz"),
    Param("rate_hz", 10.0, "control rate in realtime mode (Hz)"),
    Param("deadline_ms", 0.0, "a control step longer than this is a deadline miss (ms); 0 = the period: "
                              "1000 / rate_hz in realtime, the system's dt in lockstep (100 ms for the event-based "
                              "paddle ball)", when=LIVE),
    Param("run_dir", "", "run directory whose `latest` checkpoint is polled ('' = follow learner/checkpoint only)"),
    Param("poll_period", 0.5, "seconds between polls of run_dir", when=LIVE),
    Param("diagnostics_rate", 1.0, "/diagnostics publication rate (Hz, wall clock)", when=LIVE),
    Param("executor", "auto", "rclpy executor the node spins on: auto (events in lockstep, single in realtime) | "
                              "single (SingleThreadedExecutor) | events (rclpy.experimental.EventsExecutor: a "
                              "shorter round trip, 27-29x instead of 21-22x real time in bench closed_loop; "
                              "docs/performance.md); the environment variable SAML_EXECUTOR overrides it",
          when=START),
    Param("gate.max_constraint", math.inf, "hold back checkpoints whose recorded constraint estimates "
                                           "(E[l | region] - eps, learner's live window) exceed this; inf = take "
                                           "every valid checkpoint", finite=False),
    Param("gate.min_updates", 0, "hold back checkpoints with fewer learner updates than this"),
    Param("guard.max_disagreement", math.inf, "plan a step with the base model f_hat when the checkpoint's "
                                              "ensemble disagrees by more than this (state units, RMS over "
                                              "members) on the plan; inf = off", finite=False),
    Param("guard.bound_residual", False, "clip the learned residual to the bound the learner recorded in the "
                                         "checkpoint (1.5 x the largest residual in its buffer, per field)"),
    Param("guard.rollback", True, "live monitor: roll back to the previous model, else f_hat, when the active "
                                  "model's live one-step error on the steps it planned exceeds f_hat's (see "
                                  "guard.window ... guard.margin); on by default for every system (the paddle "
                                  "ball's transitions are its post_impact messages)"),
    Param("guard.infeasible", False, "plan a step with f_hat too when the learned model's plan violates a "
                                     "constraint some control could keep, and fly f_hat's plan if it keeps the "
                                     "constraints or violates them less"),
    Param("guard.task_check", False, "task check: when the plan flown with a learned model in use breaks a task "
                                     "constraint some control could keep, plan the step with f_hat from a cold "
                                     "start and fly f_hat's plan if it keeps every constraint (a strike); "
                                     "guard.task_strikes strikes within guard.task_window steps roll the model "
                                     "back (docs/mpc.md, the task check)"),
    Param("guard.task_window", 10, "steps planned with the model in use the task check counts strikes over"),
    Param("guard.task_strikes", 3, "strikes within guard.task_window steps that roll the model back (0 = never: "
                                   "a strike only flies f_hat's plan for that step)"),
    Param("guard.window", 5, "live transitions the monitor averages the one-step squared errors over (steps the "
                             "learned model planned)"),
    Param("guard.min_samples", 3, "transitions in the window before the monitor may roll back"),
    Param("guard.ratio", 1.0, "roll back when mean error(model) > ratio * mean error(f_hat) + margin + "
                              "margin_relative * (f_hat's mean squared one-step error over the model's data)"),
    Param("guard.margin", 0.0, "see guard.ratio (absolute, squared state units summed over the target fields)"),
    Param("guard.margin_relative", 0.02, "see guard.ratio: the margin relative to how wrong f_hat is on the data the "
                                         "model was trained on (its checkpoint's evidence; without one, on the live "
                                         "transitions seen so far); 0 = only the absolute guard.margin"),
    Param("plausible_bounds", "", "overrides of the system's plausible ranges as a YAML mapping, e.g. "
                                  "'{x.pz: [-1.0, 2000.0]}' (fields x.<state>, u.<control>, next.<target>; .inf = "
                                  "open); a state outside is answered with the safe command (rejected/bounds)"),
    Param("accept.residual_factor", 4.0, "refuse a checkpoint whose model, on its probe set or the recent states, "
                                         "differs from the base model by more than this multiple of the largest "
                                         "residual its training data showed (0 = no residual check)"),
    Param("safe_on_infeasible", False, "also answer with the safe command when the plan is finite but violates a "
                                       "constraint (by default only failed or non-finite solves and implausible "
                                       "states are)", when=LIVE),
    Param("state_timeout", 0.0, "s: answer a state older than this (by its stamp, on the node's clock) with the safe "
                                "command, and send it while no state arrives for this long (0 = off; a system "
                                "file's mpc.state_timeout by default)"),
)


def parse_solver_options(text: str) -> dict[str, Any]:
    """``solver_options`` (a YAML / JSON mapping of scalars, e.g. ``"{max_iter: 20}"``) -> dict."""
    if not text.strip():
        return {}
    data = yaml.safe_load(text)
    if not isinstance(data, dict) or not all(
        isinstance(k, str) and isinstance(v, (int, float, str, bool)) for k, v in data.items()
    ):
        raise ValueError(f"solver_options must be a mapping of names to scalars, got {text!r}")
    return data


def make_goal(system: str, values: Mapping[str, Any]) -> Any:
    """The ``goal`` argument of ``Controller.solve`` from the ``goal.*`` values of ``system`` (without the
    prefix; defaults filled in). ``ValueError``: wrong size, not finite, or a bound pair inverted."""
    return get_entry(system).make_goal(values)


def horizon_memory(system: str, horizon: int) -> tuple[str, str, int]:
    """``(parameter, what, bytes)`` for :func:`~saml_ros.core.params.memory_problems`: a lower bound of what the
    shooting MPC of ``system`` allocates for ``horizon`` steps (its dense QP over the T m controls: the Hessian
    and the state Jacobian T n x T m, in float64)."""
    schema = get_entry(system).schema()
    n, m = schema.state.size, schema.control.size
    cols = horizon * m
    return ("horizon", f"the plan's dense matrices for a horizon of {horizon} steps",
            8 * cols * (cols + horizon * n))


@dataclass(frozen=True)
class GateConfig:
    """``gate.*``: which checkpoints the MPC takes by what the learner recorded in them
    (:func:`~saml_ros.core.mpc.follower.checkpoint_gate`).

    Attributes:
        max_constraint: hold back checkpoints whose constraint estimates exceed this (``inf``: no limit).
        min_updates: hold back checkpoints with fewer learner updates than this.
    """

    max_constraint: float = math.inf
    min_updates: int = 0


@dataclass(frozen=True)
class MPCConfig:
    """The MPC node's parameters after validation (units in :data:`PARAMS`' descriptions).

    ``goal`` is the built goal object (``Controller.solve``'s argument), ``task`` the ``task.*`` values without
    the prefix, ``solver_options`` the parsed mapping; ``gate`` holds ``gate.*``, ``guard`` ``guard.*``.
    """

    system: str
    solver: str
    horizon: int
    member: int
    solver_options: dict[str, Any]
    mode: str
    rate_hz: float
    deadline_ms: float
    run_dir: str
    poll_period: float
    diagnostics_rate: float
    goal: Any
    task: dict[str, Any]
    guard: GuardConfig = GuardConfig()
    gate: GateConfig = GateConfig()
    plausible_bounds: str = ""
    accept_residual_factor: float = 4.0
    safe_on_infeasible: bool = False
    executor: str = "single"  #: the resolved executor (:func:`choose_executor`)
    state_timeout: float = 0.0  #: s, 0 = off
    system_file: str = ""

    @staticmethod
    def params(system: str) -> list[Param]:
        """The parameter table of an MPC node for ``system``: :data:`PARAMS`, then ``goal.*`` and ``task.*``."""
        entry = get_entry(system)
        table = [replace(PARAMS[0], default=system), *PARAMS[1:]]
        table = [replace(p, default=type(p.default)(entry.mpc_defaults[p.name])) if p.name in entry.mpc_defaults
                 else p for p in table]  # a system file's mpc: section sets the horizon, rate, state timeout
        table += [replace(g, name=f"goal.{g.name}", when=LIVE) for g in entry.goal_params]
        table += [replace(t, name=f"task.{t.name}") for t in entry.task_params]
        return table

    @classmethod
    def from_params(cls, values: Mapping[str, Any]) -> MPCConfig:
        """The configuration from parameter values by name (missing ones take their defaults).

        Raises:
            ParamErrors: (a ``ValueError``) an unknown system or parameter, or a value of the wrong type or out of
                range; every bad parameter is named.
        """
        problems = Problems()
        check = problems.check
        system = values.get("system", PARAMS[0].default)
        if not isinstance(system, str):
            raise ParamErrors([f"parameter 'system' must be a string, got {system!r}"])
        try:
            entry = get_entry(system)
        except ValueError as exc:
            raise ParamErrors([f"parameter 'system': {exc}"]) from None
        table = cls.params(system)
        unknown = sorted(set(values) - {p.name for p in table})
        if unknown:
            problems.add(f"unknown MPC parameter(s) {unknown} for system {system!r}", *unknown)
        p = read_params(table, values, problems)
        check(p["mode"] in MODES, "mode", f"one of {MODES}", p["mode"])
        check(p["executor"] in EXECUTOR_CHOICES, "executor", f"auto or one of {EXECUTORS}", p["executor"])
        check(p["solver"] in SOLVERS, "solver", f"one of {SOLVERS}", p["solver"])
        for name in ("rate_hz", "poll_period", "diagnostics_rate"):
            check(p[name] > 0, name, "> 0", p[name])
        check(p["deadline_ms"] >= 0, "deadline_ms", ">= 0", p["deadline_ms"])
        check(p["member"] >= 0, "member", ">= 0", p["member"])
        check(p["horizon"] >= 1 or not entry.mpc_horizon, "horizon", ">= 1", p["horizon"])
        if entry.mpc_horizon and p["horizon"] >= 1:
            for message in memory_problems([horizon_memory(system, p["horizon"])]):
                problems.add(message, "horizon")
        check(p["guard.max_disagreement"] > 0, "guard.max_disagreement", "> 0 (inf = off)",
              p["guard.max_disagreement"])
        guard = GuardConfig()
        with problems.capture("guard.window", prefix="parameters 'guard.*': "):
            guard = GuardConfig(
                max_disagreement=p["guard.max_disagreement"], bound_residual=p["guard.bound_residual"],
                rollback=p["guard.rollback"], infeasible=p["guard.infeasible"],
                monitor=MonitorConfig(window=p["guard.window"], min_samples=p["guard.min_samples"],
                                      ratio=p["guard.ratio"], margin=p["guard.margin"],
                                      margin_relative=p["guard.margin_relative"]),
                task=TaskCheckConfig(enabled=p["guard.task_check"], window=p["guard.task_window"],
                                     strikes=p["guard.task_strikes"]))
        check(not guard.needs_shooting or entry.mpc_horizon, "guard.*",
              "off for a one-shot MPC (paddle_ball), except guard.rollback", "on")
        check(p["accept.residual_factor"] >= 0, "accept.residual_factor", ">= 0", p["accept.residual_factor"])
        check(p["state_timeout"] >= 0, "state_timeout", ">= 0 (0 = off)", p["state_timeout"])
        with problems.capture("plausible_bounds", prefix="parameter 'plausible_bounds': "):
            parse_overrides(p["plausible_bounds"])
        solver_options: dict[str, Any] = {}
        with problems.capture("solver_options"):
            solver_options = parse_solver_options(p["solver_options"])
        goal: Any = None
        with problems.capture(*(f"goal.{g.name}" for g in entry.goal_params)):
            goal = entry.make_goal({g.name: p[f"goal.{g.name}"] for g in entry.goal_params})
        problems.raise_if_any()
        return cls(
            system=system, solver=p["solver"], horizon=p["horizon"], member=p["member"],
            solver_options=solver_options, mode=p["mode"], rate_hz=p["rate_hz"],
            deadline_ms=p["deadline_ms"], run_dir=p["run_dir"], poll_period=p["poll_period"],
            diagnostics_rate=p["diagnostics_rate"], goal=goal,
            gate=GateConfig(max_constraint=p["gate.max_constraint"], min_updates=p["gate.min_updates"]),
            task={t.name: p[f"task.{t.name}"] for t in entry.task_params}, guard=guard,
            plausible_bounds=p["plausible_bounds"], accept_residual_factor=p["accept.residual_factor"],
            safe_on_infeasible=p["safe_on_infeasible"], executor=choose_executor(p["executor"], p["mode"]),
            state_timeout=p["state_timeout"], system_file=p["system_file"],
        )

    def controller_options(self) -> dict[str, Any]:
        """Options of ``make_controller``: the solver options, the task options and (if the system's MPC has
        one) the horizon."""
        options = {**self.solver_options, **self.task}
        if get_entry(self.system).mpc_horizon:
            options["horizon"] = self.horizon
        return options

    def deadline_s(self, dt: float) -> float:
        """The deadline of a control step (s): ``deadline_ms``, else the period (``1 / rate_hz`` in realtime,
        the system's ``dt`` in lockstep, 0.1 s for an event-based system)."""
        if self.deadline_ms > 0:
            return self.deadline_ms / 1e3
        if self.mode == "realtime":
            return 1.0 / self.rate_hz
        return dt if dt > 0 else 0.1
