"""Online updates on the fast engine's path (saml_ros.core.online.updates, engines.stream) learn what the plain
online step learns on the same minibatches: parameters, multipliers, optimizer states, history and telemetry
averages, for every dual method and learning-rate schedule; and the health checks still keep bad minibatches and
exploding weights out of the model. Where the fused kernel is built, the fast path runs on it
(engines.fused.FusedStreamRun), and it equals the torch-path stream (engine "fast_torch") on the same minibatches."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
import torch

from saml_ros.core.online import OnlineConfig, OnlineLearner
from saml_ros.core.spec import ProblemSpec
from saml_ros.core.systems import get_system
from saml_ros.core.training import TrainConfig
from saml_ros.core.training.engines import fused
from saml_ros.core.training.health import HealthConfig

OPEN = "{x.p: [-.inf, .inf], x.v: [-.inf, .inf], u.u: [-.inf, .inf]}"


def _learner(system_name: str, engine: str, health: HealthConfig | None = None, hidden: tuple[int, ...] | None = None,
             **train: Any) -> OnlineLearner:
    system = get_system(system_name)
    spec = ProblemSpec.for_system(system.paper_spec(), system)
    tc = TrainConfig(**{"batch_size": 32, "log_every": 20, "dtype": "float64", "engine": engine, **train})
    cfg = OnlineConfig(min_transitions=200, buffer_capacity=3000, train=tc, hidden=hidden,
                       health=health or HealthConfig(), plausible_bounds=OPEN if system_name == "friction" else "")
    learner = OnlineLearner(system, spec, cfg)
    x, u, y = system.make_dataset(600, np.random.default_rng(1))
    learner.add_batch(x, u, y)
    return learner


def _state(learner: OnlineLearner) -> list[torch.Tensor]:
    tr = learner.trainer
    assert tr is not None
    out = [p.detach() for p in tr.model.net.parameters()] + [tr.lam]
    for opt in (tr.primal_opt, tr.dual.optimizer):
        for st in opt.state.values():
            out += [v for k, v in sorted(st.items()) if isinstance(v, torch.Tensor)]
    return out


def _run_both(fast: OnlineLearner, plain: OnlineLearner, chunks: list[int]) -> None:
    for n in chunks:
        assert fast.update(n) == n and plain.update(n) == n
        assert fast.updates == plain.updates
    assert fast._updates is not None and fast._updates.engine == "fast"
    assert plain._updates is not None and plain._updates.engine == "plain"
    assert fast._updates.stream is not None and fast._updates.stream.kernel_used == KERNEL


#: the fused kernel is built here (then the fast online updates run on it)
KERNEL = fused.load_kernel() is not None
needs_kernel = pytest.mark.skipif(not KERNEL, reason=f"fused kernel not available: {fused.kernel_reason()}")


def _assert_same(fast: OnlineLearner, plain: OnlineLearner, tol: float) -> None:
    sf, sp = _state(fast), _state(plain)
    assert len(sf) == len(sp)
    for a, b in zip(sf, sp):
        assert a.shape == b.shape
        assert torch.allclose(a.double(), b.double(), rtol=tol, atol=tol), float((a - b).abs().max())
    hf, hp = fast.trainer.history, plain.trainer.history  # type: ignore[union-attr]
    assert hf.step == hp.step and len(hf.step) > 0
    np.testing.assert_allclose(np.asarray(hf.objective), np.asarray(hp.objective), rtol=tol, atol=tol)
    np.testing.assert_allclose(np.asarray(hf.constraints), np.asarray(hp.constraints), rtol=tol, atol=tol)
    mf, mp = fast.compute_model_metrics(), plain.compute_model_metrics()
    for k in ("objective", "lagrangian", "error_all"):
        assert mf[k] == pytest.approx(mp[k], rel=tol, abs=tol), k
    assert fast.trainer.health.counters() == plain.trainer.health.counters()  # type: ignore[union-attr]


@pytest.mark.parametrize(
    ("dual_method", "schedule"),
    [("paper", "constant"), ("augmented", "cosine"), ("nupi", "step"), ("resilient", "cosine"),
     ("paper", "step")],
)
def test_fast_online_updates_equal_the_plain_steps_on_the_same_minibatches(dual_method: str, schedule: str) -> None:
    """Float64, chunks that cross history rows (every 20 updates) and schedule steps at odd places."""
    kw: dict[str, Any] = {"dual_method": dual_method, "primal_schedule": schedule, "dual_schedule": schedule,
                          "schedule_steps": 150}
    fast, plain = _learner("friction", "fast", **kw), _learner("friction", "plain", **kw)
    _run_both(fast, plain, [7, 30, 1, 63, 44])
    _assert_same(fast, plain, 1e-8)


def test_fast_online_updates_equal_plain_on_a_deeper_net_with_sgd_and_a_region_constraint() -> None:
    """The quadrotor's spec (a conditional region), a 16-8 net and SGD for both steps."""
    kw: dict[str, Any] = {"primal_optimizer": "sgd", "dual_optimizer": "sgd", "primal_lr": 1e-2, "dual_lr": 1e-2,
                          "dual_method": "paper"}
    fast, plain = _learner("quadrotor", "fast", **kw), _learner("quadrotor", "plain", **kw)
    _run_both(fast, plain, [25, 40])
    _assert_same(fast, plain, 1e-8)


def test_fast_online_updates_in_float32_stay_close_to_plain() -> None:
    """What the learner node runs by default (float32, the recommended recipe)."""
    fast, plain = _learner("friction", "fast", dtype="float32"), _learner("friction", "plain", dtype="float32")
    _run_both(fast, plain, [50, 50])
    for a, b in zip(_state(fast), _state(plain)):
        assert torch.allclose(a.double(), b.double(), rtol=1e-3, atol=1e-4)


def test_fast_online_updates_skip_exactly_the_minibatches_the_plain_step_skips() -> None:
    """Absurd but finite rows in the buffer: the loss check runs per update, as in the plain step, so the same
    minibatches are skipped and the rest train the model the same way."""
    fast, plain = _learner("friction", "fast"), _learner("friction", "plain")
    system = get_system("friction")
    bx, bu, by = system.make_dataset(4, np.random.default_rng(4))
    by[:, 1] = [1e200, -1e200, 1e180, 3e38]
    for learner in (fast, plain):
        learner.update(30)  # past the health warm-up
        learner.add_batch(bx, bu, by)
    _run_both(fast, plain, [100, 100])
    skipped = fast.trainer.health.counters()["train_health/skipped/loss"]  # type: ignore[union-attr]
    assert skipped > 5
    if KERNEL:  # the kernel's blocks with a bad minibatch were put back and replayed with per-update gates
        assert getattr(fast._updates.stream, "blocks_replayed", 0) > 0  # type: ignore[union-attr]
    _assert_same(fast, plain, 1e-8)


def test_fast_online_updates_put_back_a_block_whose_weights_explode() -> None:
    """The weights are checked per block of check_every updates: a block that leaves a weight above max_weight is
    undone (parameters, moments, multipliers) and counted skipped; nothing above the limit reaches the trainer."""
    health = HealthConfig(max_weight=1.2, check_every=5)
    learner = _learner("friction", "fast", health=health, primal_lr=0.3, dual_method="paper")
    learner.update(1)
    before = [t.clone() for t in _state(learner)]
    learner.update(40)
    h = learner.trainer.health  # type: ignore[union-attr]
    assert h.skipped["weights"] > 0 and h.restores > 0
    assert h.healthy_steps + sum(h.skipped.values()) == learner.updates
    assert max(float(p.detach().abs().max()) for p in learner.model.net.parameters()) <= 1.2
    if h.healthy_steps == 0:  # every block undone: the trainer is as before
        for a, b in zip(_state(learner)[: len(before)], before):
            assert torch.equal(a, b)


def test_an_unsupported_configuration_falls_back_to_the_plain_step() -> None:
    learner = _learner("friction", "fast")
    assert learner.trainer is None
    learner.update(1)
    assert learner._updates is not None and learner._updates.engine == "fast"
    tr = learner.trainer
    assert tr is not None
    tr.primal_opt.param_groups[0]["weight_decay"] = 1e-4  # e.g. a trainer built elsewhere
    learner._updates = None
    learner.update(3)
    assert learner._updates is not None and learner._updates.engine == "plain"
    assert "weight decay" in (learner._updates.plain_reason or "") and learner.updates == 4


def _run_pair(kernel: OnlineLearner, torch_path: OnlineLearner, chunks: list[int]) -> None:
    for n in chunks:
        assert kernel.update(n) == n and torch_path.update(n) == n
    ks, ts = kernel._updates.stream, torch_path._updates.stream  # type: ignore[union-attr]
    assert ks is not None and ts is not None
    assert ks.kernel_used and isinstance(ks, fused.FusedStreamRun)
    assert not ts.kernel_used and "fast_torch" in (ts.kernel_reason or "")


@needs_kernel
@pytest.mark.parametrize(
    ("dual_method", "schedule"),
    [("paper", "constant"), ("augmented", "cosine"), ("nupi", "step"), ("resilient", "cosine")],
)
def test_kernel_stream_equals_the_torch_path_stream_on_the_same_minibatches(dual_method: str, schedule: str) -> None:
    """Float64 (test_fast_train.py's bounds): the kernel-backed stream and the torch-path stream of the same
    trainer, chunks crossing history rows and health blocks at odd places."""
    kw: dict[str, Any] = {"dual_method": dual_method, "primal_schedule": schedule, "dual_schedule": schedule,
                          "schedule_steps": 150}
    kern, tp = _learner("friction", "fast", **kw), _learner("friction", "fast_torch", **kw)
    _run_pair(kern, tp, [7, 30, 1, 63, 44, 50])
    _assert_same(kern, tp, 1e-8)


@needs_kernel
def test_kernel_stream_equals_the_torch_path_stream_on_a_region_constraint_with_sgd() -> None:
    kw: dict[str, Any] = {"primal_optimizer": "sgd", "dual_optimizer": "sgd", "primal_lr": 1e-2, "dual_lr": 1e-2}
    kern, tp = _learner("quadrotor", "fast", hidden=(16, 8), **kw), _learner("quadrotor", "fast_torch",
                                                                              hidden=(16, 8), **kw)
    _run_pair(kern, tp, [25, 40, 13])
    _assert_same(kern, tp, 1e-8)


@needs_kernel
def test_kernel_stream_in_float32_stays_close_to_the_torch_path() -> None:
    kern, tp = _learner("friction", "fast", dtype="float32"), _learner("friction", "fast_torch", dtype="float32")
    _run_pair(kern, tp, [50, 50, 50])
    for a, b in zip(_state(kern), _state(tp)):
        assert torch.allclose(a.double(), b.double(), rtol=1e-4, atol=1e-5)


@needs_kernel
def test_kernel_stream_skips_and_puts_back_like_the_torch_path() -> None:
    """Bad minibatches and exploding weights: the kernel's failing blocks are replayed with the per-update gates,
    so the same updates are skipped and counted, and the rest learn the same."""
    health = HealthConfig(max_weight=1.5, check_every=5)
    kern, tp = (_learner("friction", e, health=health, primal_lr=0.2) for e in ("fast", "fast_torch"))
    system = get_system("friction")
    bx, bu, by = system.make_dataset(4, np.random.default_rng(4))
    by[:, 1] = [1e200, -1e200, 1e180, 3e38]
    for learner in (kern, tp):
        learner.update(30)
        learner.add_batch(bx, bu, by)
    _run_pair(kern, tp, [60, 60])
    assert kern._updates.stream.blocks_replayed > 0  # type: ignore[union-attr]
    h = kern.trainer.health  # type: ignore[union-attr]
    assert h.healthy_steps + sum(h.skipped.values()) == kern.updates
    _assert_same(kern, tp, 1e-8)
