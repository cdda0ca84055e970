"""The fast paddle-ball solver's internals: exact derivatives, the feasible-set projection, the search, and its
agreement with the SLSQP reference (saml_ros.systems.paddle_ball.mpc: landing_error, feasible_set, projected_newton,
multistart)."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
import torch

from saml_ros.core.model.network import DynamicsModel
from saml_ros.core.mpc import base_model_np, make_controller
from saml_ros.core.mpc.dynamics_np import NumpyDynamics
from saml_ros.core.systems import get_system
from saml_ros.systems.paddle_ball.model import PaddleBall, landing_point
from saml_ros.systems.paddle_ball.mpc import GaussNewtonPaddle, PaddleProblem, paddle_goal
from saml_ros.systems.paddle_ball.mpc.landing_error import LandingError
from saml_ros.systems.paddle_ball.mpc.projected_newton import ProjectedNewton

_SYSTEM = get_system("paddle_ball")
assert isinstance(_SYSTEM, PaddleBall)
SYSTEM: PaddleBall = _SYSTEM


def perturbed(kind: str = "residual", scale: float = 0.05, seed: int = 0) -> DynamicsModel:
    """A model with a non-zero correction phi (a fresh one has a zero output layer)."""
    model = DynamicsModel(SYSTEM, kind=kind, seed=seed).double()
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for w in model.net.weights:
            w.add_(scale * torch.randn(w.shape, generator=gen, dtype=w.dtype))
        model.out_std.mul_(0.2)
        if kind == "full":  # phi is the whole post-impact velocity: make the ball go up (about 3 m/s)
            model.net.biases[-1][..., 2] += 3.0 / float(model.out_std[0, 0, 2])
    return model


def problem(rng: np.random.Generator, model: DynamicsModel | None, spread: float = 1.0) -> PaddleProblem:
    x = np.array([rng.uniform(-1, 1), rng.uniform(-1, 1), 0.0, rng.uniform(-1, 1), rng.uniform(-1, 1),
                  rng.uniform(-6, -2)])
    vmin = rng.uniform(3.0, 4.0)
    goal = paddle_goal(target_xy=spread * rng.uniform(-1, 1, 2), v_rel=(vmin, vmin + rng.uniform(1, 2)))
    return PaddleProblem(SYSTEM, NumpyDynamics(SYSTEM, model, base=base_model_np(SYSTEM)), x, goal)


def evaluator(prob: PaddleProblem) -> LandingError:
    return LandingError(prob.dyn, prob.x, prob.goal.target_xy, SYSTEM.g)


@pytest.mark.parametrize("kind", ["base", "residual", "full"])
def test_landing_error_and_exact_derivatives(kind: str) -> None:
    model = None if kind == "base" else perturbed(kind)
    rng = np.random.default_rng(7)
    checked = 0
    for _ in range(6):
        prob = problem(rng, model)
        ev = evaluator(prob)
        theta = rng.uniform(prob.lo, prob.hi).tolist()
        pt = ev.value(theta)
        # value: the torch model (or base step) and the system's landing point
        u = torch.as_tensor(prob.control(np.array(theta))[None])
        xt = torch.as_tensor(prob.x[None])
        with torch.no_grad():
            v = SYSTEM.base_step(xt, u) if model is None else model(xt, u)[0]
        land = landing_point(xt[:, :3], v, SYSTEM.g).numpy()[0]
        np.testing.assert_allclose(pt.v, v.numpy()[0], atol=1e-12)
        np.testing.assert_allclose(pt.r, land - prob.goal.target_xy, atol=1e-12)
        if not pt.up:
            continue
        checked += 1
        jac, hess = ev.derivatives(pt, True)
        assert hess is not None
        jac_gn, none = ev.derivatives(ev.value(theta), False)
        assert none is None
        np.testing.assert_allclose(jac_gn, jac, atol=1e-14)
        # J and H = J^T J + sum_i r_i d2 r_i by central differences (of r, and of the exact gradient J^T r)
        h = 1e-6
        num_j = np.zeros((2, 5))
        num_h = np.zeros((5, 5))
        for k in range(5):
            tp, tm = list(theta), list(theta)
            tp[k] += h
            tm[k] -= h
            pp, pm = ev.value(tp), ev.value(tm)
            num_j[:, k] = (np.array(pp.r) - np.array(pm.r)) / (2 * h)
            gp = np.array(ev.derivatives(pp, False)[0]).T @ np.array(pp.r)
            gm = np.array(ev.derivatives(pm, False)[0]).T @ np.array(pm.r)
            num_h[:, k] = (gp - gm) / (2 * h)
        np.testing.assert_allclose(jac, num_j, atol=1e-6 * (1 + np.abs(num_j).max()))
        np.testing.assert_allclose(hess, num_h, atol=1e-5 * (1 + np.abs(num_h).max()))
        assert np.allclose(hess, np.transpose(hess))
        # dv/dtheta, as set on the point by derivatives()
        assert pt.dv is not None and np.array(pt.dv).shape == (3, 5)
    assert checked >= 3


def test_projection_is_feasible_and_exact_on_the_speed_ball() -> None:
    rng = np.random.default_rng(3)
    for _ in range(20):
        prob = problem(rng, None)
        feasible = prob.feasible_set()
        vmin, vmax = prob.goal.v_rel
        for _ in range(20):
            q = (prob.lo + (prob.hi - prob.lo) * rng.uniform(-0.5, 1.5, 5)).tolist()
            p = np.array(feasible.project(q))
            assert np.all(p >= prob.lo - 1e-12) and np.all(p <= prob.hi + 1e-12)
            s = float(np.linalg.norm(prob.x[3:6] - p[:3]))
            assert vmin - 1e-9 <= s <= vmax + 1e-9
            qs = float(np.linalg.norm(prob.x[3:6] - np.clip(q, prob.lo, prob.hi)[:3]))
            if qs > vmax:  # box and ball are convex: the projection is the nearest feasible point
                for _ in range(10):
                    other = p + 0.05 * rng.normal(size=5)
                    other = np.clip(other, prob.lo, prob.hi)
                    if np.linalg.norm(prob.x[3:6] - other[:3]) <= vmax:
                        assert np.linalg.norm(other - q) >= np.linalg.norm(p - q) - 1e-9


def test_search_hits_reachable_targets_and_matches_the_reference_out_of_reach() -> None:
    """Reachable targets are hit to 1e-6 m in a few iterations; out of reach (targets up to 3 m away) the fast
    solver ends no worse than SLSQP on average and feasible."""
    model = perturbed()
    fast = make_controller(SYSTEM, model, "fast")
    ref = make_controller(SYSTEM, model, "slsqp")
    rng = np.random.default_rng(11)
    reach_its, far = [], []
    for k in range(24):
        prob = problem(rng, model, spread=1.0 if k < 16 else 3.0)
        fast.reset()
        res = fast.solve(prob.x, prob.goal)
        assert res.success, res.message
        speed = float(np.linalg.norm(prob.x[3:6] - res.u[:3]))
        assert prob.goal.v_rel[0] - 1e-6 <= speed <= prob.goal.v_rel[1] + 1e-6
        if res.cost < 1e-4:
            assert res.cost <= 1e-6
            reach_its.append(res.iterations)
        else:
            ref.reset()
            far.append((res.cost, ref.solve(prob.x, prob.goal).cost))
    assert len(reach_its) >= 10 and np.mean(reach_its) <= 8
    assert len(far) >= 4
    fast_cost, ref_cost = np.array(far).T
    assert fast_cost.sum() <= ref_cost.sum() * (1 + 1e-6)
    assert np.all(fast_cost <= ref_cost * 1.05)


def test_search_respects_the_time_budget() -> None:
    model = perturbed()
    ctrl = make_controller(SYSTEM, model, "fast", max_time=0.0)
    prob = problem(np.random.default_rng(5), model, spread=3.0)
    res = ctrl.solve(prob.x, prob.goal)
    assert math.isfinite(res.cost) and np.all(res.u >= SYSTEM.control_low) and np.all(res.u <= SYSTEM.control_high)
    assert res.iterations <= 10  # the probe only


def test_runs_reuse_known_points_and_cached_derivatives_exactly() -> None:
    """A run handed the evaluation of its start point (and the derivatives cached on it) ends exactly where a run
    from scratch ends; cached derivatives equal freshly computed ones, also when ``J`` was cached first. (The third
    problem's Gauss-Newton run reaches a point where no free direction moves the landing point: ``J P J^T``
    underflows to 0, which used to raise ZeroDivisionError.)"""
    model = perturbed()
    rng = np.random.default_rng(3)
    for _ in range(6):
        prob = problem(rng, model, spread=3.0)
        ev = evaluator(prob)
        row = ProjectedNewton(ev, prob.feasible_set())
        theta = row.feasible.project(rng.uniform(prob.lo, prob.hi).tolist())
        pt = ev.value(theta)
        jac_only, _ = ev.derivatives(pt, False)
        jac, hess = ev.derivatives(pt, True)  # H added to a point that had J cached
        fresh_jac, fresh_hess = ev.derivatives(ev.value(theta), True)
        assert jac == jac_only == fresh_jac and hess == fresh_hess
        for mode in ("gauss-newton", "newton"):
            cold = row.run(theta, mode, max_iter=15)
            warm = row.run(theta, mode, max_iter=15, start=pt)
            assert (warm.theta, warm.cost, warm.iterations) == (cold.theta, cold.cost, cold.iterations)
            moved = row.run(cold.theta, mode, max_iter=15, start=pt)  # a point of another theta is not used
            assert moved.theta == row.run(cold.theta, mode, max_iter=15).theta


def test_multistart_and_every_valley_point_stay_available() -> None:
    """The optional multi-start (``max_runs > 1``) and relaxing every displaced valley point still give feasible
    plans no worse than the reference by more than 1 % out of reach."""
    model = perturbed()
    fast = make_controller(SYSTEM, model, "fast")
    assert isinstance(fast, GaussNewtonPaddle)
    fast.settings = replace(fast.settings, max_runs=4, valley_pick=False)
    ref = make_controller(SYSTEM, model, "slsqp")
    rng = np.random.default_rng(11)
    far = 0
    for _ in range(8):
        prob = problem(rng, model, spread=3.0)
        fast.reset()
        ref.reset()
        res, want = fast.solve(prob.x, prob.goal), ref.solve(prob.x, prob.goal)
        assert res.success, res.message
        far += want.cost > 1e-3
        assert res.cost <= want.cost * 1.01 + 1e-6
    assert far >= 3
