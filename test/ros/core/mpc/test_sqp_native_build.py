"""The fast SQP's C kernel (saml_ros/core/mpc/shooting/native.py): the model it evaluates is the numpy twin's,
the plans it produces are the numpy path's, and it steps aside (with the reason) where it does not apply."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from helpers import REPO

from saml_ros.core.systems import get_system
from saml_ros.systems.quadrotor.model import Quadrotor

_QUAD = get_system("quadrotor")
assert isinstance(_QUAD, Quadrotor)




def _child(code: str, env: dict[str, str]) -> str:
    run = subprocess.run([sys.executable, "-W", "always", "-c", code], capture_output=True, text=True, timeout=120,
                         cwd=REPO, env={**os.environ, **env})
    assert run.returncode == 0, run.stderr
    return run.stdout + run.stderr


_SOLVE = (
    "import numpy as np\n"
    "from saml_ros.core.mpc import make_controller\n"
    "from saml_ros.core.systems import get_system\n"
    "from saml_ros.core.mpc.shooting import native\n"
    "q = get_system('quadrotor'); c = make_controller(q, None, solver='fast')\n"
    "x = np.zeros(13); x[6] = 1.0; x[2] = 2.0\n"
    "r = c.solve(x)\n"
    "print('OK', r.success, np.isfinite(r.u).all(), 'REASON', c.native_reason)\n"
    "print('BUILT', sorted(p.name for p in native.cache_root().glob('sqp_native_*.so')) == [native.build_name()])\n"
)


def test_kernel_is_built_once_into_the_cache_and_falls_back_without_a_compiler(tmp_path: Path) -> None:
    """A fresh cache: the first process compiles the kernel there (under its hashed name) and solves on it; with
    no compiler and an empty cache the solver warns once and solves on numpy; SAML_MPC_NATIVE=0 switches it off."""
    out = _child(_SOLVE, {"SAML_KERNEL_CACHE": str(tmp_path / "a"), "SAML_MPC_NATIVE": "1"})
    assert "OK True True REASON None" in out and "BUILT True" in out
    built = next((tmp_path / "a").glob("sqp_native_*.so"))
    mtime = built.stat().st_mtime_ns
    out = _child(_SOLVE, {"SAML_KERNEL_CACHE": str(tmp_path / "a"), "SAML_MPC_NATIVE": "1", "CC": "/nonexistent/cc"})
    assert "REASON None" in out and built.stat().st_mtime_ns == mtime  # loaded, not rebuilt (no compiler needed)
    out = _child(_SOLVE, {"SAML_KERNEL_CACHE": str(tmp_path / "b"), "SAML_MPC_NATIVE": "1", "CC": "/nonexistent/cc"})
    assert "OK True True REASON build failed: RuntimeError: no C compiler" in out
    assert out.count("the MPC's C kernel is not available") == 1
    out = _child(_SOLVE, {"SAML_KERNEL_CACHE": str(tmp_path / "c"), "SAML_MPC_NATIVE": "0"})
    assert "OK True True REASON switched off (SAML_MPC_NATIVE=0)" in out
