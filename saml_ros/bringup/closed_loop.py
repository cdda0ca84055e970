"""One closed loop (:func:`run`): the run directory, the children in order, the monitor, the stop and the result.

The ROS layer (:mod:`saml_ros.bringup.monitor`, rclpy) is imported only when a loop runs, so bringup's
ROS-free parts (configuration, supervisor, results) import without rclpy.
"""

from __future__ import annotations

import importlib.util
import os
import signal
import sys
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from types import FrameType
from typing import TYPE_CHECKING, Any

import yaml

from msg_schemas.base import full_topic
from saml_ros.bringup.config import node_params, ros_params_file
from saml_ros.bringup.results import BringupResult, goal_position
from saml_ros.bringup.supervisor import Child, ProcessGroup, child_env, node_argv
from saml_ros.core.systems import get_entry

if TYPE_CHECKING:
    from saml_ros.bringup.monitor import Monitor

#: ROS node name of each child (bringup waits for them to appear before it stops them); the simulator's is its
#: registry entry's ``sim_node``
NODE_NAMES = {"learner": "learner", "mpc": "mpc", "record": "record", "learner_ua": "learner_ua"}
#: ROS arguments of the optional Uniformly Accurate learner: its own node name and telemetry / checkpoint topics
UA_REMAPS = ("-r", "__node:=learner_ua", "-r", "learner/model_error:=learner_ua/model_error",
             "-r", "learner/checkpoint:=learner_ua/checkpoint")


@dataclass
class RunOptions:
    """How :func:`run` runs (beyond the config)."""

    run_dir: Path | None = None
    record: Path | None = None
    domain_id: int | None = None
    progress_period: float = 5.0
    startup_timeout: float = 90.0
    quiet: bool = False
    learner: bool = True
    print_fn: Callable[[str], None] = print


def make_run_dir(system: str, run_dir: Path | None) -> Path:
    """``run_dir`` (created), or a fresh ``runs/bringup-<system>-<date-time>-<pid>``."""
    if run_dir is None:
        run_dir = Path("runs") / f"bringup-{system}-{time.strftime('%Y%m%d-%H%M%S')}-{os.getpid()}"
    run_dir = run_dir.resolve()
    run_dir.mkdir(parents=True, exist_ok=True)
    return run_dir


def write_run_files(config: Mapping[str, Any], run_dir: Path) -> tuple[dict[str, dict[str, Any]], dict[str, Path]]:
    """``checkpoints/``, one ROS parameter file per node (``params/<node>.yaml``) and ``bringup.yaml`` in
    ``run_dir``; returns each node's parameters and parameter file."""
    (run_dir / "checkpoints").mkdir(exist_ok=True)
    params = node_params(config, run_dir)
    files = {}
    for name, values in params.items():
        path = run_dir / "params" / f"{name}.yaml"
        path.parent.mkdir(exist_ok=True)
        path.write_text(ros_params_file(values))
        files[name] = path
    (run_dir / "bringup.yaml").write_text(yaml.safe_dump(dict(config), sort_keys=False))
    return params, files


class _Loop:
    """The state of one :func:`run`: children, monitor, stop reason."""

    def __init__(self, config: Mapping[str, Any], opts: RunOptions, run_dir: Path, files: dict[str, Path]) -> None:
        self.config, self.opts, self.files = config, opts, files
        self.system = str(config["system"])
        self.entry = get_entry(self.system)
        self.namespace = f"/{self.system}"
        self.env = child_env(opts.domain_id)
        self.logs = run_dir / "logs"
        self.procs = ProcessGroup()
        self.stop: dict[str, str] = {}
        self.say: Callable[[str], None] = (lambda s: None) if opts.quiet else opts.print_fn
        self.lockstep = config["sim"].get("mode", "lockstep") == "lockstep"
        #: a robot from a system file: its own processes instead of a simulator
        self.robot = bool(config.get("system_file"))
        self.state_topic = self.entry.schema().state_topic if self.robot else "state"

    def start_consumers(self, run_dir: Path) -> list[Child]:
        """Learner (unless ``--no-learner``), MPC and the recorder (``--record``)."""
        procs, ns, env, logs = self.procs, self.namespace, self.env, self.logs
        started = []
        if self.opts.learner:
            started.append(procs.start("learner", node_argv("learner", ns, self.files["learner"]), env,
                                       logs / "learner.log"))
            if "learner_ua" in self.files:
                (run_dir / "checkpoints_ua").mkdir(exist_ok=True)
                started.append(procs.start("learner_ua", node_argv("learner", ns, self.files["learner_ua"])
                                           + list(UA_REMAPS), env, logs / "learner_ua.log"))
        started.append(procs.start("mpc", node_argv("mpc", ns, self.files["mpc"]), env, logs / "mpc.log"))
        record = self.opts.record or self.config.get("record")
        if record:
            if importlib.util.find_spec("saml_ros.bags.record") is None:
                self.say("[bringup] --record: saml_ros.bags.record is not available; not recording")
            else:
                rec_args = ["--system", self.system, "-o", str(Path(record).resolve())]
                if self.robot:  # a robot's own topics (the recorder does not read system files)
                    schema = self.entry.schema()
                    rec_args = ["--topics", *(full_topic(ns, t) for t in (schema.state_topic, schema.cmd_topic)),
                                "-o", str(Path(record).resolve())]
                if self.lockstep:
                    rec_args.append("--use-sim-time")
                started.append(procs.start("record", [sys.executable, "-m", "saml_ros.executables", "record",
                                                      *rec_args], env, logs / "record.log"))
        self.say(f"[bringup] {self.system}: run dir {run_dir}; started "
                 + ", ".join(f"{c.name} (pid {c.pid})" for c in started)
                 + f"; ROS_DOMAIN_ID={env.get('ROS_DOMAIN_ID', '0 (default)')}")
        return started

    def activate_consumers(self, monitor: Monitor, started: list[Child]) -> None:
        """Configure, then activate the managed nodes (learner, MPC) through their lifecycle services."""
        from saml_ros.nodes.lifecycle_client import drive

        managed = [f"{self.namespace}/{NODE_NAMES[c.name]}" for c in started
                   if c.name in ("learner", "learner_ua", "mpc")]
        t0 = time.monotonic()
        errors = drive(monitor.node, lambda t: monitor.executor.spin_once(timeout_sec=t), managed,
                       ["configure", "activate"], self.opts.startup_timeout,
                       cancelled=lambda: "reason" in self.stop or bool(self.procs.exited()))
        if self.procs.exited():
            self.stop.setdefault("reason", f"child {self.procs.exited()[0].name} exited during start-up")
        elif errors:
            self.stop.setdefault("reason", "lifecycle: " + "; ".join(errors))
        else:
            self.say(f"[bringup] configured and activated {', '.join(managed)} in {time.monotonic() - t0:.1f} s")

    def start_robot(self, t_wall0: float) -> None:
        """A robot from a system file: start its own processes (``robot`` commands) in its namespace."""
        import shlex

        for i, cmd in enumerate(self.config.get("robot") or []):
            argv = shlex.split(cmd) + ["--ros-args", "-r", f"__ns:={self.namespace}"]
            if argv[0] in ("python", "python3"):  # this interpreter (the venv's), as for saml_ros's own nodes
                argv[0] = sys.executable
            child = self.procs.start(f"robot{i}", argv, self.env, self.logs / f"robot{i}.log")
            self.say(f"[bringup] started the robot's process {cmd!r} (pid {child.pid})")
        sim_time = float(self.config["sim_time"])
        self.say(f"[bringup] consumers ready after {time.monotonic() - t_wall0:.1f} s; running "
                 + (f"for {sim_time:g} s of the robot's state time" if sim_time > 0 else "until Ctrl-C"))

    def start_simulator(self, monitor: Monitor, started: list[Child], t_wall0: float) -> None:
        """Wait until the consumers listen (no state is answered by nobody), then start the simulator."""
        n_learners = (1 + ("learner_ua" in self.files)) if self.opts.learner else 0
        want = 1 + n_learners + 1  # mpc, learners, this monitor
        deadline = time.monotonic() + self.opts.startup_timeout
        while "reason" not in self.stop and monitor.subscribers("state") < want:
            monitor.executor.spin_once(timeout_sec=0.1)
            if self.procs.exited():
                self.stop.setdefault("reason", f"child {self.procs.exited()[0].name} exited during start-up")
            elif time.monotonic() > deadline:
                self.stop.setdefault("reason", f"start-up timeout ({self.opts.startup_timeout:.0f} s)")
        if "reason" in self.stop:
            return
        # the recorder subscribes only once the simulator's topics exist, so the simulator itself waits
        # (lockstep) until every consumer is matched: no transition is lost to a late subscriber
        recording = any(c.name == "record" for c in started)
        waits = ["-p", f"min_state_subscribers:={want + (1 if recording else 0)}",
                 "-p", f"min_applied_cmd_subscribers:={n_learners + (1 if recording else 0)}"]
        # the simulator ends the run itself at sim_time: stopping it from here would simulate (and record)
        # whatever it steps while the stop reaches it, seconds more at tens of times real time
        sim_time = float(self.config["sim_time"])
        if sim_time > 0:
            waits += ["-p", f"max_sim_time:={sim_time!r}"]
        sim = self.procs.start("sim", node_argv(self.entry.sim_node, self.namespace, self.files["sim"]) + waits,
                               self.env, self.logs / "sim.log")
        self.say(f"[bringup] consumers ready after {time.monotonic() - t_wall0:.1f} s; started {self.entry.sim_node} "
                 f"(pid {sim.pid}); running for {float(self.config['sim_time']):g} s of simulated time")

    def spin(self, monitor: Monitor, result: BringupResult) -> float:
        """Spin the monitor until a stop reason; the wall seconds since the first state (0 if none came)."""
        t_sim0: float | None = None
        next_progress = time.monotonic() + self.opts.progress_period
        sim_time = float(self.config["sim_time"])
        while "reason" not in self.stop:
            monitor.executor.spin_once(timeout_sec=0.05)
            if t_sim0 is None and result.states:
                t_sim0 = time.monotonic()  # the loop's speed counts from its first state
            if sim_time > 0 and result.sim_time >= sim_time:
                self.stop["reason"] = "sim_time"
            for c in self.procs.exited():
                if c.name.startswith("robot") and c.proc.returncode == 0:
                    self.stop.setdefault("reason", f"the robot's process {c.name} ended")
                if c.name == "sim" and sim_time > 0 and c.proc.returncode == 0:
                    self.stop.setdefault("reason", "sim_time")  # it exits 0 only at max_sim_time (or signalled)
                self.stop.setdefault("reason", f"child {c.name} exited (code {c.proc.returncode})")
            now = time.monotonic()
            if now >= next_progress:
                self.say(monitor.progress())
                next_progress = now + self.opts.progress_period
        return time.monotonic() - t_sim0 if t_sim0 is not None else 0.0

    def stop_children(self, monitor: Monitor | None) -> dict[str, int]:
        """Stop every child (escalating); their exit codes."""
        if monitor is not None:
            # SIGINT before a child installed its handlers (still importing) would kill it with a traceback:
            # give children that are still starting a moment to show up in the graph first
            names = {**NODE_NAMES, "sim": self.entry.sim_node}
            monitor.wait_nodes_up({c.name: names.get(c.name, c.name) for c in self.procs.children
                                   if c.proc.poll() is None and not c.name.startswith("robot")}, timeout=30.0)
        return self.procs.stop()


def run(config: Mapping[str, Any], opts: RunOptions) -> BringupResult:
    """Run one closed loop as described in :mod:`saml_ros.bringup`; returns what it observed."""
    import rclpy
    from rclpy.signals import SignalHandlerOptions

    from saml_ros.bringup.monitor import Monitor

    system = str(config["system"])
    get_entry(system)
    run_dir = make_run_dir(system, opts.run_dir)
    params, files = write_run_files(config, run_dir)
    loop = _Loop(config, opts, run_dir, files)
    # our own node must be on the same domain / discovery range as the children
    for key in ("ROS_DOMAIN_ID", "ROS_AUTOMATIC_DISCOVERY_RANGE"):
        if key in loop.env:
            os.environ[key] = loop.env[key]
    result = BringupResult(system, run_dir)

    def on_signal(signum: int, frame: FrameType | None) -> None:
        loop.stop.setdefault("reason", f"signal {signal.Signals(signum).name}")

    old_handlers = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)}
    rclpy.init(args=["bringup"], signal_handler_options=SignalHandlerOptions.NO)
    monitor = None
    t_wall0 = time.monotonic()
    try:
        monitor = Monitor(system, loop.namespace, goal_position(system, params["mpc"]), result)
        started = loop.start_consumers(run_dir)
        loop.activate_consumers(monitor, started)
        if "reason" not in loop.stop:
            if loop.robot:
                loop.start_robot(t_wall0)
            else:
                loop.start_simulator(monitor, started, t_wall0)
        result.wall_time = loop.spin(monitor, result)
        result.stop_reason = loop.stop["reason"]
        loop.say(f"[bringup] stopping ({result.stop_reason}) ...")
    finally:
        result.returncodes = loop.stop_children(monitor)
        if monitor is not None:
            monitor.node.destroy_node()
        rclpy.try_shutdown()
        for s, h in old_handlers.items():
            signal.signal(s, h)
    failed = {k: v for k, v in result.returncodes.items() if v != 0}
    result.stop_reason = result.stop_reason or loop.stop.get("reason", "error")
    result.ok = not failed and (result.stop_reason == "sim_time" or result.stop_reason.startswith("signal"))
    if failed or not result.ok:
        for c in loop.procs.children:
            if c.proc.returncode != 0 or result.stop_reason.startswith("child"):
                opts.print_fn(f"[bringup] --- last lines of {c.log_path} (exit code {c.proc.returncode}) ---\n"
                              f"{c.tail()}")
    return result
