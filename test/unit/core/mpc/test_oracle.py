"""The oracle model (the TRUE dynamics inside the MPC, ``make_controller(system, "oracle")``): its numpy twins equal
``true_step`` and torch autograd's Jacobians, the controllers keep it across ``set_model``, and a learned model
whose residual is exactly ``f - f_hat`` gives the oracle's closed-loop cost."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
import torch

from saml_ros.core.model.network import DynamicsModel
from saml_ros.core.mpc import closed_loop, make_controller
from saml_ros.core.mpc.dynamics_np import ORACLE, NumpyDynamics, TorchTrueNP
from saml_ros.core.mpc.factory import true_model_np
from saml_ros.core.systems import SYSTEM_NAMES, get_system
from saml_ros.systems.friction.dynamics_np import FrictionTrueNP
from saml_ros.systems.friction.model import FRICTION_PROFILES, FrictionDoubleIntegrator
from saml_ros.systems.paddle_ball.dynamics_np import PaddleTrueNP
from saml_ros.systems.quadrotor.dynamics_np import QuadrotorTrueNP
from saml_ros.systems.quadrotor.model import Quadrotor


def autograd_jac(system: object, x: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Jacobians of ``system.true_step`` at each row by torch autograd, ``(B, n_y, n_x)``, ``(B, n_y, n_u)``."""
    def one(xi: torch.Tensor, ui: torch.Tensor) -> torch.Tensor:
        return system.true_step(xi[None], ui[None])[0]  # type: ignore[attr-defined]

    ja, jb = torch.func.vmap(torch.func.jacrev(one, argnums=(0, 1)))(torch.from_numpy(x), torch.from_numpy(u))
    return ja.numpy(), jb.numpy()


SYSTEMS = [("friction", {}), ("friction", {"profile": "periodic"}), ("quadrotor", {}), ("quadrotor", {"drag": 0.3}),
           ("quadrotor", {"wind": 2.0, "wind_length": 3.0, "wind_floor": 1.0, "wind_ramp": 0.7}),
           ("quadrotor", {"drag": 0.3, "wind": 2.0}), ("paddle_ball", {})]
TWINS = {"friction": FrictionTrueNP, "quadrotor": QuadrotorTrueNP, "paddle_ball": PaddleTrueNP}


@pytest.mark.parametrize(("name", "params"), SYSTEMS)
def test_oracle_twin_equals_true_step_and_autograd(name: str, params: dict[str, Any]) -> None:
    system = get_system(name, **params)
    twin = true_model_np(system)
    assert isinstance(twin, TWINS[name])
    x, u = system.sample_inputs(300, np.random.default_rng(3))
    if name == "friction":  # keep away from the kink |w| = b(p), where friction just holds the cart
        assert isinstance(system, FrictionDoubleIntegrator)
        w = x[:, 1] + system.dt * u[:, 0]
        keep = np.abs(np.abs(w) - system.dt * system.friction_decel_np(x[:, 0])) > 1e-3
        x, u = x[keep], u[keep]
    y_true = system.true_step_np(x, u)
    np.testing.assert_allclose(twin.step(x, u), y_true, rtol=1e-12, atol=1e-12)
    for i in range(5):
        np.testing.assert_allclose(twin.step1(x[i], u[i]), y_true[i], rtol=1e-12, atol=1e-12)
    y, a, b = twin.step_jac(x, u)
    np.testing.assert_allclose(y, y_true, rtol=1e-12, atol=1e-12)
    ja, jb = autograd_jac(system, x, u)
    np.testing.assert_allclose(a, ja, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(b, jb, rtol=1e-9, atol=1e-9)
    # the fallback (torch autograd of true_step) agrees too
    ya, aa, ba = TorchTrueNP(system).step_jac(x[:20], u[:20])
    np.testing.assert_allclose(a[:20], aa, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(b[:20], ba, rtol=1e-9, atol=1e-9)


def test_quadrotor_oracle_jacobian_at_the_level_attitude_and_near_the_ground() -> None:
    system = get_system("quadrotor")
    assert isinstance(system, Quadrotor)
    rng = np.random.default_rng(1)
    x = np.stack([system.hover_state((rng.uniform(-1, 1), rng.uniform(-1, 1), z)) for z in (0.15, 0.5, 1.2, 2.0)])
    x[:, 3:6] = rng.uniform(-1, 1, (4, 3))
    x[:, 12] = 0.3  # yaw rate only: still level
    u = rng.uniform(1, 4, (4, 4))
    y, a, b = QuadrotorTrueNP(system).step_jac(x, u)
    ja, jb = autograd_jac(system, x, u)
    np.testing.assert_allclose(y, system.true_step_np(x, u), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(a, ja, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(b, jb, rtol=1e-9, atol=1e-9)
    # the ground effect is in there: more thrust near the ground than above 1.5 m for the same command
    assert y[0, 5] > system.base_step_np(x[:1], u[:1])[0, 5]


@pytest.mark.parametrize("name", SYSTEM_NAMES)
def test_controllers_plan_with_the_oracle_and_keep_it(name: str) -> None:
    system = get_system(name)
    ctrl = make_controller(system, ORACLE, "fast")
    dyn = ctrl.dyn  # type: ignore[attr-defined]
    assert isinstance(dyn, NumpyDynamics) and dyn.kind == ORACLE and dyn.mlp is None
    ctrl.set_model(ORACLE)  # type: ignore[arg-type]
    assert ctrl.dyn.kind == ORACLE  # type: ignore[attr-defined]
    ctrl.set_model(None)
    assert ctrl.dyn.kind == "base"  # type: ignore[attr-defined]
    with pytest.raises(ValueError, match="oracle"):
        NumpyDynamics(system, "perfect")  # type: ignore[arg-type]


def exact_friction_residual(system: FrictionDoubleIntegrator) -> DynamicsModel:
    """A residual model (hand-set PReLU weights, float64) that equals ``true_step - base_step`` EVERYWHERE for a
    constant friction b: ``v' - w = -clamp(w, -b, b) = -(relu(w + b) - relu(w - b)) + b`` with ``w = v + dt u``."""
    assert not system.bumps and not system.waves
    b = system.dt * system.mu_base
    model = DynamicsModel(system, hidden=(2, 2), kind="residual").double()
    with torch.no_grad():
        for p in model.net.parameters():
            p.zero_()
        w0, b0 = model.net.weights[0][0], model.net.biases[0][0, 0]  # input [p, v, u] -> [w + b, w - b]
        w0[1, :] = 1.0
        w0[2, :] = system.dt
        b0[:] = torch.tensor([b, -b], dtype=torch.float64)
        model.net.slopes[0].fill_(0.0)  # ReLU
        model.net.weights[1][0].copy_(torch.eye(2, dtype=torch.float64))
        model.net.slopes[1].fill_(1.0)  # identity
        model.net.weights[2][0, :, 1] = torch.tensor([-1.0, 1.0], dtype=torch.float64)
        model.net.biases[2][0, 0, 1] = b
    return model


def test_a_model_with_the_exact_residual_gives_the_oracle_cost() -> None:
    system = get_system("friction", mu_base=3.0, bumps=[])
    assert isinstance(system, FrictionDoubleIntegrator)
    model = exact_friction_residual(system)
    x, u = system.sample_inputs(2000, np.random.default_rng(0))
    with torch.no_grad():
        pred = model(torch.from_numpy(x), torch.from_numpy(u))[0].numpy()
    np.testing.assert_allclose(pred, system.true_step_np(x, u), atol=1e-12)
    rng = np.random.default_rng(5)
    starts = np.stack((rng.uniform(-2, 2, 6), np.zeros(6)), axis=1)
    # the fast solver uses exact derivatives: the same predictions (up to rounding) give the same closed loop; SLSQP's
    # finite differences across the friction kink turn rounding differences into slightly different steps
    for solver, rel in (("fast", 1e-7), ("slsqp", 1e-3)):
        exact, oracle, base = (make_controller(system, m, solver, horizon=10) for m in (model, ORACLE, None))
        for x0 in starts:
            runs = [closed_loop(system, c, x0, 15) for c in (exact, oracle)]
            cost = [float(np.abs(r.xs[:, 0]).sum()) for r in runs]
            assert cost[0] == pytest.approx(cost[1], rel=rel, abs=1e-12), (solver, x0, cost)
            np.testing.assert_allclose(runs[0].xs, runs[1].xs, rtol=rel, atol=1e3 * rel)
        # ... and the comparison can fail: the base model's closed loop (from the last start) differs
        assert not np.allclose(closed_loop(system, base, x0, 15).xs, runs[1].xs, atol=1e-3)


def test_paddle_oracle_lands_the_true_impact_map_on_target() -> None:
    from saml_ros.systems.paddle_ball.mpc import paddle_goal

    system = get_system("paddle_ball")
    rng = np.random.default_rng(2)
    errs: dict[str, list[float]] = {"oracle": [], "base": []}
    for _ in range(10):
        x0 = np.array([*rng.uniform(-0.5, 0.5, 2), 0.0, *rng.uniform(-0.5, 0.5, 2), rng.uniform(-5, -3)])
        goal = paddle_goal(target_xy=x0[:2] + rng.uniform(-0.3, 0.3, 2), v_rel=(4.0, 6.0))
        for arm, model in (("oracle", ORACLE), ("base", None)):
            run = closed_loop(system, make_controller(system, model, "fast"), x0, 1, goal=goal)
            errs[arm].append(float(run.stage_costs[0]))
    assert max(errs["oracle"]) < 1e-3  # the true map is what it planned with
    assert min(errs["base"]) > 0.05  # f_hat's restitution and missing pitch bias miss the target


def test_friction_profiles_are_named_and_selectable() -> None:
    for name, values in FRICTION_PROFILES.items():
        s = get_system("friction", profile=name)
        assert isinstance(s, FrictionDoubleIntegrator) and s.profile_name == name
        assert s.mu_base == values["mu_base"]
        rebuilt = type(s)(**s.params())
        assert rebuilt.profile_name == name and rebuilt.params() == s.params()
    default = get_system("friction")
    assert isinstance(default, FrictionDoubleIntegrator) and default.profile_name == "sticky_patch"
    periodic = get_system("friction", profile="periodic")
    assert isinstance(periodic, FrictionDoubleIntegrator)
    p = np.linspace(-2, 2, 401)
    np.testing.assert_allclose(periodic.friction_decel_np(p), 2.5 + 2.0 * np.cos(np.pi * p), atol=1e-12)
    np.testing.assert_allclose(periodic.friction_slope_np(p), -2.0 * np.pi * np.sin(np.pi * p), atol=1e-12)
    torch_mu = periodic.friction_decel(torch.from_numpy(p)).numpy()
    np.testing.assert_allclose(torch_mu, periodic.friction_decel_np(p), atol=1e-12)
    lo, hi = periodic.mu_bounds
    assert lo == pytest.approx(0.5) and hi == pytest.approx(4.5) and hi < periodic.u_max
    with pytest.raises(ValueError, match="contradicts profile"):
        get_system("friction", profile="periodic", mu_base=3.0)
    with pytest.raises(ValueError, match="profile"):
        get_system("friction", profile="nonsense")
    with pytest.raises(ValueError, match="never"):
        get_system("friction", mu_base=1.0, waves=[2.0, 1.0, 0.0])
