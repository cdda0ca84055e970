"""A user's robot, learned online vs offline vs its base model, judged on a held-out flight (issue 27, item 1).

    ./dev bench your_robot --robot arm --runs 3 --duration 150
    ./dev bench your_robot --robot diff_drive --runs 3 --duration 150 --learner-param min_transitions:=3000

For a robot folder under ``examples/`` (``system.yaml``, ``robot.py``, its own controller script), all as real
processes in a private ROS domain:

1. a **held-out flight**: the robot and its controller with another seed, recorded (``record``), no learner;
2. per run (seed ``--seed + i``): the robot, its controller, the **unmodified learner**
   (``learner -p system_file:=...``) and the recorder, ``--duration`` s of wall time; then ``train
   --system-file ... --bag <that recording>`` (**offline**, default recipe or ``--train-arg``);
3. ``examples/arm/evaluate.py`` (generic: any system file) on the held-out flight: f_hat, every online model
   (the learner's final checkpoint) and every offline model, one-step error inside and outside each constraint's
   region with block standard errors;
4. the table, and per run the ratios issue 27 asks for: online / offline in the region (goal <= 1.5) and
   f_hat / online in the region (goal >= 3), plus each training flight's pairing counters (from its bag, the
   learner's own rule) and the learner's update count.

Everything stays in ``--out`` (bags, run directories, logs, ``eval.json``, ``summary.json``); ``--heldout BAG``
reuses a held-out flight of an earlier call. The numbers depend on the machine's load (``uptime`` is printed).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from bench.ros_procs import claimed_domain

REPO = Path(__file__).resolve().parents[1]
EVALUATE = REPO / "examples" / "arm" / "evaluate.py"


@dataclass(frozen=True)
class RobotSetup:
    """How to run one example robot: its folder, namespace, scripts and what the evaluation can check."""

    folder: Path
    namespace: str
    controller: str
    robot_args: tuple[str, ...] = ()
    applied_effort: bool = False  # the state message reports the applied command (evaluate.py --applied-effort)

    @property
    def system_file(self) -> Path:
        return self.folder / "system.yaml"


ROBOTS: dict[str, RobotSetup] = {
    "arm": RobotSetup(REPO / "examples" / "arm", "/arm", "controller.py", applied_effort=True),
    "diff_drive": RobotSetup(REPO / "examples" / "diff_drive", "/dd", "wander.py"),
}
PAIRING_KEYS = ("intervals", "paired", "gap", "no_cmd", "stale_cmd", "ambiguous_cmd", "mixed_cmd", "late")


@dataclass
class Proc:
    """A child process with its log file."""

    name: str
    popen: subprocess.Popen[bytes]
    log: Path
    extra: dict[str, Any] = field(default_factory=dict)

    def output(self) -> str:
        try:
            return self.log.read_text(errors="replace")
        except OSError:
            return ""

    def alive(self) -> bool:
        return self.popen.poll() is None

    def stop(self, timeout: float) -> int:
        """SIGINT, wait ``timeout`` s, then SIGKILL its process group; the exit code."""
        if self.alive():
            self.popen.send_signal(signal.SIGINT)
            try:
                self.popen.wait(timeout)
            except subprocess.TimeoutExpired:
                os.killpg(self.popen.pid, signal.SIGKILL)
                self.popen.wait(10)
        return int(self.popen.returncode)


class Flight:
    """The processes of one recorded flight (and its learner, if any) in one ROS domain."""

    def __init__(self, setup: RobotSetup, env: dict[str, str], logs: Path) -> None:
        self.setup = setup
        self.env = env
        self.logs = logs
        self.procs: list[Proc] = []

    def start(self, name: str, cmd: list[str]) -> Proc:
        log = self.logs / f"{name}.log"
        with open(log, "wb") as out:
            popen = subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT, env=self.env, cwd=REPO,
                                     start_new_session=True)
        proc = Proc(name, popen, log)
        self.procs.append(proc)
        return proc

    def saml(self, name: str, executable: str, *args: str) -> Proc:
        return self.start(name, [sys.executable, "-m", "saml_ros.executables", executable, *args])

    def script(self, name: str, script: str, *ros_args: str) -> Proc:
        return self.start(name, [sys.executable, str(self.setup.folder / script), "--ros-args", "-r",
                                 f"__ns:={self.setup.namespace}", *ros_args])

    def stop_all(self) -> None:
        for p in reversed(self.procs):
            p.stop(10.0)


def wait_output(proc: Proc, pattern: str, timeout: float, others: list[Proc]) -> None:
    """Wait until ``proc``'s log matches ``pattern``; RuntimeError if it or one of ``others`` exits first."""
    deadline = time.monotonic() + timeout
    rx = re.compile(pattern)
    while not rx.search(proc.output()):
        for p in [proc, *others]:
            if not p.alive():
                raise RuntimeError(f"{p.name} exited ({p.popen.returncode}) while waiting for {proc.name}: "
                                   f"{pattern!r}; its log:\n{p.output()[-3000:]}")
        if time.monotonic() > deadline:
            raise RuntimeError(f"{proc.name} did not print {pattern!r} within {timeout:.0f} s; its log:\n"
                               f"{proc.output()[-3000:]}")
        time.sleep(0.2)


def topics_of(setup: RobotSetup) -> list[str]:
    """The state and command topics of the robot's system file, under its namespace."""
    import yaml

    d = yaml.safe_load(setup.system_file.read_text())
    out = []
    for key in ("state", "control"):
        t = str(d[key]["topic"])
        out.append(t if t.startswith("/") else f"{setup.namespace}/{t}")
    return out


@dataclass(frozen=True)
class Settle:
    """How long the learner keeps training on its buffer after the stream stopped (the robot parked): until it has
    made ``epochs`` passes over its training buffer (updates x batch >= epochs x buffer size, read from its
    checkpoints, counted from the first one written after the stop), at most ``seconds`` s; 0 s = none."""

    seconds: float = 0.0
    epochs: float = 20.0


def _checkpoint_meta(path: Path) -> dict[str, Any]:
    from saml_ros.core.model.checkpoint import read_checkpoint

    return read_checkpoint(path)[1]


def settle_learner(run_dir: Path, at_stop: Path, settle: Settle, procs: list[Proc]) -> dict[str, Any]:
    """Keep the learner training after the stream stopped (see :class:`Settle`). The newest checkpoint at the stop
    is copied to ``at_stop`` first (the model as the robot stopped, at most one checkpoint period old). Returns the
    update counts, the passes made and the seconds it took."""
    import shutil

    from saml_ros.core.model.checkpoint import CheckpointStore

    store = CheckpointStore(run_dir)
    latest = store.latest()
    if latest is None:
        return {"skipped": "no checkpoint at the stop"}
    shutil.copyfile(latest[0], at_stop)
    meta = _checkpoint_meta(at_stop)
    u0 = int(meta.get("updates", 0))
    batch = int(meta.get("train_config", {}).get("batch_size", 128))
    buffer = max(1, int(meta.get("learner", {}).get("buffer_size", 1)))
    want = settle.epochs * buffer / batch
    t0, version, updates = time.monotonic(), latest[1], u0
    ref: int | None = None  # passes are counted from the first checkpoint written after the stop (the copy may be
    while time.monotonic() - t0 < settle.seconds and (ref is None or updates - ref < want):  # a period old)
        dead = [p for p in procs if not p.alive()]
        if dead:
            raise RuntimeError(f"{dead[0].name} exited ({dead[0].popen.returncode}) while the learner settled")
        time.sleep(1.0)
        now = store.latest()
        if now is not None and now[1] != version:
            version = now[1]
            try:
                updates = int(_checkpoint_meta(now[0]).get("updates", updates))
            except Exception:  # noqa: BLE001 - pruned or replaced meanwhile: read the next one
                continue
            ref = updates if ref is None else ref
    done = updates - (u0 if ref is None else ref)
    return {"updates_at_stop": u0, "updates_settled": done, "buffer": buffer,
            "epochs": round(done * batch / buffer, 1), "seconds": round(time.monotonic() - t0, 1),
            "at_stop": str(at_stop)}


def fly(setup: RobotSetup, env: dict[str, str], out: Path, seed: int, duration: float,
        learner_params: list[str] | None, controller_params: tuple[str, ...] = (),
        settle: Settle = Settle()) -> dict[str, Any]:
    """One flight: recorder (+ learner when ``learner_params`` is not None), then robot and controller (with
    ``controller_params``, ``NAME:=VALUE``) for ``duration`` s; with ``settle`` the learner then trains on its buffer
    a while longer (:func:`settle_learner`). Returns what happened (paths, exit codes, wall time)."""
    out.mkdir(parents=True, exist_ok=True)
    flight = Flight(setup, env, out)
    bag, run_dir = out / "bag", out / "online"
    topics = topics_of(setup)
    info: dict[str, Any] = {"bag": str(bag), "seed": seed, "duration_s": duration}
    try:
        rec = flight.saml("record", "record", "-o", str(bag), "--topics", *topics)
        waiting = [rec]
        if learner_params is not None:
            params = [f"system_file:={setup.system_file}", f"run_dir:={run_dir}", *learner_params]
            learner = flight.saml("learner", "learner", "--ros-args", "-r", f"__ns:={setup.namespace}",
                                  *[a for p in params for a in ("-p", p)])
            waiting.append(learner)
            info["run_dir"] = str(run_dir)
            wait_output(learner, r"training starts after", 300.0, waiting)
        wait_output(rec, r"record: writing", 120.0, waiting)
        time.sleep(1.0)  # the learner activates (subscribes) right after it configured
        # the controller first: it commands only once it has a state, so the robot never waits for its commands
        ctrl = flight.script("controller", setup.controller, "-p", f"seed:={seed}",
                             *[a for p in controller_params for a in ("-p", p)])
        wait_output(rec, re.escape(f"record: recording {topics[1]} "), 120.0, [*waiting, ctrl])
        robot = flight.script("robot", "robot.py", *setup.robot_args, "-p", f"seed:={seed}")
        everyone = [*waiting, robot, ctrl]
        wait_output(rec, re.escape(f"record: recording {topics[0]} "), 120.0, everyone)
        t0 = time.monotonic()
        while time.monotonic() - t0 < duration:
            dead = [p for p in everyone if not p.alive()]
            if dead:
                raise RuntimeError(f"{dead[0].name} exited ({dead[0].popen.returncode}) during the flight; its "
                                   f"log:\n{dead[0].output()[-3000:]}")
            time.sleep(0.5)
        info["wall_s"] = round(time.monotonic() - t0, 1)
        info["exit"] = {"robot": robot.stop(10.0), "controller": ctrl.stop(10.0)}
        if learner_params is not None and settle.seconds > 0:  # the stream has paused: the recorder closes its bag,
            info["exit"]["record"] = rec.stop(60.0)            # the learner trains on its buffer a while longer
            waiting = [p for p in waiting if p is not rec]
            info["settle"] = settle_learner(run_dir, out / "online_at_stop.saml", settle, waiting)
        for p in waiting:  # both at once: the learner writes its final checkpoint, the recorder closes the bag
            p.popen.send_signal(signal.SIGINT)
        for p in waiting:
            info["exit"][p.name] = p.stop(180.0 if p.name == "learner" else 60.0)
        if any(info["exit"].values()):
            raise RuntimeError(f"a process of the flight failed: exit codes {info['exit']}; logs in {out}")
        return info
    finally:
        flight.stop_all()


def bag_counts(setup: RobotSetup, bag: Path, out: Path) -> tuple[dict[str, int], dict[str, int] | None]:
    """Pairing counters of a recording (the learner's own rule, as ``bag_info`` prints them) and, for a robot that
    reports its applied command, how many paired commands differ from it (``evaluate.py --applied-effort``)."""
    cmd = [sys.executable, str(EVALUATE), "--system-file", str(setup.system_file), "--bag", str(bag), "--json",
           str(out)]
    if setup.applied_effort:
        cmd.append("--applied-effort")
    subprocess.check_call(cmd, env=eval_env(setup), cwd=REPO, stdout=subprocess.DEVNULL)
    result = json.loads(out.read_text())
    return {k: int(v) for k, v in result["counts"].items()}, result.get("pairing_check")


def eval_env(setup: RobotSetup) -> dict[str, str]:
    """The environment of ``evaluate.py``: the repository and the robot's folder importable."""
    return dict(os.environ, PYTHONPATH=os.pathsep.join([str(REPO), str(setup.folder)]))


def updates_of(run_dir: Path) -> int | None:
    """The update count of a run directory's newest checkpoint."""
    from saml_ros.core.model.checkpoint import CheckpointStore, read_checkpoint

    latest = CheckpointStore(run_dir).latest()
    if latest is None:
        return None
    _, meta = read_checkpoint(latest[0])
    return int(meta.get("updates", 0))


def train_offline(setup: RobotSetup, env: dict[str, str], bag: Path, out: Path, seed: int,
                  train_args: list[str]) -> float:
    """``train --system-file ... --bag bag --out out``; its wall time (s)."""
    t0 = time.monotonic()
    log = out.parent / "train.log"
    with open(log, "wb") as f:
        rc = subprocess.call([sys.executable, "-m", "saml_ros.executables", "train", "--system-file",
                              str(setup.system_file), "--bag", str(bag), "--out", str(out), "--seed", str(seed),
                              "--no-progress", *train_args], stdout=f, stderr=subprocess.STDOUT, env=env, cwd=REPO)
    if rc != 0:
        raise RuntimeError(f"train failed ({rc}); its log:\n{log.read_text(errors='replace')[-3000:]}")
    return time.monotonic() - t0


def ratio(a: float, b: float) -> float:
    return a / b if b > 0 else float("nan")


def report(setup: RobotSetup, result: dict[str, Any], runs: list[dict[str, Any]]) -> tuple[str, dict[str, Any]]:
    """The table and the per-run ratios (markdown) from ``evaluate.py``'s result."""
    lines = [f"held-out flight: {result['transitions']} transitions from {result['transitions_from']} "
             f"({', '.join(result['bags'])}); standard errors over {result['block_s']:g} s blocks"]
    c = result["counts"]
    lines.append("the learner's pairing of the held-out recording: " + ", ".join(f"{k} {c.get(k, 0)}" for k in
                                                                                 PAIRING_KEYS)
                 + (f"; mis-paired {result['pairing_check']['mispaired']} of {result['pairing_check']['checked']}"
                    if "pairing_check" in result else ""))
    verdicts: dict[str, Any] = {}
    for cname, cons in result["constraints"].items():
        rows = cons["rows"]

        def cell(name: str, where: str, rows: dict[str, Any] = rows) -> str:
            s = rows[name][where]
            return f"{s['mean']:.5f} +- {s['se']:.5f}" if s["n"] else "no model"

        n_in, n_out = rows["f_hat"]["in"]["n"], rows["f_hat"]["out"]["n"]
        lines += ["", f"| model (one-step {cons['loss']} error, held-out flight) | inside '{cname}' "
                      f"(eps {cons['eps']:g}, n={n_in}) | outside (n={n_out}) |", "|---|---|---|",
                  f"| f_hat alone | {cell('f_hat', 'in')} | {cell('f_hat', 'out')} |"]
        settled = any(f"at_stop_{i + 1}" in rows for i in range(len(runs)))
        for i in range(len(runs)):
            if f"at_stop_{i + 1}" in rows:
                lines.append(f"| online, run {i + 1}, as the robot stopped | {cell(f'at_stop_{i + 1}', 'in')} | "
                             f"{cell(f'at_stop_{i + 1}', 'out')} |")
            lines.append(f"| online, run {i + 1}{', after settling' if settled else ''} | "
                         f"{cell(f'online_{i + 1}', 'in')} | {cell(f'online_{i + 1}', 'out')} |")
        for i in range(len(runs)):
            lines.append(f"| offline `train`, run {i + 1} | {cell(f'offline_{i + 1}', 'in')} | "
                         f"{cell(f'offline_{i + 1}', 'out')} |")
        stop_cols = ("as the robot stopped: online / offline | f_hat / online | updates | "
                     if settled else "")
        lines += ["", f"| run | {stop_cols}online / offline in region (goal <= 1.5) | f_hat / online in region "
                      "(goal >= 3) | updates | settled (s, passes over the buffer) | paired / intervals | "
                      "ambiguous_cmd | mixed_cmd | gap | late | mis-paired |",
                  "|---|" + "---|" * (3 if settled else 0) + "---|---|---|---|---|---|---|---|---|---|"]
        fh = rows["f_hat"]["in"]["mean"]
        per_run = []
        for i, r in enumerate(runs):
            off = rows[f"offline_{i + 1}"]["in"]["mean"]
            on = rows[f"online_{i + 1}"]["in"]["mean"]
            r1, r2 = ratio(on, off), ratio(fh, on)
            row = {"online_over_offline": r1, "fhat_over_online": r2, "ok": bool(r1 <= 1.5 and r2 >= 3)}
            head = ""
            if settled:
                st = r.get("settle") or {}
                s_on = rows.get(f"at_stop_{i + 1}", {}).get("in", {}).get("mean", float("nan"))
                s1, s2 = ratio(s_on, off), ratio(fh, s_on)
                row.update(at_stop_online_over_offline=s1, at_stop_fhat_over_online=s2,
                           at_stop_ok=bool(s1 <= 1.5 and s2 >= 3))
                head = (f"{s1:.2f} {'ok' if s1 <= 1.5 else 'NO'} | {s2:.2f} {'ok' if s2 >= 3 else 'NO'} | "
                        f"{st.get('updates_at_stop', '-')} | ")
            per_run.append(row)
            c = r["counts"]
            st = r.get("settle") or {}
            settle_cell = f"{st['seconds']:g} s, {st['epochs']:g}" if "seconds" in st else "-"
            mis = f"{r['pairing_check']['mispaired']}" if r.get("pairing_check") else "not checked"
            lines.append(f"| {i + 1} | {head}{r1:.2f} {'ok' if r1 <= 1.5 else 'NO'} | {r2:.2f} "
                         f"{'ok' if r2 >= 3 else 'NO'} | {r['updates']} | {settle_cell} | "
                         f"{c.get('paired', 0)} / {c.get('intervals', 0)} | "
                         f"{c.get('ambiguous_cmd', 0)} | {c.get('mixed_cmd', 0)} | {c.get('gap', 0)} | "
                         f"{c.get('late', 0)} | {mis} |")
        met = sum(p["ok"] for p in per_run)
        lines.append(f"\nissue 27 goal met in {met} of {len(runs)} runs ('{cname}')"
                     + (f" after settling; as the robot stopped in {sum(p['at_stop_ok'] for p in per_run)} of "
                        f"{len(runs)}" if settled else ""))
        verdicts[cname] = {"runs": per_run, "met": met}
    return "\n".join(lines), verdicts


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--robot", choices=sorted(ROBOTS), default="arm")
    ap.add_argument("--runs", type=int, default=3, help="independent online runs (seeds --seed, --seed + 1, ...)")
    ap.add_argument("--duration", type=float, default=150.0, help="wall seconds of each training flight")
    ap.add_argument("--heldout-duration", type=float, default=120.0, help="wall seconds of the held-out flight")
    ap.add_argument("--heldout", type=Path, help="reuse this held-out recording instead of flying one")
    ap.add_argument("--seed", type=int, default=0, help="first run's seed (the held-out flight uses seed + 1000)")
    ap.add_argument("--learner-param", action="append", default=[], metavar="NAME:=VALUE",
                    help="a learner parameter for every run (repeatable), e.g. min_transitions:=3000")
    ap.add_argument("--controller-param", action="append", default=[], metavar="NAME:=VALUE",
                    help="a parameter of the robot's controller in the training flights (repeatable; the held-out "
                         "flight is the plain task), e.g. homing:=20 for the arm")
    ap.add_argument("--train-arg", action="append", default=[], metavar="ARG",
                    help="an argument for the offline `train` (repeatable), e.g. --train-arg=--epochs=100")
    ap.add_argument("--settle", type=float, default=0.0, metavar="SECONDS",
                    help="after each training flight the learner keeps training on its buffer (the robot parked, "
                         "the stream paused) for at most this long; both models are evaluated: as the robot stopped "
                         "(the newest checkpoint then) and after settling. 0 = stop the learner with the robot")
    ap.add_argument("--settle-epochs", type=float, default=20.0, metavar="PASSES",
                    help="settling ends early once the learner made this many passes over its training buffer "
                         "(updates x batch / buffer size) since the stop")
    ap.add_argument("--no-offline", action="store_true", help="skip offline training (no ratios)")
    ap.add_argument("--out", type=Path, help="output directory (default: a new temporary directory)")
    args = ap.parse_args(argv)
    if args.runs < 1 or not args.duration > 0 or not args.heldout_duration > 0:
        ap.error("--runs must be >= 1, --duration and --heldout-duration > 0")
    if not (args.settle >= 0 and args.settle_epochs > 0):
        ap.error("--settle must be >= 0 and --settle-epochs > 0")
    settle = Settle(args.settle, args.settle_epochs)
    setup = ROBOTS[args.robot]
    out = args.out or Path(tempfile.mkdtemp(prefix=f"bench_your_robot_{args.robot}_"))
    out.mkdir(parents=True, exist_ok=True)
    print(f"bench_your_robot: {args.robot}, {args.runs} run(s) of {args.duration:g} s, held-out "
          f"{'reused ' + str(args.heldout) if args.heldout else f'{args.heldout_duration:g} s'}; output in {out}; "
          f"load average {os.getloadavg()[0]:.1f}", flush=True)
    t_start = time.monotonic()
    with claimed_domain() as domain:
        env = dict(os.environ, ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
                   PYTHONUNBUFFERED="1",
                   PYTHONPATH=os.pathsep.join([str(REPO), str(setup.folder), os.environ.get("PYTHONPATH", "")]))
        if args.heldout is not None:
            heldout = args.heldout
        else:
            print(f"[held-out] flying {args.heldout_duration:g} s (seed {args.seed + 1000})", flush=True)
            info = fly(setup, env, out / "heldout", args.seed + 1000, args.heldout_duration, None)
            heldout = Path(info["bag"])
        runs: list[dict[str, Any]] = []
        for i in range(args.runs):
            seed = args.seed + i
            run_out = out / f"run{i + 1}"
            print(f"[run {i + 1}/{args.runs}] flying {args.duration:g} s with the learner (seed {seed}); load "
                  f"{os.getloadavg()[0]:.1f}", flush=True)
            info = fly(setup, env, run_out, seed, args.duration, args.learner_param, tuple(args.controller_param),
                       settle)
            info["counts"], info["pairing_check"] = bag_counts(setup, Path(info["bag"]), run_out / "pairing.json")
            info["updates"] = updates_of(Path(info["run_dir"]))
            check = info["pairing_check"]
            if info.get("settle"):
                print(f"[run {i + 1}/{args.runs}] settled: {info['settle']}", flush=True)
            print(f"[run {i + 1}/{args.runs}] {info['updates']} updates; recording: "
                  + ", ".join(f"{k} {info['counts'].get(k, 0)}" for k in PAIRING_KEYS)
                  + (f"; mis-paired {check['mispaired']} of {check['checked']}" if check else ""), flush=True)
            if not args.no_offline:
                info["train_s"] = round(train_offline(setup, env, Path(info["bag"]), run_out / "offline", seed,
                                                      args.train_arg), 1)
                print(f"[run {i + 1}/{args.runs}] offline train: {info['train_s']:.0f} s", flush=True)
            runs.append(info)
    # a run whose learner never trained (fewer than min_transitions paired) has no checkpoint: its row says so
    models = [f"online_{i + 1}={r['run_dir']}" for i, r in enumerate(runs) if r["updates"] is not None]
    models += [f"at_stop_{i + 1}={r['settle']['at_stop']}" for i, r in enumerate(runs)
               if (r.get("settle") or {}).get("at_stop")]
    if not args.no_offline:
        models += [f"offline_{i + 1}={out / f'run{i + 1}' / 'offline'}" for i in range(len(runs))]
    cmd = [sys.executable, str(EVALUATE), "--system-file", str(setup.system_file), "--bag", str(heldout),
           "--json", str(out / "eval.json"), *[a for m in models for a in ("--model", m)]]
    if setup.applied_effort:
        cmd.append("--applied-effort")
    rc = subprocess.call(cmd, env=eval_env(setup), cwd=REPO, stdout=subprocess.DEVNULL)
    if rc != 0:
        print(f"bench_your_robot: evaluate.py failed ({rc})", file=sys.stderr)
        return 1
    result = json.loads((out / "eval.json").read_text())
    for cons in result["constraints"].values():  # rows of models not evaluated: empty
        for i in range(len(runs)):
            for kind in ("online", "offline"):
                cons["rows"].setdefault(f"{kind}_{i + 1}", {w: {"mean": float("nan"), "se": float("nan"), "n": 0}
                                                            for w in ("in", "out", "all")})
    table, verdicts = report(setup, result, runs)
    print("\n" + table)
    print(f"\nbench_your_robot: {time.monotonic() - t_start:.0f} s wall; load average {os.getloadavg()[0]:.1f}")
    (out / "summary.json").write_text(json.dumps({"robot": args.robot, "args": {k: str(v) for k, v in
                                                                                  vars(args).items()},
                                                  "runs": runs, "heldout": str(heldout), "verdicts": verdicts,
                                                  "table": table}, indent=1, default=str))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
