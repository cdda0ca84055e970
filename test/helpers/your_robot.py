"""Robots defined outside the package: the example robot (examples/diff_drive), its own scripts started as
processes in a test's ROS domain, and robot folders written as a user would (a system file beside its f_hat
module)."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import yaml

from helpers import REPO
from helpers.ros_helpers import Process, RosDomain

#: the example robot's folder, its system file and the namespace the tests run it in
EXAMPLE = REPO / "examples" / "diff_drive"
SYSTEM_FILE = EXAMPLE / "system.yaml"
NS = "/dd"


def launch_script(dom: RosDomain, script: Path, *ros_args: str) -> Process:
    """A plain rclpy script (the user's robot, not a saml_ros executable) in the test's domain."""
    return dom.start(script.stem, [sys.executable, str(script), "--ros-args", "-r", f"__ns:={NS}", *ros_args], REPO)


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
    """:data:`DYNAMICS`'s f_hat in numpy, ``(B, 5), (B, 2) -> (B, 5)``."""
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
