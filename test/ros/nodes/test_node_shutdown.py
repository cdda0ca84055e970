"""Every node exits cleanly on Ctrl-C under ``ros2 launch`` and on SIGTERM (real processes, private ROS domain).

A terminal's Ctrl-C under ``ros2 launch`` sends SIGINT to the terminal's whole process group (every node and the
learner's training process) and launch then sends each node SIGINT once more; 5 s later launch escalates to
SIGTERM. The test starts all eight node executables (a friction loop that trains, the other two simulators, a
recorder, a player and the Foxglove server) twice, signals one set the Ctrl-C way and the other with SIGTERM, all
at the same moment, and checks that each node exits with status 0 within 5 s, with no traceback on its output,
and that each learner wrote its final checkpoint and left no training process behind.
"""

from __future__ import annotations

import os
import re
import signal
import time
from dataclasses import dataclass
from pathlib import Path

from helpers.bag_publisher import rollout
from helpers.ros_helpers import Process, RosDomain, process_alive, wait_for

from msg_schemas import DATA_QOS, TypestoreFactory, get_schema
from saml_ros.bags.io import BagWriter, jazzy_typestore
from saml_ros.core.model.checkpoint import CheckpointStore

#: launch's grace period between its SIGINT and its SIGTERM (s)
GRACE_S = 5.0
#: the learner's final-checkpoint log lines (one of them ends every shutdown after training)
FINAL_CHECKPOINT = re.compile(r"shutdown: (final checkpoint version \d+|checkpoint version \d+ is current)")


@dataclass
class Started:
    name: str
    proc: Process
    ready: str  #: log text that says the node is up


def _write_slow_bag(path: Path, ns: str) -> None:
    """A 21-state friction bag spanning 10 s of log time (played at rate 0.05 it takes 200 s)."""
    events = rollout("friction", 21, 0, seed=3, t0_ns=10**9)
    schema, factory = get_schema("friction"), TypestoreFactory(jazzy_typestore())
    with BagWriter(path) as w:
        w.add_topic(f"{ns}/state", "sensor_msgs/msg/JointState", DATA_QOS)
        for k, ev in enumerate(events):
            t = 10**9 + k * 500_000_000
            w.write_msg(f"{ns}/state", schema.state_to_msg(ev["x"], t, factory=factory), t)


def _start_all(dom: RosDomain, tmp: Path, tag: str) -> list[Started]:
    """One set of the eight nodes; ``tag`` keeps its namespaces apart from another set in the same domain."""
    run_dir = tmp / f"learner_run{tag}"
    bag = tmp / f"slow_bag{tag}"
    _write_slow_bag(bag, f"/replay{tag}")
    realtime = ["-p", "mode:=realtime", "-p", "start_delay:=0.2"]
    loop = f"/friction{tag}"
    return [
        Started("friction_sim", dom.launch("friction_sim", *realtime, "-p", "rate_hz:=50.0", namespace=loop),
                "friction simulator"),
        Started("learner", dom.launch("learner", "-p", "system:=friction", "-p", f"run_dir:={run_dir}",
                                      "-p", "min_transitions:=50", "-p", "checkpoint_period:=1.0",
                                      "-p", "training_niceness:=0", namespace=loop), "training started"),
        Started("mpc", dom.launch("mpc", "-p", "system:=friction", "-p", "mode:=realtime", namespace=loop),
                "friction MPC"),
        Started("quadrotor_sim", dom.launch("quadrotor_sim", *realtime, namespace=f"/quadrotor{tag}"),
                "quadrotor simulator"),
        Started("paddle_ball_sim", dom.launch("paddle_ball_sim", *realtime, namespace=f"/paddle_ball{tag}"),
                "paddle_ball simulator"),
        Started("record", dom.launch("record", args=["-o", str(tmp / f"rec{tag}"), "--system", "friction",
                                                     "--namespace", loop]), "record: writing"),
        Started("play", dom.launch("play", args=[str(bag), "--rate", "0.05"]), "messages over"),
        Started("foxglove_server", dom.launch("foxglove_server", "-p", "system:=friction", "-p", "port:=0",
                                              namespace=f"/viewer{tag}"), "Foxglove WebSocket on"),
    ]


def _wait_up(nodes: list[Started], run_dir: Path) -> None:
    for n in nodes:
        wait_for(lambda n=n: bool(n.ready in n.proc.output() or not n.proc.alive()), timeout=120,  # type: ignore[misc]
                 what=f"{n.name} to come up")
        assert n.proc.alive(), f"{n.name} exited during start-up:\n{n.proc.output()}"
    # the learner checkpoints every second once training runs: wait for one, so the final one is a real save
    wait_for(lambda: CheckpointStore(run_dir).load_latest_valid() is not None, timeout=60,
             what="the learner's first checkpoint")


def _training_pid(learner: Process) -> int:
    found = re.search(r"training process pid (\d+)", learner.output())
    assert found, learner.output()
    return int(found.group(1))


def _check_clean_exits(nodes: list[Started], t_signal: float, run_dir: Path, trainer_pid: int) -> None:
    codes: dict[str, int | None] = {}
    for n in nodes:
        codes[n.name] = n.proc.wait(max(0.0, t_signal + GRACE_S - time.monotonic()))
    elapsed = time.monotonic() - t_signal
    late = [name for name, code in codes.items() if code is None]
    assert not late, f"still running {elapsed:.1f} s after the signal: {late}\n" + "\n".join(
        f"--- {n.name}:\n{n.proc.output()[-3000:]}" for n in nodes if n.name in late)
    for n in nodes:
        out = n.proc.output()
        assert codes[n.name] == 0, f"{n.name} exited with {codes[n.name]}:\n{out[-3000:]}"
        assert "Traceback" not in out and "KeyboardInterrupt" not in out, f"{n.name}:\n{out[-3000:]}"
    learner_log = next(n for n in nodes if n.name == "learner").proc.output()
    assert FINAL_CHECKPOINT.search(learner_log), learner_log[-3000:]
    assert CheckpointStore(run_dir).load_latest_valid() is not None
    assert not process_alive(trainer_pid), "the learner's training process outlived the learner"


def test_ctrl_c_under_launch_and_sigterm_every_node_exits_cleanly(ros_env: RosDomain, tmp_path: Path) -> None:
    """Two sets of the eight nodes at once: set A gets a Ctrl-C under launch (SIGINT to each process group, then
    SIGINT to each process), set B SIGTERM; every node of both must exit cleanly within the grace period."""
    ctrl_c = _start_all(ros_env, tmp_path, "")
    sigterm = _start_all(ros_env, tmp_path, "_b")
    _wait_up(ctrl_c, tmp_path / "learner_run")
    _wait_up(sigterm, tmp_path / "learner_run_b")
    trainers = (_training_pid(ctrl_c[1].proc), _training_pid(sigterm[1].proc))
    t_signal = time.monotonic()
    for n in ctrl_c:  # the terminal: SIGINT to each node's process group (the learner's includes its trainer)
        os.killpg(n.proc.pid, signal.SIGINT)
    for n in sigterm:  # launch's escalation, or a supervisor: SIGTERM to the process
        n.proc.signal(signal.SIGTERM)
    time.sleep(0.05)
    for n in ctrl_c:  # launch: SIGINT to each node process
        if n.proc.alive():
            n.proc.signal(signal.SIGINT)
    _check_clean_exits(ctrl_c, t_signal, tmp_path / "learner_run", trainers[0])
    _check_clean_exits(sigterm, t_signal, tmp_path / "learner_run_b", trainers[1])
