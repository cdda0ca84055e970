"""Misconfigured robots: several publishers on a topic that should have one are named, and can be refused.

ROS-free: the decision (:mod:`saml_ros.core.data.publishers`). Real processes: a friction learner fed by the test's own
publishers (exact counts) and the example robot from its system file (examples/diff_drive), each time a second
node starts publishing into the namespace: the learner names both nodes on ``/diagnostics`` (WARN) and, with
``pairing.refuse_multiple_publishers``, pairs nothing from that namespace until the second node is gone. The
two-robots-one-topic closed loop (simulator, a miswired second robot, learner, MPC) is test_misconfig_loop.py.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np
from helpers.ros_helpers import RosDomain, TestNode, wait_for

from msg_schemas import telemetry as tele
from saml_ros.core.data.publishers import WARN


# ------------------------------------------------------------------------------------- processes
def learner_status(diagnostics: list[Any]) -> tele.DiagnosticEntry | None:
    """The newest learner entry of the collected ``/diagnostics`` messages."""
    for msg in reversed(list(diagnostics)):
        for e in tele.diagnostics_from_msg(msg)[0]:
            if e.name.endswith("/learner"):
                return e
    return None


def value(diagnostics: list[Any], key: str) -> Any:
    e = learner_status(diagnostics)
    return None if e is None else e.values.get(key)


def test_learner_names_a_second_publisher_and_refuses_its_namespace_until_it_is_gone(
        ros_env: RosDomain, ros_node: TestNode, tmp_path: Path) -> None:
    """The test's node and a second node ``robot_b`` both publish friction states into /friction: named (WARN),
    refused and counted with ``pairing.refuse_multiple_publishers``; exact pairing again once robot_b is gone."""
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from sensor_msgs.msg import JointState

    from msg_schemas import DATA_QOS, get_schema
    from saml_ros.core.systems import get_system

    learner = ros_env.launch("learner", "-p", "system:=friction", "-p", f"run_dir:={tmp_path / 'run'}",
                             "-p", "min_transitions:=100000", "-p", "diagnostics_rate:=10.0",
                             "-p", "pairing.refuse_multiple_publishers:=true", namespace="/friction")
    diagnostics = ros_node.subscribe(DiagnosticArray, "/diagnostics")
    schema, system = get_schema("friction"), get_system("friction")
    qos = DATA_QOS.to_rclpy()
    state = ros_node.publisher(JointState, "/friction/state", qos)
    applied = ros_node.publisher(JointState, "/friction/applied_cmd", qos)
    rng = np.random.default_rng(0)
    t = [10**9]

    def send(n: int) -> None:
        """``n`` transitions of one episode (n + 1 states), stamps continuing from the last; paced so the
        learner's reader queue never overflows."""
        x = np.array([rng.uniform(-2, 2), 0.0])
        for _ in range(n):
            u = np.array([rng.uniform(-10, 10)])
            state.publish(schema.state_to_msg(x, t[0]))
            applied.publish(schema.control_to_msg(u, t[0]))
            x = system.true_step_np(x, u)
            t[0] += 100_000_000
            time.sleep(0.002)
        state.publish(schema.state_to_msg(x, t[0]))
        t[0] += 300_000_000

    def paired() -> int:
        return int(value(diagnostics, "/friction/paired") or 0)

    wait_for(lambda: value(diagnostics, "/friction/publishers/state") == "1" or not learner.alive(), 60,
             what="the learner to match the test's publishers")
    assert learner.alive(), learner.output()
    send(20)
    wait_for(lambda: paired() == 20, 20, what="20 transitions paired")
    assert value(diagnostics, "multiple_publishers") == ""

    robot_b = rclpy.create_node("robot_b", namespace="/friction", context=ros_node.context)
    second = robot_b.create_publisher(JointState, "state", qos)
    try:
        wait_for(lambda: value(diagnostics, "/friction/publishers/state") == "2", 20, what="the second publisher")
        want = f"/friction/state: /friction/robot_b, {ros_node.node.get_fully_qualified_name()}"
        # the ROS graph names a publisher's node after it knows the publisher (seconds late under load)
        wait_for(lambda: value(diagnostics, "multiple_publishers") == want, 120,
                 what="the publishers named")
        entry = learner_status(diagnostics)
        assert entry is not None and entry.level >= WARN and "not paired while so" in entry.message, entry
        send(20)  # nothing of it is paired: it could be either robot's
        second.publish(schema.state_to_msg(np.zeros(2), t[0] + 50_000_000))
        wait_for(lambda: int(value(diagnostics, "/friction/refused/state") or 0) >= 22, 20, what="refused states")
        assert int(value(diagnostics, "/friction/refused/applied_cmd")) == 20
        assert paired() == 20
    finally:
        robot_b.destroy_node()
    wait_for(lambda: value(diagnostics, "multiple_publishers") == "" and
             value(diagnostics, "/friction/publishers/state") == "1", 30, what="one publisher again")
    # the gate reopens on the learner's matched event, which it may process after /diagnostics showed one publisher:
    # one-transition episodes until one is paired
    deadline = time.monotonic() + 60
    while paired() == 20:
        assert time.monotonic() < deadline, f"pairing never resumed: {learner.output()[-2000:]}"
        send(1)
        until = time.monotonic() + 2.0
        while paired() == 20 and time.monotonic() < until:
            time.sleep(0.05)
    assert paired() == 21
    send(15)
    wait_for(lambda: paired() == 36, 20, what="pairing again")
    out = learner.output()
    assert "several publishers on /friction/state: /friction/robot_b" in out and "one publisher per topic again" in out


def test_system_file_robot_two_robots_in_one_namespace_are_named_and_refused(
        ros_env: RosDomain, ros_node: TestNode, tmp_path: Path) -> None:
    """The example robot (examples/diff_drive, learned from its system file) twice in /dd, both driven by one
    wander script: the learner names both odometry publishers and pairs nothing while both run."""
    from diagnostic_msgs.msg import DiagnosticArray
    from helpers.your_robot import EXAMPLE, NS, SYSTEM_FILE, launch_script

    learner = ros_env.launch("learner", "-p", f"system_file:={SYSTEM_FILE}", "-p", f"run_dir:={tmp_path / 'run'}",
                             "-p", "min_transitions:=100000", "-p", "diagnostics_rate:=5.0",
                             "-p", "pairing.refuse_multiple_publishers:=true", namespace=NS)
    diagnostics = ros_node.subscribe(DiagnosticArray, "/diagnostics")
    wait_for(lambda: learner_status(diagnostics) is not None or not learner.alive(), 60, what="the learner")
    assert learner.alive(), learner.output()
    robot = launch_script(ros_env, EXAMPLE / "robot.py")
    wander = launch_script(ros_env, EXAMPLE / "wander.py")
    wait_for(lambda: int(value(diagnostics, "paired") or 0) >= 20, 90, what="the robot's transitions paired")
    second = launch_script(ros_env, EXAMPLE / "robot.py", "-r", "__node:=robot_b", "-p", "x0:=-1.0")
    try:
        want = f"{NS}/odom: {NS}/diff_drive_robot, {NS}/robot_b"  # (the graph may know the endpoint first)
        wait_for(lambda: value(diagnostics, "multiple_publishers") == want, 90,
                 what=f"the publishers named: {value(diagnostics, 'multiple_publishers')!r}")
        wait_for(lambda: int(value(diagnostics, f"{NS}/refused/state") or 0) >= 100, 60, what="refused odometry")
        # what was admitted before the switch has been paired by now (the training process's queue drained)
        before = int(value(diagnostics, "paired"))
        refused = int(value(diagnostics, f"{NS}/refused/state"))
        wait_for(lambda: int(value(diagnostics, f"{NS}/refused/state")) >= refused + 100, 60, what="more refused")
        assert int(value(diagnostics, "paired")) <= before + 1  # nothing new is paired while both publish
    finally:
        second.stop()
    wait_for(lambda: value(diagnostics, "multiple_publishers") == "", 60, what="one publisher again")
    after = int(value(diagnostics, "paired"))
    wait_for(lambda: int(value(diagnostics, "paired")) >= after + 20, 60, what="pairing again")
    for p in (wander, robot):
        p.stop()
