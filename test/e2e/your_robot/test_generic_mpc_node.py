"""The MPC node with ``system_file:=`` (docs/your_robot.md, "Control it"), real processes: it commands the robot on
the robot's own topic with the robot's own message type (the example diff-drive's unstamped Twist, a WrenchStamped,
a Float64MultiArray), drives the example robot (its own rclpy node, knowing nothing of saml_ros) to its dock, refuses
and counts a NaN or out-of-bounds goal while keeping the last one, answers a stale state with the safe command, and
ends with exit 2 naming the key of a wrong ``mpc:`` section."""

from __future__ import annotations

import copy
import math
import os
import sys
import time
from pathlib import Path
from typing import Any

import pytest
import yaml
from helpers.ros_helpers import Process, RosDomain, TestNode, wait_for
from helpers.your_robot import launch_script

REPO = Path(__file__).resolve().parents[3]
EXAMPLE = REPO / "examples" / "diff_drive"
SYSTEM_FILE = EXAMPLE / "system.yaml"
NS = "/dd"


#: robots these tests load from system files are forgotten after each test (test/conftest.py)
pytestmark = pytest.mark.usefixtures("restore_registry")


def launch_robot(dom: RosDomain) -> Process:
    """The example robot (examples/diff_drive/robot.py, a plain rclpy node) in the test's domain."""
    return launch_script(dom, EXAMPLE / "robot.py")


def diagnostics_of(received: list[Any], node_suffix: str) -> dict[str, str]:
    """The newest /diagnostics values of the node whose name ends with ``node_suffix``."""
    for msg in reversed(received):
        for status in msg.status:
            if status.name.endswith(node_suffix):
                return {kv.key: kv.value for kv in status.values}
    return {}


def pose_msg(x: float, y: float, yaw: float) -> Any:
    from geometry_msgs.msg import PoseStamped

    msg = PoseStamped()
    msg.pose.position.x, msg.pose.position.y = x, y
    msg.pose.orientation.z, msg.pose.orientation.w = math.sin(yaw / 2), math.cos(yaw / 2)
    return msg


def test_mpc_drives_the_example_robot_on_its_own_topic(ros_env: RosDomain, ros_node: TestNode) -> None:
    from diagnostic_msgs.msg import DiagnosticArray
    from geometry_msgs.msg import PoseStamped, Twist
    from nav_msgs.msg import Odometry

    cmds = ros_node.subscribe(Twist, f"{NS}/cmd_vel")
    odom = ros_node.subscribe(Odometry, f"{NS}/odom")
    diag = ros_node.subscribe(DiagnosticArray, "/diagnostics")
    mpc = ros_env.launch("mpc", "-p", f"system_file:={SYSTEM_FILE}", namespace=NS)
    robot = launch_robot(ros_env)
    try:
        wait_for(lambda: len(cmds) > 20 or not mpc.alive(), timeout=90, what="commands on /dd/cmd_vel")
        assert mpc.alive(), mpc.output()
        # the robot (x = 0 at start) drives towards its dock at x = 1.5
        wait_for(lambda: odom and odom[-1].pose.pose.position.x > 1.2, timeout=60, what="the robot near its dock")
        info = wait_for(lambda: "planner" in diagnostics_of(diag, "dd/mpc") and diagnostics_of(diag, "dd/mpc"),
                        timeout=30, what="the MPC's diagnostics")
        assert "Gauss-Newton SQP" in info["planner"] and "unicycle" in info["planner"], info
        # a NaN goal and one outside the goal bounds are refused and counted, the last goal kept
        goals = ros_node.publisher(PoseStamped, f"{NS}/goal_pose")
        wait_for(lambda: goals.get_subscription_count() > 0, timeout=30, what="the MPC's goal subscription")
        goals.publish(pose_msg(math.nan, 0.0, 0.0))
        goals.publish(pose_msg(2.4, 0.0, 0.0))
        wait_for(lambda: diagnostics_of(diag, "dd/mpc").get("rejected/goal") == "2", timeout=30,
                 what="two refused goals on /diagnostics")
        assert diagnostics_of(diag, "dd/mpc")["goal"].startswith("x=1.5, y=0"), "the last goal was not kept"
        goals.publish(pose_msg(0.5, 0.6, 1.0))
        wait_for(lambda: diagnostics_of(diag, "dd/mpc").get("goal", "").startswith("x=0.5, y=0.6"), timeout=30,
                 what="the new goal on /diagnostics")
        wait_for(lambda: math.hypot(odom[-1].pose.pose.position.x - 0.5, odom[-1].pose.pose.position.y - 0.6) < 0.15,
                 timeout=90, what="the robot at the new goal")
        assert mpc.alive() and robot.alive()
    finally:
        code = mpc.stop()
    assert code == 0, mpc.output()


def test_stale_state_gets_the_safe_command(ros_env: RosDomain, ros_node: TestNode) -> None:
    from diagnostic_msgs.msg import DiagnosticArray
    from geometry_msgs.msg import Twist
    from nav_msgs.msg import Odometry

    cmds = ros_node.subscribe(Twist, f"{NS}/cmd_vel")
    diag = ros_node.subscribe(DiagnosticArray, "/diagnostics")
    state = ros_node.publisher(Odometry, f"{NS}/odom")
    mpc = ros_env.launch("mpc", "-p", f"system_file:={SYSTEM_FILE}", namespace=NS)
    wait_for(lambda: state.get_subscription_count() > 0 or not mpc.alive(), timeout=90, what="the MPC subscribed")

    def odometry(age: float) -> Odometry:
        msg = Odometry()
        t = ros_node.node.get_clock().now().nanoseconds - int(age * 1e9)
        msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(t, 1_000_000_000)
        msg.pose.pose.orientation.w = 1.0
        return msg

    # fresh states: the plan drives forward, towards the dock at x = 1.5 (the first answers may come after the
    # state_timeout on a busy machine while the planner warms up: those are safe commands, so keep sending)
    def drives_forward() -> bool:
        state.publish(odometry(0.0))
        time.sleep(0.05)
        return bool(cmds) and cmds[-1].linear.x > 0.1

    wait_for(drives_forward, timeout=30, what="a forward command to a fresh state")
    # the answers to the last fresh states may still be on their way: once the watchdog sends its safe command
    # (no state for state_timeout), they have come (a state is answered within a control period, 0.1 s, shorter)
    wait_for(lambda: bool(cmds) and cmds[-1].linear.x == 0.0 and cmds[-1].angular.z == 0.0, timeout=30,
             what="the watchdog's safe command once the fresh states stop")
    n = len(cmds)
    state.publish(odometry(2.0))  # two seconds old (state_timeout 0.25 s): the safe command
    wait_for(lambda: len(cmds) > n, timeout=30, what="the answer to a stale state")
    assert cmds[n].linear.x == 0.0 and cmds[n].angular.z == 0.0
    # no state at all: the watchdog keeps sending the safe command, counted
    wait_for(lambda: int(diagnostics_of(diag, "dd/mpc").get("safe_commands/stale", "0")) >= 3, timeout=30,
             what="safe commands while no state arrives")
    assert all(c.linear.x == 0.0 for c in cmds[n:])
    assert mpc.stop() == 0


def _custom_robot(tmp_path: Path, control: dict[str, Any]) -> Path:
    """A slider on a rail: JointState in (position and velocity of joint 'slider'), the given command out."""
    dt = 0.02
    definition = {
        "version": 1, "name": "slider", "dt": dt,
        "state": {"topic": "joint_states", "type": "sensor_msgs/msg/JointState", "fields": [
            {"name": "p", "unit": "m", "bounds": [-1.0, 1.0], "path": "position[slider]"},
            {"name": "v", "unit": "m/s", "bounds": [-2.0, 2.0], "path": "velocity[slider]"}]},
        "control": control,
        "base_model": {"builtin": "linear", "params": {"A": [[0.0, dt], [0.0, 0.0]], "B": [[0.0], [dt / 2.0]],
                                                       "c": [0.0, 0.0]}},
        "mpc": {"horizon": 15, "rate": 25, "goal": {"fields": ["p", "v"], "default": [0.5, 0.0]},
                "cost": {"stage": {"p": 10.0, "v": 0.1}, "terminal": {"p": 100.0, "v": 1.0}}},
    }
    path = tmp_path / "slider.yaml"
    path.write_text(yaml.safe_dump(definition))
    return path


@pytest.mark.parametrize("control, msg_type, read", [
    ({"topic": "force", "type": "geometry_msgs/msg/WrenchStamped",
      "fields": [{"name": "f", "unit": "N", "bounds": [-4.0, 4.0], "path": "wrench.force.x"}]},
     "geometry_msgs/msg/WrenchStamped", lambda m: m.wrench.force.x),
    ({"topic": "effort_controller/commands", "type": "std_msgs/msg/Float64MultiArray",
      "fields": [{"name": "f", "unit": "N", "bounds": [-4.0, 4.0], "path": "data[0]"}]},
     "std_msgs/msg/Float64MultiArray", lambda m: m.data[0]),
], ids=["WrenchStamped", "Float64MultiArray"])
def test_mpc_commands_a_robots_own_message_type(ros_env: RosDomain, ros_node: TestNode, tmp_path: Path,
                                                control: dict[str, Any], msg_type: str, read: Any) -> None:
    from sensor_msgs.msg import JointState

    from msg_schemas import RCLPY

    path = _custom_robot(tmp_path, control)
    cmds = ros_node.subscribe(RCLPY.cls(msg_type), f"/slider/{control['topic']}")
    state = ros_node.publisher(JointState, "/slider/joint_states")
    mpc = ros_env.launch("mpc", "-p", f"system_file:={path}")  # its namespace: /<name>
    wait_for(lambda: state.get_subscription_count() > 0 or not mpc.alive(), timeout=90, what="the MPC subscribed")
    assert mpc.alive(), mpc.output()
    p, v = 0.0, 0.0
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and not (len(cmds) > 30 and abs(p - 0.5) < 0.05):
        msg = JointState()
        t = ros_node.node.get_clock().now().nanoseconds
        msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(t, 1_000_000_000)
        msg.name, msg.position, msg.velocity = ["slider"], [p], [v]
        state.publish(msg)
        time.sleep(0.02)
        f = read(cmds[-1]) if cmds else 0.0
        p, v = p + v * 0.02, v + f / 2.0 * 0.02  # the slider, 2 kg, simulated here
    assert cmds and all(isinstance(c, RCLPY.cls(msg_type)) for c in cmds)
    assert abs(p - 0.5) < 0.05, f"the slider at {p:.3f} m after {len(cmds)} commands"
    assert all(-4.0 <= read(c) <= 4.0 for c in cmds)
    assert mpc.stop() == 0


def test_wrong_mpc_section_or_parameters_exit_2_naming_them(ros_env: RosDomain, tmp_path: Path) -> None:
    raw = yaml.safe_load(SYSTEM_FILE.read_text())
    bad = copy.deepcopy(raw)
    bad["mpc"]["cost"]["stage"]["yw"] = 1.0
    (tmp_path / "bad.yaml").write_text(yaml.safe_dump(bad))
    mpc = ros_env.launch("mpc", "-p", f"system_file:={tmp_path / 'bad.yaml'}")
    assert mpc.wait(90) == 2, mpc.output()
    assert "mpc.cost.stage.yw: 'yw' is not a goal field (did you mean 'yaw'?)" in mpc.output()
    both = ros_env.launch("mpc", "-p", "system:=quadrotor", "-p", f"system_file:={SYSTEM_FILE}")
    assert both.wait(90) == 2, both.output()
    assert "parameters 'system' and 'system_file' were both given" in both.output()
    goal = ros_env.launch("mpc", "-p", f"system_file:={SYSTEM_FILE}", "-p", "goal.setpoint:=[9.0, 0.0, 0.0, 0.0, 0.0]")
    assert goal.wait(90) == 2, goal.output()
    assert "goal.setpoint: goal field 'x' = 9 is outside its bounds" in goal.output()


def test_checkpoints_of_a_robot_with_its_own_base_model_are_taken_and_swapped(
        ros_env: RosDomain, ros_node: TestNode, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The robot's f_hat is the user's own torch function (differentiated by autograd in the planner); the
    learner's checkpoints (here written by the same trainer code) are accepted and hot-swapped between two solves,
    with the guard on (5-member ensembles)."""
    import textwrap

    import numpy as np
    import torch
    from diagnostic_msgs.msg import DiagnosticArray

    from saml_ros.core.model.checkpoint import CheckpointStore
    from saml_ros.core.model.network import DynamicsModel
    from saml_ros.core.spec import ProblemSpec
    from saml_ros.core.training import PrimalDualTrainer, TrainConfig, save_checkpoint
    from saml_ros.user_code import load_system_file

    (tmp_path / "dd_user_model.py").write_text(textwrap.dedent("""
        import torch

        def unicycle(x, u, *, dt, tau=0.12):
            a = 1.0 - torch.exp(torch.tensor(-dt / tau, dtype=x.dtype))
            out = x.clone()
            mid = x[:, 2] + 0.5 * u[:, 1] * dt
            out[:, 0] = x[:, 0] + u[:, 0] * torch.cos(mid) * dt
            out[:, 1] = x[:, 1] + u[:, 0] * torch.sin(mid) * dt
            out[:, 2] = x[:, 2] + u[:, 1] * dt
            out[:, 3] = x[:, 3] + a * (u[:, 0] - x[:, 3])
            out[:, 4] = x[:, 4] + a * (u[:, 1] - x[:, 4])
            return out
        """))
    monkeypatch.syspath_prepend(str(tmp_path))
    raw = yaml.safe_load(SYSTEM_FILE.read_text())
    raw["base_model"] = {"function": "dd_user_model:unicycle"}
    path = tmp_path / "robot.yaml"
    path.write_text(yaml.safe_dump(raw))
    system = load_system_file(path)
    store = CheckpointStore(tmp_path / "run")

    def save(seed: int) -> None:
        model = DynamicsModel(system, (32, 32), n_models=5, seed=seed)
        x, u = system.sample_inputs(512, np.random.default_rng(seed))
        model.fit_normalization(x, u, system.base_step_np(x, u) + 0.001)
        with torch.no_grad():
            model.net.weights[-1].normal_(0.0, 1e-3, generator=torch.Generator().manual_seed(seed))
        trainer = PrimalDualTrainer(model, ProblemSpec.for_system(system.paper_spec(), system), TrainConfig())
        save_checkpoint(store, trainer)

    save(1)
    diag = ros_node.subscribe(DiagnosticArray, "/diagnostics")
    launch_robot(ros_env)  # its states: a checkpoint is swapped in right before a solve
    mpc = ros_env.launch("mpc", "-p", f"system_file:={path}", "-p", f"run_dir:={store.run_dir}",
                         "-p", "poll_period:=0.2", "-p", "guard.max_disagreement:=0.05", namespace=NS,
                         env={"PYTHONPATH": os.pathsep.join([str(REPO), str(tmp_path)])})
    info = wait_for(lambda: diagnostics_of(diag, "dd/mpc").get("model_version") == "1" and diagnostics_of(diag, "dd/mpc")
                    or not mpc.alive(), timeout=90, what="checkpoint 1 in use")
    assert mpc.alive(), mpc.output()
    assert info["checkpoints_refused"] == "0", info.get("last_refusal")
    assert "torch autograd" in info["planner"] and "dd_user_model:unicycle" in info["planner"], info["planner"]
    save(2)
    wait_for(lambda: diagnostics_of(diag, "dd/mpc").get("model_version") == "2", timeout=60, what="the hot swap")
    assert mpc.stop() == 0


def test_launch_file_takes_a_system_file() -> None:
    """``ros2 launch saml_ros mpc.launch.xml system_file:=... namespace:=/dd``: one MPC with the file (no system,
    parameter file, mode or rate: the file's), every parameter one the node declares; without it, as before."""
    from helpers.launch_parse import evaluate

    from saml_ros.core.mpc.config import MPCConfig
    from saml_ros.user_code import load_system_file

    load_system_file(SYSTEM_FILE)
    result = evaluate(REPO / "launch" / "mpc.launch.xml", {"system_file": str(SYSTEM_FILE), "namespace": NS,
                                                            "run_dir": "runs/dd"})
    (mpc,) = [n for n in result.nodes if n.executable == "mpc"]
    (manager,) = [n for n in result.nodes if n.executable == "lifecycle_manager"]
    assert mpc.fqn == "/dd/mpc" and manager.namespace == NS and not [s for s in mpc.params if s.path is not None]
    assert mpc.parameters() == {"system_file": str(SYSTEM_FILE), "run_dir": "runs/dd/checkpoints",
                                "use_sim_time": False, "autostart": False}
    assert set(mpc.parameters()) - {"use_sim_time"} <= {p.name for p in MPCConfig.params("diff_drive")} | {"autostart"}
    (plain,) = [n for n in evaluate(REPO / "launch" / "mpc.launch.xml", {"system": "quadrotor"}).nodes
                if n.executable == "mpc"]
    assert plain.parameters()["system"] == "quadrotor" and "system_file" not in plain.parameters()
    # learner.launch.xml with the same arguments writes the checkpoints this MPC reads
    from saml_ros.core.online.config import learner_params

    (learner,) = [n for n in evaluate(REPO / "launch" / "learner.launch.xml", {
        "system_file": str(SYSTEM_FILE), "namespace": NS, "run_dir": "runs/dd"}).nodes if n.executable == "learner"]
    assert learner.fqn == "/dd/learner" and not [s for s in learner.params if s.path is not None]
    assert learner.parameters() == {"system_file": str(SYSTEM_FILE), "run_dir": "runs/dd/checkpoints",
                                    "use_sim_time": False, "autostart": False}
    declared = {p.name for p in learner_params()} | {"autostart"}
    assert set(learner.parameters()) - {"use_sim_time"} <= declared


def test_bringup_takes_a_system_file(tmp_path: Path) -> None:
    """``bringup --system-file FILE --robot CMD``: the learner and the MPC get the file (never ``system`` beside it),
    realtime (no simulated time); wrong combinations of options exit 2."""
    from saml_ros.bringup.cli import main
    from saml_ros.bringup.config import apply_sets, node_params, robot_config

    config = apply_sets(robot_config(SYSTEM_FILE, ["python examples/diff_drive/robot.py"]), ["mpc.guard.rollback=true"])
    params = node_params(config, tmp_path)
    for node in ("learner", "mpc"):
        assert params[node]["system_file"] == str(SYSTEM_FILE) and "system" not in params[node]
        assert params[node]["run_dir"] == str(tmp_path / "checkpoints") and "use_sim_time" not in params[node]
    assert params["mpc"]["guard.rollback"] is True and config["robot"] == ["python examples/diff_drive/robot.py"]
    assert main(["--system-file", str(SYSTEM_FILE), "--system", "quadrotor"]) == 2
    assert main(["--robot", "python robot.py"]) == 2
    bad = tmp_path / "bad.yaml"
    raw = yaml.safe_load(SYSTEM_FILE.read_text())
    raw["mpc"]["horizon"] = 0
    bad.write_text(yaml.safe_dump(raw))
    assert main(["--system-file", str(bad)]) == 2


def test_mpc_reaches_shelf_targets_with_the_arm(ros_env: RosDomain, ros_node: TestNode) -> None:
    """The MuJoCo arm (examples/arm/robot.py: JointState in, Float64MultiArray effort out) under the generic MPC of
    its system file: it lifts the arm from hanging down to the file's shelf target, then to a target sent on its
    goal topic (a JointState by joint name)."""
    from sensor_msgs.msg import JointState
    from std_msgs.msg import Float64MultiArray

    arm = REPO / "examples" / "arm"
    goal_q = yaml.safe_load((arm / "system.yaml").read_text())["mpc"]["goal"]["default"][:2]
    states = ros_node.subscribe(JointState, "/arm/joint_states")
    cmds = ros_node.subscribe(Float64MultiArray, "/arm/effort_controller/commands")
    # state_timeout 0.5 s (the file's: 0.1 s): on a loaded CI machine a state can wait that long for the node
    mpc = ros_env.launch("mpc", "-p", f"system_file:={arm / 'system.yaml'}", "-p", "state_timeout:=0.5",
                         namespace="/arm")
    robot = ros_env.start("arm", [sys.executable, str(arm / "robot.py"), "--ros-args", "-r", "__ns:=/arm"], cwd=REPO)

    def near(q: list[float]) -> bool:
        return bool(states) and max(abs(a - b) for a, b in zip(states[-1].position, q, strict=True)) < 0.15

    try:
        wait_for(lambda: len(cmds) > 20 or not mpc.alive(), timeout=120, what="effort commands on /arm")
        assert mpc.alive(), mpc.output()
        assert len(cmds[-1].data) == 2
        wait_for(lambda: near(goal_q), timeout=60, what=f"the arm at the file's shelf target {goal_q}")
        goals = ros_node.publisher(JointState, "/arm/reach_goal")
        wait_for(lambda: goals.get_subscription_count() > 0, timeout=30, what="the MPC's goal subscription")
        target = [1.0485, -1.8595]  # the gripper at x 0.5 m, z 0.1 m
        msg = JointState()
        msg.name, msg.position = ["elbow", "shoulder"], [target[1], target[0]]  # by name, in any order
        goals.publish(msg)
        wait_for(lambda: near(target), timeout=60, what=f"the arm at the new target {target}")
        assert mpc.alive() and robot.alive()
    finally:
        code = mpc.stop()
    assert code == 0, mpc.output()
