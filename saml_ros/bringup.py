"""``ros2 run saml_ros bringup``: start a whole closed loop (simulator, learner, MPC) as separate processes.

    bringup --system quadrotor --sim-time 60                 # lockstep, defaults of config/bringup_quadrotor.yaml
    bringup --config config/bringup_quadrotor.yaml --set mpc.solver=slsqp --set sim.episode_steps=60
    bringup --system friction --record runs/bag --domain-id 17

What it does:

1. makes a private run directory (``--run-dir``, default ``runs/bringup-<system>-<date>-<pid>``) holding the
   learner's checkpoints, one ROS parameter file per node (``params/<node>.yaml``) and each child's log
   (``logs/<node>.log``);
2. starts the learner and the MPC (and ``record`` with ``--record DIR``) in the system namespace
   ``/<system>``, each in its own process group, waits until they subscribe to ``state``, then starts the
   simulator (lockstep by default, so the loop runs as fast as its slowest participant);
3. prints a progress line every ``--progress-period`` wall seconds, read from the topics (simulated time from
   the state stamps, episodes, the learner's in-region model error, the MPC's model version and solve time);
4. stops after ``--sim-time`` seconds of simulated time, on Ctrl-C (SIGINT) or SIGTERM: SIGINT to every
   child's process group, then SIGTERM, then SIGKILL for what is left (no orphans: children also get
   SIGTERM from the kernel if bringup itself dies, via ``PR_SET_PDEATHSIG``), and prints a before/after
   summary (model error, task error of the episodes flown on the base model vs the last ones).

Environment: ``ROS_DOMAIN_ID`` is respected (``--domain-id`` overrides it for this run);
``ROS_AUTOMATIC_DISCOVERY_RANGE`` defaults to ``LOCALHOST`` when unset. Children inherit both.
"""

from __future__ import annotations

import argparse
import copy
import importlib.util
import math
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import FrameType
from typing import IO, Any

import numpy as np
import yaml

from saml_ros.core.systems import get_entry, system_names

#: ROS node name of each child (bringup waits for them to appear before it stops them); the simulator's is its
#: registry entry's ``sim_node``
NODE_NAMES = {"learner": "learner", "mpc": "mpc", "record": "record"}
NODE_SECTIONS = ("sim", "learner", "mpc")


# ------------------------------------------------------------------------------------------ config
def default_config(system: str) -> dict[str, Any]:
    """A deep copy of ``system``'s default bringup configuration (its registry entry's ``bringup``)."""
    return copy.deepcopy(dict(get_entry(system).bringup))


def merge_config(base: dict[str, Any], override: Mapping[str, Any]) -> dict[str, Any]:
    """``base`` updated by ``override`` (node sections are merged key by key); unknown keys are refused."""
    out = copy.deepcopy(base)
    for key, value in override.items():
        if key in NODE_SECTIONS:
            if not isinstance(value, Mapping):
                raise ValueError(f"config section {key!r} must be a mapping of parameters, got {value!r}")
            out.setdefault(key, {}).update(copy.deepcopy(dict(value)))
        elif key in ("system", "sim_time", "record"):
            out[key] = value
        else:
            raise ValueError(f"unknown config key {key!r}; valid: system, sim_time, record, {', '.join(NODE_SECTIONS)}")
    return out


def load_config(path: Path | None, system: str | None) -> dict[str, Any]:
    """The defaults of the system (from ``--system`` or the file's ``system``), updated by the YAML file."""
    override: dict[str, Any] = {}
    if path is not None:
        data = yaml.safe_load(Path(path).read_text())
        if not isinstance(data, dict):
            raise ValueError(f"{path}: a bringup config must be a YAML mapping")
        override = data
    name = system or override.get("system") or "quadrotor"
    if system and override.get("system") not in (None, system):
        raise ValueError(f"--system {system} contradicts the config's system {override['system']!r}")
    return merge_config(default_config(name), {k: v for k, v in override.items() if k != "system"})


def apply_sets(config: dict[str, Any], sets: Sequence[str]) -> dict[str, Any]:
    """Apply ``--set section.param=value`` overrides (``value`` parsed as YAML); ``sim_time=60`` also works."""
    out = copy.deepcopy(config)
    for item in sets:
        key, sep, raw = item.partition("=")
        if not sep:
            raise ValueError(f"--set wants section.param=value, got {item!r}")
        value = yaml.safe_load(raw)
        section, _, param = key.partition(".")
        if section in NODE_SECTIONS and param:
            out.setdefault(section, {})[param] = value
        elif key in ("sim_time", "record"):
            out[key] = value
        else:
            raise ValueError(f"--set {item!r}: the key must be sim_time or one of {NODE_SECTIONS} followed by .param")
    return out


def ros_params_file(params: Mapping[str, Any]) -> str:
    """A ROS 2 parameter file (YAML) applying ``params`` to every node of the process (``/**``)."""
    clean = {k: (list(v) if isinstance(v, tuple) else v) for k, v in params.items()}
    return yaml.safe_dump({"/**": {"ros__parameters": clean}}, sort_keys=True)


# ---------------------------------------------------------------------------------------- processes
# Run in the child before the node: ask the kernel to SIGTERM it when bringup dies (even by SIGKILL), give up
# if bringup is already gone, then exec the node (same pid, so it stays the leader of its process group).
_PDEATHSIG_SHIM = (
    "import ctypes, os, signal, sys\n"
    "ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGTERM, 0, 0, 0)\n"
    "os.getppid() == int(sys.argv[1]) or os._exit(1)\n"
    "os.execv(sys.executable, [sys.executable, *sys.argv[2:]])\n"
)


@dataclass
class Child:
    """A child process in its own process group (``pgid == pid``)."""

    name: str
    proc: subprocess.Popen[bytes]
    log_path: Path
    log: IO[bytes]

    @property
    def pid(self) -> int:
        return self.proc.pid

    def tail(self, lines: int = 20) -> str:
        """The last ``lines`` lines of the child's log."""
        if not self.log.closed:
            self.log.flush()
        try:
            text = self.log_path.read_text(errors="replace")
        except OSError:
            return ""
        return "\n".join(text.splitlines()[-lines:])


class ProcessGroup:
    """Starts children, each in a new process group, and stops them all: SIGINT, SIGTERM, then SIGKILL."""

    def __init__(self) -> None:
        self.children: list[Child] = []

    def start(self, name: str, argv: Sequence[str], env: Mapping[str, str], log_path: Path) -> Child:
        """Start ``argv`` (a Python module invocation: ``[python, -m, ...]``) with output to ``log_path``."""
        log_path.parent.mkdir(parents=True, exist_ok=True)
        log = open(log_path, "ab")  # noqa: SIM115 - closed in stop()
        cmd = [argv[0], "-c", _PDEATHSIG_SHIM, str(os.getpid()), *argv[1:]]
        proc = subprocess.Popen(cmd, env=dict(env), stdin=subprocess.DEVNULL, stdout=log, stderr=subprocess.STDOUT,
                                process_group=0)
        child = Child(name, proc, log_path, log)
        self.children.append(child)
        return child

    def exited(self) -> list[Child]:
        """Children that have exited."""
        return [c for c in self.children if c.proc.poll() is not None]

    def stop(self, grace_int: float = 10.0, grace_term: float = 5.0) -> dict[str, int]:
        """Stop every child (newest first gets SIGINT first); returns ``{name: returncode}``.

        Each stage signals the whole process group of every child still running, then waits up to its grace
        period; a last ``SIGKILL`` to every group catches stragglers (e.g. a grandchild whose leader is gone).
        """
        for sig, grace in ((signal.SIGINT, grace_int), (signal.SIGTERM, grace_term), (signal.SIGKILL, 5.0)):
            running = [c for c in reversed(self.children) if c.proc.poll() is None]
            if not running:
                break
            for c in running:
                _killpg(c.pid, sig)
            deadline = time.monotonic() + grace
            for c in running:
                try:
                    c.proc.wait(max(0.0, deadline - time.monotonic()))
                except subprocess.TimeoutExpired:
                    pass
        for c in self.children:
            _killpg(c.pid, signal.SIGKILL)  # stragglers in the group; harmless when it is empty
            if not c.log.closed:
                c.log.close()
        return {c.name: c.proc.returncode for c in self.children}


def _killpg(pgid: int, sig: int) -> None:
    try:
        os.killpg(pgid, sig)
    except (ProcessLookupError, PermissionError):
        pass


def child_env(domain_id: int | None) -> dict[str, str]:
    """The environment of the children: ours, with ``ROS_DOMAIN_ID`` if given, discovery on this host unless the
    user chose otherwise, unbuffered output and this package on ``PYTHONPATH``."""
    env = dict(os.environ)
    if domain_id is not None:
        env["ROS_DOMAIN_ID"] = str(domain_id)
    env.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    env["PYTHONUNBUFFERED"] = "1"
    root = str(Path(__file__).resolve().parents[1])
    parts = [p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p]
    if root not in parts:
        env["PYTHONPATH"] = os.pathsep.join([root, *parts])
    return env


def node_argv(executable: str, namespace: str, params_file: Path | None, extra: Sequence[str] = ()) -> list[str]:
    """``python -m saml_ros.executables <executable> [extra] --ros-args -r __ns:=<ns> [--params-file F]``."""
    argv = [sys.executable, "-m", "saml_ros.executables", executable, *extra, "--ros-args", "-r", f"__ns:={namespace}"]
    if params_file is not None:
        argv += ["--params-file", str(params_file)]
    return argv


# ------------------------------------------------------------------------------------ task metrics
def goal_position(system: str, mpc_params: Mapping[str, Any]) -> np.ndarray:
    """The position the task error is measured from (the MPC's ``goal.<goal_position>``, e.g. friction ``[p]``,
    quadrotor ``[x, y, z]``, paddle ``[x, y]``)."""
    entry = get_entry(system)
    return entry.position_goal({k[len("goal."):]: v for k, v in mpc_params.items() if k.startswith("goal.")})


def task_error(system: str, x: np.ndarray, goal: np.ndarray) -> float:
    """Distance (m) of state ``x`` from the goal over the entry's ``goal_fields``: friction |p - p_goal|,
    quadrotor ||p - p_goal||_2 (3-D), paddle ball: the ball's xy at an impact vs the target xy (where the
    previous bounce brought it)."""
    return get_entry(system).task_error(x, goal)


@dataclass
class Episode:
    """One episode as seen on ``state``: from a (re)start to the last state before the next jump."""

    index: int
    t_start: float  #: s (simulated)
    t_end: float
    steps: int  #: states received
    start: np.ndarray
    final: np.ndarray
    error: float  #: task error at the final state (m)
    xy_error: float  #: horizontal distance at the final state (m; = error for 1-D systems)
    model_first: int  #: MPC model version when the episode started
    model_last: int  #: MPC model version at its end


class EpisodeTracker:
    """Splits the ``state`` stream into episodes by stamp jumps (a reset leaves a gap >= 2 dt, see the
    simulator contract) and records the task error at each episode's last state.

    For the event-based paddle ball every impact is one "episode" whose error is measured at the next impact.
    """

    def __init__(self, system: str, dt: float, goal: np.ndarray) -> None:
        self.system, self.dt, self.goal = system, dt, goal
        self.episodes: list[Episode] = []
        self._cur: dict[str, Any] | None = None
        self.first_stamp: int | None = None
        self.last_stamp: int | None = None

    @property
    def sim_time(self) -> float:
        """Simulated seconds covered so far."""
        if self.first_stamp is None or self.last_stamp is None:
            return 0.0
        return (self.last_stamp - self.first_stamp) * 1e-9

    def add(self, x: np.ndarray, stamp: int, model_version: int) -> Episode | None:
        """Feed one state; returns the episode it closed, if any."""
        closed = None
        if self.first_stamp is None:
            self.first_stamp = stamp
        jump = (
            self.last_stamp is not None
            and self.dt > 0
            and (stamp - self.last_stamp > 1.5e9 * self.dt or stamp < self.last_stamp)
        )
        if self.dt == 0 and self._cur is not None:
            self._cur.update(final=x, t_end=stamp * 1e-9, steps=self._cur["steps"] + 1, model_last=model_version)
            closed = self._close()
        elif jump:
            closed = self._close()
        self.last_stamp = stamp if self.last_stamp is None else max(stamp, self.last_stamp)
        if self._cur is None:
            self._cur = {"t_start": stamp * 1e-9, "t_end": stamp * 1e-9, "steps": 1, "start": x, "final": x,
                         "model_first": model_version, "model_last": model_version}
        elif self.dt > 0:
            self._cur.update(final=x, t_end=stamp * 1e-9, steps=self._cur["steps"] + 1, model_last=model_version)
        return closed

    def _close(self) -> Episode | None:
        cur, self._cur = self._cur, None
        if cur is None or (self.dt == 0 and cur["steps"] < 2):
            return None
        final = cur["final"]
        err = task_error(self.system, final, self.goal)
        xy = get_entry(self.system).task_error(final, self.goal, fields=2)
        ep = Episode(len(self.episodes), cur["t_start"], cur["t_end"], cur["steps"], cur["start"], final, err, xy,
                     cur["model_first"], cur["model_last"])
        self.episodes.append(ep)
        return ep


# ------------------------------------------------------------------------------------------ result
@dataclass
class BringupResult:
    """What a bringup run observed (everything the summary prints)."""

    system: str
    run_dir: Path
    sim_time: float = 0.0  #: simulated seconds covered
    wall_time: float = 0.0  #: wall seconds from the first state to the stop
    stop_reason: str = ""  #: "sim_time", "signal SIGINT", "child <name> exited", "startup timeout", ...
    returncodes: dict[str, int] = field(default_factory=dict)
    episodes: list[Episode] = field(default_factory=list)
    #: (updates, in-region error) from learner/model_error, in arrival order
    model_error: list[tuple[float, float]] = field(default_factory=list)
    constraint: str = ""  #: the constraint whose region error is tracked
    model_versions: list[int] = field(default_factory=list)  #: distinct MPC model versions, in order of use
    checkpoints_announced: int = 0
    checkpoints_refused: int = 0
    solve_ms: list[float] = field(default_factory=list)
    step_ms: list[float] = field(default_factory=list)
    deadline_misses: int = 0
    states: int = 0
    ok: bool = False  #: every child exited cleanly and the run was not cut short by a failure

    def error_before_after(self, k: int = 3) -> tuple[float, float]:
        """In-region error of the base model and of the newest model (NaN if unknown).

        Before: the last finite report made before the learner's first update (the zero-initialised residual
        predicts exactly f_hat, and the last such report covers the most transitions); if training started
        before any finite report, the first finite one. After: the median of the last ``k`` finite reports.
        """
        finite = [(u, e) for u, e in self.model_error if math.isfinite(e)]
        if not finite:
            return math.nan, math.nan
        untrained = [e for u, e in finite if u == 0]
        before = untrained[-1] if untrained else finite[0][1]
        return float(before), float(np.median([e for _, e in finite[-k:]]))

    def base_and_last_episodes(self, n: int = 5) -> tuple[list[Episode], list[Episode]]:
        """Episodes flown entirely on the base model, and the last ``n`` flown entirely on learned models."""
        base = [e for e in self.episodes if e.model_last == 0]
        learned = [e for e in self.episodes if e.model_first > 0]
        return base, learned[-n:]


def format_summary(res: BringupResult, n_last: int = 5) -> str:
    """The before/after summary printed at the end of a run."""
    lines = [f"bringup summary ({res.system}): {res.sim_time:.1f} s simulated in {res.wall_time:.1f} s wall "
             f"({res.sim_time / max(res.wall_time, 1e-9):.1f}x real time), {res.states} states; stopped by "
             f"{res.stop_reason}; run dir {res.run_dir}"]
    before, after = res.error_before_after()
    last_upd = res.model_error[-1][0] if res.model_error else 0
    lines.append(f"  in-region one-step model error ({res.constraint or 'n/a'}, learner/model_error): base model "
                 f"{before:.4g} -> {after:.4g} after {last_upd:.0f} learner updates")
    base, learned = res.base_and_last_episodes(n_last)

    def stat(eps: list[Episode], attr: str) -> str:
        if not eps:
            return "n/a (no episode)"
        v = np.array([getattr(e, attr) for e in eps])
        return f"{v.mean():.3f} +- {v.std():.3f} m over {len(v)} episode(s)"

    lines.append(f"  task error, base model f_hat:   {stat(base, 'error')}")
    lines.append(f"  task error, last learned models: {stat(learned, 'error')}")
    if len(get_entry(res.system).goal_fields) > 2:
        lines.append(f"  horizontal landing error: base {stat(base, 'xy_error')}; learned {stat(learned, 'xy_error')}")
    on_learned = [e for e in res.episodes if e.model_first > 0]
    if on_learned:
        worst = max(on_learned, key=lambda e: e.error)
        lines.append(f"  worst episode on a learned model: {worst.error:.3f} m (model v{worst.model_first}, episode "
                     f"{worst.index}); {sum(e.error > 1.0 for e in on_learned)} of {len(on_learned)} ended > 1 m "
                     f"from the target")
    versions = res.model_versions
    lines.append(f"  MPC models used: {len(versions)} ({versions[0] if versions else '-'} -> "
                 f"{versions[-1] if versions else '-'}); checkpoints announced {res.checkpoints_announced}, "
                 f"refused {res.checkpoints_refused}")
    if res.step_ms:
        s = np.asarray(res.step_ms)
        lines.append(f"  MPC control step: median {np.median(s):.2f} ms, p99 {np.percentile(s, 99):.2f} ms, "
                     f"max {s.max():.2f} ms; deadline misses {res.deadline_misses}")
    bad = {k: v for k, v in res.returncodes.items() if v != 0}
    lines.append("  children exited cleanly" if not bad else f"  children with non-zero exit codes: {bad}")
    return "\n".join(lines)


# ----------------------------------------------------------------------------------------- monitor
class Monitor:
    """The bringup's own ROS node: reads the loop's topics for progress, stop condition and summary."""

    def __init__(self, system: str, namespace: str, goal: np.ndarray, result: BringupResult) -> None:
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.node import Node
        from sensor_msgs.msg import JointState
        from std_msgs.msg import String

        from msg_schemas import CHECKPOINT_QOS, DATA_QOS, RCLPY, TELEMETRY_QOS, get_schema

        self.system = get_entry(system).make_system()
        self.schema = get_schema(system)
        self.result = result
        self.namespace = namespace
        self.node = Node("bringup_monitor", namespace=namespace)
        self.executor = SingleThreadedExecutor()
        self.executor.add_node(self.node)
        self.tracker = EpisodeTracker(system, self.system.dt, goal)
        self.model_version = 0
        self.last_error: dict[str, float] = {}
        self.node.create_subscription(RCLPY.cls(self.schema.state.msg_type), self.schema.state_topic,
                                      self._on_state, DATA_QOS.to_rclpy())
        self.node.create_subscription(JointState, "learner/model_error", self._on_error, TELEMETRY_QOS.to_rclpy())
        self.node.create_subscription(JointState, "mpc/status", self._on_status, TELEMETRY_QOS.to_rclpy())
        self.node.create_subscription(String, "learner/checkpoint", self._on_checkpoint, CHECKPOINT_QOS.to_rclpy())

    def _on_state(self, msg: Any) -> None:
        from msg_schemas import SchemaError

        try:
            x, stamp = self.schema.state_from_msg(msg)
        except SchemaError:
            return
        self.result.states += 1
        ep = self.tracker.add(x, stamp, self.model_version)
        if ep is not None:
            self.result.episodes.append(ep)
        self.result.sim_time = self.tracker.sim_time

    def _on_error(self, msg: Any) -> None:
        from msg_schemas.telemetry import model_error_from_msg

        try:
            values, _ = model_error_from_msg(msg)
        except Exception:  # noqa: BLE001 - progress display only
            return
        self.last_error = values
        keys = sorted(k for k in values if k.startswith("error_in/"))
        if keys:
            self.result.constraint = keys[0].split("/", 1)[1]
            self.result.model_error.append((values.get("updates", math.nan), values[keys[0]]))

    def _on_status(self, msg: Any) -> None:
        from msg_schemas.telemetry import mpc_status_from_msg

        try:
            values, _ = mpc_status_from_msg(msg)
        except Exception:  # noqa: BLE001
            return
        version = int(values["model_version"])
        if not self.result.model_versions or self.result.model_versions[-1] != version:
            self.result.model_versions.append(version)
        self.model_version = version
        self.result.solve_ms.append(values["solve_time_ms"])
        if "step_ms" in values:
            self.result.step_ms.append(values["step_ms"])
        self.result.deadline_misses = int(values["deadline_misses"])
        self.result.checkpoints_refused = int(values.get("checkpoints_refused", 0))

    def _on_checkpoint(self, msg: Any) -> None:
        self.result.checkpoints_announced += 1

    def wait_nodes_up(self, names: Mapping[str, str], timeout: float) -> None:
        """Spin until every node name in ``names.values()`` is in the ROS graph (at most ``timeout`` s)."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            present = {n for n, _ in self.node.get_node_names_and_namespaces()}
            if set(names.values()) <= present:
                return
            self.executor.spin_once(timeout_sec=0.05)

    def subscribers(self, topic: str) -> int:
        return int(self.node.count_subscribers(f"{self.namespace}/{topic}"))

    def progress(self) -> str:
        r = self.result
        err = self.last_error
        k = r.constraint
        e_in = err.get(f"error_in/{k}", math.nan) if k else math.nan
        last_ep = r.episodes[-1] if r.episodes else None
        solve = np.median(r.solve_ms[-50:]) if r.solve_ms else math.nan
        return (f"[bringup] t_sim {r.sim_time:7.1f} s | episodes {len(r.episodes):3d}"
                f"{f' (last error {last_ep.error:.3f} m)' if last_ep else ''} | learner updates "
                f"{err.get('updates', 0):.0f}, error_in {e_in:.4g} | MPC model v{self.model_version}, "
                f"solve {solve:.1f} ms, refused {r.checkpoints_refused}")


# --------------------------------------------------------------------------------------------- run
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


def node_params(config: Mapping[str, Any], run_dir: Path) -> dict[str, dict[str, Any]]:
    """The ROS parameters of each node section, with the ones bringup owns (system, run_dir, use_sim_time)."""
    system = config["system"]
    lockstep = config["sim"].get("mode", "lockstep") == "lockstep"
    sim = dict(config["sim"])
    learner = {"system": system, "run_dir": str(run_dir / "checkpoints"), **config["learner"]}
    mpc = {"system": system, "run_dir": str(run_dir / "checkpoints"), **config["mpc"]}
    if lockstep:
        learner.setdefault("use_sim_time", True)
        mpc.setdefault("use_sim_time", True)
    return {"sim": sim, "learner": learner, "mpc": mpc}


def run(config: Mapping[str, Any], opts: RunOptions) -> BringupResult:
    """Run one closed loop as described in the module docstring; returns what it observed."""
    import rclpy
    from rclpy.signals import SignalHandlerOptions

    system = str(config["system"])
    entry = get_entry(system)
    namespace = f"/{system}"
    run_dir = make_run_dir(system, opts.run_dir)
    (run_dir / "checkpoints").mkdir(exist_ok=True)
    params = node_params(config, run_dir)
    files = {}
    for name, values in params.items():
        path = run_dir / "params" / f"{name}.yaml"
        path.parent.mkdir(exist_ok=True)
        path.write_text(ros_params_file(values))
        files[name] = path
    (run_dir / "bringup.yaml").write_text(yaml.safe_dump(dict(config), sort_keys=False))

    env = child_env(opts.domain_id)
    # our own node must be on the same domain / discovery range as the children
    for key in ("ROS_DOMAIN_ID", "ROS_AUTOMATIC_DISCOVERY_RANGE"):
        if key in env:
            os.environ[key] = env[key]
    result = BringupResult(system, run_dir)
    stop: dict[str, str] = {}

    def on_signal(signum: int, frame: FrameType | None) -> None:
        stop.setdefault("reason", f"signal {signal.Signals(signum).name}")

    old_handlers = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)}
    procs = ProcessGroup()
    say = (lambda s: None) if opts.quiet else opts.print_fn
    rclpy.init(args=["bringup"], signal_handler_options=SignalHandlerOptions.NO)
    monitor = None
    t_wall0 = time.monotonic()
    try:
        monitor = Monitor(system, namespace, goal_position(system, params["mpc"]), result)
        executor = monitor.executor
        logs = run_dir / "logs"
        started = []
        if opts.learner:
            started.append(procs.start("learner", node_argv("learner", namespace, files["learner"]), env,
                                       logs / "learner.log"))
        started.append(procs.start("mpc", node_argv("mpc", namespace, files["mpc"]), env, logs / "mpc.log"))
        record = opts.record or config.get("record")
        if record:
            if importlib.util.find_spec("saml_ros.bags.record") is None:
                say("[bringup] --record: saml_ros.bags.record is not available; not recording")
            else:
                rec_args = ["--system", system, "-o", str(Path(record).resolve())]
                if config["sim"].get("mode", "lockstep") == "lockstep":
                    rec_args.append("--use-sim-time")
                started.append(procs.start("record", [sys.executable, "-m", "saml_ros.executables", "record", *rec_args],
                                           env, logs / "record.log"))
        say(f"[bringup] {system}: run dir {run_dir}; started " + ", ".join(f"{c.name} (pid {c.pid})" for c in started)
            + f"; ROS_DOMAIN_ID={env.get('ROS_DOMAIN_ID', '0 (default)')}")
        # start the simulator only once the consumers listen, so no state is answered by nobody
        want = 1 + (1 if opts.learner else 0) + 1  # mpc, learner, this monitor
        deadline = time.monotonic() + opts.startup_timeout
        while "reason" not in stop and monitor.subscribers("state") < want:
            executor.spin_once(timeout_sec=0.1)
            if procs.exited():
                stop.setdefault("reason", f"child {procs.exited()[0].name} exited during start-up")
            elif time.monotonic() > deadline:
                stop.setdefault("reason", f"start-up timeout ({opts.startup_timeout:.0f} s)")
        if "reason" not in stop:
            # the recorder subscribes only once the simulator's topics exist, so the simulator itself waits
            # (lockstep) until every consumer is matched: no transition is lost to a late subscriber
            recording = any(c.name == "record" for c in started)
            waits = ["-p", f"min_state_subscribers:={want + (1 if recording else 0)}",
                     "-p", f"min_applied_cmd_subscribers:={(1 if opts.learner else 0) + (1 if recording else 0)}"]
            sim = procs.start("sim", node_argv(entry.sim_node, namespace, files["sim"]) + waits, env,
                              logs / "sim.log")
            say(f"[bringup] consumers ready after {time.monotonic() - t_wall0:.1f} s; started {entry.sim_node} "
                f"(pid {sim.pid}); running for {float(config['sim_time']):g} s of simulated time")
        t_sim0: float | None = None
        next_progress = time.monotonic() + opts.progress_period
        sim_time = float(config["sim_time"])
        while "reason" not in stop:
            executor.spin_once(timeout_sec=0.05)
            if t_sim0 is None and result.states:
                t_sim0 = time.monotonic()  # the loop's speed counts from its first state
            if sim_time > 0 and result.sim_time >= sim_time:
                stop["reason"] = "sim_time"
            for c in procs.exited():
                stop.setdefault("reason", f"child {c.name} exited (code {c.proc.returncode})")
            now = time.monotonic()
            if now >= next_progress:
                say(monitor.progress())
                next_progress = now + opts.progress_period
        result.wall_time = time.monotonic() - t_sim0 if t_sim0 is not None else 0.0
        result.stop_reason = stop["reason"]
        say(f"[bringup] stopping ({result.stop_reason}) ...")
    finally:
        if monitor is not None:
            # SIGINT before a child installed its handlers (still importing) would kill it with a traceback:
            # give children that are still starting a moment to show up in the graph first
            names = {**NODE_NAMES, "sim": entry.sim_node}
            monitor.wait_nodes_up({c.name: names.get(c.name, c.name) for c in procs.children if c.proc.poll() is None},
                                  timeout=30.0)
        result.returncodes = procs.stop()
        if monitor is not None:
            monitor.node.destroy_node()
        rclpy.try_shutdown()
        for s, h in old_handlers.items():
            signal.signal(s, h)
    failed = {k: v for k, v in result.returncodes.items() if v != 0}
    result.stop_reason = result.stop_reason or stop.get("reason", "error")
    result.ok = not failed and (result.stop_reason == "sim_time" or result.stop_reason.startswith("signal"))
    if failed or not result.ok:
        for c in procs.children:
            if c.proc.returncode != 0 or result.stop_reason.startswith("child"):
                opts.print_fn(f"[bringup] --- last lines of {c.log_path} (exit code {c.proc.returncode}) ---\n"
                              f"{c.tail()}")
    return result


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="bringup", description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__.split("\n", 1)[1])
    p.add_argument("--system", choices=system_names(), help="system to run (default: the config's, else quadrotor)")
    p.add_argument("--config", type=Path, help="bringup YAML (sections sim, learner, mpc; see config/bringup_quadrotor.yaml)")
    p.add_argument("--sim-time", type=float, help="stop after this many seconds of simulated time (0 = until Ctrl-C)")
    p.add_argument("--set", action="append", default=[], metavar="SECTION.PARAM=VALUE",
                   help="override a node parameter, e.g. --set mpc.solver=slsqp (repeatable)")
    p.add_argument("--run-dir", type=Path, help="run directory (default: a new runs/bringup-<system>-<date>-<pid>)")
    p.add_argument("--record", type=Path, help="also record the loop into this bag directory (saml_ros record)")
    p.add_argument("--domain-id", type=int, help="ROS_DOMAIN_ID for this run (default: the environment's)")
    p.add_argument("--no-learner", action="store_true", help="run simulator + MPC only (base model or run-dir checkpoints)")
    p.add_argument("--progress-period", type=float, default=5.0, help="seconds (wall) between progress lines")
    p.add_argument("--startup-timeout", type=float, default=90.0, help="seconds to wait for the nodes to come up")
    p.add_argument("--quiet", action="store_true", help="print only the summary")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(sys.argv[1:] if argv is None else argv)
    try:
        config = apply_sets(load_config(args.config, args.system), args.set)
        if args.sim_time is not None:
            config["sim_time"] = args.sim_time
    except (OSError, ValueError, yaml.YAMLError) as exc:
        print(f"bringup: {exc}", file=sys.stderr)
        return 2
    if args.domain_id is not None and not 0 <= args.domain_id <= 101:
        print("bringup: --domain-id must be in 0..101", file=sys.stderr)
        return 2
    opts = RunOptions(run_dir=args.run_dir, record=args.record, domain_id=args.domain_id,
                      progress_period=args.progress_period, startup_timeout=args.startup_timeout,
                      quiet=args.quiet, learner=not args.no_learner)
    res = run(config, opts)
    print(format_summary(res), flush=True)
    return 0 if res.ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
