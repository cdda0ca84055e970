"""The generic simulator node: a thin rclpy wrapper around a :class:`~saml_ros.core.worlds.sim_core.SimCore`.

One class runs all three simulators; a :class:`~sim_nodes.binding.SimBinding` (in ``friction_sim.py``,
``quadrotor_sim.py``, ``paddle_ball_sim.py``) names the system and its extra parameters; the system's registry
entry builds the core (``SystemEntry.simulator``).

* Topics (``msg_schemas``, relative to the namespace, default ``/<system>``): publishes ``state``,
  ``applied_cmd`` (and ``post_impact`` / ``flight`` for the paddle ball), subscribes ``cmd``; ``/clock``
  (``publish_clock``) and ``/diagnostics`` (counters, every ``diagnostics_period`` s).
* Service ``~/reset`` (std_srvs/Trigger): the next step starts a new episode.
* Every timer runs on the steady clock: the simulator is the clock source, so ``use_sim_time`` never
  drives it. Realtime stamps start at the wall time of the first state; lockstep stamps at 1 s.
* Bad commands are rejected (log line, throttled; counter ``rejected/<reason>``), never fatal.
  SIGINT / SIGTERM (any number of them), or ``max_sim_time`` reached, end the node with exit code 0; bad
  parameters with 2.
"""

from __future__ import annotations

import dataclasses
import sys
import time
from collections.abc import Sequence
from typing import Any

import rclpy
import rclpy.parameter
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.task import Future
from std_srvs.srv import Trigger

from msg_schemas import DATA_QOS, RCLPY, SchemaError
from msg_schemas.cdr import CdrCodec
from msg_schemas.telemetry import (
    OK,
    WARN,
    DiagnosticEntry,
    diagnostics_to_msg,
)
from saml_ros.core.systems import get_entry
from saml_ros.core.worlds.pacing import Pacer
from saml_ros.core.worlds.sim_core import (
    LOCKSTEP_T0_NS,
    Output,
)
from saml_ros.nodes.ros_params import ParamGuard, start_params
from saml_ros.nodes.runtime import (
    catch_stop_signals,
    exit_process,
    init_rclpy,
    shutdown,
    single_torch_thread,
    spin_until_stopped,
)
from sim_nodes.binding import SimBinding, config_from_params, read_sim_params
from sim_nodes.emitters import make_emitters

#: exit code for invalid parameters (as argparse's usage errors)
USAGE_ERROR = 2
#: wall seconds the node keeps spinning after max_sim_time so reliable messages reach their readers
FINISH_GRACE_S = 0.5
#: counters whose increase turns the diagnostics level to WARN
_WARN_PREFIXES = ("rejected/", "lockstep_misses", "cmd_timeouts", "diverged", "failures")


class SimNode(Node):
    """See the module docstring."""

    def __init__(self, binding: SimBinding) -> None:
        super().__init__(binding.node_name, namespace=f"/{binding.system}")
        self.binding = binding
        if self.get_parameter("use_sim_time").value:
            # the simulator is the clock source: following its own /clock would only add work per step
            self.get_logger().warning("use_sim_time is ignored: the simulator publishes /clock itself")
            self.set_parameters([rclpy.parameter.Parameter("use_sim_time", value=False)])
        p = self._declare_parameters()
        self.params = p
        entry = get_entry(binding.system)
        self.system = entry.make_system(**{k[len("system."):]: v for k, v in p.items() if k.startswith("system.")})
        self.schema = entry.schema()
        self.core = entry.simulator(self.system, config_from_params(p), p)
        self.lockstep = self.core.config.lockstep
        self._pacer = Pacer(p["max_speed"] if self.lockstep else 0.0)
        self.done_future = Future()
        self._finish_at: float | None = None
        self._started_wall = time.monotonic()
        self._warned_at: dict[str, float] = {}
        self._last_diag: dict[str, Any] = {}
        self._last_diag_time = time.monotonic()

        emitters = make_emitters(self, self.schema, bool(p["publish_clock"]))
        self._emit = emitters.emit
        self.state_pub, self.applied_pub, self.diag_pub = emitters.state_pub, emitters.applied_pub, emitters.diag_pub
        # the cmd subscription keeps rclpy's QoS-event handlers (a best-effort cmd publisher is reported)
        # raw: the CDR bytes are read without a message object (msg_schemas.cdr; malformed ones as before)
        self._cmd_cdr = CdrCodec(self.schema.control)
        self.cmd_sub = self.create_subscription(RCLPY.cls(self.schema.control.msg_type), self.schema.cmd_topic,
                                                self._on_cmd, DATA_QOS.to_rclpy(), raw=True)
        self.create_service(Trigger, "~/reset", self._on_reset)

        steady = Clock(clock_type=ClockType.STEADY_TIME)
        self._start_timer = self.create_timer(0.05, self._try_start, clock=steady)
        if not self.lockstep:
            self.create_timer(1.0 / p["rate_hz"], self._on_tick, clock=steady)
        # lockstep deadline and end-of-run checks; few timers, as each one costs time in every executor wait
        self.create_timer(min(0.05, p["lockstep_timeout"] / 4), self._on_housekeeping, clock=steady)
        self._diag_timer = self.create_timer(p["diagnostics_period"], self._publish_diagnostics, clock=steady)
        self.params_guard = ParamGuard(self, binding.param_table(), self._check_values, self._apply_live)
        self.get_logger().info(
            f"{binding.system} simulator, {p['mode']}"
            + (f" at {p['rate_hz']:g} Hz" if not self.lockstep else f" (lockstep_timeout {p['lockstep_timeout']} s"
               + (f", at most {p['max_speed']:g}x real time" if p["max_speed"] > 0 else "") + ")")
            + f", episode_steps {p['episode_steps']}, max_sim_time {p['max_sim_time']} s, seed {p['seed']}"
        )

    # ---------------------------------------------------------------------------------------- parameters
    def _declare_parameters(self) -> dict[str, Any]:
        """Declare the binding's parameters (dynamically typed: each value is converted by the core), check them
        and what the command line gives; ``ParamErrors`` naming every problem."""
        return read_sim_params(self.binding, start_params(self, self.binding.param_table(), self._check_values,
                                                          dynamic_typing=True))

    def _check_values(self, values: dict[str, Any]) -> dict[str, Any]:
        return read_sim_params(self.binding, values)

    def _apply_live(self, live: dict[str, Any]) -> None:
        """Parameters that apply at once: ``episode_steps`` (from the current episode on), ``max_speed`` (lockstep)
        and ``diagnostics_period``."""
        self.params.update(live)
        if "episode_steps" in live:
            self.core.config = dataclasses.replace(self.core.config, episode_steps=live["episode_steps"])
        if "max_speed" in live and self.lockstep:
            self._pacer.set_speed(live["max_speed"])
        if "diagnostics_period" in live:
            self._diag_timer.timer_period_ns = int(live["diagnostics_period"] * 1e9)

    # ---------------------------------------------------------------------------------------- publishing
    def _publish(self, outputs: list[Output]) -> None:
        for kind, vec, stamp in outputs:
            self._emit[kind](vec, stamp)
        if self.core.done and self._finish_at is None:
            self._finish_at = time.monotonic() + FINISH_GRACE_S
            self._publish_diagnostics()  # the final counters, delivered during the grace period
            self.get_logger().info(f"max_sim_time {self.params['max_sim_time']} s reached: finishing")

    def _warn_throttled(self, key: str, text: str, period: float = 5.0) -> None:
        now = time.monotonic()
        if now - self._warned_at.get(key, -1e9) >= period:
            self._warned_at[key] = now
            self.get_logger().warning(text)

    # ---------------------------------------------------------------------------------------- callbacks
    def _try_start(self) -> None:
        if time.monotonic() - self._started_wall < self.params["start_delay"]:
            return
        if self.lockstep and self.params["wait_for_controller"]:
            cmd_publishers = self.count_publishers(self.cmd_sub.topic_name)
            n_state = self.state_pub.get_subscription_count()
            n_applied = self.applied_pub.get_subscription_count()
            want_state = max(1, int(self.params["min_state_subscribers"]))
            want_applied = int(self.params["min_applied_cmd_subscribers"])
            if cmd_publishers == 0 or n_state < want_state or n_applied < want_applied:
                self._warn_throttled("waiting", f"lockstep: waiting for a controller and subscribers before the "
                                                f"first state (cmd publishers {cmd_publishers}/1, state "
                                                f"subscribers {n_state}/{want_state}, applied_cmd subscribers "
                                                f"{n_applied}/{want_applied})")
                return
        self._start_timer.cancel()
        self.destroy_timer(self._start_timer)
        t0 = LOCKSTEP_T0_NS if self.lockstep else time.time_ns()
        self._publish(self.core.begin(time.monotonic_ns(), t0))

    def _on_cmd(self, msg: Any) -> None:
        now = time.monotonic_ns()
        try:
            u, stamp = self._cmd_cdr.decode(msg, self.cmd_sub.topic_name)
        except SchemaError as exc:
            self.core.reject(exc.reason, str(exc))
            self._warn_throttled("reject", f"rejected cmd: {exc}")
            return
        # lockstep speed limit (max_speed), for the answer the simulator waits for only: a short sleep (nothing
        # else is due in lockstep while the state is answered); a wrong stamp is rejected at once
        wait = self._pacer.wait_s(stamp, now) if stamp == self.core.awaiting else 0.0
        if wait > 0.0:
            time.sleep(min(wait, 1.0))
            now = time.monotonic_ns()
        rejected_before = self.core.n_rejections
        self._publish(self.core.on_cmd(u, stamp, now))
        if self.core.n_rejections != rejected_before:
            self._warn_throttled("reject", f"rejected cmd: {self.core.last_rejection}")

    def _on_tick(self) -> None:
        self._publish(self.core.tick(time.monotonic_ns()))

    def _on_housekeeping(self) -> None:
        outputs = self.core.poll(time.monotonic_ns())
        if outputs:
            self._warn_throttled("miss", f"lockstep: no valid cmd within {self.params['lockstep_timeout']} s; "
                                         "applied the held command / safe default")
            self._publish(outputs)
        if self._finish_at is not None and time.monotonic() >= self._finish_at and not self.done_future.done():
            self.done_future.set_result(True)

    def _on_reset(self, request: Any, response: Any) -> Any:
        response.message = self.core.request_reset()
        response.success = True
        self.get_logger().info(response.message)
        return response

    def _publish_diagnostics(self) -> None:
        values = self.core.diagnostics()
        now = time.monotonic()
        steps = int(values.get("steps", 0))
        rate = (steps - int(self._last_diag.get("steps", 0))) / max(now - self._last_diag_time, 1e-9)
        values["steps_per_second"] = f"{rate:.1f}"
        values["parameter_changes_refused"] = self.params_guard.refused
        if self._pacer.max_speed > 0:
            values["max_speed_waited_s"] = f"{self._pacer.waited_s:.2f}"
        warn = any(k.startswith(_WARN_PREFIXES) and values[k] != self._last_diag.get(k, 0) for k in values)
        self._last_diag, self._last_diag_time = values, now
        entry = DiagnosticEntry(
            name=self.get_fully_qualified_name(),
            level=WARN if warn else OK,
            message="commands rejected, missed or timed out since the last report" if warn else "running",
            values=values,
        )
        self.diag_pub.publish(diagnostics_to_msg([entry], self.core.sim_now_ns()))


def run(binding: SimBinding, argv: Sequence[str] | None = None) -> int:
    """Run the simulator node of ``binding`` until SIGINT / SIGTERM or ``max_sim_time`` (exit code 0).

    ``argv`` excludes the program name (default ``sys.argv[1:]``); ROS arguments follow ``--ros-args``. Signals
    only set a stop flag (:mod:`saml_ros.nodes.runtime`): a callback is never interrupted, however many arrive.
    Run as the process entry (``argv`` None) the process ends right after rclpy's shutdown
    (:func:`~saml_ros.nodes.runtime.exit_process`).
    """
    stop = catch_stop_signals()
    args = [binding.node_name, *(sys.argv[1:] if argv is None else argv)]
    ros_start = args.index("--ros-args") if "--ros-args" in args else len(args)
    if any(a in ("-h", "--help") for a in args[1:ros_start]):
        print(binding.usage())
        return 0
    # one small state per step: extra torch threads only contend for the cores (the built-in simulators step
    # numpy or MuJoCo and never import torch; a world that steps true_step in torch does)
    single_torch_thread()
    init_rclpy(args)
    node: SimNode | None = None
    code = 0
    try:
        try:
            node = SimNode(binding)
        except ValueError as exc:
            print(f"{binding.node_name}: {exc}", file=sys.stderr)
            code = USAGE_ERROR
        else:
            done = node.done_future
            spin_until_stopped(node, stop, lambda: not done.done(), executor=node.params["executor"])
    finally:
        shutdown(node)
    if argv is None:
        exit_process(code)
    return code
