"""End-to-end runs of tiny versions of every experiment runner (saml_ros.experiments): the output files are
well formed, the numbers are consistent with each other, and every plan the MPC returned respected its
constraints (control bounds; quadrotor height bound; paddle roll/pitch bounds)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest


def test_all_runs_each_experiment_in_its_own_process_and_reports_failures(tmp_path: Path,
                                                                         capsys: pytest.CaptureFixture[str]) -> None:
    """``experiment all``'s parallel runner: real child processes, two at once; one child completes and writes its
    results, the other fails (friction has no field ``nets``) and is reported with its log, not hidden."""
    from saml_ros.experiments.run_all import run_parallel

    tiny = {"nets": "((2, 1),)", "sizes": "(100,)", "n_datasets": "2", "epochs": "2", "n_pstar": "20000",
            "n_test": "500"}
    options = [a for k, v in tiny.items() for a in ("--set", f"{k}={v}")]
    (tmp_path / "friction").mkdir()
    (tmp_path / "friction" / "results.json").write_text('{"claims": [{"stale": 1}]}')  # an earlier run's
    failed, cpu = run_parallel(["convergence", "friction"], tmp_path, options, jobs=2, status_every=0.5)
    assert failed == ["friction"]
    saved = json.loads((tmp_path / "convergence" / "results.json").read_text())
    assert len(saved["cells"]) == 1 and saved["claims"]
    assert "expected FIELD=VALUE" in (tmp_path / "friction" / "run.log").read_text()
    assert not (tmp_path / "friction" / "results.json").exists()  # no stale results beside a failed run
    assert cpu > 0.0
    assert "experiment all: " in capsys.readouterr().out  # the status line while they ran


def test_all_terminates_its_children_on_sigterm(tmp_path: Path) -> None:
    """SIGTERM to ``experiment all`` (a CI cancel, ``timeout``) ends the running experiments too."""
    import os
    import signal
    import subprocess
    import sys
    import time

    def children() -> list[int]:
        found = []
        for pid in filter(str.isdigit, os.listdir("/proc")):
            try:
                cmd = (Path("/proc") / pid / "cmdline").read_bytes().split(b"\0")
            except OSError:
                continue
            if str(tmp_path).encode() in b" ".join(cmd) and b"saml_ros.experiments.cli" in cmd:
                found.append(int(pid))
        return found

    parent = subprocess.Popen([sys.executable, "-m", "saml_ros.experiments.cli", "all", "--quick", "--jobs", "2",
                               "--out", str(tmp_path)], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 60.0
        while len([p for p in children() if p != parent.pid]) < 2 and time.monotonic() < deadline:
            time.sleep(0.2)
        assert len([p for p in children() if p != parent.pid]) == 2, "two experiments should be running"
        parent.send_signal(signal.SIGTERM)
        assert parent.wait(timeout=30) != 0
        deadline = time.monotonic() + 10.0
        while children() and time.monotonic() < deadline:
            time.sleep(0.2)
        assert children() == []
    finally:
        if parent.poll() is None:
            parent.kill()
