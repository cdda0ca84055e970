"""Tests of the three systems (saml_ros.core.systems): registry, dynamics properties, API conveniences."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest
import torch

from saml_ros.core.dynamics.quaternion import (
    quat_from_axis_angle,
    quat_mul,
    quat_rotate,
    quat_to_rotmat,
    tilt_angle,
)
from saml_ros.core.dynamics.system import System
from saml_ros.core.spec import ProblemSpec
from saml_ros.core.systems import SYSTEM_NAMES, default_params, get_system
from saml_ros.systems.friction.model import FrictionDoubleIntegrator
from saml_ros.systems.paddle_ball.model import (
    PaddleBall,
    landing_point,
    normal_from_roll_pitch,
    roll_pitch_from_normal,
    rotate_y,
)
from saml_ros.systems.quadrotor.model import Quadrotor

F64 = torch.float64


def _inputs(system: System, n: int, seed: int = 0, dtype: torch.dtype = F64) -> tuple[torch.Tensor, torch.Tensor]:
    x, u = system.sample_inputs(n, np.random.default_rng(seed))
    return torch.as_tensor(x, dtype=dtype), torch.as_tensor(u, dtype=dtype)


# ------------------------------------------------------------------------------------------- registry
def test_registry_names_and_overrides() -> None:
    assert SYSTEM_NAMES == ("friction", "quadrotor", "paddle_ball")
    for name in SYSTEM_NAMES:
        s = get_system(name)
        assert s.name == name
        assert s.state.size == {"friction": 2, "quadrotor": 13, "paddle_ball": 6}[name]
        assert s.control_low.shape == s.control_high.shape == (s.control.size,)
        assert np.all(s.control_low < s.control_high)
        assert isinstance(s.schema_hash(), str)
        # params() rebuilds an equal system
        assert isinstance(s, (FrictionDoubleIntegrator, Quadrotor, PaddleBall))
        rebuilt = type(s)(**s.params())
        assert rebuilt.params() == s.params()
        assert set(s.params()) == set(default_params(name))
    flat = get_system("friction", bumps=[1.0, 0.1, 0.2, 0.5, -1.0, 0.3])
    assert isinstance(flat, FrictionDoubleIntegrator) and flat.bumps == ((1.0, 0.1, 0.2), (0.5, -1.0, 0.3))
    quad = get_system("quadrotor", alpha=0.3)
    assert isinstance(quad, Quadrotor) and quad.alpha == 0.3
    assert get_system("paddle_ball").target.name == "post_impact_velocity"
    assert get_system("friction").target is get_system("friction").state


def test_registry_errors() -> None:
    with pytest.raises(ValueError, match="friction.*quadrotor.*paddle_ball"):
        get_system("cartpole")
    with pytest.raises(ValueError, match="valid parameters"):
        get_system("quadrotor", wobble=1.0)
    bad: list[tuple[str, dict[str, Any], str]] = [
        ("friction", {"dt": 0.0}, "dt"),
        ("friction", {"mu_base": -1.0}, "mu_base"),
        ("friction", {"bumps": [[1.0, 0.0]]}, "bumps"),
        ("friction", {"bumps": [1.0, 0.0, 0.3, 2.0]}, "bumps"),
        ("friction", {"bumps": [[-1.0, 0.0, 0.3]]}, "amplitude"),
        ("friction", {"bumps": [[1.0, 0.0, 0.0]]}, "width"),
        ("quadrotor", {"alpha": 1.5}, "alpha"),
        ("quadrotor", {"inertia": [1.0, 0.0, 1.0]}, "inertia"),
        ("quadrotor", {"f_max": 2.0}, "lift"),
        ("quadrotor", {"mass": float("nan")}, "mass"),
        ("paddle_ball", {"restitution_true": 0.0}, "restitution_true"),
        ("paddle_ball", {"restitution_base": "high"}, "restitution_base"),
        ("paddle_ball", {"slow_fraction": 2.0}, "slow_fraction"),
    ]
    for name, kw, word in bad:
        with pytest.raises(ValueError, match=word):
            get_system(name, **kw)


def test_paper_specs_compile_and_regions_hold_data() -> None:
    expected = {"friction": (0.03, 0.08), "quadrotor": (0.2, 0.4), "paddle_ball": (0.02, 0.09)}
    for name in SYSTEM_NAMES:
        s = get_system(name)
        spec = ProblemSpec.for_system(s.paper_spec(), s)
        x, u, y = s.make_dataset(4000, np.random.default_rng(1))
        masks = spec.masks(*(torch.as_tensor(a) for a in (x, u, y)))
        frac = float(masks[-1].double().mean())  # type: ignore[union-attr]
        lo, hi = expected[name]
        assert lo < frac < hi, (name, frac)


# ------------------------------------------------------------------------------------------- friction
def test_frictionless_closed_form_over_many_steps() -> None:
    s = FrictionDoubleIntegrator()
    rng = np.random.default_rng(2)
    x0 = torch.as_tensor(np.stack((rng.uniform(-2, 2, 50), rng.uniform(-2.5, 2.5, 50)), 1))
    u = torch.as_tensor(rng.uniform(-10, 10, (50, 1)))
    x = x0
    steps = 40
    for _ in range(steps):
        x = s.base_step(x, u)
    p_t = x0[:, 0] + steps * s.dt * x0[:, 1] + s.dt**2 * u[:, 0] * steps * (steps - 1) / 2
    v_t = x0[:, 1] + steps * s.dt * u[:, 0]
    torch.testing.assert_close(x[:, 0], p_t, rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(x[:, 1], v_t, rtol=1e-10, atol=1e-10)


def test_friction_opposes_motion_and_never_reverses_velocity() -> None:
    s = FrictionDoubleIntegrator()
    x, u = _inputs(s, 20000, seed=3)
    # half of the batch with near-zero velocity after the command, where sticking matters
    x[10000:, 1] = torch.as_tensor(np.random.default_rng(4).uniform(-0.4, 0.4, 10000))
    u[10000:, 0] = torch.as_tensor(np.random.default_rng(5).uniform(-3, 3, 10000))
    x[-5:, 1] = 0.0
    u[-5:, 0] = 0.0
    w = s.base_step(x, u)[:, 1]
    true = s.true_step(x, u)
    v_next = true[:, 1]
    b = s.friction_decrement(x[:, 0])
    assert torch.all(b > 0)
    assert torch.all(v_next * w >= 0), "friction reversed the velocity"
    assert torch.all(v_next.abs() <= w.abs())
    moving = w != 0
    assert torch.all(v_next.abs()[moving] < w.abs()[moving]), "friction must reduce |v| whenever moving"
    stuck = w.abs() <= b
    assert stuck.sum() > 1000 and (~stuck).sum() > 1000
    assert torch.all(v_next[stuck] == 0)
    torch.testing.assert_close(v_next[~stuck], w[~stuck] - b[~stuck] * torch.sign(w[~stuck]))
    torch.testing.assert_close(true[:, 0], s.base_step(x, u)[:, 0])  # position is frictionless


def test_friction_profile_positive_and_varies_near_origin() -> None:
    s = FrictionDoubleIntegrator()
    p = torch.linspace(-0.5, 0.5, 201, dtype=F64)
    mu = s.friction_decel(p)
    assert torch.all(mu > 0)
    assert float(mu.max() - mu.min()) > 1.0  # clearly position-varying inside the accuracy region
    big = torch.linspace(-2, 2, 401, dtype=F64)
    assert 0.5 < float(s.friction_decel(big).min()) and float(s.friction_decel(big).max()) < 5.0


# ------------------------------------------------------------------------------------------- quadrotor
def test_quadrotor_quaternion_stays_unit_over_long_rollout() -> None:
    quad = Quadrotor()
    rng = np.random.default_rng(6)
    for dtype, tol in ((F64, 1e-12), (torch.float32, 1e-5)):
        x, _ = _inputs(quad, 16, seed=7, dtype=dtype)
        for _ in range(500):
            u = torch.as_tensor(rng.uniform(0, 10, (16, 4)), dtype=dtype)
            x = quad.true_step(x, u)
            x = torch.cat((x[:, :10], x[:, 10:].clamp(-20, 20)), dim=1)  # keep rates bounded
        assert x.dtype == dtype
        norms = torch.linalg.vector_norm(x[:, 6:10], dim=1)
        assert torch.all((norms - 1).abs() < tol), norms


def test_ground_effect_zero_high_up_and_positive_near_ground() -> None:
    quad = Quadrotor()
    x, _ = _inputs(quad, 2000, seed=8)
    # any orientation at all, high enough that no propeller is below h_max
    q = torch.as_tensor(np.random.default_rng(9).normal(size=(2000, 4)))
    x[:, 6:10] = q / q.norm(dim=1, keepdim=True)
    x[:, 2] = quad.h_max + quad.arm_length + torch.rand(2000, dtype=F64) * 3 + 1e-9
    assert torch.all(quad.ground_effect_gain(x) == 0)
    # level, 0.3 m up: every motor gets alpha * (1 - 0.3 / h_max)
    level = torch.as_tensor(quad.hover_state((1.0, 2.0, 0.3)))[None]
    k = quad.ground_effect_gain(level)
    torch.testing.assert_close(k, torch.full((1, 4), quad.alpha * (1 - 0.3 / quad.h_max), dtype=F64))
    # tilted about x (roll): motor 4 (+y) goes up, motor 2 (-y) goes down and gets more ground effect
    tilted = level.clone()
    tilted[0, 6:10] = quat_from_axis_angle(torch.tensor([1.0, 0.0, 0.0], dtype=F64), torch.tensor(0.3, dtype=F64))
    h = quad.motor_heights(tilted)[0]
    assert h[3] > 0.3 > h[1] and abs(float(h[0]) - 0.3) < 1e-12
    kt = quad.ground_effect_gain(tilted)[0]
    assert kt[1] > kt[0] > kt[3] > 0
    assert torch.all(kt < k[0])  # tilting away from level reduces the effect at equal height


def test_quadrotor_hover_and_base_true_agreement() -> None:
    quad = Quadrotor()
    hover = torch.as_tensor(quad.hover_state((0.5, -1.0, 3.0)))[None]
    u = torch.as_tensor(quad.hover_thrust())[None]
    torch.testing.assert_close(quad.base_step(hover, u), hover, rtol=0, atol=1e-12)
    torch.testing.assert_close(quad.true_step(hover, u), hover, rtol=0, atol=1e-12)  # above h_max
    low = torch.as_tensor(quad.hover_state((0.0, 0.0, 0.5)))[None]
    assert float(quad.true_step(low, u)[0, 5]) > 0.1  # ground effect pushes the hovering vehicle up
    assert float(quad.base_step(low, u)[0, 5]) == 0.0
    x, u_r = _inputs(quad, 3000, seed=10)
    high = x[:, 2] > quad.h_max + quad.arm_length
    assert high.sum() > 1000 and (~high).sum() > 500
    torch.testing.assert_close(quad.true_step(x, u_r)[high], quad.base_step(x, u_r)[high], rtol=0, atol=0)
    diff = (quad.true_step(x, u_r) - quad.base_step(x, u_r))[~high]
    # one Euler step: ground effect shows up only in v and omega, never in p or q
    assert torch.all(diff[:, 0:3] == 0) and torch.all(diff[:, 6:10] == 0)
    assert float(diff[:, 3:6].abs().max()) > 0.1


def test_quadrotor_torque_signs_match_motor_layout() -> None:
    quad = Quadrotor()
    hover = torch.as_tensor(quad.hover_state((0.0, 0.0, 5.0)))[None]
    base_u = torch.as_tensor(quad.hover_thrust())[None]
    arms = torch.tensor([[1.0, 0, 0], [0, -1.0, 0], [-1.0, 0, 0], [0, 1.0, 0]], dtype=F64)
    for motor in range(4):
        u = base_u.clone()
        u[0, motor] += 1.0
        dw = (quad.base_step(hover, u)[0, 10:13] - hover[0, 10:13]) / quad.dt
        # roll / pitch torques equal r x F for the documented motor layout (unit lever arm)
        r_x_f = torch.linalg.cross(arms[motor], torch.tensor([0.0, 0.0, 1.0], dtype=F64))
        torch.testing.assert_close(dw[:2], r_x_f[:2])
        assert float(dw[2]) == (1.0 if motor in (0, 2) else -1.0)
    u = base_u.clone()
    u[0, 3] += 1.0  # raise f4: positive roll about x
    x1 = quad.base_step(hover, u)
    assert float(x1[0, 10]) > 0
    x2 = quad.base_step(x1, base_u)
    assert float(x2[0, 7]) > 0  # qx grows: rolled positively about x
    body_z = quat_rotate(x2[:, 6:10], torch.tensor([[0.0, 0.0, 1.0]], dtype=F64))[0]
    assert float(body_z[1]) < 0  # rolling about +x tips the thrust axis towards -y


def test_quaternion_kinematics_use_body_rates() -> None:
    quad = Quadrotor()
    x = torch.as_tensor(quad.hover_state((0.0, 0.0, 5.0)))[None]
    yaw90 = quat_from_axis_angle(torch.tensor([0.0, 0.0, 1.0], dtype=F64), torch.tensor(math.pi / 2, dtype=F64))
    x[0, 6:10] = yaw90
    x[0, 10] = 1.0  # body x axis = world y after the yaw: a body roll rotates about world y
    q1 = quad.base_step(x, torch.as_tensor(quad.hover_thrust())[None])[0, 6:10]
    body_z = quat_to_rotmat(q1)[:, 2]
    assert float(body_z[0]) > 0.05 and abs(float(body_z[1])) < 1e-12
    # first-order agreement with the exact composition q ⊗ exp(omega dt / 2)
    exact = quat_mul(yaw90, quat_from_axis_angle(torch.tensor([1.0, 0.0, 0.0], dtype=F64),
                                                 torch.tensor(quad.dt, dtype=F64)))
    assert float((q1 - exact).norm()) < 0.01
    # normalised Euler step: q ⊗ [1, omega dt / 2] / norm, a rotation by 2 atan(dt / 2)
    assert float(tilt_angle(q1)) == pytest.approx(2 * math.atan(quad.dt / 2), abs=1e-12)


def test_quadrotor_sample_inputs_follow_the_paper() -> None:
    quad = Quadrotor()
    x, u = quad.sample_inputs(5000, np.random.default_rng(11))
    assert x.shape == (5000, 13) and u.shape == (5000, 4)
    assert np.all(np.abs(x[:, :2]) <= 10) and x[:, 2].min() >= 0.1 and x[:, 2].max() <= 5
    assert np.all(np.abs(x[:, 3:6]) <= 6) and np.all(np.abs(x[:, 10:]) <= 2.5)
    np.testing.assert_allclose(np.linalg.norm(x[:, 6:10], axis=1), 1.0, atol=1e-12)
    angles = 2 * np.arccos(np.clip(x[:, 6], -1, 1))
    assert angles.max() <= 0.4 + 1e-9 and angles.max() > 0.39
    assert u.min() >= 0 and u.max() <= 10


# ------------------------------------------------------------------------------------------- paddle ball
def test_paddle_ball_models_agree_without_bias_and_bounce_straight() -> None:
    same = PaddleBall(restitution_true=0.8, restitution_base=0.8, normal_bias_y=0.0)
    x, u = _inputs(same, 2000, seed=12)
    torch.testing.assert_close(same.true_step(x, u), same.base_step(x, u), rtol=0, atol=1e-12)
    default = PaddleBall()
    assert float((default.true_step(x, u) - default.base_step(x, u)).abs().max()) > 0.5
    drop = torch.tensor([[0.3, -0.2, 0.0, 0.0, 0.0, -4.0]], dtype=F64)
    still_flat = torch.tensor([[0.0, 0.0, 0.0, 0.0, 0.0, 1.0]], dtype=F64)
    torch.testing.assert_close(default.base_step(drop, still_flat), torch.tensor([[0.0, 0.0, 0.6 * 4.0]], dtype=F64))
    torch.testing.assert_close(same.true_step(drop, still_flat), torch.tensor([[0.0, 0.0, 0.8 * 4.0]], dtype=F64))
    # the real paddle is tilted about +y: the ball is deflected towards +x
    assert float(default.true_step(drop, still_flat)[0, 0]) > 0
    # commanded normals are normalised inside the dynamics
    scaled = u.clone()
    scaled[:, 3:6] *= 1.3
    torch.testing.assert_close(default.true_step(x, scaled), default.true_step(x, u))
    # the printed formula: both normal and tangential relative components are scaled by a_r
    slide = torch.tensor([[0.0, 0.0, 0.0, 2.0, 0.0, -4.0]], dtype=F64)
    paddle_up = torch.tensor([[0.0, 0.0, 1.0, 0.0, 0.0, 1.0]], dtype=F64)
    torch.testing.assert_close(default.base_step(slide, paddle_up), torch.tensor([[1.2, 0.0, 0.6 * 5 + 1]], dtype=F64))


def test_landing_point() -> None:
    p = torch.tensor([[0.4, -0.7, 0.0], [1.0, 2.0, 0.5], [0.0, 0.0, 0.0]], dtype=F64)
    v = torch.tensor([[0.0, 0.0, 3.0], [1.0, -2.0, 9.81 / 2], [1.0, 1.0, -2.0]], dtype=F64)
    out = landing_point(p, v)
    torch.testing.assert_close(out, torch.tensor([[0.4, -0.7], [2.0, 0.0], [0.0, 0.0]], dtype=F64))
    torch.testing.assert_close(PaddleBall(g=9.81).landing_point(p, v), out)


def test_paddle_roll_pitch_helpers_and_bias_is_pitch_offset() -> None:
    roll = torch.tensor([0.0, 0.2, -0.3], dtype=F64)
    pitch = torch.tensor([0.1, -0.25, 0.3], dtype=F64)
    n = normal_from_roll_pitch(roll, pitch)
    torch.testing.assert_close(n.norm(dim=1), torch.ones(3, dtype=F64))
    r2, p2 = roll_pitch_from_normal(n * 2.0)
    torch.testing.assert_close(r2, roll)
    torch.testing.assert_close(p2, pitch)
    torch.testing.assert_close(rotate_y(n, 0.2), normal_from_roll_pitch(roll, pitch + 0.2))


def test_paddle_sample_inputs_are_approaching_impacts() -> None:
    pb = PaddleBall()
    x, u = pb.sample_inputs(5000, np.random.default_rng(13))
    n_true = rotate_y(torch.as_tensor(u[:, 3:6]), pb.normal_bias_y).numpy()
    v_rel = x[:, 3:6] - u[:, 0:3]
    assert np.all(np.einsum("ij,ij->i", v_rel, u[:, 3:6]) < 0)
    assert np.all(np.einsum("ij,ij->i", v_rel, n_true) < 0)
    tilt = np.arccos(np.clip(u[:, 5], -1, 1))
    assert tilt.max() <= 0.35 + 1e-9
    speed = np.linalg.norm(v_rel, axis=1)
    fast = speed > 1.5
    assert 0.85 < fast.mean() < 0.95
    assert np.mean((speed > 3) & (speed < 6)) > 0.5  # the controller's |v_rel| range is well covered
    assert np.all(u >= pb.control_low) and np.all(u <= pb.control_high)


# ------------------------------------------------------------------------------------------- all systems
@pytest.mark.parametrize("name", SYSTEM_NAMES)
def test_dtype_shapes_and_float32_agreement(name: str) -> None:
    s = get_system(name)
    x64, u64 = _inputs(s, 64, seed=14)
    for step in (s.true_step, s.base_step):
        y64 = step(x64, u64)
        y32 = step(x64.float(), u64.float())
        assert y64.dtype == F64 and y32.dtype == torch.float32
        assert y64.shape == y32.shape == (64, s.target.size)
        assert torch.all(torch.isfinite(y64))
        # float32 can flip the friction stick / slip decision only exactly at the threshold
        assert float((y32.double() - y64).abs().max()) < 1e-4


@pytest.mark.parametrize("name", SYSTEM_NAMES)
def test_gradients_flow(name: str) -> None:
    s = get_system(name)
    x, u = _inputs(s, 6, seed=15)
    for step in (s.true_step, s.base_step):
        torch.autograd.gradcheck(step, (x.clone().requires_grad_(), u.clone().requires_grad_()))
    xg, ug = _inputs(s, 256, seed=16)
    xg.requires_grad_()
    ug.requires_grad_()
    s.true_step(xg, ug).square().sum().backward()
    assert xg.grad is not None and ug.grad is not None
    assert torch.all(torch.isfinite(xg.grad)) and torch.all(torch.isfinite(ug.grad))
    assert float(ug.grad.abs().sum()) > 0


def test_quadrotor_gradient_finite_at_level_attitude() -> None:
    quad = Quadrotor()
    x = torch.as_tensor(quad.hover_state((0.0, 0.0, 0.4)))[None].requires_grad_()
    u = torch.as_tensor(quad.hover_thrust())[None].requires_grad_()
    quad.true_step(x, u).sum().backward()
    assert x.grad is not None and torch.all(torch.isfinite(x.grad))
    assert float(x.grad[0, 2]) != 0  # height matters near the ground


@pytest.mark.parametrize("name", SYSTEM_NAMES)
def test_functorch_jacobians_and_batched_vs_single(name: str) -> None:
    s = get_system(name)
    x, u = _inputs(s, 8, seed=17)

    def single(xi: torch.Tensor, ui: torch.Tensor) -> torch.Tensor:
        return s.true_step(xi[None], ui[None])[0]

    jac_x, jac_u = torch.func.vmap(torch.func.jacrev(single, argnums=(0, 1)))(x, u)
    assert jac_x.shape == (8, s.target.size, s.state.size) and jac_u.shape == (8, s.target.size, s.control.size)
    batched = s.true_step_np(x.numpy(), u.numpy())
    for i in range(8):
        np.testing.assert_allclose(s.true_step_np(x[i].numpy(), u[i].numpy()), batched[i], rtol=0, atol=1e-12)
        np.testing.assert_allclose(s.base_step_np(x[i].numpy(), u[i].numpy()), s.base_step_np(x.numpy(), u.numpy())[i],
                                   rtol=0, atol=1e-12)
    assert s.true_step_np(x[0].numpy(), u[0].numpy()).shape == (s.target.size,)


@pytest.mark.parametrize("name", SYSTEM_NAMES)
def test_make_dataset_shapes_noise_and_determinism(name: str) -> None:
    s = get_system(name)
    x, u, y = s.make_dataset(3000, np.random.default_rng(18))
    assert x.shape == (3000, s.state.size) and u.shape == (3000, s.control.size) and y.shape == (3000, s.target.size)
    assert x.dtype == u.dtype == y.dtype == np.float64
    np.testing.assert_array_equal(y, s.true_step_np(x, u))
    x2, u2, y2 = s.make_dataset(3000, np.random.default_rng(18))
    np.testing.assert_array_equal(x, x2)
    np.testing.assert_array_equal(y, y2)
    field = s.target.names[-1]
    xn, un, yn = s.make_dataset(3000, np.random.default_rng(18), noise={field: 0.2})
    resid = yn - s.true_step_np(xn, un)
    j = s.target.index(field)
    assert np.all(np.delete(resid, j, axis=1) == 0)
    assert 0.18 < resid[:, j].std() < 0.22


def test_write_figures(tmp_path: pytest.TempPathFactory) -> None:
    from saml_ros.systems.plots import write_figures  # matplotlib: only the process that runs this test loads it

    paths = write_figures(tmp_path)  # type: ignore[arg-type]
    assert [p.name for p in paths] == ["friction_profile.png", "ground_effect.png"]
    for p in paths:
        assert p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and p.stat().st_size > 10_000
