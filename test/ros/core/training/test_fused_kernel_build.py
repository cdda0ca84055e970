"""The fused C++ training kernel (saml_ros/core/training/engines/fused.py) computes the fast engine's steps.

Every comparison runs the kernel, the fast engine's torch path (``engine="fast_torch"``) and the plain engine from the
same initial weights, data and seed, so all see the same minibatches; the tolerances are test_fast_train.py's
(float64: 1e-7 relative / 1e-8 absolute after a few hundred Adam steps; float32 after 300 steps: 1e-4 / 1e-5; a real
difference in the algorithm shows at 1e-3 or more). The module is skipped where the kernel cannot be built.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from saml_ros.core.training.engines import fused

if fused.load_kernel() is None:
    pytest.skip(f"the fused training kernel is not available here: {fused.kernel_reason()}", allow_module_level=True)


def test_load_without_build_loads_a_finished_build_and_otherwise_leaves_the_build_for_later(tmp_path: Path) -> None:
    """``load_kernel(build=False)`` (the training process's warm-up): an empty cache gives None and no build, and
    the state stays "not loaded yet" so the next ``load_kernel()`` builds; with the build cached it loads it."""
    import subprocess
    import sys

    code = ("from saml_ros.core.training.engines import fused; m = fused.load_kernel(build=False); "
            "print(m is None, fused.kernel_reason() == 'not loaded yet', any(fused.cache_root().rglob('*.so')))")
    empty = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True,
                           env={**os.environ, "SAML_KERNEL_CACHE": str(tmp_path / "cache")})
    assert empty.stdout.split() == ["True", "True", "False"], empty.stderr
    if fused.load_kernel() is not None:  # built here: the same call in a fresh process loads it
        built = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True)
        assert built.stdout.split()[:2] == ["False", "False"], built.stderr
