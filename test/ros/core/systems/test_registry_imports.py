"""The system registry: every built-in system reaches every part from its entry, and the registry is open."""

from __future__ import annotations

import subprocess
import sys

from helpers import REPO


def test_importing_the_registry_imports_neither_torch_mujoco_nor_the_mpc() -> None:
    code = ("import sys, saml_ros.core.systems.registry, msg_schemas; "
            "print(sorted(m for m in sys.modules if m in ('torch', 'mujoco', 'rclpy') "
            "or m.startswith(('saml_ros.core.mpc', 'saml_ros.core.worlds'))))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True,
                         cwd=REPO)
    assert out.stdout.strip() == "[]", out.stderr
