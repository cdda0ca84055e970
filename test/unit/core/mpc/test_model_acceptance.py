"""Checkpoint acceptance (saml_ros.core.mpc.acceptance) and the evidence it reads (saml_ros.core.model.evidence):
the MPC refuses non-finite, implausible and out-of-evidence models, counts each refusal by reason and keeps its model.
The node-level check (a real MPC process that keeps landing) is in test_mpc_node.py."""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np
import torch
from helpers.models import QUAD, quad_evidence, quad_model, save_quad_checkpoint

from msg_schemas.telemetry import CHECKPOINT_REFUSAL_REASONS
from saml_ros.core.data.plausibility import Plausibility
from saml_ros.core.model.checkpoint import CheckpointStore
from saml_ros.core.model.evidence import DataEvidence
from saml_ros.core.model.io import load_model
from saml_ros.core.mpc.acceptance import ACCEPTANCE_REASONS, check_model
from saml_ros.core.mpc.config import MPCConfig
from saml_ros.core.mpc.follower import REFUSAL_REASONS
from saml_ros.core.mpc.service import MPCService
from saml_ros.core.systems import get_system

LOG = logging.getLogger("test_model_acceptance")


def test_the_reasons_are_the_documented_ones() -> None:
    assert REFUSAL_REASONS == CHECKPOINT_REFUSAL_REASONS
    assert ACCEPTANCE_REASONS == ("non_finite", "implausible", "residual", "heldout")


def test_evidence_statistics_merge_and_round_trip(tmp_path: Path) -> None:
    x, u, y = QUAD.make_dataset(1000, np.random.default_rng(0))
    ev = DataEvidence.from_data(QUAD, x, u, y, probe_rows=100)
    assert ev is not None and ev.n == 1000 and ev.probe_x.shape == (100, 13) and ev.probe_u.shape == (100, 4)
    r = y - QUAD.base_step_np(x, u)
    np.testing.assert_allclose(ev.residual_max, np.abs(r).max(0))
    assert ev.residual_max[QUAD.target.index("px")] == 0.0  # f_hat's positions are exact
    assert ev.residual_max[QUAD.target.index("vz")] > 0.1  # the ground effect
    older = DataEvidence(500, ev.residual_max * 2, ev.residual_rms, ev.target_std, ev.probe_x, ev.probe_u)
    merged = ev.merged(older, 1500)
    np.testing.assert_array_equal(merged.residual_max, ev.residual_max * 2)
    assert merged.n == 1500 and merged.probe_x is ev.probe_x
    path, _ = save_quad_checkpoint(CheckpointStore(tmp_path / "run"), quad_model(), ev)
    loaded = load_model(path)
    back = DataEvidence.from_checkpoint(loaded.arrays, loaded.meta, QUAD)
    assert back is not None and back.n == 1000
    np.testing.assert_allclose(back.residual_max, ev.residual_max)
    np.testing.assert_array_equal(back.probe_x, ev.probe_x)
    assert DataEvidence.from_checkpoint(loaded.arrays, loaded.meta, get_system("friction")) is None  # other layouts
    assert DataEvidence.from_data(QUAD, x[:0], u[:0], y[:0]) is None


def test_check_model_refuses_each_kind_of_bad_model(tmp_path: Path) -> None:
    store = CheckpointStore(tmp_path / "run")
    bounds = Plausibility.for_system(QUAD)
    ev = quad_evidence()
    cases = {
        None: (quad_model(), None),
        "non_finite": (quad_model(), "biases"),
        "implausible": (quad_model(bias={"pz": 1e6}), None),  # a residual of 1e6 m: the example
        "residual": (quad_model(bias={"vz": 30.0}), None),  # plausible, but 10x more than any transition showed
    }
    for want, (model, poison) in cases.items():
        got = check_model(load_model(save_quad_checkpoint(store, model, ev, poison)[0]), bounds)
        assert (got[0] if got else None) == want, (want, got)
    assert "the training data never showed more than" in check_model(  # type: ignore[index]
        load_model(save_quad_checkpoint(store, quad_model(bias={"vz": 30.0}), ev)[0]), bounds)[1]


def test_recent_states_probe_where_the_stored_probe_set_does_not_reach(tmp_path: Path) -> None:
    """The model is fine where it was trained (|px| <= 2 m) and broken from px = 3 m on; the MPC flies at px = 5 m."""
    store = CheckpointStore(tmp_path / "run")
    bounds = Plausibility.for_system(QUAD)
    model = quad_model(hidden=(4,))
    with torch.no_grad():  # one PReLU unit that switches on beyond px = 3 m and pushes vz by 25 m/s per metre
        h = model.net.weights[0]
        i = QUAD.state.index("px")
        std, mean = float(model.in_std[0, 0, i]), float(model.in_mean[0, 0, i])
        h[0, :, 0] = 0.0
        h[0, i, 0] = std  # pre-activation = px - mean (in m) ...
        model.net.biases[0][0, 0, 0] = mean - 3.0  # ... - 3
        model.net.slopes[0].fill_(0.0)
        model.net.weights[1][0, 0, :] = 0.0
        model.net.weights[1][0, 0, QUAD.target.index("vz")] = 25.0 / float(model.out_std[0, 0, QUAD.target.index("vz")])
    loaded = load_model(save_quad_checkpoint(store, model, quad_evidence(px=2.0))[0])
    assert check_model(loaded, bounds) is None  # its own probe set shows nothing wrong
    recent = np.stack([QUAD.hover_state((5.0, 0.0, 2.0))] * 3), np.full((3, 4), 2.45)
    got = check_model(loaded, bounds, recent)
    assert got is not None and got[0] == "residual" and "vz" in got[1]
    # without stored evidence only the recent states' plausibility is checked
    bare = load_model(save_quad_checkpoint(store, quad_model(bias={"pz": 1e6}), None)[0])
    assert check_model(bare, bounds) is None
    assert check_model(bare, bounds, recent)[0] == "implausible"  # type: ignore[index]


def test_the_mpc_refuses_bad_checkpoints_counts_each_reason_and_keeps_its_model(tmp_path: Path) -> None:
    store = CheckpointStore(tmp_path / "run")
    sent: list[np.ndarray] = []
    service = MPCService(MPCConfig.from_params({"system": "quadrotor", "run_dir": str(store.run_dir)}),
                         lambda u, s: sent.append(u), LOG)
    ev = quad_evidence()
    _, v1 = save_quad_checkpoint(store, quad_model(), ev)
    service.start()  # loads version 1 before the first solve
    try:
        assert service.model_version == v1 == 1
        x = QUAD.hover_state((1.0, -1.0, 2.0))
        for reason, (model, poison) in (("non_finite", (quad_model(1), "weights")),
                                        ("implausible", (quad_model(2, {"pz": 1e6}), None)),
                                        ("residual", (quad_model(3, {"vz": 30.0}), None))):
            save_quad_checkpoint(store, model, ev, poison)
            assert service.watcher.poll_once() is None
            service.control_step(x, 10**9 + len(sent) * 10**8, time.perf_counter())
            diag = service.diagnostic_values()
            assert diag[f"checkpoints_refused/{reason}"] == 1, diag
            assert service.model_version == 1 and diag["last_refusal"]
        assert service.diagnostic_values()["checkpoints_refused"] == 3
        _, v5 = save_quad_checkpoint(store, quad_model(4), ev)  # a good one after that is taken
        ready = service.watcher.poll_once()
        assert ready is not None and ready.version == v5 == 5
    finally:
        service.stop()
