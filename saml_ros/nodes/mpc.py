"""The MPC node (``ros2 run saml_ros mpc``): answers every ``state`` with a ``cmd`` from the newest model.

Subscribes ``state`` (DATA_QOS) and ``learner/checkpoint`` (CHECKPOINT_QOS, transient local); publishes
``cmd`` (stamped with the state it answers), ``mpc/status`` (one message per solve) and ``/diagnostics``.

* ``mode: lockstep``: every state is answered at once, in the subscription callback (a lockstep simulator
  waits for that answer). ``mode: realtime``: a steady-clock timer at ``rate_hz`` answers the newest state
  received since the last tick (older ones are skipped and counted).
* Models: the node starts on the base model f_hat when ``run_dir`` holds no checkpoint. A
  :class:`~saml_ros.core.model_watch.ModelWatcher` follows ``learner/checkpoint`` and polls ``run_dir``
  (``latest``) as a fallback, loads new checkpoints on a background thread and the control step swaps the
  ready model in between two solves. Incompatible or corrupt checkpoints are refused (log + counter +
  ``mpc/status`` ``checkpoints_refused``) and the current model is kept.
* Deadline: a control step (swap + solve + publish, from the state's arrival in lockstep or the timer tick in
  realtime) that takes longer than ``deadline_ms`` counts as a deadline miss.

See docs/nodes.md for the parameters and examples.
"""

from __future__ import annotations

import importlib
import math
import time
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from msg_schemas import CHECKPOINT_QOS, DATA_QOS, TELEMETRY_QOS, SchemaError, SystemSchema, get_schema
from msg_schemas.telemetry import (
    CHECKPOINT_TOPIC,
    DIAGNOSTICS_TOPIC,
    MPC_STATUS_TOPIC,
    OK,
    WARN,
    DiagnosticEntry,
    checkpoint_from_msg,
    diagnostics_to_msg,
    mpc_status_to_msg,
)
from saml_ros.core.model_io import LoadedModel
from saml_ros.core.model_watch import REFUSAL_REASONS, ModelWatcher, ReadyModel
from saml_ros.core.mpc.qp import DEFAULT_BACKEND as QP_BACKEND
from saml_ros.core.systems import get_system
from saml_ros.core.systems.base import System
from saml_ros.nodes.runtime import (
    catch_stop_signals,
    full_argv,
    init_rclpy,
    process_main,
    shutdown,
    spin_until_stopped,
    wants_help,
)

MODES = ("lockstep", "realtime")
#: exit code for invalid parameters (as argparse's usage errors)
USAGE_ERROR = 2
SOLVERS = ("fast", "slsqp")


# ------------------------------------------------------------------------------------ goals (ROS-free)
@dataclass(frozen=True)
class GoalParam:
    """One goal parameter ``goal.<name>`` of a system: default value, unit and meaning."""

    name: str
    default: Any
    description: str


#: goal parameters per system (declared as ``goal.<name>``)
GOAL_PARAMS: dict[str, tuple[GoalParam, ...]] = {
    "friction": (GoalParam("position", 0.0, "target position p (m); the paper drives the cart to the origin"),),
    "quadrotor": (
        GoalParam("position", [0.0, 0.0, 0.0], "landing target [x, y, z] (m, world); the paper lands at the origin"),
    ),
    "paddle_ball": (
        GoalParam("target_xy", [0.0, 0.0], "where the ball should come down, [x, y] (m, world)"),
        GoalParam("roll_min", -0.4, "lower bound of the paddle roll (rad)"),
        GoalParam("roll_max", 0.4, "upper bound of the paddle roll (rad)"),
        GoalParam("pitch_min", -0.4, "lower bound of the paddle pitch (rad)"),
        GoalParam("pitch_max", 0.4, "upper bound of the paddle pitch (rad)"),
        GoalParam("v_rel_min", 3.0, "lower bound of the ball's speed relative to the paddle after impact (m/s)"),
        GoalParam("v_rel_max", 5.0, "upper bound of the ball's speed relative to the paddle after impact (m/s)"),
    ),
}

#: task options per system forwarded to ``make_controller`` (declared as ``task.<name>``)
TASK_PARAMS: dict[str, tuple[GoalParam, ...]] = {
    "friction": (),
    "quadrotor": (
        GoalParam("min_height", 0.2, "lowest allowed height of the centre of mass over the horizon (m)"),
        GoalParam("qw_tol", 0.05, "attitude at the end of the horizon: |qw_T - 1| <= qw_tol"),
    ),
    "paddle_ball": (),
}


def make_goal(system: str, values: dict[str, Any]) -> Any:
    """The ``goal`` argument of ``Controller.solve`` from the ``goal.*`` parameter values of ``system``.

    Raises:
        ValueError: a value has the wrong size, is not finite, or a bound pair is inverted.
    """
    def vec(name: str, size: int) -> np.ndarray:
        arr = np.atleast_1d(np.asarray(values[name], dtype=np.float64))
        if arr.shape != (size,) or not np.all(np.isfinite(arr)):
            raise ValueError(f"goal.{name} must be {size} finite number(s), got {values[name]!r}")
        return arr

    if system == "friction":
        return vec("position", 1)
    if system == "quadrotor":
        return vec("position", 3)
    if system == "paddle_ball":
        from saml_ros.core.mpc import paddle_goal

        for lo, hi in (("roll_min", "roll_max"), ("pitch_min", "pitch_max"), ("v_rel_min", "v_rel_max")):
            if not float(values[lo]) <= float(values[hi]):
                raise ValueError(f"goal.{lo} = {values[lo]} must be <= goal.{hi} = {values[hi]}")
        return paddle_goal(
            target_xy=vec("target_xy", 2),
            roll=(float(values["roll_min"]), float(values["roll_max"])),
            pitch=(float(values["pitch_min"]), float(values["pitch_max"])),
            v_rel=(float(values["v_rel_min"]), float(values["v_rel_max"])),
        )
    raise ValueError(f"no MPC goal for system {system!r}")


def safe_control(system: System) -> np.ndarray:
    """The control published when a solve raises: the simulators' safe default (see docs/architecture.md)."""
    if system.name == "quadrotor":
        return np.asarray(system.hover_thrust(), dtype=np.float64)  # type: ignore[attr-defined]
    if system.name == "paddle_ball":
        return np.array([0.0, 0.0, 0.0, 0.0, 0.0, 1.0])
    return np.zeros(system.control.size)


def make_gate(max_constraint: float, min_updates: int) -> Callable[[LoadedModel], str | None] | None:
    """The checkpoint gate of ``gate.*``: hold back checkpoints with fewer than ``min_updates`` updates, or whose
    recorded constraint estimates (``metrics["constraint/<k>"]``, the learner's E[l | region] - eps on its live
    window) exceed ``max_constraint``. ``None`` when both are disabled (``inf`` and 0)."""
    if math.isinf(max_constraint) and max_constraint > 0 and min_updates <= 0:
        return None

    def accept(loaded: LoadedModel) -> str | None:
        updates = int(loaded.meta.get("updates", 0))
        if updates < min_updates:
            return f"{updates} learner updates < gate.min_updates = {min_updates}"
        if not math.isinf(max_constraint):
            metrics = loaded.meta.get("metrics") or {}
            cons = {k: v for k, v in metrics.items() if k.startswith("constraint/")}
            if not cons:
                return "its metrics hold no constraint estimate (constraint/<k>)"
            bad = {k: round(float(v), 6) for k, v in cons.items()
                   if not (isinstance(v, int | float) and math.isfinite(v) and v <= max_constraint)}
            if bad:
                return f"constraint estimate {bad} > gate.max_constraint = {max_constraint:g}"
        return None

    return accept


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


# ---------------------------------------------------------------------------------------------- node
def _build_node_class() -> type:
    """The rclpy node class (built lazily so that importing this module does not import rclpy)."""
    from rclpy.clock import Clock, ClockType
    from rclpy.node import Node

    parameter_descriptor = importlib.import_module("rcl_interfaces.msg").ParameterDescriptor

    class MPCNode(Node):
        """See the module docstring."""

        def __init__(self, system_name: str, namespace: str | None = None) -> None:
            super().__init__("mpc", namespace=namespace)
            self.system: System = get_system(system_name)
            self.schema: SystemSchema = get_schema(system_name)
            p = self._declare_parameters(parameter_descriptor)
            self.mode: str = p["mode"]
            self.rate_hz: float = p["rate_hz"]
            self.deadline_s = self._deadline(p["deadline_ms"])
            self.goal = make_goal(system_name, {g.name: p[f"goal.{g.name}"] for g in GOAL_PARAMS[system_name]})
            options = parse_solver_options(p["solver_options"])
            options.update({t.name: p[f"task.{t.name}"] for t in TASK_PARAMS[system_name]})
            from saml_ros.core.mpc import make_controller

            if system_name != "paddle_ball":  # the paddle problem is one-shot (no horizon)
                options["horizon"] = p["horizon"]
            self.controller = make_controller(self.system, None, solver=p["solver"], member=p["member"], **options)
            self.u_low = np.asarray(self.system.control_low, dtype=np.float64)
            self.u_high = np.asarray(self.system.control_high, dtype=np.float64)
            self.u_safe = np.clip(safe_control(self.system), self.u_low, self.u_high)

            self.model_version = 0
            self.model_path = ""
            self.counters: Counter[str] = Counter()
            self.last_stamp: int | None = None
            self.pending: tuple[np.ndarray, int, float] | None = None  # realtime: newest unanswered state
            self.step_ms_max_swap = 0.0
            self._last_warn: dict[str, float] = {}

            run_dir = p["run_dir"]
            self.watcher = ModelWatcher(self.system, Path(run_dir) if run_dir else None,
                                        poll_period=p["poll_period"], logger=self.get_logger(),
                                        accept=make_gate(p["gate.max_constraint"], p["gate.min_updates"]))
            if run_dir:  # start on the newest valid checkpoint if there is one (before the first solve)
                ready = self.watcher.poll_once(source="initial")
                if ready is not None:
                    self.watcher.take()
                    self._swap(ready)
            self.watcher.start()
            if self.model_version == 0:
                self.get_logger().info("no checkpoint yet: running on the base model f_hat")

            from diagnostic_msgs.msg import DiagnosticArray
            from sensor_msgs.msg import JointState
            from std_msgs.msg import String

            state_cls = _msg_class(self.schema.state.msg_type)
            self.cmd_pub = self.create_publisher(_msg_class(self.schema.control.msg_type), self.schema.cmd_topic,
                                                 DATA_QOS.to_rclpy())
            self.status_pub = self.create_publisher(JointState, MPC_STATUS_TOPIC, TELEMETRY_QOS.to_rclpy())
            self.diag_pub = self.create_publisher(DiagnosticArray, DIAGNOSTICS_TOPIC, TELEMETRY_QOS.to_rclpy())
            self.create_subscription(state_cls, self.schema.state_topic, self._on_state, DATA_QOS.to_rclpy())
            self.create_subscription(String, CHECKPOINT_TOPIC, self._on_checkpoint, CHECKPOINT_QOS.to_rclpy())
            steady = Clock(clock_type=ClockType.STEADY_TIME)
            if self.mode == "realtime":
                self.create_timer(1.0 / self.rate_hz, self._on_tick, clock=steady)
            self.create_timer(1.0 / max(p["diagnostics_rate"], 1e-3), self._publish_diagnostics, clock=steady)
            self.get_logger().info(
                f"{system_name} MPC ({p['solver']}{', QP ' + QP_BACKEND if p['solver'] == 'fast' else ''}, "
                f"{'one-shot' if system_name == 'paddle_ball' else 'T=' + str(p['horizon'])}, {self.mode}"
                f"{f' at {self.rate_hz:g} Hz' if self.mode == 'realtime' else ''}, deadline "
                f"{1e3 * self.deadline_s:.0f} ms), goal {self.goal!r}, run_dir {run_dir or '(none)'}"
            )

        # ---------------------------------------------------------------------------- parameters
        def _declare_parameters(self, descriptor: Any) -> dict[str, Any]:
            name = self.system.name
            table: list[tuple[str, Any, str]] = [
                ("system", name, "system name: friction | quadrotor | paddle_ball (read before the node starts)"),
                ("solver", "fast", "MPC solver: fast (SQP, warm-started) | slsqp (scipy reference, slow)"),
                ("horizon", 10, "planning horizon T (steps; ignored by the one-shot paddle problem)"),
                ("member", 0, "ensemble member of the checkpoint's model used for planning"),
                ("solver_options", "", "extra solver options as a YAML mapping, e.g. '{max_iter: 20}'"),
                ("mode", "lockstep", "lockstep: answer every state at once | realtime: answer the newest "
                                     "state at rate_hz"),
                ("rate_hz", 10.0, "control rate in realtime mode (Hz)"),
                ("deadline_ms", 0.0, "a control step longer than this is a deadline miss (ms); 0 = the "
                                     "period: 1000 / rate_hz in realtime, the system's dt in lockstep "
                                     "(100 ms for the event-based paddle ball)"),
                ("run_dir", "", "run directory whose `latest` checkpoint is polled ('' = follow "
                                "learner/checkpoint only)"),
                ("poll_period", 0.5, "seconds between polls of run_dir"),
                ("diagnostics_rate", 1.0, "/diagnostics publication rate (Hz, wall clock)"),
                ("gate.max_constraint", math.inf, "hold back checkpoints whose recorded constraint estimates "
                                                  "(E[l | region] - eps, learner's live window) exceed this; inf = "
                                                  "take every valid checkpoint"),
                ("gate.min_updates", 0, "hold back checkpoints with fewer learner updates than this"),
            ]
            table += [(f"goal.{g.name}", g.default, g.description) for g in GOAL_PARAMS[name]]
            table += [(f"task.{t.name}", t.default, t.description) for t in TASK_PARAMS[name]]
            out: dict[str, Any] = {}
            for key, default, text in table:
                self.declare_parameter(key, default, descriptor(description=text))
                out[key] = self.get_parameter(key).value
            if out["system"] != name:
                raise ValueError(f"parameter system={out['system']!r} does not match the node's system {name!r}")
            if out["mode"] not in MODES:
                raise ValueError(f"mode must be one of {MODES}, got {out['mode']!r}")
            if out["solver"] not in SOLVERS:
                raise ValueError(f"solver must be one of {SOLVERS}, got {out['solver']!r}")
            if not (out["rate_hz"] > 0 and out["poll_period"] > 0 and out["deadline_ms"] >= 0):
                raise ValueError("rate_hz and poll_period must be > 0 and deadline_ms >= 0")
            return out

        def _deadline(self, deadline_ms: float) -> float:
            if deadline_ms > 0:
                return deadline_ms / 1e3
            if self.mode == "realtime":
                return 1.0 / self.rate_hz
            return self.system.dt if self.system.dt > 0 else 0.1

        # ---------------------------------------------------------------------------- callbacks
        def _on_checkpoint(self, msg: Any) -> None:
            try:
                info = checkpoint_from_msg(msg, CHECKPOINT_TOPIC)
            except SchemaError as exc:
                self._reject(exc.reason, str(exc))
                return
            self.watcher.notify(info.path, info.version, info.schema_hash)

        def _on_state(self, msg: Any) -> None:
            t_arrival = time.perf_counter()
            try:
                x, stamp = self.schema.state_from_msg(msg, self.schema.state_topic)
            except SchemaError as exc:
                self._reject(exc.reason, str(exc))
                return
            if self.last_stamp is not None and stamp == self.last_stamp:
                self._reject("duplicate", f"state stamped {stamp} ns was already answered")
                return
            if self.mode == "lockstep":
                self._control_step(x, stamp, t_arrival)
            else:
                if self.pending is not None:
                    self.counters["skipped_states"] += 1
                self.pending = (x, stamp, t_arrival)

        def _on_tick(self) -> None:
            if self.pending is None:
                return
            (x, stamp, _), self.pending = self.pending, None
            self._control_step(x, stamp, time.perf_counter())

        # ---------------------------------------------------------------------------- control
        def _control_step(self, x: np.ndarray, stamp: int, t_start: float) -> None:
            if self.last_stamp is not None:
                dt_ns = stamp - self.last_stamp
                # a reset, a new episode or a restarted simulator: the warm start is meaningless
                if dt_ns < 0 or (self.system.dt > 0 and dt_ns > 1.5e9 * self.system.dt):
                    self.controller.reset()
                    self.counters["warm_start_resets"] += 1
            self.last_stamp = stamp
            swap_ms = 0.0
            ready = self.watcher.take()
            if ready is not None:
                t0 = time.perf_counter()
                self._swap(ready)
                swap_ms = 1e3 * (time.perf_counter() - t0)
            try:
                res = self.controller.solve(x, self.goal)
                u = np.asarray(res.u, dtype=np.float64)
                if u.shape != (self.system.control.size,) or not np.all(np.isfinite(u)):
                    raise ValueError(f"solver returned an invalid control {u!r}")
                values = {"solve_time_ms": 1e3 * res.solve_time, "cost": float(res.cost),
                          "iterations": float(res.iterations), "success": float(bool(res.success))}
                if not res.success:
                    self.counters["solves_failed"] += 1
                    self._warn_throttled("fail", f"solve at t={stamp * 1e-9:.3f} s not successful: {res.message}")
            except Exception as exc:  # noqa: BLE001 - never leave the simulator without an answer
                u = self.u_safe
                self.counters["solver_errors"] += 1
                self._warn_throttled("error", f"solver raised {type(exc).__name__}: {exc}; sent the safe control")
                values = {"solve_time_ms": math.nan, "cost": math.nan, "iterations": 0.0, "success": 0.0}
            u = np.clip(u, self.u_low, self.u_high)
            self.cmd_pub.publish(self.schema.control_to_msg(u, stamp))
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
            }
            self.status_pub.publish(mpc_status_to_msg(values, stamp))

        def _swap(self, ready: ReadyModel) -> None:
            self.controller.set_model(ready.loaded.model)
            old, self.model_version, self.model_path = self.model_version, ready.version, str(ready.path)
            self.counters["swaps"] += 1
            self.get_logger().info(f"model version {old} -> {ready.version} ({ready.path.name})")

        # ---------------------------------------------------------------------------- telemetry
        def _reject(self, reason: str, text: str) -> None:
            self.counters[f"rejected/{reason}"] += 1
            self._warn_throttled(f"rejected/{reason}", f"dropped a message ({reason}): {text}")

        def _warn_throttled(self, key: str, text: str, period: float = 5.0) -> None:
            now = time.monotonic()
            if now - self._last_warn.get(key, -math.inf) >= period:
                self._last_warn[key] = now
                n = self.counters.get(key, 0)
                self.get_logger().warning(text + (f" (x{n} so far)" if n > 1 else ""))

        def diagnostic_values(self) -> dict[str, Any]:
            stats = self.watcher.stats()
            values: dict[str, Any] = {k: v for k, v in sorted(self.counters.items())}
            values["model_version"] = self.model_version
            values["model_path"] = self.model_path
            values["checkpoints_loaded"] = stats["loaded"]
            values["checkpoints_refused"] = stats["refused"]
            for r in REFUSAL_REASONS:
                values[f"checkpoints_refused/{r}"] = stats[f"refused/{r}"]
            values["last_refusal"] = stats["last_refusal"]
            values["checkpoints_gated"] = stats["gated"]
            values["last_gated"] = stats["last_gated"]
            values["max_step_ms_during_swap"] = round(self.step_ms_max_swap, 3)
            return values

        def _publish_diagnostics(self) -> None:
            values = self.diagnostic_values()
            refused = values["checkpoints_refused"]
            level = WARN if refused or self.counters["solver_errors"] else OK
            message = (f"model version {self.model_version}; {values['solves']} solves" if "solves" in values
                       else f"model version {self.model_version}; waiting for states")
            if refused:
                message += f"; {refused} checkpoint(s) refused, last: {values['last_refusal']}"
            entry = DiagnosticEntry(self.get_fully_qualified_name(), level, message, values)
            self.diag_pub.publish(diagnostics_to_msg([entry], self.get_clock().now().nanoseconds))

        def destroy_node(self) -> None:
            self.watcher.stop()
            super().destroy_node()

    return MPCNode


def _msg_class(type_name: str) -> Any:
    from msg_schemas import RCLPY

    return RCLPY.cls(type_name)


# ---------------------------------------------------------------------------------------------- main
def create_node() -> Any:
    """Create the MPC node (``rclpy.init`` must have been called with ``args``).

    The node lives in ``/<system>`` unless the command line remaps ``__ns``: a probe node reads ``system``
    first, because the namespace must be known when the node is created.
    """
    from rclpy.node import Node

    probe = Node("mpc")
    system = probe.declare_parameter("system", "friction").value
    remapped = probe.get_namespace() != "/"
    probe.destroy_node()
    get_system(system)  # a clear error for an unknown name
    cls = _build_node_class()
    return cls(system, None if remapped else f"/{system}")




@process_main
def main(argv: Sequence[str] | None = None) -> int:
    """``mpc [--ros-args ...]``: run the node until SIGINT / SIGTERM (exit 0); bad parameters exit 2."""
    args = full_argv("mpc", argv)
    if wants_help(args):
        print(__doc__)
        print("usage: mpc --ros-args [-p system:=quadrotor] [-p mode:=lockstep] [--params-file config/mpc.yaml] "
              "[-r __ns:=/quadrotor]")
        return 0
    stop = catch_stop_signals()
    import rclpy
    import torch

    torch.set_num_threads(1)  # checkpoints are tiny; extra threads would only contend for the cores
    init_rclpy(args)
    node = None
    try:
        try:
            node = create_node()
        except (ValueError, TypeError) as exc:
            rclpy.logging.get_logger("mpc").fatal(f"configuration error: {exc}")
            return USAGE_ERROR
        spin_until_stopped(node, stop)
        return 0
    finally:
        shutdown(node)


if __name__ == "__main__":
    raise SystemExit(main())
