"""Primal-dual trainer (Algorithm 1) on problems with known solutions."""

from __future__ import annotations

import logging
from copy import deepcopy

import numpy as np
import pytest
import torch

from saml_ros.core.models import DynamicsModel
from saml_ros.core.spec import ProblemSpec
from saml_ros.core.training import DualVariables, PrimalDualTrainer, TrainConfig, Transitions


def _two_groups(n: int = 200) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Half the targets are 1 (region A: next.y >= 0.5), half are 0; inputs are constant."""
    y = np.zeros((n, 1))
    y[: n // 2] = 1.0
    return np.ones((n, 1)), np.zeros((n, 1)), y


CONVEX_SPEC = {
    "name": "convex",
    "objective": {"loss": "squared_l2"},
    "constraints": [
        {"name": "ones", "loss": "squared_l2", "eps": 0.04, "mean": "conditional",
         "region": {"box": {"next.y": [0.5, None]}}},
    ],
}


def _trainer(system, spec_dict, config, seed=0):
    spec = ProblemSpec.for_system(spec_dict, system)
    model = DynamicsModel(system, hidden=(), kind="full", seed=seed)
    x, u, y = _two_groups()
    model.fit_normalization(x, u, y)
    tr = PrimalDualTrainer(model, spec, config)
    return tr, Transitions(model, spec, x, u, y), spec


@pytest.mark.parametrize("primal", ["sgd", "adam"])
def test_convex_problem_converges_to_optimum_and_multiplier(toy_system, primal):
    # min E[(c - y)^2]  s.t.  E[(c - 1)^2 | y = 1] <= 0.04  ->  c* = 0.8, P* = 0.34, lambda* = 1.5
    lr = 0.05 if primal == "sgd" else 0.01
    cfg = TrainConfig(epochs=3000, batch_size=200, primal_lr=lr, dual_lr=0.05,
                      primal_optimizer=primal, dual_optimizer="sgd", dtype="float64")
    tr, data, _ = _trainer(toy_system, CONVEX_SPEC, cfg)
    tr.fit(data)
    c = float(tr.model.predict_np(np.ones(1), np.zeros(1))[0])
    ev = tr.evaluate(data)
    assert c == pytest.approx(0.8, abs=5e-3)
    assert float(tr.lam[0, 0]) == pytest.approx(1.5, abs=0.05)
    assert float(ev["objective"][0]) == pytest.approx(0.34, abs=5e-3)
    assert float(ev["lagrangian"][0]) == pytest.approx(0.34, abs=5e-3)
    assert tr.feasibility().ok


def test_uniform_baseline_ignores_constraint(toy_system):
    cfg = TrainConfig(epochs=2000, batch_size=200, primal_lr=0.05, primal_optimizer="sgd", dtype="float64")
    spec = ProblemSpec.for_system(CONVEX_SPEC, toy_system).uniform()
    model = DynamicsModel(toy_system, hidden=(), kind="full")
    x, u, y = _two_groups()
    model.fit_normalization(x, u, y)
    tr = PrimalDualTrainer(model, spec, cfg)
    tr.fit(Transitions(model, spec, x, u, y))
    assert spec.n_constraints == 0
    assert float(tr.model.predict_np(np.ones(1), np.zeros(1))[0]) == pytest.approx(0.5, abs=5e-3)


def test_infeasible_constraint_grows_lambda_and_is_reported(toy_system, caplog):
    spec = dict(CONVEX_SPEC)
    spec["constraints"] = CONVEX_SPEC["constraints"] + [
        {"name": "zeros", "loss": "squared_l2", "eps": 0.04, "region": {"box": {"next.y": [None, 0.5]}}},
    ]
    cfg = TrainConfig(epochs=600, batch_size=200, primal_lr=0.01, dual_lr=0.05,
                      primal_optimizer="adam", dual_optimizer="sgd", dtype="float64")
    tr, data, _ = _trainer(toy_system, spec, cfg)
    with caplog.at_level(logging.WARNING, logger="saml_ros.trainer"):
        tr.fit(data)
    lam = tr.history.as_arrays()["lambdas"][:, 0, :]
    # c cannot be both >= 0.8 and <= 0.2: the sum of violations stays >= 0.36 - 0.08 > 0, so the
    # multipliers grow without bound (linearly in the number of steps)
    assert lam[-1].sum() > lam[len(lam) // 2].sum() + 1.0
    report = tr.feasibility()
    assert not report.ok
    assert any("infeasible" in r.message for r in caplog.records)


def test_ensemble_members_are_independent(toy_system):
    """Training E members together equals training each alone (same seeds, same data order)."""
    cfg = TrainConfig(epochs=30, batch_size=32, primal_lr=1e-2, dual_lr=1e-2, dtype="float64", seed=3)
    spec = ProblemSpec.for_system(CONVEX_SPEC, toy_system)
    x, u, y = _two_groups()
    rng = np.random.default_rng(0)
    y = y + rng.normal(0, 0.1, y.shape)
    ens = DynamicsModel(toy_system, hidden=(4, 2), kind="full", n_models=3, seed=1)
    ens.fit_normalization(x, u, y)
    tr = PrimalDualTrainer(ens, spec, cfg)
    tr.fit(Transitions(ens, spec, x, u, y))
    # replay member 1 alone with the same init and the same permutation stream
    solo = DynamicsModel(toy_system, hidden=(4, 2), kind="full", n_models=3, seed=1).member(1).double()
    solo.fit_normalization(x, u, y)
    tr1 = PrimalDualTrainer(solo, spec, cfg)
    data1 = Transitions(solo, spec, x, u, y)
    gen = torch.Generator().manual_seed(3)
    n, b = len(data1), 32
    for _ in range(30):
        perm = torch.argsort(torch.rand(3, n, generator=gen), dim=1)[1:2]
        for j in range(n // b):
            idx = perm[:, j * b:(j + 1) * b]
            xx, uu, yy, bb = data1.take(idx)
            tr1.step(xx, uu, yy, bb, data1.take_masks(idx))
    for p_ens, p_solo in zip(ens.net.parameters(), solo.net.parameters()):
        # equal up to float64 rounding amplified by Adam; any coupling between members would be O(1e-2)
        torch.testing.assert_close(p_ens[1], p_solo[0], rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(tr.lam[1], tr1.lam[0], rtol=1e-5, atol=1e-6)


def test_lambda_never_negative_and_dual_uses_detached_constraint(toy_system):
    cfg = TrainConfig(epochs=50, batch_size=16, primal_lr=1e-2, dual_lr=0.5, dtype="float64")
    tr, data, _ = _trainer(toy_system, CONVEX_SPEC, cfg)
    tr.fit(data)
    lam = tr.history.as_arrays()["lambdas"]
    assert (lam >= 0).all()
    assert all(p.grad is None or torch.isfinite(p.grad).all() for p in tr.model.parameters())


def test_dual_variables_ascend_project_and_round_trip():
    """The multipliers on their own: SGD ascent is lambda + lr * g, projected onto lambda >= 0 per entry; a state
    round trip (value and optimizer state) continues identically; with K = 0 a step does nothing."""
    dual = DualVariables(2, 2, torch.float64, optimizer="sgd", lr=0.5)
    dual.step(torch.tensor([[1.0, -1.0], [0.2, 0.4]], dtype=torch.float64))
    torch.testing.assert_close(dual.value, torch.tensor([[0.5, 0.0], [0.1, 0.2]], dtype=torch.float64))
    dual.step(torch.tensor([[-0.4, 2.0], [-1.0, 0.0]], dtype=torch.float64))
    torch.testing.assert_close(dual.value, torch.tensor([[0.3, 1.0], [0.0, 0.2]], dtype=torch.float64))
    adam = DualVariables(1, 3, torch.float64, optimizer="adam", lr=0.1)
    g = torch.tensor([[0.3, -0.2, 0.1]], dtype=torch.float64)
    adam.step(g)
    copy = DualVariables(1, 3, torch.float64, optimizer="adam", lr=0.1)
    copy.load_state_dict(deepcopy(adam.state_dict()))  # torch optimizers' state_dicts hold references
    for d in (adam, copy):
        d.step(g)
    torch.testing.assert_close(copy.value, adam.value, rtol=0, atol=0)
    assert (adam.value >= 0).all() and adam.value[0, 1] == 0 and adam.value[0, 0] > 0
    none = DualVariables(3, 0, torch.float32)
    none.step(torch.zeros(3, 0))
    assert none.value.shape == (3, 0) and not none.optimizer.state
