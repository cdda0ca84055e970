"""How a simulator node is described: its parameters (:class:`SimBinding`).

Each simulator module (``friction_sim``, ``quadrotor_sim``, ``paddle_ball_sim``) defines one ``BINDING``; the
generic rclpy node in :mod:`sim_nodes.sim_node` runs it, with the ROS-free simulator core that the system's
registry entry builds (``SystemEntry.simulator``) from the parameter values.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from saml_ros.core.data.plausibility import parse_overrides
from saml_ros.core.params import LIVE, Param, Problems, read_params
from saml_ros.core.systems import default_params
from saml_ros.core.worlds.sim_core import LOCKSTEP_T0_NS, MODES, SimConfig

#: parameters of every simulator node (a binding may override a default by listing the same name)
COMMON_PARAMS: tuple[Param, ...] = (
    Param("mode", "realtime", "realtime: step every 1 / rate_hz wall seconds with the newest command | "
                              "lockstep: publish x_k, wait for the cmd stamped t_k, step (as fast as the slowest "
                              "participant)"),
    Param("rate_hz", 10.0, "realtime step rate (Hz, wall clock)"),
    Param("cmd_timeout", 0.5, "a command is held this long (s; wall clock in realtime, simulated time in "
                              "lockstep), then the safe default applies and is counted (0 = hold forever)"),
    Param("lockstep_timeout", 1.0, "lockstep: wall seconds to wait for the cmd answering a state before "
                                   "applying the held command / safe default (counted as a miss)"),
    Param("max_speed", 0.0, "lockstep: at most this many simulated seconds per wall second (0 = as fast as the "
                            "slowest participant); keeps the CPU share of processes beside the loop, such as "
                            "learners, per simulated second independent of the controller's speed", when=LIVE),
    Param("max_sim_time", 0.0, "simulated seconds after which the node exits (0 = run forever)"),
    Param("episode_steps", 0, "steps per episode, then a new start state (0 = one endless episode)", when=LIVE),
    Param("initial_state", [], "start state of every episode (the system's state vector); empty = drawn by "
                               "the start sampler"),
    Param("seed", 0, "seed of the start sampler (negative: fresh entropy)"),
    Param("publish_clock", True, "publish simulated time on /clock (lockstep runs: other nodes set "
                                 "use_sim_time); turn off when several simulators share a ROS domain"),
    Param("start_delay", 1.0, "wall seconds between start-up and the first state (lets discovery finish)"),
    Param("wait_for_controller", True, "lockstep: also wait until the cmd topic has a publisher and state "
                                       "has a subscriber before the first state"),
    Param("min_state_subscribers", 1, "lockstep with wait_for_controller: matched state subscriptions to wait "
                                      "for before the first state (e.g. MPC + learner + recorder = 3)"),
    Param("min_applied_cmd_subscribers", 0, "lockstep with wait_for_controller: matched applied_cmd "
                                            "subscriptions to wait for (learner, recorder) before the first state"),
    Param("cmd_reject_margin", 0.5, "commands further outside the control bounds than this fraction of the "
                                    "bounds' width are rejected; closer ones are clipped"),
    Param("diagnostics_period", 1.0, "seconds between /diagnostics messages (wall clock)", when=LIVE),
    Param("executor", "events", "rclpy executor the node spins on: events (rclpy.experimental.EventsExecutor, "
                                "faster per lockstep step, docs/performance.md) | single (SingleThreadedExecutor); "
                                "the environment variable SAML_EXECUTOR overrides it"),
    Param("plausible_bounds", "", "overrides of the system's plausible state ranges as a YAML mapping, e.g. "
                                  "'{x.pz: [-1.0, 2000.0]}'; a time-stepped simulator whose state leaves them "
                                  "restarts the episode (counted as diverged)"),
)


@dataclass(frozen=True)
class SimBinding:
    """The parameters of one system's simulator node.

    Attributes:
        system: registry name (also the default namespace ``/<system>``).
        node_name: node (and executable) name, e.g. ``"quadrotor_sim"``.
        params: system-specific parameters, and overridden defaults of :data:`COMMON_PARAMS`.
        system_params: constructor parameters of the system exposed as ``system.<name>``, with descriptions.
    """

    system: str
    node_name: str
    params: tuple[Param, ...]
    system_params: tuple[tuple[str, str], ...]

    def all_params(self) -> list[Param]:
        """Common parameters (with this binding's defaults) followed by the system-specific ones."""
        own = {p.name: p for p in self.params}
        out = [own.pop(p.name, p) for p in COMMON_PARAMS]
        return out + list(own.values())

    def param_table(self) -> list[Param]:
        """:meth:`all_params` and the system's constructor parameters as ``system.<name>`` (their defaults)."""
        defaults = default_params(self.system)
        return self.all_params() + [Param(f"system.{name}", as_param_default(defaults[name]), text)
                                    for name, text in self.system_params]

    def usage(self) -> str:
        """The node's ``--help`` text: how to run it and every parameter with its default."""
        lines = [f"usage: {self.node_name} [--ros-args [-p NAME:=VALUE] [--params-file config/{self.node_name}"
                 f".yaml] [-r __ns:=/{self.system}]]", "", "parameters:"]
        lines += [f"  {p.name} (default {p.default!r}): {p.description}" for p in self.param_table()]
        return "\n".join(lines)


def as_param_default(value: Any) -> Any:
    """A system constructor default as a ROS parameter value (tuples -> lists, nested lists flattened)."""
    if isinstance(value, tuple | list):
        flat: list[float] = []
        for v in value:
            flat.extend(as_param_default(v) if isinstance(v, tuple | list) else [float(v)])
        return flat
    return float(value) if isinstance(value, int) and not isinstance(value, bool) else value


def check_params(p: dict[str, Any], problems: Problems | None = None) -> None:
    """Check the ranges of the converted values ``p``: each problem recorded in ``problems``, or without it
    ``ParamErrors`` naming every parameter out of range."""
    from saml_ros.nodes.runtime import EXECUTORS

    own = Problems() if problems is None else problems
    check = own.check
    check(p["executor"] in EXECUTORS, "executor", f"one of {list(EXECUTORS)}", p["executor"])
    check(p["mode"] in MODES, "mode", f"one of {list(MODES)}", p["mode"])
    for name in ("rate_hz", "diagnostics_period", "lockstep_timeout"):
        check(p[name] > 0, name, "> 0", p[name])
    for name in ("start_delay", "cmd_timeout", "max_sim_time", "episode_steps", "cmd_reject_margin"):
        check(p[name] >= 0, name, ">= 0", p[name])
    check(math.isfinite(p["max_speed"]) and p["max_speed"] >= 0, "max_speed", ">= 0 (0 = no limit)", p["max_speed"])
    with own.capture("plausible_bounds", prefix="parameter 'plausible_bounds': "):
        parse_overrides(p["plausible_bounds"])
    if problems is None:
        own.raise_if_any()


def read_sim_params(binding: SimBinding, values: dict[str, Any]) -> dict[str, Any]:
    """The simulator node's parameter values ``values`` (by name) converted to their types and checked
    (:func:`check_params`); ``ParamErrors`` naming every bad one."""
    problems = Problems()
    p = read_params(binding.param_table(), values, problems)
    check_params(p, problems)
    problems.raise_if_any()
    return p


def config_from_params(p: dict[str, Any], t0_ns: int = LOCKSTEP_T0_NS) -> SimConfig:
    """The :class:`SimConfig` of the node parameters ``p`` (names of :data:`COMMON_PARAMS`)."""
    return SimConfig(
        mode=p["mode"],
        cmd_timeout=p["cmd_timeout"],
        lockstep_timeout=p["lockstep_timeout"],
        max_sim_time=p["max_sim_time"],
        episode_steps=p["episode_steps"],
        initial_state=tuple(p["initial_state"]),
        seed=p["seed"],
        reject_margin=p["cmd_reject_margin"],
        t0_ns=t0_ns,
        plausible_bounds=p["plausible_bounds"],
    )
