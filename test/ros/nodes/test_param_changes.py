"""Parameter changes on running nodes and parameters at start-up, through real processes and the real parameter
service (``rcl_interfaces/srv/SetParameters``, what ``ros2 param set`` calls; its exit code is 0 even when the node
refuses, so the tests read the service's result).

* one test per parameter class on a running node: a bad value is refused with its reason, the node keeps doing
  what it did and ``GetParameters`` still reports the old value; a good value takes effect (float: the learner's
  ``checkpoint_period`` changes how often checkpoints are written, the MPC's ``deadline_ms`` what counts as a
  miss; int: a simulator's ``episode_steps`` how often episodes end; string choice and int through configure: the
  MPC's ``mode`` and ``horizon`` after deactivate / cleanup / configure / activate; list: the quadrotor MPC's
  ``goal.position`` changes its commands);
* start-up: every executable exits 2 naming a parameter it does not declare; several bad parameters are reported
  together; ``system`` with ``system_file`` is refused, and the MPC (no ``system_file`` yet) refuses that name.
"""

from __future__ import annotations

import re
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from helpers import REPO
from helpers.ros_helpers import Process, RosDomain, TestNode, wait_for

rclpy = pytest.importorskip("rclpy")


SYSTEM_FILE = REPO / "examples" / "diff_drive" / "system.yaml"


# ----------------------------------------------------------------------------------------------- helpers
def set_param(probe: TestNode, node: str, name: str, value: Any) -> tuple[bool, str]:
    """``(successful, reason)`` of setting ``name`` on ``node`` through its SetParameters service."""
    from rcl_interfaces.srv import SetParameters
    from rclpy.parameter import Parameter

    request = SetParameters.Request(parameters=[Parameter(name, value=value).to_parameter_msg()])
    # sent again after 15 s without an answer (a lost request or response): setting one value twice changes nothing
    # (a refusal would be counted twice: 15 s is far beyond a loaded node's answer)
    result = probe.call(SetParameters, f"{node}/set_parameters", request, resend_after=15.0).results[0]
    return bool(result.successful), str(result.reason)


def get_param(probe: TestNode, node: str, name: str) -> Any:
    """The value ``node``'s GetParameters service reports for ``name``."""
    from rcl_interfaces.srv import GetParameters
    from rclpy.parameter import parameter_value_to_python

    response = probe.call(GetParameters, f"{node}/get_parameters", GetParameters.Request(names=[name]),
                          resend_after=5.0)
    value = parameter_value_to_python(response.values[0])
    return list(value) if isinstance(value, list | tuple) or hasattr(value, "tolist") else value


def refused(probe: TestNode, node: str, name: str, value: Any, reason: str, old: Any) -> None:
    """Setting ``name`` to ``value`` is refused with a reason matching ``reason``, and the old value stays."""
    ok, why = set_param(probe, node, name, value)
    assert not ok, f"{name} = {value!r} was accepted"
    assert re.search(reason, why), (name, value, why)
    assert get_param(probe, node, name) == old


def change_state(probe: TestNode, node: str, label: str) -> bool:
    from lifecycle_msgs.msg import Transition
    from lifecycle_msgs.srv import ChangeState

    request = ChangeState.Request(transition=Transition(label=label))
    return bool(probe.call(ChangeState, f"{node}/change_state", request).success)


def wait_log(proc: Process, text: str, timeout: float = 90.0) -> None:
    wait_for(lambda: text in proc.output() or not proc.alive(), timeout, what=f"{text!r} in the {proc.name} log")
    assert text in proc.output(), f"{proc.name} exited ({proc.popen.poll()}):\n{proc.output()[-3000:]}"


class Diagnostics:
    """The newest /diagnostics values of one node (by its status name), and when each status arrived."""

    def __init__(self, probe: TestNode, name: str) -> None:
        from diagnostic_msgs.msg import DiagnosticArray

        from msg_schemas import TELEMETRY_QOS
        from msg_schemas.telemetry import diagnostics_from_msg

        self.name = name
        self.values: dict[str, str] = {}
        self.times: list[float] = []

        def on_msg(msg: Any) -> None:
            for entry in diagnostics_from_msg(msg)[0]:
                if entry.name == name:
                    self.values = dict(entry.values)
                    self.times.append(time.monotonic())

        probe.subscribe(DiagnosticArray, "/diagnostics", TELEMETRY_QOS.to_rclpy(), on_msg)

    def get(self, key: str, default: float = -1.0) -> float:
        return float(self.values.get(key, default))

    def rate(self, since: float) -> float:
        """Statuses per second received after ``since`` (monotonic s)."""
        times = [t for t in self.times if t >= since]
        return (len(times) - 1) / (times[-1] - times[0]) if len(times) > 2 else 0.0


def friction_transitions(n: int, seed: int = 0) -> list[tuple[str, int, np.ndarray]]:
    """``n`` friction transitions as (kind, stamp ns, vector) events: episodes of 20 steps from the paper's input
    distribution, each state followed by its applied command, episodes 3 dt apart."""
    from saml_ros.core.systems import get_system

    system = get_system("friction")
    rng = np.random.default_rng(seed)
    dt_ns = int(round(system.dt * 1e9))
    events: list[tuple[str, int, np.ndarray]] = []
    t = 1_000_000_000
    x = system.sample_inputs(1, rng)[0][0]
    for k in range(n):
        if k % 20 == 0 and k:
            events.append(("state", t, x))
            t += 3 * dt_ns
            x = system.sample_inputs(1, rng)[0][0]
        u = system.sample_inputs(1, rng)[1][0]
        events += [("state", t, x), ("applied_cmd", t, u)]
        x = system.true_step_np(x, u)
        t += dt_ns
    events.append(("state", t, x))
    return events


# ----------------------------------------------------------------------------------------------- learner
def test_learner_float_parameter_refused_when_bad_and_a_new_checkpoint_period_changes_how_often_it_writes(
        ros_env: RosDomain, ros_node: TestNode, tmp_path: Path) -> None:
    """Float (``checkpoint_period``, applies at once): ``abc``, ``-5.0`` refused with the reason, no checkpoint
    appears at the old period of 1000 s, the service reports 1000.0; ``0.5`` makes checkpoints appear every
    half second. Other classes on the same node: a string choice (``buffer.policy lifo``), an unknown ``system``,
    a string for a float (``train.primal_lr fast``), a batch the machine cannot hold and a valid change of a
    parameter read at configure are refused, each with its reason."""
    from sensor_msgs.msg import JointState

    from msg_schemas import DATA_QOS, get_schema

    node = "/friction/learner"
    learner = ros_env.launch("learner", "-p", f"run_dir:={tmp_path / 'run'}", "-p", "min_transitions:=100",
                             "-p", "checkpoint_period:=1000.0", "-p", "diagnostics_rate:=4.0", namespace="/friction")
    diag = Diagnostics(ros_node, node)
    schema = get_schema("friction")
    pubs = {kind: ros_node.publisher(JointState, f"/friction/{kind}", DATA_QOS.to_rclpy())
            for kind in ("state", "applied_cmd")}
    wait_log(learner, "training starts after")
    wait_for(lambda: all(p.get_subscription_count() > 0 for p in pubs.values()), 60, what="the learner's subscriptions")
    for kind, stamp, vec in friction_transitions(300):
        msg = schema.state_to_msg(vec, stamp) if kind == "state" else schema.control_to_msg(vec, stamp)
        pubs[kind].publish(msg)
        time.sleep(0.002)
    wait_for(lambda: diag.get("updates", 0) > 0, 90, what="training updates")

    refused(ros_node, node, "checkpoint_period", "abc", r"parameter 'checkpoint_period': expected float, got 'abc'",
            1000.0)
    refused(ros_node, node, "checkpoint_period", -5.0, r"parameter 'checkpoint_period' must be > 0, got -5\.0", 1000.0)
    refused(ros_node, node, "buffer.policy", "lifo", r"parameter 'buffer.policy' must be one of \['fifo', 'reservoir'\]",
            "fifo")
    refused(ros_node, node, "system", "bogus", r"parameter 'system': unknown system 'bogus'", "friction")
    refused(ros_node, node, "train.primal_lr", "fast", r"parameter 'train.primal_lr': expected float, got 'fast'",
            0.003)
    refused(ros_node, node, "train.batch_size", 10**12,
            r"parameter 'train.batch_size': minibatches of 1000000000000 .* would take 1\d\d\.\d\d TiB, more than the",
            128)
    refused(ros_node, node, "buffer.policy", "reservoir", r"read at configure and /friction/learner is configured: "
            r"deactivate it and clean it up", "fifo")
    # the node keeps its behaviour: still training, no checkpoint at the period of 1000 s
    updates = diag.get("updates")
    wait_for(lambda: diag.get("updates") > updates, 60, what="more updates")
    assert diag.get("checkpoints_written", 0) == 0 and not list((tmp_path / "run").glob("*.saml")), diag.values
    assert diag.get("parameter_changes_refused") >= 7, diag.values
    assert learner.alive()

    ok, why = set_param(ros_node, node, "checkpoint_period", 0.5)
    assert ok, why
    assert get_param(ros_node, node, "checkpoint_period") == 0.5
    wait_log(learner, "parameter change applied: checkpoint_period = 0.5")
    t0 = time.monotonic()
    wait_for(lambda: diag.get("checkpoints_written", 0) >= 4, 60, what="4 checkpoints at the new period")
    assert time.monotonic() - t0 < 30  # 4 at 0.5 s (plus training time under load), against none in 1000 s
    assert learner.alive()


# ----------------------------------------------------------------------------------------------- MPC
class MpcProbe:
    """States to a quadrotor MPC and its commands and statuses back."""

    def __init__(self, probe: TestNode) -> None:
        from nav_msgs.msg import Odometry
        from sensor_msgs.msg import JointState

        from msg_schemas import DATA_QOS, TELEMETRY_QOS, get_schema
        from msg_schemas.telemetry import mpc_status_from_msg

        self.schema = get_schema("quadrotor")
        self.cmds: dict[int, np.ndarray] = {}
        self.status: dict[int, dict[str, float]] = {}
        self.state_pub = probe.publisher(Odometry, "/quadrotor/state", DATA_QOS.to_rclpy())

        def on_cmd(msg: Any) -> None:
            u, stamp = self.schema.control_from_msg(msg)
            self.cmds[stamp] = u

        self.cmd_sub = probe.subscribe(JointState, "/quadrotor/cmd", DATA_QOS.to_rclpy(), on_cmd)
        def on_status(msg: Any) -> None:
            values, stamp = mpc_status_from_msg(msg)
            self.status[stamp] = values

        probe.subscribe(JointState, "/quadrotor/mpc/status", TELEMETRY_QOS.to_rclpy(), on_status)
        self.stamp = 1_000_000_000

    def step(self, x: np.ndarray, proc: Process, timeout: float = 30.0) -> np.ndarray:
        """Publish ``x`` (the next stamp, 0.1 s on) until its command and status arrive (the first may be lost to
        discovery); the command."""
        self.stamp += 100_000_000
        stamp = self.stamp
        deadline = time.monotonic() + timeout
        while stamp not in self.cmds:
            assert proc.alive(), proc.output()[-3000:]
            assert time.monotonic() < deadline, f"no cmd for {stamp}:\n{proc.output()[-3000:]}"
            self.state_pub.publish(self.schema.state_to_msg(x, stamp))
            t_end = time.monotonic() + 1.0
            while stamp not in self.cmds and time.monotonic() < t_end:
                time.sleep(0.01)
        wait_for(lambda: stamp in self.status, timeout, what=f"the status of {stamp}")
        return self.cmds[stamp]

    def last_status(self) -> dict[str, float]:
        return self.status[self.stamp]


def test_mpc_list_float_string_choice_and_int_parameters_checked_and_good_ones_take_effect(
        ros_env: RosDomain, ros_node: TestNode) -> None:
    """The quadrotor MPC. List (``goal.position``, live): a wrong length and strings refused, the commands and the
    reported value unchanged; a new goal changes the commands. Float (``deadline_ms``, live): ``-1.0`` and ``abc``
    refused, ``0.001`` makes every step a deadline miss. String choice (``mode``) and int (``horizon``), read at
    configure: a bad choice / range refused with the reason, a good value refused while active ("deactivate it
    and clean it up"), accepted once unconfigured and in effect after configure + activate. ``system`` (start-up
    only) is refused with "restart"."""
    from saml_ros.core.systems import get_system

    node = "/quadrotor/mpc"
    mpc = ros_env.launch("mpc", "-p", "system:=quadrotor", namespace="/quadrotor")
    probe = MpcProbe(ros_node)
    wait_log(mpc, "commands once active")
    x = get_system("quadrotor").hover_state((0.5, -0.3, 1.0))  # type: ignore[attr-defined]
    for _ in range(3):
        u0 = probe.step(x, mpc)

    # list
    refused(ros_node, node, "goal.position", [1.0, 2.0], r"goal.position must be 3 finite", [0.0, 0.0, 0.0])
    refused(ros_node, node, "goal.position", ["a", "b", "c"], r"parameter 'goal.position': expected a list of float",
            [0.0, 0.0, 0.0])
    np.testing.assert_allclose(probe.step(x, mpc), u0, atol=1e-3)  # same goal, same command
    ok, why = set_param(ros_node, node, "goal.position", [2.0, 1.0, 2.0])
    assert ok, why
    assert get_param(ros_node, node, "goal.position") == [2.0, 1.0, 2.0]
    for _ in range(3):
        u1 = probe.step(x, mpc)
    assert np.max(np.abs(u1 - u0)) > 0.05, (u0, u1)  # a goal 1.5 m away and 1 m up: other commands

    # float
    misses = probe.last_status()["deadline_misses"]
    refused(ros_node, node, "deadline_ms", -1.0, r"parameter 'deadline_ms' must be >= 0, got -1\.0", 0.0)
    refused(ros_node, node, "deadline_ms", "abc", r"parameter 'deadline_ms': expected float, got 'abc'", 0.0)
    probe.step(x, mpc)
    assert probe.last_status()["deadline_misses"] == misses  # the 100 ms deadline: no miss
    ok, why = set_param(ros_node, node, "deadline_ms", 0.001)
    assert ok, why
    probe.step(x, mpc)
    probe.step(x, mpc)
    assert probe.last_status()["deadline_misses"] == misses + 2  # no solve takes under a microsecond

    # string choice and int, read at configure; and a parameter read at start-up
    refused(ros_node, node, "mode", "fast", r"parameter 'mode' must be one of \('lockstep', 'realtime'\), got 'fast'",
            "lockstep")
    refused(ros_node, node, "horizon", -3, r"parameter 'horizon' must be >= 1, got -3", 10)
    # rclpy's own check of an int parameter's type (its reason does not name the parameter)
    refused(ros_node, node, "horizon", "abc", r"Wrong parameter type, expected 'Type.INTEGER' got 'Type.STRING'", 10)
    refused(ros_node, node, "mode", "realtime", r"parameter 'mode' is read at configure and /quadrotor/mpc is "
            r"configured: deactivate it and clean it up", "lockstep")
    refused(ros_node, node, "horizon", 5, r"parameter 'horizon' is read at configure", 10)
    refused(ros_node, node, "system", "friction", r"parameter 'system' is read only at start-up: restart "
            r"/quadrotor/mpc", "quadrotor")
    probe.step(x, mpc)  # still answering
    assert change_state(ros_node, node, "deactivate") and change_state(ros_node, node, "cleanup")
    for name, value in (("mode", "realtime"), ("horizon", 5)):
        ok, why = set_param(ros_node, node, name, value)
        assert ok, (name, why)
    assert change_state(ros_node, node, "configure") and change_state(ros_node, node, "activate")
    wait_log(mpc, "quadrotor MPC (fast, QP")
    assert re.search(r"T=5, realtime at 10 Hz", mpc.output()), mpc.output()[-2000:]
    probe.step(x, mpc)  # answered by the realtime timer
    assert mpc.alive()


# ----------------------------------------------------------------------------------------------- simulator
def test_simulator_int_and_float_parameters_checked_and_good_ones_take_effect(ros_env: RosDomain,
                                                                              ros_node: TestNode) -> None:
    """friction_sim in realtime. Int (``episode_steps``, live): ``-1`` and ``2.5`` refused, the old value kept;
    ``5`` makes an episode end every 5 steps. Float (``diagnostics_period``, live): ``0`` refused, ``0.2`` turns
    1 status a second into 5. A list (``initial_state``) and a seed, read at start-up: refused with "restart"."""
    node = "/friction/friction_sim"
    sim = ros_env.launch("friction_sim", "-p", "mode:=realtime", "-p", "rate_hz:=20.0", "-p", "start_delay:=0.2",
                         "-p", "publish_clock:=false", "-p", "episode_steps:=1000", namespace="/friction")
    diag = Diagnostics(ros_node, node)
    wait_for(lambda: diag.get("steps", 0) > 0, 60, what="simulator steps")

    refused(ros_node, node, "episode_steps", -1, r"parameter 'episode_steps' must be >= 0, got -1", 1000)
    refused(ros_node, node, "episode_steps", 2.5, r"parameter 'episode_steps': expected int, got 2\.5", 1000)
    refused(ros_node, node, "diagnostics_period", 0.0, r"parameter 'diagnostics_period' must be > 0", 1.0)
    refused(ros_node, node, "diagnostics_period", "abc", r"expected float, got 'abc'", 1.0)
    refused(ros_node, node, "initial_state", ["a"], r"parameter 'initial_state': expected a list of float", [])
    refused(ros_node, node, "initial_state", [1.0, 0.0], r"parameter 'initial_state' is read only at start-up: "
            r"restart /friction/friction_sim", [])
    refused(ros_node, node, "seed", 3, r"read only at start-up", 0)
    steps = diag.get("steps")
    wait_for(lambda: diag.get("steps") >= steps + 30, 60, what="30 more steps")
    assert diag.get("episodes_completed", 0) <= 0 and diag.get("parameter_changes_refused") == 7, diag.values
    t_slow = time.monotonic()
    wait_for(lambda: time.monotonic() - t_slow > 3.5, 10)
    slow = diag.rate(t_slow)

    for name, value in (("episode_steps", 5), ("diagnostics_period", 0.2)):
        ok, why = set_param(ros_node, node, name, value)
        assert ok, (name, why)
        assert get_param(ros_node, node, name) == value
    steps, t_fast = diag.get("steps"), time.monotonic()
    wait_for(lambda: diag.get("steps") >= steps + 40, 60, what="40 more steps")
    assert diag.get("episodes_completed") >= 6, diag.values  # 40 steps of 5-step episodes
    fast = diag.rate(t_fast)
    assert 0.6 < slow < 1.5 and fast > 3.0, (slow, fast)
    assert sim.alive()


# ----------------------------------------------------------------------------------------------- start-up
#: executable -> (arguments before --ros-args, ROS arguments that would start it)
STARTS: dict[str, tuple[list[str], list[str]]] = {
    "learner": ([], []),
    "mpc": ([], []),
    "friction_sim": ([], ["-p", "mode:=realtime"]),
    "quadrotor_sim": ([], ["-p", "mode:=realtime"]),
    "paddle_ball_sim": ([], ["-p", "mode:=realtime"]),
    "lifecycle_manager": ([], []),
    "foxglove_server": ([], ["-p", "port:=0"]),
    "record": (["--system", "friction", "-o", "BAG"], []),
    "play": (["BAG"], []),
}


def _bag(path: Path) -> Path:
    """A small friction bag (three states) for ``play``."""
    from msg_schemas import DATA_QOS, TypestoreFactory, get_schema
    from saml_ros.bags.io import BagWriter, jazzy_typestore

    factory = TypestoreFactory(jazzy_typestore())
    schema = get_schema("friction")
    with BagWriter(path) as w:
        w.add_topic("/friction/state", "sensor_msgs/msg/JointState", DATA_QOS)
        for k in range(1, 4):
            w.write_msg("/friction/state", schema.state_to_msg(np.zeros(2), k * 10**9, factory=factory), k * 10**9)
    return path


def test_every_executable_exits_2_naming_a_parameter_it_does_not_declare(ros_env: RosDomain, tmp_path: Path) -> None:
    """``-p checkpont_period:=3.0`` (a typo) and ``-p bogus:=1``: rclpy would ignore both; every node exits 2 and
    names them, with a suggestion where one is close."""
    procs = {}
    bag = _bag(tmp_path / "in_bag")
    for exe, (args, ros) in STARTS.items():
        args = [str(bag if exe == "play" else tmp_path / "out_bag") if a == "BAG" else a for a in args]
        procs[exe] = ros_env.launch(exe, *ros, "-p", "checkpont_period:=3.0", "-p", "bogus:=1", args=args,
                                    namespace="/friction")
    for exe, proc in procs.items():
        rc = proc.wait(120)
        log = proc.output()
        assert rc == 2, (exe, rc, log[-3000:])
        assert "parameter 'bogus' is not a parameter of" in log, (exe, log[-3000:])
        assert "parameter 'checkpont_period' is not a parameter of" in log, (exe, log[-3000:])
    assert "did you mean 'checkpoint_period'" in procs["learner"].output()


def test_several_bad_parameters_are_reported_together_and_system_with_system_file_is_refused(
        ros_env: RosDomain, tmp_path: Path) -> None:
    """Start-up reports every bad parameter at once (the learner at configure, the MPC, a simulator); the learner
    and the MPC refuse ``system`` with ``system_file`` (never running as another system's controller)."""
    runs = {
        "learner": (ros_env.launch(
            "learner", "-p", f"run_dir:={tmp_path / 'r1'}", "-p", "checkpoint_period:=-5.0", "-p", "buffer.policy:=lifo",
            "-p", "train.primal_lr:=fast", "-p", "checkpoint_keep:=abc", "-p", "train.batch_size:=1000000000000",
            namespace="/friction"),
            ["parameter 'checkpoint_period' must be > 0", "parameter 'buffer.policy' must be one of",
             "parameter 'train.primal_lr': expected float, got 'fast'", "parameter 'checkpoint_keep': expected int",
             "parameter 'train.batch_size': minibatches of 1000000000000"]),
        "learner_file": (ros_env.launch(
            "learner", "-p", f"run_dir:={tmp_path / 'r2'}", "-p", "system:=friction", "-p", f"system_file:={SYSTEM_FILE}",
            namespace="/friction"),
            ["parameters 'system' and 'system_file' were both given"]),
        "mpc": (ros_env.launch(
            "mpc", "-p", "mode:=fast", "-p", "rate_hz:=abc", "-p", "horizon:=0", "-p", "solver:=ipopt",
            namespace="/friction"),
            ["parameter 'mode' must be one of", "parameter 'rate_hz': expected float", "parameter 'horizon' must be >= 1",
             "parameter 'solver' must be one of"]),
        "mpc_file": (ros_env.launch("mpc", "-p", "system:=friction", "-p", f"system_file:={SYSTEM_FILE}",
                                    namespace="/dd"),
                     ["parameters 'system' and 'system_file' were both given"]),
        "sim": (ros_env.launch(
            "friction_sim", "-p", "mode:=x", "-p", "rate_hz:=abc", "-p", "seed:=1.5", "-p", "max_speed:=-1.0",
            namespace="/friction"),
            ["parameter 'mode' must be one of", "parameter 'rate_hz': expected float", "parameter 'seed': expected int",
             "parameter 'max_speed' must be >= 0"]),
    }
    for name, (proc, texts) in runs.items():
        rc = proc.wait(120)
        log = proc.output()
        assert rc == 2, (name, rc, log[-3000:])
        lines = [line for line in log.splitlines() if all(t in line for t in texts)]
        assert lines, (name, texts, log[-3000:])  # all of them on one line: reported together
