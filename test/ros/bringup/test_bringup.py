"""bringup: configuration, episode bookkeeping, process groups, and whole closed loops in real processes.

The closed-loop tests run the double integrator with friction (its MPC is the cheapest) in a private ROS domain:
the learner's in-region model error falls and the MPC switches checkpoints while the loop runs; SIGINT, SIGTERM,
the end of the simulated time and even SIGKILL of bringup leave no process of the loop behind.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import yaml
from helpers.ros_helpers import Process, RosDomain, wait_for

from saml_ros.bringup import (
    ProcessGroup,
)
from saml_ros.core.worlds.sim_core import LOCKSTEP_T0_NS


def test_process_group_escalates_and_kills_the_whole_group(tmp_path: Path) -> None:
    # a child that ignores SIGINT and SIGTERM and has a grandchild in its process group
    code = ("import signal, subprocess, sys, time\n"
            "signal.signal(signal.SIGINT, signal.SIG_IGN); signal.signal(signal.SIGTERM, signal.SIG_IGN)\n"
            "p = subprocess.Popen([sys.executable, '-c', 'import time; time.sleep(60)'])\n"
            "print(p.pid, flush=True); time.sleep(60)\n")
    group = ProcessGroup()
    child = group.start("stubborn", [sys.executable, "-c", code], dict(os.environ), tmp_path / "stubborn.log")
    grandchild = int(wait_for(lambda: (tmp_path / "stubborn.log").read_text().strip(), 20, what="grandchild pid"))
    assert os.getpgid(grandchild) == child.pid  # same group as its parent, not ours
    t0 = time.monotonic()
    codes = group.stop(grace_int=0.5, grace_term=0.5)
    assert codes["stubborn"] == -signal.SIGKILL and time.monotonic() - t0 < 10
    assert_group_gone(child.pid)


# ------------------------------------------------------------------------------------- processes
def assert_group_gone(pgid: int, timeout: float = 10.0) -> None:
    """No process of process group ``pgid`` is left (waits up to ``timeout`` s for the kernel to finish)."""
    deadline = time.monotonic() + timeout
    while True:
        try:
            os.killpg(pgid, 0)
        except ProcessLookupError:
            return
        if time.monotonic() > deadline:
            left = subprocess.run(["ps", "-o", "pid,pgid,stat,args", "-g", str(pgid)], capture_output=True, text=True)
            raise AssertionError(f"process group {pgid} still has processes:\n{left.stdout}")
        time.sleep(0.1)


def child_pids(output: str) -> dict[str, int]:
    """``{name: pid}`` of the children bringup reported starting."""
    return {m.group(1): int(m.group(2)) for m in re.finditer(r"(\w+) \(pid (\d+)\)", output)}


FRICTION = ["--system", "friction", "--progress-period", "0.5",
            "--set", "learner.min_transitions=100", "--set", "learner.checkpoint_period=1.0",
            "--set", "learner.telemetry_rate=10.0", "--set", "sim.episode_steps=60"]


def start_bringup(ros_env: RosDomain, tmp_path: Path, *extra: str) -> Process:
    return ros_env.launch("bringup", args=[*FRICTION, "--run-dir", str(tmp_path / "run"), *extra])


def progress_value(output: str, pattern: str) -> list[float]:
    return [float(v) for v in re.findall(pattern, output)]


def test_closed_loop_learns_switches_models_and_stops_on_sigint(ros_env: RosDomain, tmp_path: Path) -> None:
    proc = start_bringup(ros_env, tmp_path, "--sim-time", "0")
    try:
        # wait until the MPC flies a learned model and the learner has trained a while
        # (a few hundred updates: the first dozen can leave the in-region error above the base model's)
        wait_for(lambda: (v := progress_value(proc.output(), r"MPC model v(\d+)")) and v[-1] >= 2
                 and (n := progress_value(proc.output(), r"learner updates (\d+)")) and n[-1] >= 300
                 or not proc.alive(), 150, what="the MPC to switch to a learned model")
        assert proc.alive(), proc.output()
        pids = child_pids(proc.output())
        assert {"learner", "mpc", "friction_sim"} <= set(pids), proc.output()
        proc.signal(signal.SIGINT)
        assert proc.wait(40) == 0, proc.output()
    finally:
        proc.stop()
    out = proc.output()
    found = re.search(r"model error \(near_origin, learner/model_error\): base model (\S+) -> (\S+) after", out)
    assert found, out
    before, after = map(float, found.groups())
    assert after < before, out
    # f_hat first, then at least two learned models; the last one flown is a learned one (not always the newest:
    # the guard's live monitor may have rolled a model back to its predecessor, seen under load)
    versions = re.search(r"MPC models used: (\d+) \((\d+) -> (\d+)\)", out)
    assert versions is not None and int(versions.group(1)) >= 3 and int(versions.group(2)) == 0, out
    assert int(versions.group(3)) >= 1, out
    assert "stopped by signal SIGINT" in out and "children exited cleanly" in out
    for pid in pids.values():
        assert_group_gone(pid)
    assert list((tmp_path / "run" / "checkpoints").glob("ckpt-*.saml"))


def test_bringup_stops_after_the_simulated_time_and_on_sigterm(ros_env: RosDomain, tmp_path: Path) -> None:
    bag = tmp_path / "bag"
    proc = start_bringup(ros_env, tmp_path, "--no-learner", "--sim-time", "3", "--record", str(bag))
    try:
        assert proc.wait(120) == 0, proc.output()
    finally:
        proc.stop()
    out = proc.output()
    assert "stopped by sim_time" in out and "children exited cleanly" in out
    found = re.search(r"summary \(friction\): (\S+) s simulated", out)
    assert found, out
    sim = float(found.group(1))
    # the simulator itself ends the run at sim_time: nothing is simulated (or recorded) while the stop travels
    assert 3.0 <= sim < 3.2
    assert "max_sim_time 3.0 s reached" in (tmp_path / "run" / "logs" / "sim.log").read_text()
    assert "record" in child_pids(out)
    meta = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    # the newest message logged (simulated time: the run starts at LOCKSTEP_T0_NS = 1 s) is within sim_time
    end_ns = meta["starting_time"]["nanoseconds_since_epoch"] + meta["duration"]["nanoseconds"]
    assert end_ns < LOCKSTEP_T0_NS + 3.2e9
    assert "/friction/state" in {t["topic_metadata"]["name"] for t in meta["topics_with_message_count"]}
    for pid in child_pids(out).values():
        assert_group_gone(pid)
    proc = start_bringup(ros_env, tmp_path, "--no-learner", "--sim-time", "0")
    try:
        # a SIGTERM while the simulator is still starting: bringup lets it come up, then stops everything
        wait_for(lambda: "friction_sim (pid" in proc.output() or not proc.alive(), 90, what="the simulator")
        proc.signal(signal.SIGTERM)
        assert proc.wait(40) == 0, proc.output()
    finally:
        proc.stop()
    assert "stopped by signal SIGTERM" in proc.output()
    for pid in child_pids(proc.output()).values():
        assert_group_gone(pid)


def test_sigkill_of_bringup_takes_the_children_down(ros_env: RosDomain, tmp_path: Path) -> None:
    proc = start_bringup(ros_env, tmp_path, "--no-learner", "--sim-time", "0")
    try:
        wait_for(lambda: "friction_sim (pid" in proc.output() or not proc.alive(), 90, what="the simulator")
        pids = child_pids(proc.output())
        proc.signal(signal.SIGKILL)  # no chance to clean up: the kernel's parent-death signal must do it
        proc.wait(10)
        for pid in pids.values():
            assert_group_gone(pid, timeout=30)
    finally:
        proc.stop()
