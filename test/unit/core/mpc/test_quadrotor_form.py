"""The quadrotor's f_hat in array-namespace form equals the torch f_hat, with exact CasADi Jacobians."""

from __future__ import annotations

import numpy as np
import torch

from saml_ros.core.dynamics.base_forms import TORCH
from saml_ros.systems.quadrotor.generic_form import quadrotor_base, quadrotor_f_hat, quadrotor_params
from saml_ros.systems.quadrotor.model import Quadrotor


def test_form_equals_the_torch_f_hat_and_its_jacobians_equal_autograd() -> None:
    system = Quadrotor(inertia=(0.9, 1.1, 1.3), mass=1.2)
    x, u = system.sample_inputs(16, np.random.default_rng(0))
    want = system.base_step(torch.from_numpy(x), torch.from_numpy(u)).numpy()
    base = quadrotor_base(system)
    y, jx, ju = base.step_jac(x, u)
    np.testing.assert_allclose(base.step(x, u), want, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(y, want, rtol=1e-12, atol=1e-12)
    got = quadrotor_f_hat(torch.from_numpy(x), torch.from_numpy(u), dt=system.dt, xp=TORCH, **quadrotor_params(system))
    np.testing.assert_allclose(got.numpy(), want, rtol=1e-12, atol=1e-12)
    from torch.autograd.functional import jacobian

    ax, au = jacobian(lambda a, b: system.base_step(a, b).sum(0), (torch.from_numpy(x), torch.from_numpy(u)))
    np.testing.assert_allclose(jx, ax.permute(1, 0, 2).numpy(), rtol=1e-9, atol=1e-10)
    np.testing.assert_allclose(ju, au.permute(1, 0, 2).numpy(), rtol=1e-9, atol=1e-10)
