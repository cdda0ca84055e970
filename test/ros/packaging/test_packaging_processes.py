"""The ament_python packaging: package.xml, setup.cfg, the executables table, and a real colcon build."""

from __future__ import annotations

import configparser
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from helpers import REPO

from saml_ros.executables import EXECUTABLES

VENV_BIN = Path(sys.executable).parent
IN_CI = os.environ.get("CI", "").lower() == "true"


def test_entry_module_exit_code_for_unknown_name() -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "saml_ros.executables", "definitely_not_an_exe"],
        capture_output=True, text=True, timeout=60, cwd=REPO,
    )  # fmt: skip
    assert proc.returncode == 2
    assert "learner" in proc.stderr


@pytest.mark.parametrize("delay", [0.3, 1.0, 2.0])
def test_a_stop_signal_while_a_node_starts_ends_it_quietly(delay: float, tmp_path: Path) -> None:
    """SIGINT (as Ctrl-C under ros2 launch sends it) at any moment of a node's start-up, while it still imports
    rclpy and torch or once its own handlers run: exit status 0, no traceback, well within launch's 5 s grace."""
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", ROS_DOMAIN_ID="231")
    proc = subprocess.Popen([sys.executable, "-m", "saml_ros.executables", "learner", "--ros-args", "-p",
                             f"run_dir:={tmp_path / 'run'}"], cwd=REPO, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)
    time.sleep(delay)
    proc.send_signal(signal.SIGINT)
    out, _ = proc.communicate(timeout=30)
    assert proc.returncode == 0, out
    assert "Traceback" not in out and "KeyboardInterrupt" not in out, out


def test_importing_the_entry_point_is_light() -> None:
    """A stop signal before the entry point installs its quiet handler hits Python's default (a ``KeyboardInterrupt``
    traceback): what runs before it, ``import saml_ros`` (which registers the built-in systems) and the executables
    table, imports none of numpy, torch and rclpy (numpy alone took 0.25 s there, inside the 0.3 s case above)."""
    probe = ("import sys, saml_ros.executables; "
             "print(sorted(m for m in ('numpy', 'torch', 'rclpy', 'yaml') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=60, cwd=REPO)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]", out.stdout


def _colcon() -> str | None:
    return shutil.which("colcon", path=f"{VENV_BIN}{os.pathsep}{os.environ.get('PATH', '')}")


def _top_level(path: Path) -> set[str]:
    return {p.name for p in path.iterdir()}


def test_colcon_build_installs_every_executable(tmp_path: Path) -> None:
    colcon = _colcon()
    if colcon is None:
        if IN_CI:
            pytest.fail("colcon is not installed but CI=true: install requirements.txt (colcon-common-extensions)")
        pytest.skip("colcon not installed (pip install colcon-common-extensions 'setuptools<80'); runs in CI")
    (tmp_path / "src").mkdir()
    (tmp_path / "src" / "saml_ros").symlink_to(REPO, target_is_directory=True)
    before = _top_level(REPO)
    env = dict(os.environ, PATH=f"{VENV_BIN}{os.pathsep}{os.environ.get('PATH', '')}")
    install = tmp_path / "install"
    t0 = time.monotonic()
    proc = subprocess.run(
        [colcon, "--log-base", str(tmp_path / "log"), "build", "--base-paths", "src",
         "--build-base", str(tmp_path / "build"), "--install-base", str(install)],
        cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    elapsed = time.monotonic() - t0
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert elapsed < 60, f"colcon build took {elapsed:.1f} s"
    # the build writes no artefacts into the source tree (egg-info etc. go to --build-base); other files
    # may appear meanwhile (people work in this tree), so only build artefacts count
    new = _top_level(REPO) - before
    assert not {n for n in new if n.endswith(".egg-info") or n in ("build", "install", "log")}, new

    prefix = install / "saml_ros"
    for name in EXECUTABLES:
        exe = prefix / "lib" / "saml_ros" / name
        assert exe.is_file() and os.access(exe, os.X_OK), f"missing executable {exe}"
    assert (prefix / "share" / "saml_ros" / "package.xml").is_file()
    assert (prefix / "share" / "ament_index" / "resource_index" / "packages" / "saml_ros").is_file()
    for cfg in (REPO / "config").glob("*.yaml"):
        assert (prefix / "share" / "saml_ros" / "config" / cfg.name).is_file(), cfg.name
    # ros2 launch saml_ros <file> finds the launch files, and their $(find-pkg-share saml_ros)/config/... exists
    launch_files = sorted((REPO / "launch").glob("*.launch.xml"))
    layout_files = sorted((REPO / "layouts").glob("*.*"))
    assert len(launch_files) >= 6 and len(layout_files) >= 6
    for src, sub in [(f, "launch") for f in launch_files] + [(f, "layouts") for f in layout_files]:
        installed = prefix / "share" / "saml_ros" / sub / src.name
        assert installed.is_file() and installed.read_bytes() == src.read_bytes(), f"not installed: {installed}"
    from helpers.launch_parse import evaluate

    share = prefix / "share" / "saml_ros"
    for launch in launch_files:
        own = launch.name.split(".")[0]  # a system's launch file takes its own system only
        for system in (own,) if own in ("friction", "quadrotor", "paddle_ball") else ("friction", "quadrotor",
                                                                                       "paddle_ball"):
            result = evaluate(share / "launch" / launch.name, {"system": system}, share=share)
            assert all(f.is_relative_to(share) for f in result.files), result.files
            for node in result.nodes:
                assert (prefix / "lib" / "saml_ros" / node.executable).is_file(), node.executable
                for psrc in node.params:
                    assert psrc.path is None or (psrc.path.is_file() and psrc.path.is_relative_to(share)), psrc.path

    site = next((prefix / "lib").glob("python3*/site-packages"))
    for pkg in ("saml_ros", "msg_schemas", "sim_nodes"):
        if (REPO / pkg / "__init__.py").is_file():
            assert (site / pkg / "__init__.py").is_file(), f"package {pkg} not installed"
    # the paddle ball's MuJoCo scene, in its system's folder
    scenes = sorted((REPO / "saml_ros" / "systems" / "paddle_ball" / "assets").glob("*.xml"))
    assert scenes
    for xml in scenes:
        assert (site / xml.relative_to(REPO)).is_file(), f"MuJoCo model {xml.relative_to(REPO)} not installed"
    # the compiled kernels' sources (the fused training step, the shooting SQP): an installed package compiles
    # them on first use
    for kernel in (Path("saml_ros/core/training/engines/kernels/fused_step.cpp"),
                   Path("saml_ros/core/mpc/shooting/kernels/sqp_native.c")):
        assert (REPO / kernel).is_file()
        assert (site / kernel).is_file(), f"the kernel source {kernel} is not installed"
    # the console scripts point at exactly the table in saml_ros/executables.py
    entry_points = configparser.ConfigParser(delimiters=("=",))
    entry_points.read(next(site.glob("saml_ros-*.egg-info")) / "entry_points.txt")
    console = {k: v.replace(" ", "") for k, v in entry_points["console_scripts"].items()}
    assert console == {name: "saml_ros.executables:entry" for name in EXECUTABLES}
    # an installed script runs the executable it is named after
    script = subprocess.run([str(prefix / "lib" / "saml_ros" / "bag_info"), "--help"], cwd=tmp_path,
                            env=dict(env, PYTHONPATH=str(site)), capture_output=True, text=True, timeout=120)
    assert script.returncode == 0 and "bag_info" in script.stdout, script.stdout + script.stderr

    # ament_index finds the package, and the installed Python package imports from the install space
    probe = (
        "import ament_index_python, saml_ros.executables as e; "
        "print(ament_index_python.get_package_prefix('saml_ros')); print(e.__file__)"
    )
    child_env = dict(env, AMENT_PREFIX_PATH=str(prefix), PYTHONPATH=str(site))
    out = subprocess.run(
        [sys.executable, "-c", probe], cwd=tmp_path, env=child_env, capture_output=True, text=True, timeout=60
    )
    assert out.returncode == 0, out.stderr
    found_prefix, module_file = out.stdout.split()
    assert Path(found_prefix) == prefix
    assert Path(module_file).is_relative_to(site)
