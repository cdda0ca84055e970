"""The generic planner against the hand-written quadrotor SQP (issue 28's parity), and its whole-horizon CasADi
functions: the quadrotor landing task planned through the generic path gives the hand-written SQP's plans (same
iterations, same controls to rounding), the compiled functions give the virtual machine's numbers, a missing
compiler is said and changes nothing, and a hot swap writes numbers into the kept rollout."""

from __future__ import annotations

import shutil
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

from saml_ros.core.model.network import DynamicsModel
from saml_ros.core.mpc.factory import make_controller
from saml_ros.core.mpc.generic import GenericSQP, codegen
from saml_ros.core.mpc.generic.dynamics import GenericDynamics, SymbolicBase, make_base
from saml_ros.core.mpc.generic.horizon import HorizonRollout
from saml_ros.core.mpc.generic.sqp import _condense
from saml_ros.systems.quadrotor.generic_form import quadrotor_base, quadrotor_generic_task
from saml_ros.systems.quadrotor.model import Quadrotor
from saml_ros.user_code import load_system_file

REPO = Path(__file__).resolve().parents[4]
EXAMPLE = REPO / "examples" / "diff_drive" / "system.yaml"
pytestmark = pytest.mark.usefixtures("restore_registry")  # the robots these tests load are registered by name


def _starts(system: Quadrotor) -> list[np.ndarray]:
    moving = system.hover_state((0.4, -0.3, 1.5))
    moving[3:6] = (0.5, -0.4, -0.6)  # flying sideways and down
    moving[6:10] = (0.995, 0.06, -0.05, 0.05)  # tilted (normalised by the step)
    moving[6:10] /= np.linalg.norm(moving[6:10])
    moving[10:13] = (0.3, -0.2, 0.1)
    return [system.hover_state((1.0, -1.0, 2.0)), system.hover_state((-2.0, 0.5, 3.0)), moving]


def test_generic_quadrotor_plans_equal_the_hand_written_ones() -> None:
    """Three starts, each three steps of a closed loop on f_hat (so solves 2 and 3 warm-start from the previous
    plan): the same SQP iterations, and plans equal to 1e-6 N (the two planners take the same steps with the same
    options; what is left is floating-point summation order, <= 2e-10 N on the bench's 30 problems)."""
    system = Quadrotor()
    hand = make_controller(system, None, "fast", horizon=10, tilt_max=0.2)
    gen = GenericSQP(system, None, task=quadrotor_generic_task(system), f_hat=quadrotor_base(system), compile=False)
    goal = np.zeros(3)
    for x0 in _starts(system):
        hand.reset()
        gen.reset()
        x = x0
        for _ in range(3):
            a, b = hand.solve(x, goal), gen.solve(x, goal)
            assert a.success and b.success
            assert a.iterations == b.iterations
            np.testing.assert_allclose(b.plan_u, a.plan_u, rtol=0, atol=1e-6)
            np.testing.assert_allclose(b.plan_x, a.plan_x, rtol=0, atol=1e-8)
            exact = gen.problem.cost(b.plan_x, b.plan_u, gen.problem.reference(x, goal), None, exact=True)
            assert exact == pytest.approx(a.cost, rel=1e-9)  # the sum of distances (the hand-written's cost)
            x = system.base_step_np(x[None], a.u[None])[0]


def fitted_model(system: object, seed: int) -> DynamicsModel:
    """A 32-32 residual network with a fitted normalisation and a random last layer (as test_generic_mpc's)."""
    m = DynamicsModel(system, (32, 32), "residual", seed=seed).double()  # type: ignore[arg-type]
    rng = np.random.default_rng(seed)
    x, u = system.sample_inputs(500, rng)  # type: ignore[attr-defined]
    m.fit_normalization(x, u, system.base_step_np(x, u) + 0.01 * rng.normal(size=x.shape))  # type: ignore[attr-defined]
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        m.net.weights[-1].copy_(torch.randn(m.net.weights[-1].shape, generator=gen, dtype=torch.float64) * 0.3)
    return m


def _diff_drive_horizon(compile: bool, T: int = 3) -> tuple[HorizonRollout, GenericDynamics]:
    system = load_system_file(EXAMPLE)
    base = make_base(system)
    assert isinstance(base, SymbolicBase)
    dyn = GenericDynamics(system, base, compile=compile)
    dyn.prepare(T)
    roll = base.horizon(T, (2,), None, compile=compile)
    return roll, dyn


@pytest.mark.skipif(shutil.which("cc") is None, reason="no C compiler")
def test_compiled_horizon_equals_the_virtual_machine(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The diff-drive's f_hat (its yaw wrapped) at T = 3: the compiled rollouts and sensitivities equal CasADi's
    virtual machine and the condensed step Jacobians; the second planner loads the build, compiling nothing."""
    monkeypatch.setenv("SAML_KERNEL_CACHE", str(tmp_path))
    monkeypatch.delenv("SAML_MPC_NATIVE", raising=False)
    built = len(codegen.COMPILE_SECONDS)
    roll_c, dyn_c = _diff_drive_horizon(True)
    assert roll_c.compiled is None
    assert "compiled to C" in dyn_c.describe()
    assert len(codegen.COMPILE_SECONDS) == built + 1 and list(tmp_path.glob("casadi_generic_T3_*.so"))
    roll_v, dyn_v = _diff_drive_horizon(False)
    assert roll_v.compiled is not None and "virtual machine" in dyn_v.describe()
    rng = np.random.default_rng(0)
    x0 = np.array([0.3, -0.2, 3.12, 0.4, 1.8])  # turning left: the yaw passes pi within the horizon
    us = rng.uniform(-1.0, 1.0, size=(3, 2))
    us[:, 1] = 1.8
    xs = dyn_c.rollout(x0, us)
    np.testing.assert_allclose(xs, dyn_v.rollout(x0, us), rtol=0, atol=1e-12)
    assert xs[-1, 2] > np.pi  # the prediction keeps the turns
    batch = us[None] * np.linspace(0.2, 1.0, 6)[:, None, None]  # more than one call's 4 sequences
    np.testing.assert_allclose(dyn_c.rollout_batch(x0, batch), dyn_v.rollout_batch(x0, batch), rtol=0, atol=1e-12)
    np.testing.assert_allclose(dyn_c.rollout_batch(x0, batch)[2], dyn_v.rollout(x0, batch[2]), rtol=0, atol=1e-12)
    sens = dyn_c.sensitivities(xs[:-1], us)
    assert sens is not None and dyn_v.sensitivities(xs[:-1], us) is None  # the VM path condenses in numpy
    _, a, b = dyn_v.step_jac(xs[:-1], us)
    np.testing.assert_allclose(sens, _condense(a, b), rtol=0, atol=1e-12)
    again = GenericDynamics(load_system_file(EXAMPLE), make_base(load_system_file(EXAMPLE)), compile=True)
    again.prepare(3)
    assert len(codegen.COMPILE_SECONDS) == built + 1  # loaded from the cache


@pytest.mark.skipif(shutil.which("cc") is None, reason="no C compiler")
def test_compiled_network_horizon_equals_numpy(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """With a residual network (and its bound): the compiled rollouts and sensitivities (CasADi matrix expressions)
    equal stepping the numpy network and condensing its exact Jacobians; a hot swap and a new bound are numbers."""
    monkeypatch.setenv("SAML_KERNEL_CACHE", str(tmp_path))
    monkeypatch.delenv("SAML_MPC_NATIVE", raising=False)
    system = load_system_file(EXAMPLE)
    # exact Jacobians (the example file rounds the network's kinks, smoothing 0.2: then numpy takes them)
    ctrl = GenericSQP(system, fitted_model(system, seed=1), horizon=3, compile=True, smoothing=0.0)
    plain = GenericSQP(system, fitted_model(system, seed=1), horizon=3, smoothing=0.0)
    assert GenericSQP(system, fitted_model(system, seed=1), horizon=3, compile=True).dyn.sensitivities(
        np.zeros((3, 5)), np.zeros((3, 2))) is None
    assert "compiled to C" in ctrl.describe() and "virtual machine" in plain.describe()
    rng = np.random.default_rng(2)
    x0 = np.array([0.3, -0.2, 3.12, 0.4, 1.8])
    us = rng.uniform(-1.0, 1.0, size=(3, 2))
    built = len(codegen.COMPILE_SECONDS)
    for seed, bound in ((1, None), (2, None), (3, np.full(5, 0.004))):
        for c in (ctrl, plain):
            c.set_model(fitted_model(system, seed=seed))
            c.set_residual_bound(bound)
        xs = ctrl.dyn.rollout(x0, us)
        np.testing.assert_allclose(xs, plain.dyn.rollout(x0, us), rtol=0, atol=1e-12)
        batch = us[None] * np.linspace(0.2, 1.0, 5)[:, None, None]
        np.testing.assert_allclose(ctrl.dyn.rollout_batch(x0, batch), plain.dyn.rollout_batch(x0, batch), rtol=0,
                                   atol=1e-12)
        sens = ctrl.dyn.sensitivities(xs[:-1], us)
        _, a, b = plain.dyn.step_jac(xs[:-1], us)
        assert sens is not None and plain.dyn.sensitivities(xs[:-1], us) is None
        np.testing.assert_allclose(sens, _condense(a, b), rtol=0, atol=1e-10)
        np.testing.assert_allclose(ctrl.solve(x0).plan_u, plain.solve(x0).plan_u, rtol=0, atol=1e-8)
    assert len(codegen.COMPILE_SECONDS) == built  # nothing compiled after the first planner's construction


def test_without_a_compiler_the_planner_says_so_and_plans_the_same(tmp_path: Path,
                                                                    monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("SAML_KERNEL_CACHE", str(tmp_path))
    monkeypatch.setenv("CC", str(tmp_path / "no-such-cc"))
    monkeypatch.delenv("SAML_MPC_NATIVE", raising=False)
    monkeypatch.setattr(codegen, "_WARNED", set())
    system = load_system_file(EXAMPLE)
    with pytest.warns(RuntimeWarning, match="not compiled .*no C compiler"):
        ctrl = GenericSQP(system, horizon=3, compile=True)
    assert "virtual machine (not compiled: RuntimeError: no C compiler" in ctrl.describe()
    assert not list(tmp_path.glob("*.so"))
    plain = GenericSQP(system, horizon=3)
    x = np.array([0.2, 0.3, 0.4, 0.1, 0.0])
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # one warning per process, not one per planner
        GenericSQP(system, horizon=3, compile=True)
    np.testing.assert_allclose(ctrl.solve(x).plan_u, plain.solve(x).plan_u, rtol=0, atol=1e-12)


def test_hot_swap_writes_numbers_into_the_kept_rollout() -> None:
    """A new network's weights go into the whole-horizon rollout built for the first: the same CasADi object
    predicts what stepping the new network in numpy predicts (the residual bound too)."""
    system = load_system_file(EXAMPLE)
    ctrl = GenericSQP(system, fitted_model(system, seed=1))
    rolls = dict(ctrl._base._horizons)  # type: ignore[union-attr]
    assert len(rolls) == 1
    x0 = np.array([0.2, 0.3, 3.0, 0.3, 1.0])
    us = np.random.default_rng(1).uniform(-1.0, 1.0, size=(ctrl.horizon, 2))
    for seed, bound in ((2, None), (3, np.full(5, 0.004))):
        ctrl.set_model(fitted_model(system, seed=seed))
        ctrl.set_residual_bound(bound)
        assert ctrl._base._horizons == rolls  # type: ignore[union-attr]
        want = np.empty((ctrl.horizon + 1, 5))
        want[0] = x0
        for t in range(ctrl.horizon):
            want[t + 1] = ctrl.dyn.step(want[t][None], us[t][None])[0]
        np.testing.assert_allclose(ctrl.dyn.rollout(x0, us), want, rtol=0, atol=1e-12)
