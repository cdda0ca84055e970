"""Two robots in one namespace, one wired wrong, in a real closed loop (docs/mpc.md, "Two robots on one topic").

    ./dev bench misconfig [--system friction] [--sim-time 300] [--runs 1] [--no-second] [--set mpc.guard.rollback=false]

Real processes in a private ROS domain: ``bringup --system <system>`` with that system's default settings
(simulator, learner, MPC) and a second robot (bench/miswired_robot.py) publishing ``state`` and ``applied_cmd``
into the same namespace half a period later, in lockstep with the same MPC, its command wired backwards. This
process watches the topics (its own rclpy node) and reports:

* what ``/diagnostics`` says: the learner's and the MPC's ``multiple_publishers`` (the node names);
* the robot wired right (the simulator's stamps): each episode's final error (m) and whether a learned model
  planned any of its steps, beside the base model f_hat flown ROS-free from the same start states (the
  headroom: ``closed_loop`` on the true dynamics); the check: no episode flown on a learned model ends more than
  f_hat's worst + 0.1 m;
* the MPC's roll backs, its model versions, and the last checkpoint's one-step error on the robot's true dynamics
  (fresh samples of the paper's distribution) against f_hat's.

``--no-second`` runs the same loop with the one robot: the good case (the roll back must not roll a good model
back). ``--fly RUN_DIR`` (ROS-free) flies the newest checkpoint of a loop's run directory from fresh starts twice,
the live monitor's roll back off and on (every transition shown to it, as the MPC node does), and compares: the
cost of the roll back on that model. :func:`run_loop` is what test/test_misconfig_loop.py runs, shorter.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from saml_ros.core.data.publishers import UNKNOWN_NODE

REPO = Path(__file__).resolve().parents[1]
#: the check's margin over the base model's worst episode (m)
MARGIN = 0.1


@dataclass
class LoopRecord:
    """What one loop showed (see the module docstring)."""

    system: str
    second: bool
    run_dir: str = ""
    wiring: str = "reversed"  #: the second robot's miswiring
    sim_time: float = 0.0
    wall_time: float = 0.0
    bringup_rc: int | None = None
    robot_rc: int | None = None
    episodes: list[dict[str, Any]] = field(default_factory=list)  #: the robot wired right
    learner_shared: str = ""  #: the learner's multiple_publishers (the last non-empty one seen)
    mpc_shared: str = ""
    learner_message: str = ""  #: the learner's diagnostics message when it named them
    learner_level: int = -1
    rollbacks: int = 0
    refused: int = 0  #: checkpoints the MPC refused before flying them (its acceptance check)
    versions: list[int] = field(default_factory=list)  #: MPC model versions in order of use
    learned_steps: int = 0  #: steps of the robot wired right planned with a learned model
    checkpoint_error: float = math.nan  #: last checkpoint's mean squared one-step error, fresh samples
    base_error: float = math.nan  #: f_hat's on the same samples
    tail: str = ""  #: bringup's last lines
    rollback_lines: list[str] = field(default_factory=list)  #: the MPC's log lines of its roll backs
    #: version -> (its one-step error, f_hat's) on fresh samples, for each version rolled back (NaN: pruned)
    rolled_back: dict[int, tuple[float, float]] = field(default_factory=dict)

    def flown_on_learned(self) -> list[dict[str, Any]]:
        return [e for e in self.episodes if e["learned_steps"] > 0]

    def base_worst(self) -> float:
        return max((e["base_error"] for e in self.episodes), default=math.nan)

    def verdict(self) -> bool:
        """No episode flown on a learned model ends more than the base model's worst + :data:`MARGIN`."""
        worst = self.base_worst()
        return all(e["error"] <= worst + MARGIN for e in self.flown_on_learned())

    def summary(self) -> str:
        learned = self.flown_on_learned()
        worst = max((e["error"] for e in learned), default=math.nan)
        mean = float(np.mean([e["error"] for e in learned])) if learned else math.nan
        on_base = [e["error"] for e in self.episodes if e["learned_steps"] == 0]
        base_mean = float(np.mean([e["base_error"] for e in self.episodes])) if self.episodes else math.nan
        ratio = self.checkpoint_error / self.base_error if self.base_error > 0 else math.nan
        return "\n".join([
            f"{self.system}, {f'two robots (the second wired {self.wiring})' if self.second else 'one robot'}: "
            f"{self.sim_time:.0f} s simulated in {self.wall_time:.0f} s wall; run dir {self.run_dir}",
            f"  /diagnostics: learner multiple_publishers = {self.learner_shared!r} (level {self.learner_level}); "
            f"mpc multiple_publishers = {self.mpc_shared!r}",
            f"  last checkpoint: one-step squared error {self.checkpoint_error:.4g} against f_hat's "
            f"{self.base_error:.4g} ({ratio:.1f} x), fresh samples of the robot's true dynamics",
            f"  MPC: models {self.versions}, roll backs {self.rollbacks}, refused {self.refused}, steps planned "
            f"with a learned model {self.learned_steps}",
            f"  episodes of the robot wired right: {len(self.episodes)}; on f_hat only {len(on_base)} "
            f"(worst {max(on_base, default=math.nan):.4f} m); flown on a learned model {len(learned)} "
            f"(mean {mean:.4f} m, worst {worst:.4f} m); f_hat from the same starts: mean {base_mean:.4f} m, worst "
            f"{self.base_worst():.4f} m",
            *(f"  MPC: {line}" for line in self.rollback_lines),
            *(f"  rolled back v{v}: one-step squared error {m:.4g} against f_hat's {b:.4g} on fresh samples"
              for v, (m, b) in self.rolled_back.items()),
            f"  check: every episode flown on a learned model ends within f_hat's worst + {MARGIN} m: "
            f"{'yes' if self.verdict() else 'NO'}",
        ])


class Observer:
    """This process's rclpy node: the state stream, ``mpc/status`` and ``/diagnostics`` of the loop."""

    def __init__(self, system: str, namespace: str) -> None:
        import rclpy
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.qos import HistoryPolicy

        import msg_schemas.telemetry as tele
        from msg_schemas import DATA_QOS, RCLPY, TELEMETRY_QOS, get_schema

        self.tele = tele
        self.schema = get_schema(system)
        self.ctx = rclpy.Context()
        rclpy.init(context=self.ctx)
        self.node = rclpy.create_node("misconfig_observer", context=self.ctx)
        self.lock = threading.Lock()
        self.states: list[tuple[int, np.ndarray]] = []
        self.status: dict[int, dict[str, float]] = {}
        self.arrivals: list[int] = []  #: the model version of each status, in arrival order
        self.diag: dict[str, tele.DiagnosticEntry] = {}
        #: per node, the last entry naming several publishers (one naming all their nodes kept over one that does not)
        self.shared: dict[str, tele.DiagnosticEntry] = {}
        jt = RCLPY.cls(tele.JOINT_STATE)

        def keep_all(spec: Any) -> Any:  # a burst waits in the reader queue instead of being dropped
            profile = spec.to_rclpy()
            profile.history = HistoryPolicy.KEEP_ALL
            return profile

        self.node.create_subscription(RCLPY.cls(self.schema.state.msg_type), f"{namespace}/{self.schema.state_topic}",
                                      self._on_state, keep_all(DATA_QOS))
        self.node.create_subscription(jt, f"{namespace}/{tele.MPC_STATUS_TOPIC}", self._on_status,
                                      keep_all(TELEMETRY_QOS))
        self.node.create_subscription(RCLPY.cls(tele.DIAGNOSTIC_ARRAY), tele.DIAGNOSTICS_TOPIC, self._on_diag,
                                      keep_all(TELEMETRY_QOS))
        self.executor = SingleThreadedExecutor(context=self.ctx)
        self.executor.add_node(self.node)
        self.thread = threading.Thread(target=self._spin, daemon=True)
        self.thread.start()

    def _spin(self) -> None:
        try:
            self.executor.spin()
        except Exception:  # noqa: BLE001 - the context is shut down by close()
            pass

    def _on_state(self, msg: Any) -> None:
        x, stamp = self.schema.state_from_msg(msg)
        with self.lock:
            self.states.append((stamp, x))

    def _on_status(self, msg: Any) -> None:
        values, stamp = self.tele.mpc_status_from_msg(msg)
        with self.lock:
            self.status[stamp] = values
            self.arrivals.append(int(values["model_version"]))

    def _on_diag(self, msg: Any) -> None:
        entries, _ = self.tele.diagnostics_from_msg(msg)
        with self.lock:
            for e in entries:
                self.diag[e.name] = e
                shared = str(e.values.get("multiple_publishers", ""))
                # a value naming every publisher's node is kept over a later one the ROS graph had not named yet
                if shared and (UNKNOWN_NODE not in shared or e.name not in self.shared
                               or UNKNOWN_NODE in str(self.shared[e.name].values["multiple_publishers"])):
                    self.shared[e.name] = e

    def close(self) -> None:
        self.executor.shutdown(timeout_sec=1.0)
        self.node.destroy_node()
        self.ctx.try_shutdown()
        self.thread.join(2.0)


def _start(cmd: list[str], env: dict[str, str], log: Path) -> subprocess.Popen[bytes]:
    with open(log, "wb") as out:
        return subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT, env=env, cwd=REPO, start_new_session=True)


def _stop(proc: subprocess.Popen[bytes], timeout: float = 30.0) -> int:
    from bench.ros_procs import interrupt

    if proc.poll() is None:
        interrupt(proc, timeout)
    return int(proc.returncode)


def run_loop(system: str = "friction", sim_time: float = 300.0, run_dir: Path | None = None, second: bool = True,
             sets: Sequence[str] = (), wiring: str = "reversed", timeout: float = 1800.0,
             progress: Callable[[str], None] = print, until: Callable[[LoopRecord, Observer], bool] | None = None,
             ) -> LoopRecord:
    """One loop (see the module docstring) in the current ROS domain (``ROS_DOMAIN_ID`` of the environment):
    ``bringup`` with the system's defaults and ``sets`` (``section.param=value``), the second robot unless
    ``second`` is False; it ends after ``sim_time`` s of simulated time, or once ``until(partial record,
    observer)`` says so (checked every second)."""
    from saml_ros.bringup import default_config
    from saml_ros.bringup.results import EpisodeTracker, goal_position
    from saml_ros.core.systems import get_entry
    from saml_ros.core.worlds.sim_core import LOCKSTEP_T0_NS

    entry = get_entry(system)
    sys_obj = entry.make_system()
    dt_ns = int(round(sys_obj.dt * 1e9))
    namespace = f"/{system}"
    run_dir = Path(run_dir or tempfile.mkdtemp(prefix=f"misconfig_{system}_")).resolve()
    run_dir.mkdir(parents=True, exist_ok=True)
    env = dict(os.environ, PYTHONUNBUFFERED="1",
               PYTHONPATH=os.pathsep.join(p for p in (str(REPO), os.environ.get("PYTHONPATH", "")) if p))
    record = LoopRecord(system, second, str(run_dir), wiring)
    observer = Observer(system, namespace)
    bringup_cmd = [sys.executable, "-m", "saml_ros.executables", "bringup", "--system", system, "--run-dir",
                   str(run_dir), "--sim-time", repr(float(sim_time)), "--progress-period", "10"]
    for s in sets:
        bringup_cmd += ["--set", s]
    t0 = time.monotonic()
    procs: list[subprocess.Popen[bytes]] = []
    robot = None
    try:
        bringup = _start(bringup_cmd, env, run_dir / "bringup.out")
        procs.append(bringup)
        if second:
            # it starts when the MPC, the learner and the observer listen (the simulator's own start condition)
            robot = _start([sys.executable, "-m", "bench.miswired_robot", "--system", system, "--namespace",
                            namespace, "--wiring", wiring, "--min-subscribers", "3", "--max-sim-time", repr(float(sim_time))],
                           env, run_dir / "robot_b.out")
            procs.append(robot)
        deadline = t0 + timeout
        while bringup.poll() is None and time.monotonic() < deadline:
            time.sleep(1.0)
            if until is not None and until(record, observer):
                break
        record.wall_time = time.monotonic() - t0
    finally:
        if robot is not None:
            record.robot_rc = _stop(robot)
        record.bringup_rc = _stop(procs[0], 60.0)
        observer.close()
    record.tail = "\n".join((run_dir / "bringup.out").read_text(errors="replace").splitlines()[-25:])

    # --------------------------------------------------------------------------------------- the record
    with observer.lock:
        states = sorted(observer.states, key=lambda s: s[0])
        status = dict(observer.status)
        arrivals = list(observer.arrivals)
        diag = dict(observer.diag)
        shared = dict(observer.shared)
    for name, e in shared.items():
        if name.endswith("/learner"):
            record.learner_shared, record.learner_message, record.learner_level = (
                e.values["multiple_publishers"], e.message, e.level)
        elif name.endswith("/mpc"):
            record.mpc_shared = e.values["multiple_publishers"]
    mpc = next((e for n, e in diag.items() if n.endswith("/mpc")), None)
    if mpc is not None:
        record.rollbacks = int(mpc.values.get("guard_rollbacks", 0))
        record.refused = int(mpc.values.get("checkpoints_refused", 0))
    # the robot wired right: the simulator's stamps (the second robot's are half a period off)
    mine = [(t, x) for t, x in states if not second or dt_ns == 0 or (t - LOCKSTEP_T0_NS) % dt_ns == 0]
    if mine:
        record.sim_time = (mine[-1][0] - mine[0][0]) * 1e-9
    config = default_config(system)
    tracker = EpisodeTracker(system, sys_obj.dt, goal_position(system, config["mpc"]))
    for t, x in mine:
        tracker.add(x, t, int(status.get(t, {}).get("model_version", 0)))
    if mine and dt_ns > 0:
        tracker.add(mine[-1][1], mine[-1][0] + 10 * dt_ns, 0)  # a jump: closes the last episode
    versions: list[int] = []
    for v in arrivals:  # the two robots' stamps are apart in wall time: in arrival order, not by stamp
        if not versions or versions[-1] != v:
            versions.append(v)
    record.versions = versions
    base = _base_errors(system, config, [ep.start for ep in tracker.episodes], [ep.steps - 1 for ep in tracker.episodes])
    for ep, b in zip(tracker.episodes, base, strict=True):
        if ep.steps < 2:
            continue
        # the steps that led to its final state (the answer to the final state belongs to what follows)
        stamps = [t for t, _ in mine if ep.t_start - 1e-6 <= t * 1e-9 < ep.t_end - 1e-6]
        # a learned model planned the step (model_source: only with a guard remedy on; without, every step of a
        # learned version is)
        learned = sum(1 for t in stamps if t in status and status[t].get("model_version", 0.0) > 0
                      and status[t].get("model_source", 1.0) == 1.0)
        record.learned_steps += learned
        record.episodes.append({"start": ep.start.tolist(), "steps": ep.steps, "error": ep.error,
                                "base_error": b, "learned_steps": learned, "versions": [ep.model_first,
                                                                                        ep.model_last]})
    record.checkpoint_error, record.base_error = _checkpoint_errors(system, run_dir / "checkpoints")
    mpc_log = run_dir / "logs" / "mpc.log"
    if mpc_log.exists():
        record.rollback_lines = [line.split("]: ", 1)[-1] for line in mpc_log.read_text(errors="replace").splitlines()
                                 if "rolled back from model version" in line or "before flying it" in line]
    for line in record.rollback_lines:  # each rolled-back version on fresh samples (if the learner kept it)
        version = int(line.split("model version ")[1].split()[0])  # rolled back from / refused model version N
        record.rolled_back[version] = _checkpoint_errors(system, run_dir / "checkpoints", version)
    progress(record.summary())
    return record


def _base_errors(system: str, config: dict[str, Any], starts: list[np.ndarray], steps: list[int]) -> list[float]:
    """Final task error of f_hat's MPC (the bringup's MPC settings) from each start, ROS-free on the true
    dynamics."""
    from saml_ros.bringup.results import goal_position, task_error
    from saml_ros.core.mpc import closed_loop, make_controller
    from saml_ros.core.mpc.config import MPCConfig
    from saml_ros.core.systems import get_system

    mpc = MPCConfig.from_params({"system": system, **config["mpc"]})
    controller = make_controller(get_system(system), None, mpc.solver, **mpc.controller_options())
    goal = goal_position(system, config["mpc"])
    out = []
    for x0, n in zip(starts, steps, strict=True):
        run = closed_loop(controller.system, controller, x0, max(n, 0), mpc.goal)
        out.append(task_error(system, run.xs[-1], goal))
    return out


def _checkpoint_errors(system: str, checkpoints: Path, version: int = 0, n: int = 4000) -> tuple[float, float]:
    """Mean squared one-step error of the newest checkpoint in ``checkpoints`` (or of ``version``) and of f_hat,
    on ``n`` fresh samples of the paper's distribution through the true dynamics (NaN without that checkpoint)."""
    from saml_ros.core.model.checkpoint import CheckpointError, CheckpointStore
    from saml_ros.core.model.io import load_model
    from saml_ros.core.systems import get_system

    try:
        store = CheckpointStore(checkpoints)
        latest = store.latest() if version == 0 else (store.path_for(version), version)
    except (OSError, CheckpointError):
        return math.nan, math.nan
    if latest is None or not latest[0].exists():
        return math.nan, math.nan
    sys_obj = get_system(system)
    x, u, y = sys_obj.make_dataset(n, np.random.default_rng(12345))
    model = load_model(latest[0]).model
    pred = model.predict_np(x, u)
    base = sys_obj.base_step_np(x, u)
    return float(((pred - y) ** 2).sum(1).mean()), float(((base - y) ** 2).sum(1).mean())


def _observer_hook(ctrl: Any, system: Any, stepped: bool, cpu: list[Any]) -> Callable[[Any], None]:
    """A ``closed_loop`` hook showing ``ctrl`` each live transition (the next state, or the paddle ball's
    post-impact velocity from the true dynamics), its CPU time summed into ``cpu`` (seconds, steps)."""

    def observe(step: Any) -> None:
        t0 = time.process_time()
        u = np.asarray(step.result.u, dtype=np.float64)
        y = step.x_next if stepped else system.true_step_np(step.x, u)
        ctrl.observe(step.x, u, y)
        cpu[0] += time.process_time() - t0
        cpu[1] += 1

    return observe


def fly(run_dir: Path, n_starts: int = 30, steps: int = 0, seed: int = 7, version: int = 0) -> dict[str, Any]:
    """The newest checkpoint of ``run_dir`` (or ``version``) flown ROS-free from ``n_starts`` fresh starts (``seed``), each
    ``steps`` long (0 = the simulator's episode length; the paddle ball: 20 bounces), with the live monitor's roll
    back off and on, and f_hat from the same starts (the MPC settings of the run's ``bringup.yaml``): per setting
    the final task errors (m; the paddle ball: every bounce's landing error), roll backs and the monitor's CPU time
    per step."""
    import yaml

    from saml_ros.bringup.results import goal_position, task_error
    from saml_ros.core.model.checkpoint import CheckpointStore
    from saml_ros.core.model.io import load_model
    from saml_ros.core.mpc import closed_loop
    from saml_ros.core.mpc.config import MPCConfig
    from saml_ros.core.mpc.guard import GuardConfig, make_guarded_controller
    from saml_ros.core.systems import get_entry

    config = yaml.safe_load((run_dir / "bringup.yaml").read_text())
    system_name = str(config["system"])
    entry = get_entry(system_name)
    mpc = MPCConfig.from_params({"system": system_name, **config["mpc"]})
    system = entry.make_system()
    store = CheckpointStore(run_dir / "checkpoints")
    latest = store.latest() if version == 0 else (store.path_for(version), version)
    if latest is None or not latest[0].exists():
        raise FileNotFoundError(f"no such checkpoint in {run_dir / 'checkpoints'}")
    model = load_model(latest[0]).model
    one_step = _checkpoint_errors(system_name, run_dir / "checkpoints", latest[1])
    rng = np.random.default_rng(seed)
    stepped = system.target.names == system.state.names
    if stepped:
        steps = steps or int(config["sim"].get("episode_steps", 100))
        assert entry.stepped_model is not None
        model_of = entry.stepped_model(system)
        starts = [model_of.sample_start(rng) for _ in range(n_starts)]
    else:
        steps = steps or 20
        starts = list(system.sample_inputs(n_starts, rng)[0])
    goal = goal_position(system_name, config["mpc"])
    out: dict[str, Any] = {"run_dir": str(run_dir), "checkpoint": [str(latest[0]), latest[1]], "steps": steps,
                           "starts": n_starts, "one_step_error": one_step}
    for name, rollback in (("f_hat", False), ("roll back off", False), ("roll back on", True)):
        ctrl = make_guarded_controller(system, mpc.solver, GuardConfig(rollback=rollback, monitor=mpc.guard.monitor),
                                       member=mpc.member, **mpc.controller_options())
        errors: list[float] = []
        cpu = [0.0, 0]
        observe = _observer_hook(ctrl, system, stepped, cpu)
        for x0 in starts:
            ctrl.reset_models()
            if name != "f_hat":
                ctrl.set_model(model, latest[1])
            run = closed_loop(system, ctrl, x0, steps, mpc.goal, on_step=observe)
            if stepped:
                errors.append(task_error(system_name, run.xs[-1], goal))
            else:
                errors.extend(float(c) for c in run.stage_costs)
        out[name] = {"mean": float(np.mean(errors)), "worst": float(np.max(errors)),
                     "rollbacks": int(ctrl.counters["rollbacks"]), "steps_on_f_hat": int(ctrl.counters["solves_base"]),
                     "monitor_ms_per_step": 1e3 * cpu[0] / max(cpu[1], 1)}
    print(f"{system_name}: checkpoint v{latest[1]} of {run_dir}, {n_starts} starts x {steps} steps "
          f"({'episodes' if stepped else 'bounces'}); its one-step squared error {one_step[0]:.4g} against f_hat's "
          f"{one_step[1]:.4g} on fresh samples of the paper's distribution")
    for name in ("f_hat", "roll back off", "roll back on"):
        r = out[name]
        print(f"  {name}: error mean {r['mean']:.4f} m, worst {r['worst']:.4f} m; roll backs {r['rollbacks']}, "
              f"steps on f_hat {r['steps_on_f_hat']}; monitor {r['monitor_ms_per_step']:.3f} ms CPU per step")
    return out


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="bench misconfig", description=__doc__.split("\n\n")[0])
    ap.add_argument("--system", default="friction")
    ap.add_argument("--sim-time", type=float, default=300.0, help="s of simulated time per loop")
    ap.add_argument("--runs", type=int, default=1)
    ap.add_argument("--no-second", action="store_true", help="one robot only (the good case)")
    ap.add_argument("--wiring", default="reversed", help="the second robot's miswiring (bench/miswired_robot.py)")
    ap.add_argument("--set", action="append", default=[], dest="sets", help="bringup --set section.param=value")
    ap.add_argument("--json", type=Path, default=None, help="write the records here")
    ap.add_argument("--fly", type=Path, default=None, metavar="RUN_DIR",
                    help="ROS-free: fly RUN_DIR's newest checkpoint with the roll back off and on")
    ap.add_argument("--starts", type=int, default=30, help="--fly: fresh starts")
    ap.add_argument("--version", type=int, default=0, help="--fly: this checkpoint version (0 = the newest)")
    args = ap.parse_args(argv)
    if args.fly is not None:
        result = fly(args.fly, args.starts, version=args.version)
        if args.json is not None:
            args.json.write_text(json.dumps(result, indent=1))
        return 0
    from bench.ros_procs import claimed_domain

    records = []
    with claimed_domain() as domain:
        os.environ["ROS_DOMAIN_ID"] = str(domain)
        os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
        print(f"bench misconfig: ROS_DOMAIN_ID={domain}; load average {os.getloadavg()[0]:.1f}", flush=True)
        for i in range(args.runs):
            records.append(run_loop(args.system, args.sim_time, None, not args.no_second, args.sets, args.wiring))
            print(f"run {i + 1}/{args.runs} done", flush=True)
    if args.json is not None:
        args.json.write_text(json.dumps([r.__dict__ for r in records], indent=1, default=str))
    return 0 if all(r.verdict() for r in records) else 1


if __name__ == "__main__":
    raise SystemExit(main())
