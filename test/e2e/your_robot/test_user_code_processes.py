"""User code next to the system file (saml_ros.user_code, issue 27 item 4).

``base_model: {function: "dynamics:f_hat"}`` imports ``dynamics.py`` from the system file's folder (or the folders
``base_model.path`` names, relative to the file), with no ``PYTHONPATH``; the definition stores the folder
absolute, so a checkpoint finds the module from any working directory. The end-to-end test runs the learner as a
real process from another working directory, with a robot folder of its own in a temporary directory, and then
``bag_info``, ``load_model`` and ``export`` as fresh processes with only saml_ros itself on ``PYTHONPATH``.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
from helpers.ros_helpers import Process, RosDomain, wait_for
from helpers.your_robot import EXAMPLE, REPO, f_hat_np, robot_folder

NS = "/dd"


# ------------------------------------------------------------------------------------------ real processes
def bare_env() -> dict[str, str]:
    """The environment of a user's shell: saml_ros itself importable, nothing of the robot's on PYTHONPATH."""
    env = dict(os.environ, PYTHONPATH=str(REPO), PYTHONUNBUFFERED="1")
    return env


def run_py(args: list[str], cwd: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, *args], cwd=cwd, env=bare_env(), capture_output=True, text=True,
                          timeout=300)


def launch_script(dom: RosDomain, script: Path, *ros_args: str) -> Process:
    return dom.start(script.stem, [sys.executable, str(script), "--ros-args", "-r", f"__ns:={NS}", *ros_args],
                     cwd=REPO)


LOAD = textwrap.dedent("""
    import json, sys
    import numpy as np
    from saml_ros.api import load_model
    m = load_model(sys.argv[1])
    x, u = m.system.sample_inputs(16, np.random.default_rng(3))
    print(json.dumps({"x": x.tolist(), "u": u.tolist(), "base": m.base(x, u).tolist(),
                      "predict": m.predict(x, u).tolist(), "dt": m.dt, "updates": m.loaded.meta["updates"]}))
""")


def test_learner_load_model_bag_info_export_find_the_robots_code(ros_env: RosDomain, tmp_path: Path) -> None:
    from diagnostic_msgs.msg import DiagnosticArray  # noqa: F401  (rclpy importable here)

    system_file = robot_folder(tmp_path)  # tmp/my_robot/{system.yaml, dynamics.py, robot_constants.py}
    work = tmp_path / "elsewhere"
    work.mkdir()
    rel = os.path.relpath(system_file, work)  # ../my_robot/system.yaml
    learner = ros_env.launch("learner", "-p", f"system_file:={rel}", "-p", "run_dir:=run",
                             "-p", "min_transitions:=150", "-p", "checkpoint_period:=1.0", namespace=NS,
                             env={"PYTHONPATH": str(REPO)}, cwd=work)
    rec = ros_env.launch("record", args=["-o", str(work / "bag"), "--topics", f"{NS}/odom", f"{NS}/cmd_vel"],
                         env={"PYTHONPATH": str(REPO)}, cwd=work)
    wait_for(lambda: "record: recording" in rec.output() or "record: writing" in rec.output() or not rec.alive(),
             what="the recorder")
    robot = launch_script(ros_env, EXAMPLE / "robot.py", "-p", "x0:=0.4")
    wander = launch_script(ros_env, EXAMPLE / "wander.py", "-p", "seed:=5")
    run = work / "run"
    try:
        wait_for(lambda: (run / "latest").exists() or not learner.alive(), timeout=240,
                 what="a checkpoint of the learner")
        assert learner.alive(), learner.output()
    finally:
        wander.stop()
        robot.stop()
    learner.signal(signal.SIGINT)
    rec.signal(signal.SIGINT)
    assert learner.stop(timeout=60) == 0, learner.output()
    assert rec.stop(timeout=30) == 0, rec.output()
    assert "configuration error" not in learner.output()

    # load_model, from the working directory, with only saml_ros on the path: the base model is the robot's
    res = run_py(["-c", LOAD, "run"], work)
    assert res.returncode == 0, res.stderr
    got = json.loads(res.stdout.strip().splitlines()[-1])
    x, u = np.array(got["x"]), np.array(got["u"])
    np.testing.assert_allclose(np.array(got["base"]), f_hat_np(x, u, got["dt"]), atol=1e-5)
    assert got["updates"] > 0
    # ... and from another directory, by absolute path
    res = run_py(["-c", LOAD, str(run)], tmp_path)
    assert res.returncode == 0, res.stderr

    # bag_info pairs the recording with the robot's own file (relative to the working directory)
    res = run_py(["-m", "saml_ros.executables", "bag_info", "bag", "--system-file", rel, "--json"], work)
    assert res.returncode == 0, res.stderr
    info = json.loads(res.stdout)
    assert "diff_drive" in json.dumps(info) and info, info

    # export: ONNX / TorchScript / numpy with the robot's f_hat inside, checked against the model
    res = run_py(["-m", "saml_ros.executables", "export", "run", "-o", "exported"], work)
    assert res.returncode == 0, res.stdout + res.stderr
    meta = json.loads((work / "exported" / "model.json").read_text())
    assert meta["base_exported"] is True, meta

    # the robot's folder moves away: a clear error naming the module and the folder it was looked for in
    shutil.move(str(system_file.parent), str(tmp_path / "moved_robot"))
    res = run_py(["-c", LOAD, "run"], work)
    assert res.returncode != 0
    assert "no module 'dynamics' (dynamics.py or a package dynamics/) in" in res.stderr, res.stderr
    assert f"{system_file.parent} (no such folder)" in res.stderr, res.stderr
