"""The example arm (examples/arm/): a robot defined entirely outside the package, in MuJoCo.

Without ROS: the user's base model is exactly the arm's rigid-body dynamics once the unknown effects (payload,
joint friction, elbow spring) are taken out of the MuJoCo model, and those effects matter more on the shelf (the
spec's region) than elsewhere on the controller's own flights; the evaluation's block standard errors.

End to end with real processes: the arm's driver node, its controller at the state's rate on its own timer and
the unmodified learner (``system_file:=examples/arm/system.yaml``) for a few seconds until a checkpoint appears;
then a second, held-out flight recorded to a bag, on which ``examples/arm/evaluate.py`` compares the learner's
checkpoint with f_hat. The full measurement is ``./dev bench your_robot --robot arm`` (bench/bench_your_robot.py).
"""

from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys
import time
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest
import torch
from helpers.ros_helpers import Process, RosDomain, TestNode, wait_for

REPO = Path(__file__).resolve().parents[3]
EXAMPLE = REPO / "examples" / "arm"
SYSTEM_FILE = EXAMPLE / "system.yaml"
NS = "/arm"
SHELF_BOX = ((0.0, 1.4), (-2.2, -0.7))  # the spec's region (system.yaml), q1 and q2 (rad)


def example_module(name: str) -> ModuleType:
    """A module of examples/arm under a name no other test uses (``arm_example_<name>``)."""
    if str(EXAMPLE) not in sys.path:
        sys.path.insert(0, str(EXAMPLE))  # the example's own imports (arm_model)
    key = f"arm_example_{name}"
    if key not in sys.modules:
        spec = importlib.util.spec_from_file_location(key, EXAMPLE / f"{name}.py")
        assert spec is not None and spec.loader is not None
        module = importlib.util.module_from_spec(spec)
        sys.modules[key] = module
        spec.loader.exec_module(module)
    return sys.modules[key]


#: robots these tests load from system files are forgotten after each test (test/conftest.py)
pytestmark = pytest.mark.usefixtures("restore_registry")


def flight(seconds: float, seed: int, unknown_effects: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The arm and its controller at 100 Hz without ROS, exact readings: ``x, u, next x``."""
    sim_mod, ctl_mod = example_module("sim"), example_module("controller")
    arm = sim_mod.ArmSim(seed=seed, noise=0.0, unknown_effects=unknown_effects)
    ctl = ctl_mod.Reacher(seed=seed)
    xs, us = [], []
    for k in range(int(seconds * 100)):
        x = arm.measure()
        arm.step(ctl.command(k * 0.01, x[:2], x[2:]), 0.01)
        xs.append(x)
        us.append(arm.applied.copy())
    xa = np.array(xs)
    return xa[:-1], np.array(us)[:-1], xa[1:]


def test_base_model_is_the_arm_without_its_unknown_effects() -> None:
    from saml_ros.user_code import load_system_file

    example_module("arm_model")
    system = load_system_file(SYSTEM_FILE)  # the user's f_hat, as the learner loads it
    x, u, y = flight(20.0, seed=3, unknown_effects=False)
    with torch.no_grad():
        pred = system.base_model(torch.as_tensor(x), torch.as_tensor(u)).numpy()
    assert np.max(np.abs(pred - y)) < 1e-9  # f_hat integrates exactly as MuJoCo does

    x, u, y = flight(60.0, seed=3)
    with torch.no_grad():
        err = np.linalg.norm(system.base_model(torch.as_tensor(x), torch.as_tensor(u)).numpy() - y, axis=1)
    shelf = (x[:, 0] >= SHELF_BOX[0][0]) & (x[:, 0] <= SHELF_BOX[0][1]) & \
        (x[:, 1] >= SHELF_BOX[1][0]) & (x[:, 1] <= SHELF_BOX[1][1])
    assert 0.2 < shelf.mean() < 0.8, shelf.mean()  # the controller reaches the shelf and leaves it
    # what f_hat lacks is far above the 0.012 the spec asks for, and larger on the shelf than elsewhere
    assert err[shelf].mean() > 1.5 * err[~shelf].mean() > 0.05, (err[shelf].mean(), err[~shelf].mean())
    assert np.all(np.abs(u) <= [30.0, 15.0])


def test_block_standard_error() -> None:
    ev = example_module("evaluate")
    rng = np.random.default_rng(0)
    # blocks of 100 identical values: the transitions are not independent, the blocks are
    means = rng.normal(1.0, 0.1, 50)
    loss = np.repeat(means, 100)
    blocks = np.repeat(np.arange(50), 100)
    s = ev.block_stat(loss, np.ones_like(loss, bool), blocks)
    assert s.n == 5000 and s.blocks == 50
    assert s.mean == pytest.approx(means.mean())
    assert s.se == pytest.approx(means.std(ddof=1) / np.sqrt(50), rel=1e-9)  # not std / sqrt(5000)
    empty = ev.block_stat(loss, np.zeros_like(loss, bool), blocks)
    assert empty.n == 0 and np.isnan(empty.mean)


def launch_script(dom: RosDomain, script: str, *ros_args: str) -> Process:
    """One of the example's own rclpy scripts (not a saml_ros executable) in the test's domain."""
    return dom.start(Path(script).stem, [sys.executable, str(EXAMPLE / script), "--ros-args", "-r", f"__ns:={NS}",
                                         *ros_args], cwd=REPO)


def test_arm_learned_online_then_evaluated_on_a_held_out_flight(ros_env: RosDomain, ros_node: TestNode,
                                                                tmp_path: Path) -> None:
    from sensor_msgs.msg import JointState

    run, bag = tmp_path / "run", tmp_path / "heldout"
    user_code = {"PYTHONPATH": os.pathsep.join([str(REPO), str(EXAMPLE)])}  # the system file's f_hat
    learner = ros_env.launch("learner", "-p", f"system_file:={SYSTEM_FILE}", "-p", f"run_dir:={run}",
                             "-p", "min_transitions:=300", "-p", "checkpoint_period:=2.0", namespace=NS, env=user_code)
    wait_for(lambda: "training starts after" in learner.output() or not learner.alive(), timeout=180,
             what="the learner to configure")
    assert learner.alive(), learner.output()
    # the reaching task only (every target on the shelf), so a short flight covers the spec's region
    ctrl = launch_script(ros_env, "controller.py", "-p", "seed:=1", "-p", "task_fraction:=1.0")
    robot = launch_script(ros_env, "robot.py", "-p", "seed:=1")
    try:
        wait_for(lambda: any(run.glob("ckpt-*.saml")) or not learner.alive() or not robot.alive(), timeout=180,
                 what="a checkpoint")
        assert learner.alive() and robot.alive(), learner.output() + robot.output()
        time.sleep(3.0)  # a few more seconds of training
    finally:
        robot.stop()
        ctrl.stop()
    assert learner.stop(timeout=60) == 0, learner.output()
    assert "configuration error" not in learner.output()

    # the held-out flight: another seed, another time, recorded
    rec = ros_env.launch("record", args=["-o", str(bag), "--topics", f"{NS}/joint_states",
                                         f"{NS}/effort_controller/commands"])
    wait_for(lambda: "record: writing" in rec.output() or not rec.alive(), what="the recorder")
    states = ros_node.subscribe(JointState, f"{NS}/joint_states")
    ctrl = launch_script(ros_env, "controller.py", "-p", "seed:=2", "-p", "task_fraction:=1.0")
    wait_for(lambda: f"recording {NS}/effort_controller/commands " in rec.output() or not rec.alive(), timeout=60,
             what="the recorder to subscribe the commands")
    robot = launch_script(ros_env, "robot.py", "-p", "seed:=2")
    try:
        wait_for(lambda: f"recording {NS}/joint_states " in rec.output() or not rec.alive(), timeout=60,
                 what="the recorder to subscribe the joint states")
        start = len(states)
        wait_for(lambda: len(states) - start >= 800 or not robot.alive(), timeout=120, what="8 s of joint states")
        assert robot.alive(), robot.output()
    finally:
        robot.stop()
        ctrl.stop()
    assert rec.stop(timeout=30) == 0, rec.output()

    out = tmp_path / "eval.json"
    proc = subprocess.run([sys.executable, str(EXAMPLE / "evaluate.py"), "--system-file", str(SYSTEM_FILE),
                           "--bag", str(bag), "--model", f"online={run}", "--applied-effort", "--json", str(out)],
                          capture_output=True, text=True, cwd=REPO, env=dict(os.environ, **user_code), timeout=300)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "| f_hat |" in proc.stdout and "| online |" in proc.stdout, proc.stdout
    result = json.loads(out.read_text())
    # of about 800 states: under load the commands jitter and more transitions are dropped as ambiguous (568-575
    # in loaded full-suite runs, 600+ alone)
    assert result["transitions"] >= 500, result["transitions"]
    check = result["pairing_check"]
    assert check["checked"] > 0 and check["checked"] + check["unchecked"] == result["counts"]["paired"], check
    rows = result["constraints"]["shelf"]["rows"]
    assert rows["f_hat"]["in"]["n"] >= 100, rows["f_hat"]["in"]
    # a few seconds of online learning already beat the user's rigid-body model on the shelf, held out
    assert rows["online"]["in"]["mean"] < 0.5 * rows["f_hat"]["in"]["mean"], rows
