"""The fused C++ training kernel (saml_ros/core/training/engines/fused.py) computes the fast engine's steps.

Every comparison runs the kernel, the fast engine's torch path (``engine="fast_torch"``) and the plain engine from the
same initial weights, data and seed, so all see the same minibatches; the tolerances are test_fast_train.py's
(float64: 1e-7 relative / 1e-8 absolute after a few hundred Adam steps; float32 after 300 steps: 1e-4 / 1e-5; a real
difference in the algorithm shows at 1e-3 or more). The module is skipped where the kernel cannot be built.
"""

from __future__ import annotations

import warnings
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from helpers.training import FRICTION, METHODS, SPECS, assert_same_run, friction_data

from saml_ros.core.model.network import DynamicsModel
from saml_ros.core.spec import ProblemSpec
from saml_ros.core.training import PrimalDualTrainer, TrainConfig, Transitions
from saml_ros.core.training.engines import fused

if fused.load_kernel() is None:
    pytest.skip(f"the fused training kernel is not available here: {fused.kernel_reason()}", allow_module_level=True)

RTOL, ATOL = 1e-7, 1e-8  # float64


def _trainers(spec_dict: dict[str, Any], cfg: TrainConfig, engines: tuple[str, ...] = ("plain", "fast_torch", "fast"),
              n: int = 240, hidden: tuple[int, ...] = (4, 2), e: int = 1, per_member: bool = False,
              kind: str = "residual") -> list[tuple[PrimalDualTrainer, Transitions]]:
    """Identical trainers, one per engine, and their datasets."""
    spec = ProblemSpec.for_system(spec_dict, FRICTION)
    x, u, y = friction_data(n, list(range(e)) if per_member else None)
    out = []
    for engine in engines:
        model = DynamicsModel(FRICTION, hidden, kind, n_models=e, seed=7)
        model.fit_normalization(x, u, y)
        tr = PrimalDualTrainer(model, spec, replace(cfg, engine=engine))
        out.append((tr, Transitions(model, spec, x, u, y)))
    return out


def _fit_all(runs: list[tuple[PrimalDualTrainer, Transitions]]) -> list[PrimalDualTrainer]:
    for tr, data in runs:
        tr.fit(data)
    return [tr for tr, _ in runs]


def _check_all(runs: list[tuple[PrimalDualTrainer, Transitions]], rtol: float = RTOL, atol: float = ATOL) -> None:
    """Fit the three trainers of :func:`_trainers` and :func:`_check` them."""
    plain, torch_path, kernel = _fit_all(runs)
    _check(plain, torch_path, kernel, rtol, atol)


def _check(plain: PrimalDualTrainer, torch_path: PrimalDualTrainer, kernel: PrimalDualTrainer, rtol: float,
           atol: float) -> None:
    """The kernel ran, and agrees with the torch path and with the plain engine."""
    assert kernel.kernel_used and not torch_path.kernel_used and not plain.kernel_used
    assert torch_path.engine_used == kernel.engine_used == "fast"
    assert_same_run(plain, kernel, rtol=rtol, atol=atol)
    torch_path.engine_used = "plain"  # assert_same_run checks the engine names of its pair
    assert_same_run(torch_path, kernel, rtol=rtol, atol=atol)


def _paper64(**kw: Any) -> TrainConfig:
    base: dict[str, Any] = {"epochs": 6, "batch_size": 8, "primal_lr": 3e-3, "dual_lr": 5e-2, "dtype": "float64",
                            "seed": 5, "log_every": 7}
    return TrainConfig.paper(**{**base, **kw})


# every loss and mean, the float32 paper setting, every dual method and the learning-rate schedules: test_fast_train.py
# runs the kernel ("fast"), the torch path and the plain engine in those settings and makes this file's checks there
# (_check_torch_path), one plain run for both comparisons


@pytest.mark.parametrize("hidden", [(), (5,), (4, 2), (8, 4, 2), (24, 3), (40, 17)])
@pytest.mark.parametrize("e", [1, 3])
def test_kernel_for_every_depth_width_and_ensemble_size(hidden: tuple[int, ...], e: int) -> None:
    """No hidden layer, one to three hidden layers, widths below, at and above one register block (16 floats),
    shared data and an ensemble. 60 steps: a layer's arithmetic done differently shows in the first ones."""
    runs = _trainers(SPECS["mixed"], _paper64(epochs=2), hidden=hidden, e=e)
    _check_all(runs)


@pytest.mark.parametrize("variant", ["per_member", "full_model", "sgd", "adam_primal_sgd_dual", "dual_adam_own_betas",
                                     "batch_not_multiple_of_4"])
def test_kernel_for_models_and_optimizers(variant: str) -> None:
    kw: dict[str, Any] = {}
    cfg = _paper64(batch_size=16)
    if variant == "per_member":
        kw = {"e": 4, "per_member": True}
    elif variant == "full_model":
        kw = {"kind": "full", "hidden": (8, 4)}
    elif variant == "sgd":
        cfg = replace(cfg, primal_optimizer="sgd", dual_optimizer="sgd", primal_lr=0.05)
    elif variant == "adam_primal_sgd_dual":
        cfg = replace(cfg, dual_optimizer="sgd", dual_lr=1.0)
    elif variant == "batch_not_multiple_of_4":
        cfg = replace(cfg, batch_size=11)
    runs = _trainers(SPECS["paper"], cfg, **kw)
    if variant == "dual_adam_own_betas":
        for tr, _ in runs:
            tr.dual.optimizer.param_groups[0]["betas"] = (0.8, 0.99)
    _check_all(runs)


@pytest.mark.parametrize("method", ["augmented", "resilient", "nupi"])
def test_kernel_float32_ensemble_with_every_loss(method: str) -> None:
    """float32, an ensemble of 3 on per-member data, the mixed spec (l1, l2, squared_l2 groups) and a 16-8 net."""
    cfg = TrainConfig(epochs=6, batch_size=32, seed=3, **{k: v for k, v in METHODS[method].items()})
    runs = _trainers(SPECS["mixed"], cfg, n=1000, hidden=(16, 8), e=3, per_member=True)
    _check_all(runs, rtol=1e-4, atol=1e-5)


def test_kernel_with_callbacks_logging_and_resume() -> None:
    """A callback after each epoch sees the current model; fits resume (the kernel, then the torch path, then the
    kernel again) exactly as the plain engine does; online steps in between are logged at the next point."""
    cfg = _paper64(epochs=2, batch_size=16, log_every=5)
    (plain, dp), (_, _), (kern, dk) = _trainers(SPECS["paper"], cfg)
    seen: dict[str, list[float]] = {"plain": [], "fast": []}

    def probe(tr: PrimalDualTrainer) -> None:
        seen[tr.config.engine].append(float(tr.evaluate(dk)["lagrangian"][0]))

    plain.fit(dp, callback=probe)
    kern.fit(dk, callback=probe)
    assert kern.kernel_used and len(seen["fast"]) == 2
    np.testing.assert_allclose(seen["fast"], seen["plain"], rtol=1e-9)
    x, u, y = (torch.as_tensor(a[:16]) for a in friction_data(16, None))
    for tr in (plain, kern):
        tr.step(x, u, y)
    kern.config = replace(cfg, engine="fast_torch")
    plain.fit(dp)
    kern.fit(dk)
    assert not kern.kernel_used
    kern.config = replace(cfg, engine="fast")
    plain.fit(dp)
    kern.fit(dk)
    assert kern.kernel_used
    assert_same_run(plain, kern, rtol=RTOL, atol=ATOL)


@pytest.mark.parametrize("method", ["paper", "augmented"])
def test_kernel_trains_at_a_bound_changed_between_fits(method: str) -> None:
    """``train``'s aim (``offline.pipelines.train_models(margin="auto")``) fits part of the run at eps, then swaps
    the trainer's spec for one with lower bounds and fits the rest: the kernel's cached set-up is rebuilt for the
    new bounds (the engines agree), and training at the lower bound differs from training at eps."""
    from saml_ros.core.training.verdict import aimed_spec

    cfg = _paper64(epochs=6, **({} if method == "paper" else METHODS[method]))
    runs = _trainers(SPECS["paper"], cfg, engines=("plain", "fast_torch", "fast", "fast"))
    for i, (tr, data) in enumerate(runs):
        tr.fit(data, epochs=3, diagnose=False)
        if i < 3:  # the last one stays at eps: the reference that the aim changed something
            tr.spec = aimed_spec(tr.spec, [0.5 * tr.spec.constraints[0].eps])
        tr.fit(data, epochs=3)
    plain, torch_path, kernel, at_eps = (tr for tr, _ in runs)
    _check(plain, torch_path, kernel, rtol=RTOL, atol=ATOL)
    assert kernel.diagnosis is not None and kernel.diagnosis.constraints[0].eps == 0.5 * 0.035
    assert not torch.allclose(kernel.lam, at_eps.lam, rtol=1e-3)


def test_kernel_health_check_skips_a_bad_block_like_the_torch_path() -> None:
    """A non-finite target in the data: the kernel's block check puts the state back and counts the block's steps
    skipped, exactly as the torch path does (same counters, finite weights, same result)."""
    cfg = _paper64(epochs=3, batch_size=16)
    runs = _trainers(SPECS["paper"], cfg, engines=("fast_torch", "fast"))
    for _, data in runs:
        data.base[5] = float("inf")  # f_hat of one sample: every minibatch with it is unhealthy
    torch_path, kernel = _fit_all(runs)
    assert kernel.kernel_used
    assert torch_path.health.skipped == kernel.health.skipped and sum(kernel.health.skipped.values()) > 0
    assert torch_path.health.restores == kernel.health.restores
    assert torch_path.health.healthy_steps == kernel.health.healthy_steps
    for a, b in zip(torch_path.model.parameters(), kernel.model.parameters()):
        assert torch.isfinite(b).all()
        torch.testing.assert_close(b, a, rtol=RTOL, atol=ATOL)


def test_switch_off_and_fast_torch_run_the_torch_path(monkeypatch: pytest.MonkeyPatch) -> None:
    """``SAML_FUSED_KERNEL=0`` and ``engine="fast_torch"`` both run the torch path, bit for bit."""
    cfg = _paper64(epochs=2)
    (ref, dr), (off, do) = _trainers(SPECS["mixed"], cfg, engines=("fast_torch", "fast"))
    ref.fit(dr)
    monkeypatch.setenv(fused.SWITCH_ENV, "0")
    assert fused.switched_off() and fused.load_kernel() is None
    assert "switched off" in str(fused.kernel_reason())
    off.fit(do)
    assert not ref.kernel_used and not off.kernel_used and off.engine_used == "fast"
    for a, b in zip(ref.model.parameters(), off.model.parameters()):
        assert torch.equal(a, b)
    monkeypatch.setenv(fused.SWITCH_ENV, "1")
    assert not fused.switched_off() and fused.load_kernel() is not None


def test_a_failing_build_falls_back_to_the_torch_path_with_one_warning(tmp_path: Path,
                                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    broken = tmp_path / "fused_step.cpp"
    broken.write_text('#include "no_such_header_saml.h"\n' + fused.KERNEL_SOURCE.read_text())
    monkeypatch.setenv("SAML_KERNEL_CACHE", str(tmp_path / "cache"))
    monkeypatch.setattr(fused, "KERNEL_SOURCE", broken)
    monkeypatch.setattr(fused, "_STATE", fused._KernelState())
    cfg = _paper64(epochs=2)
    (ref, dr), (tr, dt) = _trainers(SPECS["paper"], cfg, engines=("fast_torch", "fast"))
    ref.fit(dr)
    with pytest.warns(RuntimeWarning, match="fused training kernel not available"):
        tr.fit(dt)
    assert not tr.kernel_used and tr.engine_used == "fast"
    assert fused.load_kernel() is None
    assert "build failed" in str(fused.kernel_reason()) and fused.build_error()
    for a, b in zip(ref.model.parameters(), tr.model.parameters()):
        assert torch.equal(a, b)
    with warnings.catch_warnings():  # one warning per process: a second fit is quiet
        warnings.simplefilter("error")
        tr.fit(dt)


def test_a_stale_torch_build_lock_neither_hangs_a_load_nor_a_build(tmp_path: Path) -> None:
    """A process killed during the first build (Ctrl-C) leaves torch's ``lock`` file in the build directory;
    torch.utils.cpp_extension would wait for it forever. A finished build is imported without touching it, and a
    build (here: of a broken copy, which fails fast) removes it under the kernel's own flock and goes on."""
    kernel = fused.load_kernel()
    if kernel is None:
        pytest.skip(f"no kernel here: {fused.kernel_reason()}")
    name = fused.build_name()
    built = fused.cache_root() / name
    copy = tmp_path / name
    copy.mkdir()
    (copy / f"{name}.so").write_bytes((built / f"{name}.so").read_bytes())
    (copy / "lock").touch()
    assert hasattr(fused._load_built(name, copy), "FusedKernel")
    broken = tmp_path / "fused_step.cpp"
    broken.write_text('#include "no_such_header_saml.h"\n' + fused.KERNEL_SOURCE.read_text())
    stale = tmp_path / "stale"
    stale.mkdir()
    (stale / "lock").touch()
    with pytest.raises(Exception, match="no_such_header_saml|Error building"):
        fused._build("saml_fused_step_broken", broken, stale, verbose=False)
    assert not (stale / "lock").exists()


def test_build_name_depends_on_source_torch_and_cpu(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A cached build is only ever loaded by the same source, torch version, flags and CPU."""
    name = fused.build_name()
    assert name.startswith("saml_fused_step_")
    other = tmp_path / "fused_step.cpp"
    other.write_text(fused.KERNEL_SOURCE.read_text() + "\n// changed\n")
    assert fused.build_name(other) != name
    cpu_id = fused.cpu_id
    monkeypatch.setattr(fused, "cpu_id", lambda: "model name: another cpu\nflags: sse2")
    assert fused.build_name() != name
    monkeypatch.setattr(fused, "cpu_id", cpu_id)
    monkeypatch.setattr(torch, "__version__", "0.0.0")
    assert fused.build_name() != name
    monkeypatch.delenv("SAML_KERNEL_CACHE", raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    assert fused.cache_root() == tmp_path / "saml_ros" / "fused_kernel"


@pytest.mark.parametrize("dtype", ["float64", "float32"])
def test_the_kernels_end_of_fit_evaluation_is_evaluate_spec(dtype: str) -> None:
    """The diagnosis at the end of a kernel fit uses the kernel's own pass over the data: the same values as
    ``trainer.evaluate`` (every loss and region kind of the mixed spec, an ensemble on per-member data)."""
    cfg = _paper64(epochs=2, dtype=dtype, dual_method="augmented", penalty=0.5)
    ((tr, data),) = _trainers(SPECS["mixed"], cfg, engines=("fast",), e=2, per_member=True, hidden=(8, 4))
    tr.fit(data)
    assert tr.kernel_used and tr.diagnosis is not None
    assert [c.verdict for c in tr.diagnosis.constraints] == [c.verdict for c in tr.diagnose(data).constraints]
    engine = fused.FusedEngine()
    engine.fit(tr, data, 0)  # no epoch: only the evaluation at the current state
    assert engine.kernel_used and engine.evaluation is not None
    ref = tr.evaluate(data)
    tol = 1e-12 if dtype == "float64" else 1e-6
    for key in ("objective", "constraints", "lagrangian", "lambdas"):
        np.testing.assert_allclose(engine.evaluation[key], ref[key], rtol=tol, atol=tol, err_msg=key)


def test_a_trainers_kernel_run_is_kept_between_fits_until_what_it_was_built_from_changes() -> None:
    """Repeated fits of one trainer on one dataset reuse its FusedRun (no set-up per fit) and give the torch path's
    results; an in-place edit of the data, another batch size or another dataset object build a new one."""
    cfg = _paper64(epochs=1)
    (ref, dr), (tr, dt) = _trainers(SPECS["mixed"], cfg, engines=("fast_torch", "fast"))
    runs = []
    for _ in range(3):
        ref.fit(dr)
        tr.fit(dt)
        runs.append(fused._RUNS[tr][1])
    assert runs[0] is runs[1] is runs[2]
    _same(ref, tr)
    for change in ("edit", "config", "data"):
        if change == "edit":
            for d in (dr, dt):
                d.y[3] += 0.5
        elif change == "config":
            ref.config = replace(ref.config, batch_size=12)
            tr.config = replace(tr.config, batch_size=12)
        else:
            dr = Transitions(ref.model, ref.spec, dr.x.numpy(), dr.u.numpy(), dr.y.numpy())
            dt = Transitions(tr.model, tr.spec, dt.x.numpy(), dt.u.numpy(), dt.y.numpy())
        ref.fit(dr)
        tr.fit(dt)
        assert fused._RUNS[tr][1] is not runs[-1], change
        runs.append(fused._RUNS[tr][1])
        _same(ref, tr)


def _same(torch_path: PrimalDualTrainer, kernel: PrimalDualTrainer) -> None:
    assert kernel.kernel_used and not torch_path.kernel_used
    torch_path.engine_used = "plain"  # assert_same_run checks the engine names of its pair
    assert_same_run(torch_path, kernel, rtol=RTOL, atol=ATOL)


def test_a_kernel_set_up_failure_runs_the_torch_path(monkeypatch: pytest.MonkeyPatch) -> None:
    """A configuration the kernel object refuses (here: a failing constructor) runs the torch path, same result."""
    cfg = _paper64(epochs=2)
    (ref, dr), (tr, dt) = _trainers(SPECS["paper"], cfg, engines=("fast_torch", "fast"))

    def refuse(self: fused.FusedRun, bsz: int) -> Any:
        raise RuntimeError("fused kernel: refused")

    monkeypatch.setattr(fused.FusedRun, "_kernel", refuse)
    ref.fit(dr)
    tr.fit(dt)
    assert not tr.kernel_used
    for a, b in zip(ref.model.parameters(), tr.model.parameters()):
        assert torch.equal(a, b)
