"""The simulator nodes as real processes, checked by a stock rclpy node in the test process.

Each test runs in a private ROS domain (ros_helpers); node start-up (torch import) takes seconds on the shared
machine, so each test starts its processes together and checks several behaviours of them.
"""

from __future__ import annotations

import math
import signal
import threading
import time
from typing import Any

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import TwistStamped
from helpers.ros_helpers import REPO, RosDomain, TestNode, wait_for
from nav_msgs.msg import Odometry
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import JointState
from std_srvs.srv import Trigger

from msg_schemas import DATA_QOS, get_schema
from msg_schemas.telemetry import clock_from_msg, diagnostics_from_msg
from saml_ros.systems.quadrotor.model import Quadrotor

DT_NS = 100_000_000
TIMEOUT = 60.0  # start-up on a loaded 2-core machine
QUAD_START = "[0.0, 0.0, 2.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]"


def diagnostics_of(msgs: list[Any], node_name: str) -> dict[str, str]:
    """The newest /diagnostics values of the node whose full name is ``node_name``."""
    for msg in reversed(list(msgs)):
        for entry in diagnostics_from_msg(msg)[0]:
            if entry.name == node_name:
                return dict(entry.values)
    return {}


def counter(msgs: list[Any], node_name: str, key: str) -> int:
    return int(diagnostics_of(msgs, node_name).get(key, 0))


def by_stamp(msgs: list[Any], decode: Any) -> dict[int, np.ndarray]:
    out = {}
    for m in list(msgs):
        v, t = decode(m)
        out[t] = v
    return out


def test_quadrotor_lockstep_applies_exactly_the_stamped_cmd_and_rejects_bad_ones(
    ros_env: RosDomain, ros_node: TestNode
) -> None:
    schema = get_schema("quadrotor")
    quad = Quadrotor()
    ns = "/robot1"
    qos = DATA_QOS.to_rclpy()
    cmd_pub = ros_node.publisher(JointState, f"{ns}/cmd", qos)
    rng = np.random.default_rng(0)
    sent: dict[int, np.ndarray] = {}  # stamp -> command expected to be applied
    held: list[tuple[int, np.ndarray]] = []  # a state the test thread answers late
    n_steps = 14

    def answer(msg: Odometry) -> None:
        x, t = schema.state_from_msg(msg)
        k = len(sent)
        if k >= n_steps:
            return
        u = quad.hover_thrust() + rng.uniform(-0.3, 0.3, 4)
        if k == 2:  # rejected: NaN, wrong length, far out of bounds, another state's stamp; then the real one
            cmd_pub.publish(schema.control_to_msg(np.full(4, np.nan), t))
            cmd_pub.publish(JointState(header=msg.header, name=[f"rotor{i}" for i in range(1, 5)],
                                       effort=[1.0, 2.0, 3.0]))
            cmd_pub.publish(schema.control_to_msg(np.full(4, 100.0), t))
            cmd_pub.publish(schema.control_to_msg(u, t - DT_NS))
        if k == 4:  # slightly out of bounds: clipped to f_max
            u = np.array([10.4, 10.4, 10.4, 10.4])
        sent[t] = np.minimum(u, quad.f_max)
        if k == 6:
            held.append((t, u))  # answered by the test thread after a pause
            return
        cmd_pub.publish(schema.control_to_msg(u, t))

    states = ros_node.subscribe(Odometry, f"{ns}/state", qos, callback=answer)
    applied = ros_node.subscribe(JointState, f"{ns}/applied_cmd", qos)
    clock = ros_node.subscribe(Clock, "/clock", qos)
    diags = ros_node.subscribe(DiagnosticArray, "/diagnostics")
    sim = ros_env.launch(
        "quadrotor_sim", "--params-file", str(REPO / "config" / "quadrotor_sim.yaml"),
        "-p", f"initial_state:={QUAD_START}", "-p", "start_delay:=0.3", "-p", "lockstep_timeout:=20.0",
        "-p", "diagnostics_period:=0.3", "-p", "episode_steps:=0", namespace=ns,
    )
    wait_for(lambda: held, TIMEOUT, what=f"7 states; sim output:\n{sim.output()}")
    n_before = len(states)
    time.sleep(1.0)  # the simulator must wait for the answer
    assert len(states) == n_before
    t_held, u_held = held[0]
    cmd_pub.publish(schema.control_to_msg(u_held, t_held))
    wait_for(lambda: len(applied) >= n_steps and len(states) > n_steps, TIMEOUT, what="all steps")

    xs = by_stamp(states, schema.state_from_msg)
    us = by_stamp(applied, schema.control_from_msg)
    stamps = sorted(xs)
    assert np.diff(stamps[: n_steps + 1]).tolist() == [DT_NS] * n_steps
    for t in stamps[:n_steps]:
        np.testing.assert_array_equal(us[t], sent[t])  # exactly the command answering x(t), clipped
        assert xs[t][2] > 0.5  # far from the ground: no contact involved
        np.testing.assert_allclose(xs[t + DT_NS], quad.true_step_np(xs[t], us[t]), rtol=0, atol=1e-9)
    clock_ns = {clock_from_msg(c) for c in list(clock)}
    assert set(stamps[: n_steps + 1]) <= clock_ns

    name = f"{ns}/quadrotor_sim"
    wait_for(lambda: counter(diags, name, "steps") >= n_steps, TIMEOUT, what="diagnostics")
    values = diagnostics_of(diags, name)
    for key in ("rejected/nan", "rejected/shape", "rejected/bounds", "rejected/late", "cmd_clipped"):
        assert int(values.get(key, 0)) == 1, (key, values)
    assert int(values.get("lockstep_misses", 0)) == 0 and values["mode"] == "lockstep"
    assert sim.alive()
    start = time.monotonic()
    assert sim.stop(timeout=10.0) == 0 and time.monotonic() - start < 5.0


def test_friction_realtime_timeout_reset_misses_and_shutdown(ros_env: RosDomain, ros_node: TestNode) -> None:
    schema = get_schema("friction")
    qos = DATA_QOS.to_rclpy()
    rt, ls = "/rt", "/ls"
    cmd_pub = ros_node.publisher(JointState, f"{rt}/cmd", qos)
    states = ros_node.subscribe(JointState, f"{rt}/state", qos)
    applied = ros_node.subscribe(JointState, f"{rt}/applied_cmd", qos)
    ls_applied = ros_node.subscribe(JointState, f"{ls}/applied_cmd", qos)
    ls_states = ros_node.subscribe(JointState, f"{ls}/state", qos)
    diags = ros_node.subscribe(DiagnosticArray, "/diagnostics")
    realtime = ros_env.launch(
        "friction_sim", "-p", "mode:=realtime", "-p", "rate_hz:=20.0", "-p", "cmd_timeout:=0.3",
        "-p", "start_delay:=0.3", "-p", "seed:=1", "-p", "diagnostics_period:=0.3", "-p", "publish_clock:=false",
        namespace=rt,
    )
    # lockstep with a controller that never answers: every state is a miss; max_sim_time ends the run
    ros_node.publisher(JointState, f"{ls}/cmd", qos)  # the simulator waits for a cmd publisher to exist
    lockstep = ros_env.launch(
        "friction_sim", "-p", "mode:=lockstep", "-p", "lockstep_timeout:=0.25",
        "-p", "cmd_timeout:=0.15", "-p", "start_delay:=0.3", "-p", "max_sim_time:=0.5",
        "-p", "diagnostics_period:=0.3", namespace=ls,
    )
    wait_for(lambda: len(states) >= 3, TIMEOUT, what=f"realtime states; output:\n{realtime.output()}")

    # hold a command, then stop sending: after cmd_timeout the safe default u = 0 applies
    stop_sending = threading.Event()

    def send() -> None:
        while not stop_sending.is_set():
            _, t = schema.state_from_msg(states[-1])
            cmd_pub.publish(schema.control_to_msg(np.array([3.0]), t))
            time.sleep(0.05)

    sender = threading.Thread(target=send, daemon=True)
    sender.start()
    wait_for(lambda: any(schema.control_from_msg(m)[0][0] == 3.0 for m in list(applied)), TIMEOUT, what="u = 3")
    time.sleep(0.5)
    stop_sending.set()
    sender.join()
    n_sent = len(applied)

    def tail() -> list[float]:
        return [schema.control_from_msg(m)[0][0] for m in list(applied)[n_sent:]]

    # the held u = 3 for cmd_timeout = 0.3 s more, then u = 0 for good
    wait_for(lambda: tail()[-5:] == [0.0] * 5, TIMEOUT, what="the safe default after cmd_timeout")
    values = tail()
    first_zero = values.index(0.0)
    assert set(values[:first_zero]) <= {3.0} and set(values[first_zero:]) == {0.0}, values
    name = f"{rt}/friction_sim"
    wait_for(lambda: counter(diags, name, "cmd_timeouts") > 0, TIMEOUT, what="cmd_timeouts on /diagnostics")

    # reset: the next state is 2 dt later and the last state before it has no applied_cmd
    response = ros_node.call(Trigger, f"{rt}/friction_sim/reset")
    assert response.success
    n_reset = len(states)
    wait_for(lambda: len(states) >= n_reset + 4, TIMEOUT, what="states after the reset")
    stamps = [schema.state_from_msg(m)[1] for m in list(states)]
    gaps = np.diff(stamps) // DT_NS
    assert gaps.tolist().count(2) == 1 and set(gaps.tolist()) == {1, 2}
    jump = int(np.argmax(gaps))
    # every state with a successor dt later has its applied_cmd: checked from the first applied_cmd this node
    # received (the two subscriptions are matched by discovery one after the other, so the first states can come
    # before the applied_cmd subscription exists), once the applied_cmd stream has caught up with the states
    first = min(schema.control_from_msg(m)[1] for m in list(applied))
    expected = {stamps[i] for i in range(len(stamps) - 1) if gaps[i] == 1 and stamps[i] >= first}

    def applied_stamps() -> set[int]:
        return {schema.control_from_msg(m)[1] for m in list(applied)}

    wait_for(lambda: expected <= applied_stamps(), TIMEOUT, what="an applied_cmd for every state stepped from")
    assert stamps[jump] not in applied_stamps()
    assert len(expected) >= 10, (len(expected), len(stamps))  # the check covers most of the run
    after = schema.state_from_msg(states[jump + 1])[0]
    assert -2.0 <= after[0] <= 2.0 and after[1] == 0.0

    # SIGTERM ends the realtime node cleanly
    start = time.monotonic()
    realtime.signal(signal.SIGTERM)
    assert realtime.wait(10.0) == 0 and time.monotonic() - start < 5.0

    # the lockstep node missed every state, applied the safe default and exited at max_sim_time
    assert lockstep.wait(TIMEOUT) == 0, lockstep.output()
    assert [schema.control_from_msg(m)[0][0] for m in list(ls_applied)] == [0.0] * 5
    assert len(ls_states) == 6
    ls_name = f"{ls}/friction_sim"
    assert counter(diags, ls_name, "lockstep_misses") == 5 and counter(diags, ls_name, "cmd_timeouts") == 5


def test_paddle_ball_lockstep_publishes_state_applied_cmd_and_post_impact_with_one_stamp(
    ros_env: RosDomain, ros_node: TestNode
) -> None:
    schema = get_schema("paddle_ball")
    qos = DATA_QOS.to_rclpy()
    ns = "/paddle_ball"
    cmd_pub = ros_node.publisher(JointState, f"{ns}/cmd", qos)
    u = np.array([0.0, 0.0, 1.0, -math.sin(0.2), 0.0, math.cos(0.2)])  # real normal vertical (bias 0.2 rad)

    def answer(msg: Odometry) -> None:
        cmd_pub.publish(schema.control_to_msg(u, schema.state_from_msg(msg)[1]))

    states = ros_node.subscribe(Odometry, f"{ns}/state", qos, callback=answer)
    applied = ros_node.subscribe(JointState, f"{ns}/applied_cmd", qos)
    post = ros_node.subscribe(TwistStamped, f"{ns}/post_impact", qos)
    flight = ros_node.subscribe(Odometry, f"{ns}/flight")
    sim = ros_env.launch("paddle_ball_sim", "-p", "mode:=lockstep", "-p", "initial_state:=[0.0, 0.0, 1.0, 0.0, 0.0, 0.0]",
                         "-p", "start_delay:=0.3", "-p", "lockstep_timeout:=20.0")
    try:
        wait_for(lambda: len(post) >= 3 and len(states) >= 4, TIMEOUT, what="3 impacts")
    except TimeoutError as exc:
        raise AssertionError(f"{exc}: {len(states)} states, {len(applied)} applied, {len(post)} impacts; simulator "
                             f"{'alive' if sim.alive() else 'exited'}, output:\n{sim.output()}") from None
    xs = by_stamp(states, schema.state_from_msg)
    us = by_stamp(applied, schema.control_from_msg)
    ys = by_stamp(post, schema.target_from_msg)
    assert set(ys) == set(us) and set(us) <= set(xs)
    for t, y in ys.items():
        np.testing.assert_allclose(us[t], np.concatenate((u[:3], u[3:] / np.linalg.norm(u[3:]))), atol=1e-12)
        assert abs(xs[t][2]) < 1e-9 and xs[t][5] < -3.0 and y[2] > 3.0  # falling at the plane, bounced up
    # flight is telemetry (keep last 10): in lockstep a whole flight's samples leave in one burst, and a loaded
    # machine delivers some after the impacts that ended the wait, or drops part of a burst; more flights follow.
    wait_for(lambda: len(flight) > 10, TIMEOUT, what="11 flight samples")
    assert sim.stop() == 0


def test_lockstep_max_speed_limits_simulated_seconds_per_wall_second(ros_env: RosDomain,
                                                                     ros_node: TestNode) -> None:
    """``max_speed``: an instant controller would run the lockstep friction loop at hundreds of times real time; at
    ``max_speed:=2`` the 3 simulated seconds take at least 1.5 wall seconds, and the waits are counted (50 ms of
    wall time per step: a round trip to this test's controller on a loaded machine stays below it, so the
    simulator waits; at 5x, 20 ms a step, a slow round trip left nothing to wait)."""
    schema = get_schema("friction")
    qos = DATA_QOS.to_rclpy()
    ns = "/paced"
    cmd_pub = ros_node.publisher(JointState, f"{ns}/cmd", qos)
    arrivals: list[tuple[float, int]] = []

    def answer(msg: JointState) -> None:
        _, t = schema.state_from_msg(msg)
        arrivals.append((time.monotonic(), t))
        cmd_pub.publish(schema.control_to_msg(np.zeros(1), t))

    ros_node.subscribe(JointState, f"{ns}/state", qos, callback=answer)
    diags = ros_node.subscribe(DiagnosticArray, "/diagnostics")
    sim = ros_env.launch(
        "friction_sim", "-p", "mode:=lockstep", "-p", "max_speed:=2.0", "-p", "max_sim_time:=3.0",
        "-p", "start_delay:=0.3", "-p", "lockstep_timeout:=20.0", "-p", "diagnostics_period:=0.2",
        "-p", "publish_clock:=false", namespace=ns,
    )
    assert sim.wait(TIMEOUT) == 0, sim.output()
    assert "at most 2x real time" in sim.output()
    assert len(arrivals) >= 25, sim.output()
    (w0, t0), (w1, t1) = arrivals[0], arrivals[-1]
    sim_span = (t1 - t0) * 1e-9
    assert sim_span >= 2.4
    assert w1 - w0 >= 0.95 * sim_span / 2.0, (w1 - w0, sim_span)
    name = f"{ns}/friction_sim"
    wait_for(lambda: float(diagnostics_of(diags, name).get("max_speed_waited_s", 0.0)) > 0.1, 10.0,
             what="the waits counted on /diagnostics")
    assert counter(diags, name, "lockstep_misses") == 0
