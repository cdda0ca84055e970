"""Offline pipeline: the Sufficiently Accurate trade-off on the double integrator, the train CLI."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np

from saml_ros.core.model_io import load_model
from saml_ros.core.spec import ProblemSpec
from saml_ros.core.systems import get_system
from saml_ros.core.training import TrainConfig
from saml_ros.offline.pipelines import compare

ROOT = Path(__file__).resolve().parents[1]


def test_sufficient_beats_uniform_inside_region_and_loses_outside():
    """A short version of the paper's double-integrator experiment (5k samples, 30 epochs, a faster dual
    step than the paper's 1e-4 so the multiplier becomes active within the budget); the full run is
    `./dev demo --offline` (docs/results.md)."""
    system = get_system("friction")
    spec = ProblemSpec.for_system(system.paper_spec(), system)
    cmp = compare(system, spec, TrainConfig(epochs=30, batch_size=128, dual_lr=1e-2), seeds=[0, 1, 2],
                  n_train=5000, n_test=20000)
    sa, ua = cmp.eval_sufficient.regions[0], cmp.eval_uniform.regions[0]
    assert (sa.inside < ua.inside).all(), (sa.inside, ua.inside)     # every seed, paired
    assert sa.outside.mean() > ua.outside.mean()
    assert cmp.claim_holds()
    assert (cmp.sufficient.trainer.lam > 0).all() and cmp.uniform.trainer.lam.numel() == 0
    assert "| Sufficiently Accurate |" in cmp.table()


def test_train_cli_writes_a_usable_checkpoint_and_report(tmp_path):
    out = tmp_path / "run"
    proc = subprocess.run(
        [sys.executable, "-m", "saml_ros.executables", "train", "--system", "friction", "--samples", "2000",
         "--epochs", "3", "--seeds", "2", "--test-samples", "1000", "--out", str(out), "--no-progress"],
        cwd=ROOT, capture_output=True, text=True, timeout=300,
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


def test_train_cli_rejects_a_bad_spec_without_writing(tmp_path):
    spec = tmp_path / "bad.yaml"
    spec.write_text("objective: {loss: l2}\nconstraints:\n  - {eps: 0.1, region: {box: {x.q: [0, 1]}}}\n")
    out = tmp_path / "run"
    proc = subprocess.run(
        [sys.executable, "-m", "saml_ros.executables", "train", "--system", "friction", "--spec", str(spec),
         "--out", str(out)], cwd=ROOT, capture_output=True, text=True, timeout=120,
    )
    assert proc.returncode == 2
    assert "'x.q'" in proc.stderr
    assert not out.exists()
