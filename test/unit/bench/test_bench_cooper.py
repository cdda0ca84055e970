"""``bench cooper`` compares our dual methods with the cooper library's on one footing: the same initialisations,
data, normalisation and minibatch order. Checked here: cooper's Lagrangian with Adam on the multiplier at our
rates takes our ``lagrangian`` trainer's steps (float64, a short run), and the bench's ``--quick`` run works."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from bench import bench_cooper


def test_coopers_lagrangian_with_adam_takes_our_lagrangians_steps() -> None:
    torch.set_num_threads(1)
    s = bench_cooper.make_setup([0, 1], restarts=2, n=640, epochs=3)
    s.dtype = "float64"
    cfg = bench_cooper.base_config(s, dual_method="lagrangian", engine="plain")
    ours, lam_ours = bench_cooper.train_ours(s, cfg)
    theirs, lam_theirs = bench_cooper.train_cooper(s, "lagrangian", cfg.dual_lr, dual_adam=True)
    assert lam_ours.shape == lam_theirs.shape == (3, 4) and lam_ours.max() > 0.01
    np.testing.assert_allclose(lam_theirs, lam_ours, rtol=1e-9, atol=1e-12)
    for a, b in zip(ours.net.parameters(), theirs.net.parameters()):
        torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-12)
    # and the fast engine (the bench's) agrees with both to float rounding
    fast, lam_fast = bench_cooper.train_ours(s, bench_cooper.base_config(s, dual_method="lagrangian"))
    np.testing.assert_allclose(lam_fast, lam_ours, rtol=1e-7, atol=1e-9)


def test_quick_run_prints_the_comparison(capsys: pytest.CaptureFixture[str]) -> None:
    assert bench_cooper.main(["--quick", "--methods", "default", "cooper: nuPI"]) == 0
    out = capsys.readouterr().out
    assert "| ours: default TrainConfig() (lagrangian, Adam 0.01) |" in out
    assert "| cooper: nuPI, step 1e-2/eps, K_P 10 |" in out and "at the best optimum" in out
