"""Bring your own robot: a system file the learner refuses, with the key named (docs/your_robot.md).

The example robot learned online, recorded, trained from its bag, controlled and exported, as the tutorial's
reader runs it: test_tutorial.py.
"""

from __future__ import annotations

from pathlib import Path

import pytest
from helpers.ros_helpers import RosDomain
from helpers.your_robot import NS, SYSTEM_FILE

pytestmark = pytest.mark.usefixtures("restore_registry")  # robots these tests load are registered by name


@pytest.mark.parametrize("problem, message", [
    ("path", "state.fields[0].path"),
    ("missing", "no such file"),
])
def test_learner_refuses_a_bad_system_file(ros_env: RosDomain, tmp_path: Path, problem: str, message: str) -> None:
    path = tmp_path / "robot.yaml"
    if problem == "path":
        path.write_text(SYSTEM_FILE.read_text().replace("pose.pose.position.x", "pose.pose.positon.x"))
    learner = ros_env.launch("learner", "-p", f"system_file:={path}", "-p", f"run_dir:={tmp_path / 'run'}",
                             namespace=NS)
    assert learner.wait(60) == 2, learner.output()
    out = learner.output()
    assert "configuration error" in out and message in out, out
