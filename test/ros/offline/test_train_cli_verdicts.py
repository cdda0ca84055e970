"""Offline verdicts on held-out data (saml_ros.core.training.verdict), the aim below eps, the restart selection on
held-out estimates, whole stretches of time held out of recordings, and what `train` prints, stores and exits with."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import pytest
from helpers import REPO
from helpers.offline import WIDE

from saml_ros.core.model.checkpoint import read_checkpoint
from saml_ros.core.training import heldout as H


def _train(argv: list[str], out: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "saml_ros.executables", "train", "--system", "friction",
                           "--out", str(out), "--no-progress", *argv],
                          cwd=REPO, capture_output=True, text=True, timeout=600)


def test_a_model_that_memorises_its_data_is_never_reported_met(tmp_path: Path) -> None:
    """A 64-64 net on 400 transitions whose velocity carries noise of 0.2 m/s: it fits its training data (in-region
    error 0.09 against eps 0.12, and the training diagnosis says met) but not fresh data (about 0.2, the noise
    floor). `train` reports "met on training data only", never met, in print, metrics.json and the checkpoint; with
    --require-met it exits 1."""
    spec = tmp_path / "wide.yaml"
    spec.write_text(json.dumps(WIDE))
    out = tmp_path / "run"
    proc = _train(["--spec", str(spec), "--hidden", "64", "64", "--samples", "400", "--noise", "v=0.2",
                   "--epochs", "200", "--batch-size", "32", "--require-met"], out)
    assert proc.returncode == 1, proc.stderr
    assert "verdict [met_on_training_only] constraint 'wide': MET ON TRAINING DATA ONLY" in proc.stdout
    assert "verdict [met]" not in proc.stdout and "0/1 constraints met on held-out data (level WARN)" in proc.stdout
    metrics = json.loads((out / "metrics.json").read_text())
    v = metrics["verdict"]["constraints"]["wide"]
    assert v["verdict"] == H.MET_ON_TRAINING_ONLY and metrics["verdict"]["level"] == 1
    member = v["members"][0]
    assert member["training"] <= 0.12 < member["heldout"]["mean"] and member["heldout"]["n"] >= H.MIN_N
    assert v["convergence"] == "met"  # what the training data said: the old verdict would have been "met"
    _, meta = read_checkpoint(out / "ckpt-000001.saml")
    assert meta["heldout_verdict"]["constraints"]["wide"]["verdict"] == H.MET_ON_TRAINING_ONLY
    assert meta["metrics"]["verdict"] == meta["heldout_verdict"] and meta["aim"]["margin"] == "auto"


def test_train_reports_met_with_its_held_out_estimate_and_records_the_aim(tmp_path: Path) -> None:
    """The wide bound without noise: met on held-out data with confidence; the printed line has the held-out
    estimate +- its standard error, the training value and the aim; metrics.json and the checkpoint hold them."""
    spec = tmp_path / "wide.yaml"
    spec.write_text(json.dumps(WIDE))
    out = tmp_path / "run"
    proc = _train(["--spec", str(spec), "--samples", "2000", "--epochs", "30", "--seeds", "2", "--require-met"], out)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    line = next(ln for ln in proc.stdout.splitlines() if "verdict [" in ln)
    assert line.startswith("train: verdict [met] constraint 'wide': met by 2/2 members (held-out ")
    assert "+-" in line and "<= eps 0.12" in line and "training " in line and "aimed at " in line
    assert "held-out data: 20000 fresh transitions" in proc.stdout
    metrics = json.loads((out / "metrics.json").read_text())
    aim = metrics["aim"]["constraints"]["wide"]
    assert metrics["aim"]["margin"] == "auto" and metrics["aim"]["measured_at_epoch"] == 15
    assert 0.06 <= aim["aim"] < 0.12 and aim["train_se"] > aim["heldout_se"] > 0
    assert aim["aim"] == pytest.approx(0.12 - H.Z * math.hypot(aim["train_se"], aim["heldout_se"]))
    v = metrics["verdict"]["constraints"]["wide"]
    assert v["verdict"] == H.MET and v["aim"] == aim["aim"] and len(v["members"]) == 2
    for m in v["members"]:
        assert m["upper"] == pytest.approx(m["heldout"]["mean"] + H.Z * m["heldout"]["se"]) and m["upper"] <= 0.12
    # the training diagnosis is against the aim; the checkpoint's spec is the problem as given
    assert metrics["feasibility"]["constraints"]["wide"]["eps"] == aim["aim"]
    _, meta = read_checkpoint(out / "ckpt-000001.saml")
    assert meta["spec"]["constraints"][0]["eps"] == 0.12 and meta["aim"] == metrics["aim"]
    # a margin that is not 'auto', 'none' or a fraction of eps in [0, 0.5] is refused before anything runs
    bad = _train(["--margin", "0.9"], tmp_path / "bad")
    assert bad.returncode == 2 and "margin must be" in bad.stderr and not (tmp_path / "bad").exists()
