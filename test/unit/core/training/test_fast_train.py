"""The fast training engine computes the same Algorithm 1 as the plain autograd loop.

Every comparison runs both engines from the same initial weights, data and generator seed, so they see the
same minibatches in the same order. In float64 the two differ only by summation order (about 1e-16 relative;
Adam can amplify a near-cancelling gradient component, hence the 1e-8 bounds, still far below any algorithmic
difference, which shows up at 1e-3 or more). In float32, the default, see the tolerances stated per test.

"fast" runs the fused C++ kernel where it is built (test_fused_kernel.py); there the tests below marked so also run the
fast engine's torch path (``fast_torch``) and check that the kernel equals it: one plain run serves both comparisons,
which test_fused_kernel.py then does not repeat.
"""

from __future__ import annotations

import functools
from dataclasses import replace
from typing import Any

import numpy as np
import pytest
import torch
from helpers.training import FRICTION, METHODS, SPECS, assert_same_run, friction_data

from saml_ros.core.model.network import DynamicsModel
from saml_ros.core.spec import ProblemSpec
from saml_ros.core.training import PrimalDualTrainer, TrainConfig, Transitions
from saml_ros.core.training.engines import fast as fast_engine
from saml_ros.core.training.engines import fused
from saml_ros.offline.pipelines import evaluate_models


def _trainer(
    spec_dict: dict[str, Any], cfg: TrainConfig, engine: str, n: int = 240, hidden: tuple[int, ...] = (4, 2),
    e: int = 1, per_member: bool = False, kind: str = "residual",
) -> tuple[PrimalDualTrainer, Transitions]:
    """A trainer with ``engine`` and its dataset; the same initial weights, data and seed for every engine."""
    spec = ProblemSpec.for_system(spec_dict, FRICTION)
    x, u, y = friction_data(n, list(range(e)) if per_member else None)
    model = DynamicsModel(FRICTION, hidden, kind, n_models=e, seed=7)
    model.fit_normalization(x, u, y)
    return PrimalDualTrainer(model, spec, replace(cfg, engine=engine)), Transitions(model, spec, x, u, y)


def _pair(
    spec_dict: dict[str, Any], cfg: TrainConfig, n: int = 240, hidden: tuple[int, ...] = (4, 2),
    e: int = 1, per_member: bool = False, kind: str = "residual",
) -> tuple[PrimalDualTrainer, PrimalDualTrainer, Transitions, Transitions]:
    """Two identical trainers (engine "plain" and "fast") and their datasets."""
    (plain, dp), (fast, df) = (_trainer(spec_dict, cfg, engine, n, hidden, e, per_member, kind)
                               for engine in ("plain", "fast"))
    return plain, fast, dp, df


def _check_torch_path(spec_dict: dict[str, Any], cfg: TrainConfig, plain: PrimalDualTrainer, fast: PrimalDualTrainer,
                      rtol: float, atol: float, **kw: Any) -> PrimalDualTrainer | None:
    """Where the fused kernel is built ("fast" ran it): the fast engine's torch path (``fast_torch``) on the same
    setting, and the kernel equals it too (test_fused_kernel.py's check, made on this file's plain run); ``None``
    where there is no kernel (then "fast" was the torch path, compared with the plain engine already)."""
    if fused.load_kernel() is None:
        return None
    torch_path, data = _trainer(spec_dict, cfg, "fast_torch", **kw)
    torch_path.fit(data)
    assert fast.kernel_used and not torch_path.kernel_used and not plain.kernel_used
    assert torch_path.engine_used == "fast"
    torch_path.engine_used = "plain"  # assert_same_run checks the engine names of its pair
    assert_same_run(torch_path, fast, rtol=rtol, atol=atol)
    return torch_path


@pytest.mark.parametrize("name", sorted(SPECS))
def test_fast_equals_plain_for_every_loss_and_mean(name: Any) -> None:
    """120 steps of Adam (the paper's optimizer) in float64: same weights, lambdas, optimizer state, history (and
    the kernel's equal to the torch path's, :func:`_check_torch_path`). The multipliers are active from the first
    epochs on (lambda > 2 by step 120 for every constrained spec): an engine that did any step's arithmetic
    differently would be off by 1e-3 or more, ten thousand times the bound."""
    cfg = TrainConfig.paper(epochs=4, batch_size=8, primal_lr=3e-3, dual_lr=5e-2, dtype="float64", seed=5,
                            log_every=7)
    plain, fast, dp, df = _pair(SPECS[name], cfg)
    assert fast_engine.unsupported_reason(fast, df) is None
    plain.fit(dp)
    fast.fit(df)
    assert plain.steps == 4 * 30
    if name != "uniform":
        assert plain.history.as_arrays()["lambdas"].max() > 0, "the test should exercise an active multiplier"
    assert_same_run(plain, fast, rtol=1e-7, atol=1e-8)
    _check_torch_path(SPECS[name], cfg, plain, fast, rtol=1e-7, atol=1e-8)


@pytest.mark.parametrize(
    "variant",
    ["ensemble_shared", "ensemble_per_member", "full_model", "sgd", "adam_primal_sgd_dual", "dual_adam_own_betas",
     "linear_model"],
)
def test_fast_equals_plain_for_models_and_optimizers(variant: Any) -> None:
    """Ensembles, full models, no hidden layer, and every optimizer pairing: the dual Adam merged into the
    primal flat tensor (the default), a separate dual Adam (other betas), SGD."""
    kw: dict[str, Any] = {}
    cfg = TrainConfig.paper(epochs=6, batch_size=16, primal_lr=3e-3, dual_lr=5e-2, dtype="float64", seed=2)
    if variant == "ensemble_shared":
        kw = {"e": 3}
    elif variant == "ensemble_per_member":
        kw = {"e": 3, "per_member": True}
    elif variant == "full_model":
        kw = {"kind": "full", "hidden": (8, 4)}
    elif variant == "sgd":
        cfg = replace(cfg, primal_optimizer="sgd", dual_optimizer="sgd", primal_lr=0.05)
    elif variant == "adam_primal_sgd_dual":
        cfg = replace(cfg, dual_optimizer="sgd", dual_lr=1.0)
    else:
        kw = {"hidden": ()}
    plain, fast, dp, df = _pair(SPECS["paper"], cfg, **kw)
    if variant == "dual_adam_own_betas":
        for tr in (plain, fast):
            tr.dual.optimizer.param_groups[0]["betas"] = (0.8, 0.99)
    merged = fast_engine.FastRun(fast, df).k_dual is not None
    assert merged == (variant not in ("sgd", "adam_primal_sgd_dual", "dual_adam_own_betas"))
    plain.fit(dp)
    fast.fit(df)
    assert_same_run(plain, fast, rtol=1e-7, atol=1e-8)


def test_float32_paper_setting_matches_to_rounding() -> None:
    """The default dtype: 300 steps of the paper's friction problem (4-2 net, Adam 1e-3 / dual Adam).

    float32 rounding (about 6e-8 relative per operation) enters every step and Adam rescales each gradient
    component by its running RMS, so differences grow over training; after 300 steps they stay below 1e-5
    on weights of size ~0.5 and 1e-6 on lambda, where any real difference in the algorithm gives > 1e-3.
    """
    cfg = TrainConfig.paper(epochs=10, batch_size=100, dual_lr=1e-2, seed=1)
    plain, fast, dp, df = _pair(SPECS["paper"], cfg, n=3000)
    plain.fit(dp)
    fast.fit(df)
    assert plain.steps == 300
    assert_same_run(plain, fast, rtol=1e-4, atol=1e-5)
    _check_torch_path(SPECS["paper"], cfg, plain, fast, rtol=1e-4, atol=1e-5, n=3000)


def test_heldout_metrics_match_after_a_full_short_training() -> None:
    """The convergence experiment's setting (noise sigma = 0.2 on v, 8-4 nets, 3 datasets as one ensemble),
    trained to the end in float32 with each engine: held-out objective, constraint and per-region errors agree
    to 1e-4 (they are ~0.2 and differ between seeds by ~1e-2)."""
    spec = ProblemSpec.for_system(FRICTION.paper_spec(), FRICTION)
    x, u, y = friction_data(1500, [0, 1, 2], noise=0.2)
    xt, ut, yt = FRICTION.make_dataset(5000, np.random.default_rng(99), {"v": 0.2})
    evals = []
    for engine in ("plain", "fast"):
        model = DynamicsModel(FRICTION, (8, 4), n_models=3, seed=3)
        model.fit_normalization(x, u, y)
        tr = PrimalDualTrainer(model, spec, TrainConfig.paper(epochs=25, batch_size=128, dual_lr=1e-2, engine=engine))
        tr.fit(Transitions(model, spec, x, u, y))
        assert tr.engine_used == engine
        evals.append(evaluate_models(model, spec, xt, ut, yt))
    plain, fast = evals
    np.testing.assert_allclose(fast.objective, plain.objective, atol=1e-4)
    np.testing.assert_allclose(fast.constraints, plain.constraints, atol=1e-4)
    for rp, rf in zip(plain.regions, fast.regions):
        np.testing.assert_allclose(rf.inside, rp.inside, atol=1e-4)
        np.testing.assert_allclose(rf.outside, rp.outside, atol=1e-4)
    assert np.ptp(plain.objective) > 1e-3  # the seeds differ far more than the engines


def test_unsupported_settings_fall_back_to_the_plain_loop() -> None:
    """AMSGrad has no fast implementation: fit() must run the plain loop, with plain results."""
    cfg = TrainConfig.paper(epochs=3, batch_size=16, dual_lr=1e-2, dtype="float64")
    reference, fast, dr, df = _pair(SPECS["paper"], replace(cfg, engine="plain"))
    for tr in (reference, fast):
        tr.primal_opt.param_groups[0]["amsgrad"] = True
    fast.config = replace(cfg, engine="fast")
    reason = fast_engine.unsupported_reason(fast, df)
    assert reason is not None and "amsgrad" in reason
    with pytest.raises(ValueError, match="amsgrad"):
        fast_engine.FastRun(fast, df)
    reference.fit(dr)
    fast.fit(df)
    assert fast.engine_used == "plain"
    for a, b in zip(reference.model.parameters(), fast.model.parameters()):
        assert torch.equal(a, b)
    # the same trainer without AMSGrad takes the fast path and ends elsewhere
    _, other, _, do = _pair(SPECS["paper"], cfg)
    other.fit(do)
    assert other.engine_used == "fast"
    diff = max(float((a - b).abs().max()) for a, b in zip(other.model.state_dict().values(),
                                                           fast.model.state_dict().values()))
    assert diff > 1e-6  # AMSGrad changed the result: the fallback did run it


def test_engines_can_be_mixed_and_resumed() -> None:
    """Optimizer state goes through the torch optimizers: fast, then plain, then fast again (with values from
    online steps pending in between) equals plain all the way; a callback sees the current model."""
    cfg = TrainConfig.paper(epochs=2, batch_size=16, dual_lr=5e-2, dtype="float64", seed=4, log_every=5)
    plain, mixed, dp, dm = _pair(SPECS["paper"], cfg)
    seen: dict[str, list[float]] = {"plain": [], "fast": []}

    def probe(tr: PrimalDualTrainer) -> None:
        seen[tr.config.engine].append(float(tr.evaluate(dm)["lagrangian"][0]))

    plain.fit(dp, callback=probe)
    mixed.fit(dm, callback=probe)
    assert len(seen["plain"]) == len(seen["fast"]) == 2
    np.testing.assert_allclose(seen["fast"], seen["plain"], rtol=1e-9)
    x, u, y = (torch.as_tensor(a[:16]) for a in friction_data(16, None))
    for tr in (plain, mixed):
        tr.step(x, u, y)  # an online step: its values are pending when fit() starts
    mixed.config = replace(cfg, engine="plain")
    plain.fit(dp)
    mixed.fit(dm)
    mixed.config = replace(cfg, engine="fast")
    plain.fit(dp)
    mixed.fit(dm)
    assert [mixed.engine_used, plain.engine_used] == ["fast", "plain"]
    plain.engine_used = "plain"
    mixed.engine_used = "fast"
    assert_same_run(plain, mixed, rtol=1e-7, atol=1e-8)
    # a checkpoint-style round trip of the state restores the same trainer
    restored, _, _, _ = _pair(SPECS["paper"], cfg)
    restored.load_state(mixed.state())
    for a, b in zip(restored.model.parameters(), mixed.model.parameters()):
        assert torch.equal(a, b)


@functools.cache
def _paper_method_lambda(spec_name: str) -> torch.Tensor:
    """lambda after the plain engine's run of :func:`test_fast_equals_plain_for_every_dual_method`'s setting with
    the paper's method (Adam on lambda, lr 5e-2): the reference every method is compared with. The paper's method
    reads none of the other methods' parameters (penalty, nupi_*, relax_cost), so one run per spec serves all."""
    cfg = TrainConfig.paper(epochs=3, batch_size=8, primal_lr=3e-3, dual_lr=5e-2, dtype="float64", seed=5,
                            log_every=7)
    ref, data = _trainer(SPECS[spec_name], cfg, "plain")
    ref.fit(data)
    return ref.lam.clone()


@pytest.mark.parametrize("method", sorted(METHODS))
@pytest.mark.parametrize("spec_name", ["paper", "mixed"])
def test_fast_equals_plain_for_every_dual_method(method: Any, spec_name: Any) -> None:
    """Every dual method in flat form: 90 steps in float64 with the same bounds as the paper's method (lambda, the
    dual optimizer's state, the history); the methods do move lambda differently from the paper's (by 0.17 or more
    at the end of these 90 steps, against the 1e-3 checked), but for the Lagrangian, which is the paper's
    arithmetic under another name.

    Where the fused kernel is built, the kernel also equals the torch path (:func:`_check_torch_path`)."""
    cfg = TrainConfig.paper(**{"epochs": 3, "batch_size": 8, "primal_lr": 3e-3, "dual_lr": 5e-2, "dtype": "float64",
                               "seed": 5, "log_every": 7, **METHODS[method]})
    plain, fast, dp, df = _pair(SPECS[spec_name], cfg)
    assert fast_engine.unsupported_reason(fast, df) is None
    plain.fit(dp)
    fast.fit(df)
    assert plain.history.as_arrays()["lambdas"].max() > 0
    assert_same_run(plain, fast, rtol=1e-7, atol=1e-8)
    _check_torch_path(SPECS[spec_name], cfg, plain, fast, rtol=1e-7, atol=1e-8)
    ref_lam = _paper_method_lambda(spec_name)
    if method == "lagrangian":
        assert torch.equal(ref_lam, plain.lam)
    else:
        assert float((ref_lam - plain.lam).abs().max()) > 1e-3  # the method changed the run


@pytest.mark.parametrize("schedules", [("cosine", "cosine"), ("step", "step"), ("cosine", "constant"),
                                       ("constant", "step")])
@pytest.mark.parametrize("method", ["paper", "lagrangian", "nupi", "augmented", "resilient"])
def test_fast_equals_plain_under_learning_rate_schedules(schedules: Any, method: Any) -> None:
    """Schedules in both engines: the same rates per update (equal schedules keep the dual Adam merged into the
    primal flat tensor, different ones do not; the augmented Lagrangian's SGD step is the penalty times the dual
    schedule's factor), a horizon of the run's own length, and the optimizers' final learning rates are the last
    update's. 90 steps: the step schedule drops its three times and the cosine spans the whole run whatever its
    length (the horizon is the run's own).

    Where the fused kernel is built, the kernel also equals the torch path (:func:`_check_torch_path`)."""
    primal, dual = schedules
    cfg = TrainConfig.paper(**{"epochs": 3, "batch_size": 8, "primal_lr": 3e-3, "dual_lr": 5e-2, "dtype": "float64",
                               "seed": 5, "log_every": 7, "primal_schedule": primal, "dual_schedule": dual,
                               "lr_floor": 0.1, "lr_drops": 3, **({} if method == "paper" else METHODS[method])})
    plain, fast, dp, df = _pair(SPECS["paper"], cfg)
    plain.fit(dp)
    fast.fit(df)
    run = fast_engine.FastRun(fast, df)
    # the methods whose lambda an Adam moves (nuPI has its controller, the augmented Lagrangian its SGD step)
    assert (run.k_dual is not None) == (method in ("paper", "lagrangian", "resilient") and primal == dual)
    assert_same_run(plain, fast, rtol=1e-7, atol=1e-8)
    steps = plain.steps
    torch_path = _check_torch_path(SPECS["paper"], cfg, plain, fast, rtol=1e-7, atol=1e-8)
    for tr in (plain, fast) if torch_path is None else (plain, fast, torch_path):
        assert tr.schedules is not None
        ps, ds = tr.schedules
        assert ps.horizon == steps  # epochs x minibatches per epoch
        assert tr.primal_opt.param_groups[0]["lr"] == ps.lr(steps - 1)
        assert tr.dual.lr == ds.lr(steps - 1)
