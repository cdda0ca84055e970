"""``bench loop_parts --save / --against``: the check that a speed change leaves the MPC's commands as they were."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from bench.bench_loop_parts import main  # noqa: E402
from saml_ros.core.mpc.shooting import native  # noqa: E402


def test_against_reports_identical_commands_and_catches_a_change(tmp_path: Path,
                                                                 capsys: pytest.CaptureFixture[str]) -> None:
    saved = tmp_path / "ref.npz"
    assert main(["--steps", "12", "--save", str(saved)]) == 0
    assert "message conversions per message" in capsys.readouterr().out
    ref = np.load(saved)
    assert ref["commands"].shape == (12, 4) and ref["iterations"].shape == (12,)
    assert main(["--steps", "12", "--against", str(saved), "--no-conversions"]) == 0  # the loop is deterministic
    out = capsys.readouterr().out
    assert "identical" in out
    # the MPC service reports which numerics its SQP ran (its /diagnostics value solver_kernel)
    assert ("SQP numerics C:" if native.load_library() is not None else "SQP numerics numpy (") in out
    changed = tmp_path / "changed.npz"
    cmds = ref["commands"].copy()
    cmds[5, 2] += 1e-12
    np.savez(changed, commands=cmds, iterations=ref["iterations"])
    assert main(["--steps", "12", "--against", str(changed), "--no-conversions"]) == 1
    assert "DIFFERENT" in capsys.readouterr().out
    # a rounding-size change
    assert main(["--steps", "12", "--against", str(changed), "--tol", "1e-9", "--no-conversions"]) == 0
    assert "equal within 1e-09" in capsys.readouterr().out
    cmds[5, 2] += 1e-3
    np.savez(changed, commands=cmds, iterations=ref["iterations"])
    assert main(["--steps", "12", "--against", str(changed), "--tol", "1e-9", "--no-conversions"]) == 1
    assert "DIFFERENT" in capsys.readouterr().out
