"""/diagnostics on wall time whatever the simulated clock does (real processes).

A lockstep friction loop answered at once by the test (an instant controller) runs its simulated clock at tens of
times real time; the learner runs with ``use_sim_time``. Every node publishes /diagnostics at its documented rate of
wall time: the learner at ``diagnostics_rate`` (1 Hz here), the simulator every ``diagnostics_period`` (1 s). Before,
the learner's timer ran on the node clock and sent 58-81 statuses in 8 s of wall time at 10-25x (issue 29).
"""

from __future__ import annotations

import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from helpers.ros_helpers import RosDomain, TestNode, wait_for
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import JointState

from msg_schemas import DATA_QOS, get_schema
from msg_schemas.telemetry import clock_from_msg, diagnostics_from_msg

NS = "/friction"
WINDOW = 10.0  # wall seconds counted


def test_learner_diagnostics_at_1_hz_of_wall_time_under_a_fast_lockstep_loop(
        tmp_path: Path, ros_env: RosDomain, ros_node: TestNode) -> None:
    schema = get_schema("friction")
    qos = DATA_QOS.to_rclpy()
    cmd_pub = ros_node.publisher(JointState, f"{NS}/cmd", qos)
    lock = threading.Lock()
    statuses: dict[str, list[float]] = {}  # node name -> wall times of its statuses
    clock: list[tuple[float, int]] = []  # (wall time, simulated ns)

    def answer(msg: JointState) -> None:
        _, t = schema.state_from_msg(msg)
        cmd_pub.publish(schema.control_to_msg(np.zeros(1), t))

    def on_diag(msg: Any) -> None:
        now = time.monotonic()
        with lock:
            for entry in diagnostics_from_msg(msg)[0]:
                statuses.setdefault(entry.name, []).append(now)

    def on_clock(msg: Any) -> None:
        with lock:
            clock.append((time.monotonic(), clock_from_msg(msg)))

    ros_node.subscribe(JointState, f"{NS}/state", qos, callback=answer)
    ros_node.subscribe(DiagnosticArray, "/diagnostics", callback=on_diag)
    ros_node.subscribe(Clock, "/clock", callback=on_clock)
    learner = ros_env.launch("learner", "-p", "use_sim_time:=true", "-p", "diagnostics_rate:=1.0",
                             "-p", f"run_dir:={tmp_path / 'run'}", "-p", "min_transitions:=200",
                             "-p", "checkpoint_period:=5.0", namespace=NS)
    wait_for(lambda: "training starts after" in learner.output() or not learner.alive(), 90.0,
             what="the learner to be active")
    assert learner.alive(), learner.output()
    sim = ros_env.launch("friction_sim", "-p", "mode:=lockstep", "-p", "min_state_subscribers:=2",
                         "-p", "min_applied_cmd_subscribers:=1", "-p", "lockstep_timeout:=5.0",
                         "-p", "diagnostics_period:=1.0", "-p", "episode_steps:=100", namespace=NS)
    wait_for(lambda: len(clock) > 100, 60.0, what="the lockstep loop to run")
    time.sleep(2.0)  # past start-up
    # consecutive windows of WINDOW wall seconds until one ran at 10x real time or faster (the loop's speed is the
    # machine's: measured 17x at load 12 on 2 cores)
    deadline = time.monotonic() + 6 * WINDOW
    while True:
        with lock:
            t0, n0 = time.monotonic(), {k: len(v) for k, v in statuses.items()}
            sim0 = clock[-1][1]
        time.sleep(WINDOW)
        with lock:
            t1, n1 = time.monotonic(), {k: len(v) for k, v in statuses.items()}
            sim1 = clock[-1][1]
            gaps = {k: np.diff([t for t in v if t0 <= t <= t1]) for k, v in statuses.items()}
        wall = t1 - t0
        speed = (sim1 - sim0) * 1e-9 / wall
        counts = {k: n1.get(k, 0) - n0.get(k, 0) for k in n1}
        print(f"simulated time at {speed:.1f}x real time; statuses in {wall:.1f} s of wall time: {counts}; "
              f"median gaps (s): { {k: round(float(np.median(g)), 3) for k, g in gaps.items() if len(g)} }")
        if speed >= 10.0 or time.monotonic() > deadline:
            break
    assert learner.alive() and sim.alive()
    assert speed >= 10.0, f"the lockstep loop ran at {speed:.1f}x real time only"
    for name in (f"{NS}/learner", f"{NS}/friction_sim"):  # 1 Hz of wall time, within 20 %
        assert 0.8 * wall <= counts.get(name, 0) <= 1.2 * wall, (name, counts)
        assert abs(float(np.median(gaps[name])) - 1.0) <= 0.2, (name, gaps[name])
