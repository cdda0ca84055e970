"""Offline pipeline: the Sufficiently Accurate trade-off on the double integrator, the train CLI."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
from helpers import REPO

from saml_ros.core.model.io import load_model
from saml_ros.core.systems import get_system


def test_train_cli_writes_a_usable_checkpoint_and_report(tmp_path: Path) -> None:
    out = tmp_path / "run"
    proc = subprocess.run(
        [sys.executable, "-m", "saml_ros.executables", "train", "--system", "friction", "--samples", "2000",
         "--epochs", "3", "--seeds", "2", "--test-samples", "1000", "--out", str(out), "--no-progress"],
        cwd=REPO, capture_output=True, text=True, timeout=300,
    )
    assert proc.returncode == 0, proc.stderr
    assert "held-out objective" in proc.stdout
    for name in ("latest", "ckpt-000001.saml", "history.json", "metrics.json", "training_curves.png", "spec.yaml"):
        assert (out / name).is_file(), name
    loaded = load_model(out / "ckpt-000001.saml", expect=get_system("friction"))
    assert loaded.model.n_models == 2
    metrics = json.loads((out / "metrics.json").read_text())
    assert len(metrics["test"]["regions"]["near_origin"]["inside"]) == 2
    x = np.zeros((1, 2))
    assert np.isfinite(loaded.model.predict_np(x, np.ones((1, 1)))).all()


def test_train_cli_dual_method_restarts_and_feasibility_report(tmp_path: Path) -> None:
    """--dual-method / --train pick the method and its parameters; --restarts keeps one member per seed chosen on
    the held-out split; the feasibility verdict is printed and in metrics.json. A bound of 0.2 m/s is met by the
    4-2 net in 20 epochs; the checkpoint holds the 2 kept members."""
    spec = tmp_path / "loose.yaml"
    spec.write_text("objective: {loss: l2}\nconstraints:\n  - {name: near_origin, loss: l2, eps: 0.2, region: "
                    "{norm: {fields: [x.p, x.v], ord: inf, max: 0.5}}}\n")
    out = tmp_path / "run"
    proc = subprocess.run(
        [sys.executable, "-m", "saml_ros.executables", "train", "--system", "friction", "--spec", str(spec),
         "--samples", "2000", "--epochs", "20", "--seeds", "2", "--restarts", "3", "--dual-method", "resilient",
         "--train", "relax_cost=500", "--train", "primal_schedule=step", "--test-samples", "1000", "--out",
         str(out), "--no-progress", "--prelu-init", "-1"],
        cwd=REPO, capture_output=True, text=True, timeout=600,
    )
    assert proc.returncode == 0, proc.stderr
    assert "dual method resilient, schedules step / cosine" in proc.stdout
    assert "verdict [met]" in proc.stdout and proc.stdout.count("kept member") == 2
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["train_config"]["relax_cost"] == 500 and metrics["train_config"]["dual_method"] == "resilient"
    sel = metrics["selection"]
    assert sel["restarts"] == 3 and len(sel["chosen"]) == 2 and all(sel["feasible"])
    assert sel["chosen"][0] in (0, 1, 2) and sel["chosen"][1] in (3, 4, 5)
    # selection on a fresh set (--test-samples of them), with standard errors; the kept members met the bound there
    assert sel["n"] == 1000 and sel["status"] == ["met", "met"] and len(sel["heldout_objective_se"]) == 6
    assert metrics["verdict"]["constraints"]["near_origin"]["verdict"] == "met"
    feas = metrics["feasibility"]["constraints"]["near_origin"]
    assert feas["verdict"] == "met" and feas["n_met"] == 2 and len(feas["members"]) == 2
    assert feas["lhs_min"] < 0.2
    loaded = load_model(out / "ckpt-000001.saml", expect=get_system("friction"))
    assert loaded.model.n_models == 2
    # --prelu-init -1: the first PReLU started as |h| (learned since, so near -1, not at PyTorch's 0.25)
    assert metrics["prelu_init"] == -1.0
    first, second = (s.detach().numpy().ravel() for s in loaded.model.net.slopes)
    assert np.all(first < -0.5) and np.all(np.abs(second - 0.25) < 0.5), (first, second)
    bad = subprocess.run(
        [sys.executable, "-m", "saml_ros.executables", "train", "--system", "friction", "--train", "nupi_gain=1",
         "--out", str(tmp_path / "bad")], cwd=REPO, capture_output=True, text=True, timeout=120,
    )
    assert bad.returncode == 2 and "--train expects FIELD=VALUE" in bad.stderr


def test_train_cli_rejects_a_bad_spec_without_writing(tmp_path: Path) -> None:
    spec = tmp_path / "bad.yaml"
    spec.write_text("objective: {loss: l2}\nconstraints:\n  - {eps: 0.1, region: {box: {x.q: [0, 1]}}}\n")
    out = tmp_path / "run"
    proc = subprocess.run(
        [sys.executable, "-m", "saml_ros.executables", "train", "--system", "friction", "--spec", str(spec),
         "--out", str(out)], cwd=REPO, capture_output=True, text=True, timeout=120,
    )
    assert proc.returncode == 2
    assert "'x.q'" in proc.stderr
    assert not out.exists()
