"""The fast SQP's C kernel (saml_ros/core/mpc/shooting/native.py): the model it evaluates is the numpy twin's,
the plans it produces are the numpy path's, and it steps aside (with the reason) where it does not apply."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from saml_ros.core.model.network import DynamicsModel
from saml_ros.core.mpc import base_model_np, make_controller
from saml_ros.core.mpc.dynamics_np import NumpyDynamics
from saml_ros.core.mpc.guard import BoundedDynamics
from saml_ros.core.mpc.shooting import native
from saml_ros.core.mpc.shooting.sqp import SQPShootingMPC
from saml_ros.core.systems import get_system
from saml_ros.systems.friction.model import FrictionDoubleIntegrator
from saml_ros.systems.friction.task import friction_task
from saml_ros.systems.quadrotor.model import Quadrotor
from saml_ros.systems.quadrotor.task import quadrotor_task

_QUAD = get_system("quadrotor")
assert isinstance(_QUAD, Quadrotor)
QUAD: Quadrotor = _QUAD


def _model(kind: str, seed: int = 0, hidden: tuple[int, ...] = (16, 8)) -> DynamicsModel:
    """A quadrotor model with a clearly non-zero phi and a negative PReLU slope (the kink's other side matters)."""
    model = DynamicsModel(QUAD, kind=kind, hidden=hidden, seed=seed).double()
    x, u, y = QUAD.make_dataset(256, np.random.default_rng(seed))
    model.fit_normalization(x, u, y)
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for w in model.net.weights:
            w.add_(0.3 * torch.randn(w.shape, generator=gen, dtype=w.dtype))
        for s in model.net.slopes:
            s.fill_(-0.2)
    return model


def _dynamics(kind: str) -> NumpyDynamics | BoundedDynamics:
    model = None if kind == "base" else _model("full" if kind == "full" else "residual")
    dyn = NumpyDynamics(QUAD, model, base=base_model_np(QUAD))
    if kind == "bounded":
        assert dyn.mlp is not None
        phi = dyn.mlp.forward(*QUAD.sample_inputs(64, np.random.default_rng(3))[:2])
        # a bound that clips some fields of some samples and not others
        return BoundedDynamics(dyn, np.median(np.abs(phi), axis=0))
    return dyn


@pytest.mark.parametrize("kind", ["base", "residual", "full", "bounded"])
def test_kernel_model_is_the_numpy_twin(kind: str) -> None:
    """Prediction and Jacobians equal the numpy model's up to summation order; f_hat's rollouts bit for bit."""
    dyn = _dynamics(kind)
    task = quadrotor_task(QUAD)
    assert native.unsupported_reason(dyn, task) is None
    lib = native.load_library()
    assert lib is not None
    nat = native.NativeSQP(lib, dyn, task, np.ones(40), 1.0)
    x, u = QUAD.sample_inputs(32, np.random.default_rng(1))
    y, a, b = nat.step_batch(x, u)
    y_ref, a_ref, b_ref = dyn.step_jac(x, u)
    np.testing.assert_allclose(y, y_ref, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(a, a_ref, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(b, b_ref, rtol=1e-10, atol=1e-12)
    if isinstance(dyn, BoundedDynamics):  # the clipped fields' Jacobian rows are f_hat's: some clipped, some not
        assert dyn.mlp is not None
        assert 0 < int((np.abs(dyn.mlp.forward(x, u)) >= dyn.bound).sum()) < y.size
    us = np.random.default_rng(2).uniform(0.0, 4.0, (10, 4))
    xs = nat.rollout(x[0], us)
    want = [x[0]]
    for t in range(10):
        want.append(dyn.step1(want[-1], us[t]))
    if kind == "base":
        np.testing.assert_array_equal(xs, np.stack(want))
    else:
        np.testing.assert_allclose(xs, np.stack(want), rtol=1e-11, atol=1e-12)


@pytest.mark.parametrize(("kind", "tilt", "goal"), [("base", False, None), ("base", True, (0.0, 0.0, 0.2)),
                                                     ("residual", True, (0.0, 0.0, 0.2)), ("bounded", False, None)])
def test_kernel_plans_are_the_numpy_paths(kind: str, tilt: bool, goal: tuple[float, ...] | None) -> None:
    """From the same states and warm starts, the SQP on the C kernel and on numpy plan the same commands (to
    rounding) with the same iteration counts: the quadrotor flown by the numpy path, 3 episodes of 25 steps."""
    opts = {"tilt_max": 0.2} if tilt else {}
    fast = make_controller(QUAD, None, solver="fast", **opts)
    ref = make_controller(QUAD, None, solver="fast", native=False, **opts)
    assert isinstance(fast, SQPShootingMPC) and isinstance(ref, SQPShootingMPC)
    if kind != "base":
        fast.dyn = ref.dyn = _dynamics(kind)  # type: ignore[assignment]
    g = None if goal is None else np.array(goal)
    rng = np.random.default_rng(0)
    diffs, iters, active = [], [], 0
    for _ in range(3):
        x = np.zeros(13)
        x[6] = 1.0
        x[0:3] = rng.uniform([-2.0, -2.0, 1.0], [2.0, 2.0, 4.0])
        x[3:6] = rng.normal(0.0, 0.5, 3)
        ref.reset()
        for _ in range(25):
            prev = ref.warm_start_plan()
            if prev is None:
                fast.reset()
            else:
                fast.set_warm_start(*prev)
            r_ref = ref.solve(x, g)
            r_fast = fast.solve(x, g)
            diffs.append(float(np.abs(r_fast.u - r_ref.u).max()))
            iters.append((r_fast.iterations, r_ref.iterations))
            active += int(r_ref.constraint_violation > 0 or not r_ref.converged)
            x = QUAD.true_step_np(x[None], r_ref.u[None])[0]
    assert fast.native_reason is None
    assert ref.native_reason == "switched off (solver option native: false)"
    assert max(diffs) < 1e-7, max(diffs)
    assert all(a == b for a, b in iters)
    assert sum(a for a, _ in iters) > 75  # the solves iterated (not all certified at once)


def test_kernel_steps_aside_where_it_does_not_apply() -> None:
    """The friction task's exact l1 model and the oracle run the numpy path, with the reason."""
    friction = get_system("friction")
    assert isinstance(friction, FrictionDoubleIntegrator)
    ctl = make_controller(friction, None, solver="fast")
    assert isinstance(ctl, SQPShootingMPC)
    ctl.solve(np.array([0.5, 0.0]))
    assert "scalar stage cost" in str(ctl.native_reason)
    oracle = make_controller(QUAD, "oracle", solver="fast")
    assert isinstance(oracle, SQPShootingMPC)
    x = np.zeros(13)
    x[6], x[2] = 1.0, 2.0
    oracle.solve(x)
    assert "oracle" in str(oracle.native_reason)
    # 516 controls: beyond the kernel's buffers (one SQP iteration: the path is chosen before the first one; a full
    # numpy solve of this size costs seconds)
    long = make_controller(QUAD, None, solver="fast", horizon=129, max_iter=1)
    assert isinstance(long, SQPShootingMPC)
    long.solve(x)
    assert "horizon 129" in str(long.native_reason)
    wide = NumpyDynamics(QUAD, _model("residual", hidden=(600,)), base=base_model_np(QUAD))
    assert "limits" in str(native.unsupported_reason(wide, quadrotor_task(QUAD)))
    assert "scalar" in str(native.unsupported_reason(wide, friction_task(friction)))


def test_kernel_merit_refuses_a_non_finite_trajectory_as_numpy_does() -> None:
    """A trial point whose last quaternion is NaN (it does not enter the position cost) has merit +inf on both
    paths, so the line search rejects it; finite points have the same merit."""
    ctl = make_controller(QUAD, None, solver="fast", native=False)
    assert isinstance(ctl, SQPShootingMPC)
    task = ctl.task
    lib = native.load_library()
    assert lib is not None
    nat = native.NativeSQP(lib, ctl.dyn, task, ctl._u_hi - ctl._u_lo, ctl.radial)
    nat.set_target(task.target, ctl.eps)
    x0 = np.zeros(13)
    x0[6], x0[2] = 1.0, 2.0
    xs = ctl.rollout(x0, np.tile(QUAD.hover_thrust(), (10, 1)) * 1.1)
    merit, c = nat.merit(xs, 10.0)
    ref, _, c_ref = ctl._merit(xs, task, 10.0)
    assert merit == pytest.approx(ref, rel=1e-13) and np.allclose(c, c_ref, rtol=1e-13, atol=1e-15)
    xs[-1, 7] = np.nan
    assert ctl._merit(xs, task, 10.0)[0] == np.inf
    assert nat.merit(xs, 10.0)[0] == np.inf
