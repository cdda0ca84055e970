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
import pickle
import shutil
import signal
import subprocess
import sys
import textwrap
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import ros_helpers
import yaml
from ros_helpers import Process, RosDomain, wait_for

from saml_ros.core.systems.system_file import SystemFileError

REPO = Path(__file__).resolve().parents[1]
EXAMPLE = REPO / "examples" / "diff_drive"
NS = "/dd"

ros_env = ros_helpers.ros_env

# a unicycle whose speeds follow the commands with a first-order lag; its constant lives in a sibling module
DYNAMICS = '''
import torch

from {constants} import TAU


def f_hat(x, u, *, dt, gain=1.0):
    """Next state of the diff-drive base: unicycle kinematics, speeds lag the commands by TAU."""
    px, py, yaw, v, w = x.unbind(-1)
    a = dt / (TAU + dt)
    v2 = v + a * (gain * u[:, 0] - v)
    w2 = w + a * (u[:, 1] - w)
    vm, wm = 0.5 * (v + v2), 0.5 * (w + w2)
    ym = yaw + 0.5 * wm * dt
    return torch.stack([px + vm * dt * torch.cos(ym), py + vm * dt * torch.sin(ym), yaw + wm * dt, v2, w2], -1)
'''


def f_hat_np(x: np.ndarray, u: np.ndarray, dt: float, tau: float = 0.12, gain: float = 1.0) -> np.ndarray:
    px, py, yaw, v, w = x.T
    a = dt / (tau + dt)
    v2, w2 = v + a * (gain * u[:, 0] - v), w + a * (u[:, 1] - w)
    vm, wm = 0.5 * (v + v2), 0.5 * (w + w2)
    ym = yaw + 0.5 * wm * dt
    return np.stack([px + vm * dt * np.cos(ym), py + vm * dt * np.sin(ym), yaw + wm * dt, v2, w2], -1)


def robot_folder(root: Path, module: str = "dynamics", constants: str = "robot_constants",
                 base_model: dict | None = None, sub: str = "") -> Path:
    """A robot folder as a user would write it: system.yaml beside its own f_hat module (and a sibling module)."""
    folder = root / "my_robot"
    code = folder / sub if sub else folder
    code.mkdir(parents=True, exist_ok=True)
    (code / f"{module}.py").write_text(DYNAMICS.format(constants=constants))
    (code / f"{constants}.py").write_text("TAU = 0.12\n")
    raw = yaml.safe_load((EXAMPLE / "system.yaml").read_text())
    raw["base_model"] = base_model or {"function": f"{module}:f_hat", "params": {"gain": 1.0}}
    (folder / "system.yaml").write_text(yaml.safe_dump(raw))
    return folder / "system.yaml"


@pytest.fixture(autouse=True)
def _clean_imports() -> Iterator[None]:
    """The modules these tests import and the robots they register stay local to each test."""
    from saml_ros.core.systems import system_names, unregister_system

    path, mods, names = list(sys.path), set(sys.modules), set(system_names())
    yield
    sys.path[:] = path
    for m in set(sys.modules) - mods:
        sys.modules.pop(m, None)
    for n in set(system_names()) - names:
        unregister_system(n)


# ------------------------------------------------------------------------------------------ in process
def test_module_next_to_the_system_file_is_found_and_recorded(tmp_path: Path, monkeypatch: pytest.MonkeyPatch
                                                              ) -> None:
    from saml_ros.user_code import UserFunction, load_system_file

    path = robot_folder(tmp_path, module="ucp_dyn_a", constants="ucp_const_a")
    monkeypatch.chdir(tmp_path.parent)  # not the robot's folder
    system = load_system_file(os.path.relpath(path))
    base = system.definition["base_model"]
    assert base["path"] == [str(path.parent.resolve())]  # recorded absolute: a checkpoint finds it anywhere
    assert isinstance(system.user_function, UserFunction)
    x, u = system.sample_inputs(8, np.random.default_rng(0))
    np.testing.assert_allclose(system.base_step_np(x, u), f_hat_np(x, u, system.dt), atol=1e-6)
    # it pickles as its name and folder (how it reaches the learner's training process)
    again = pickle.loads(pickle.dumps(system.user_function))
    assert again.target == "ucp_dyn_a:f_hat" and again.search == (str(path.parent.resolve()),)


def test_path_key_names_a_folder_relative_to_the_file(tmp_path: Path) -> None:
    from saml_ros.user_code import load_system_file

    path = robot_folder(tmp_path, module="ucp_dyn_b", constants="ucp_const_b", sub="models",
                        base_model={"function": "ucp_dyn_b:f_hat", "path": "models"})
    system = load_system_file(path)
    assert system.definition["base_model"]["path"] == [str((path.parent / "models").resolve())]
    x, u = system.sample_inputs(4, np.random.default_rng(1))
    np.testing.assert_allclose(system.base_step_np(x, u), f_hat_np(x, u, system.dt), atol=1e-6)


def test_missing_module_names_the_file_and_where_it_looked(tmp_path: Path) -> None:
    from saml_ros.user_code import load_system_file, system_from_definition

    path = robot_folder(tmp_path, module="ucp_dyn_c", constants="ucp_const_c")
    (path.parent / "ucp_dyn_c.py").unlink()
    with pytest.raises(SystemFileError, match=r"base model function 'ucp_dyn_c:f_hat': no module 'ucp_dyn_c' "
                                              r"\(ucp_dyn_c.py or a package ucp_dyn_c/\) in .*my_robot \(the system "
                                              r"file's folder, or base_model.path\), nor on the Python path"):
        load_system_file(path)
    # a definition stored by a checkpoint whose robot folder has moved away
    path = robot_folder(tmp_path / "two", module="ucp_dyn_d", constants="ucp_const_d")
    definition = load_system_file(path).params()["definition"]
    shutil.move(str(path.parent), str(tmp_path / "moved"))
    sys.modules.pop("ucp_dyn_d", None)
    with pytest.raises(SystemFileError, match=r"no module 'ucp_dyn_d' .* in .*my_robot \(no such folder\)"):
        system_from_definition(definition)


def test_two_robots_with_modules_of_one_name_are_refused_clearly(tmp_path: Path) -> None:
    from saml_ros.user_code import load_system_file

    first = robot_folder(tmp_path / "a", module="ucp_dyn_e", constants="ucp_const_e")
    load_system_file(first)
    second = robot_folder(tmp_path / "b", module="ucp_dyn_e", constants="ucp_const_e2")
    raw = yaml.safe_load(second.read_text())
    raw["name"] = "other_robot"
    second.write_text(yaml.safe_dump(raw))
    with pytest.raises(SystemFileError, match=r"a module 'ucp_dyn_e' is already imported in this process from "
                                              r".*a/my_robot, not from .*b/my_robot"):
        load_system_file(second)


def test_path_only_for_functions() -> None:
    from saml_ros.core.systems.base_models import BaseModelError, BaseModelSpec

    with pytest.raises(BaseModelError, match="only a 'function' base model"):
        BaseModelSpec.parse({"builtin": "hold", "path": "."})
    with pytest.raises(BaseModelError, match="expected a directory or a list"):
        BaseModelSpec.parse({"function": "a:b", "path": [3]})


# ------------------------------------------------------------------------------------------ real processes
def bare_env() -> dict[str, str]:
    """The environment of a user's shell: saml_ros itself importable, nothing of the robot's on PYTHONPATH."""
    env = dict(os.environ, PYTHONPATH=str(REPO), PYTHONUNBUFFERED="1")
    return env


def run_py(args: list[str], cwd: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, *args], cwd=cwd, env=bare_env(), capture_output=True, text=True,
                          timeout=300)


def launch_script(dom: RosDomain, script: Path, *ros_args: str) -> Process:
    log = dom.log_dir / f"{script.stem}-{time.monotonic_ns()}.log"
    with open(log, "wb") as out:
        popen = subprocess.Popen([sys.executable, str(script), "--ros-args", "-r", f"__ns:={NS}", *ros_args],
                                 stdout=out, stderr=subprocess.STDOUT, env=dict(os.environ, PYTHONUNBUFFERED="1"),
                                 cwd=REPO, start_new_session=True)
    proc = Process(script.stem, popen, log)
    dom.processes.append(proc)
    return proc


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
