"""MPC solvers (saml_ros.core.mpc): prediction model, QP subproblems, the three tasks, hot swap, failures."""

from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.optimize
import torch

from saml_ros.core.model.network import DynamicsModel
from saml_ros.core.mpc import LoopStep, base_model_np, closed_loop, make_controller
from saml_ros.core.mpc.dynamics_np import NumpyDynamics
from saml_ros.core.mpc.shooting import ShootingMPC
from saml_ros.core.mpc.shooting.qp import DEFAULT_BACKEND, L1QP, solve_box_qp, solve_qp
from saml_ros.core.mpc.shooting.sqp import SQPShootingMPC
from saml_ros.core.systems import get_system
from saml_ros.systems.paddle_ball.model import landing_point
from saml_ros.systems.paddle_ball.mpc import paddle_goal

SYSTEMS = ("friction", "quadrotor", "paddle_ball")
#: both QP backends where daqp is installed (requirements.txt installs it), else the numpy one
QP_BACKENDS = ("ipm", "daqp") if DEFAULT_BACKEND == "daqp" else ("ipm",)


def perturbed(system_name: str, seed: int = 0, scale: float = 0.3, kind: str = "residual",
              n_models: int = 1) -> DynamicsModel:
    """A model with a non-zero correction phi (a fresh one has a zero output layer, i.e. phi = 0)."""
    system = get_system(system_name)
    model = DynamicsModel(system, kind=kind, n_models=n_models, seed=seed).double()
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for w in model.net.weights:
            w.add_(scale * torch.randn(w.shape, generator=gen, dtype=w.dtype))
        model.out_std.mul_(0.2)
    return model


# ------------------------------------------------------------------------------------------ prediction model
@pytest.mark.parametrize("name", SYSTEMS)
@pytest.mark.parametrize("kind", ["base", "residual", "full"])
def test_numpy_model_and_jacobians_match_torch(name: str, kind: str) -> None:
    system = get_system(name)
    model = None if kind == "base" else perturbed(name, kind=kind)
    x, u = system.sample_inputs(6, np.random.default_rng(1))
    dyn = NumpyDynamics(system, model, base=base_model_np(system))  # the numpy twin against torch autograd
    y, a, b = dyn.step_jac(x, u)

    def torch_fn(xi: torch.Tensor, ui: torch.Tensor) -> torch.Tensor:
        if model is None:
            return system.base_step(xi[None], ui[None])[0]
        return model(xi[None], ui[None])[0, 0]

    ja, jb = torch.func.vmap(torch.func.jacrev(torch_fn, argnums=(0, 1)))(torch.from_numpy(x), torch.from_numpy(u))
    ref = system.base_step_np(x, u) if model is None else model.predict_np(x, u)
    np.testing.assert_allclose(y, ref, atol=1e-12)
    np.testing.assert_allclose(dyn.step(x, u), ref, atol=1e-12)
    np.testing.assert_allclose(np.stack([dyn.step1(x[i], u[i]) for i in range(6)]), ref, atol=1e-12)
    np.testing.assert_allclose(a, ja.detach().numpy(), atol=1e-10)
    np.testing.assert_allclose(b, jb.detach().numpy(), atol=1e-10)
    # the SQP's paths: Jacobians without the prediction (the base model's own when it has one), and rollouts
    # (the base model's rollout1 without a network) give exactly what step_jac and step1 give
    aj, bj = dyn.jacobians(x, u)
    np.testing.assert_array_equal(aj, a)
    np.testing.assert_array_equal(bj, b)
    if y.shape != x.shape:  # the paddle predicts an impact, not the next state: nothing to roll out
        return
    xs = dyn.rollout(x[0], u)
    want = [x[0]]
    for t in range(6):
        want.append(dyn.step1(want[-1], u[t]))
    np.testing.assert_array_equal(xs, np.stack(want))


@pytest.mark.parametrize(("name", "kind", "hidden"), [("friction", "residual", (4, 2)), ("friction", "full", (4, 2)),
                                                  ("friction", "residual", ()), ("quadrotor", "residual", (16, 8))])
def test_batched_rollout_equals_step_by_step(name: str, kind: str, hidden: tuple[int, ...]) -> None:
    """``rollout_batch`` (fused for the linear friction base and for full models, plain steps otherwise) predicts
    the same states as T one-sample steps, for every sequence of the batch."""
    system = get_system(name)
    model = DynamicsModel(system, kind=kind, hidden=hidden, seed=3).double()
    gen = torch.Generator().manual_seed(3)
    with torch.no_grad():
        for w in model.net.weights:
            w.add_(0.3 * torch.randn(w.shape, generator=gen, dtype=w.dtype))
        for s in model.net.slopes:  # one slope outside [0, 1]: the np.where branch of PReLU
            s.fill_(-0.3)
    dyn = NumpyDynamics(system, model, base=base_model_np(system))
    rng = np.random.default_rng(0)
    x0 = system.sample_inputs(1, rng)[0][0]
    us = np.stack([system.sample_inputs(7, rng)[1] for _ in range(5)], 0).transpose(1, 0, 2)  # (K=7, T=5, m)
    xs = dyn.rollout_batch(x0, us)
    assert xs.shape == (7, 6, system.state.size)
    for k in range(7):
        x = x0.copy()
        np.testing.assert_allclose(xs[k, 0], x0)
        for t in range(5):
            x = dyn.step1(x, us[k, t])
            np.testing.assert_allclose(xs[k, t + 1], x, rtol=1e-12, atol=1e-12)


def test_batched_rollout_results_are_independent() -> None:
    """The fused rollout reuses one buffer per batch size: a returned prediction must not change with the next call."""
    system = get_system("friction")
    dyn = NumpyDynamics(system, perturbed("friction"), base=base_model_np(system))
    assert dyn.fused_rollout
    x0 = np.array([0.4, -0.2])
    us = np.linspace(-5.0, 5.0, 30).reshape(3, 10, 1)
    first = dyn.rollout_batch(x0, us)
    kept = first.copy()
    dyn.rollout_batch(-x0, -us)
    np.testing.assert_array_equal(first, kept)
    np.testing.assert_allclose(first[1], dyn.rollout_batch(x0, us[1:2])[0], rtol=1e-12, atol=1e-14)


@pytest.mark.parametrize(("kind", "hidden"), [("residual", (4, 2)), ("full", (4, 2)), ("residual", ()),
                                               ("residual", (3,))])
def test_fused_jacobians_equal_jacobians(kind: str, hidden: tuple[int, ...]) -> None:
    """The Jacobians read from a fused rollout's activation pattern are ``jacobians`` at that sequence's states."""
    system = get_system("friction")
    model = DynamicsModel(system, kind=kind, hidden=hidden, seed=3).double()
    gen = torch.Generator().manual_seed(3)
    with torch.no_grad():
        for w in model.net.weights:
            w.add_(0.5 * torch.randn(w.shape, generator=gen, dtype=w.dtype))
        for s in model.net.slopes:  # not ReLU: the masks' other value matters
            s.fill_(-0.3)
    dyn = NumpyDynamics(system, model, base=base_model_np(system))
    us = np.random.default_rng(0).uniform(-5.0, 5.0, (7, 10, 1))
    x0 = np.array([0.3, -0.5])
    assert dyn.fused_jacobians(7, 10, 0, dyn.fused_calls) is None  # nothing rolled out yet
    xs = dyn.rollout_batch(x0, us)
    stamp = dyn.fused_calls
    dyn.rollout_batch(x0, us[:3])  # another batch size keeps its own buffer
    patterns = set()
    for i in range(7):
        ab = dyn.fused_jacobians(7, 10, i, stamp)
        assert ab is not None
        a_ref, b_ref = dyn.jacobians(xs[i, :-1], us[i])
        np.testing.assert_allclose(ab[0], a_ref, rtol=1e-12, atol=1e-13)
        np.testing.assert_allclose(ab[1], b_ref, rtol=1e-12, atol=1e-13)
        patterns |= {tuple(r) for r in ab[1].reshape(10, -1).round(9)}
    assert len(patterns) >= (3 if hidden else 1)  # several activation patterns were met
    dyn.rollout_batch(-x0, -us)  # the same batch size again: that buffer now holds other sequences
    assert dyn.fused_jacobians(7, 10, 0, stamp) is None
    assert dyn.fused_jacobians(7, 10, 0, dyn.fused_calls) is not None


def test_fused_jacobians_need_a_small_network() -> None:
    """A network too wide for the pattern table (the quadrotor's full 16-8 model: 24 units) gives None."""
    system = get_system("quadrotor")
    dyn = NumpyDynamics(system, perturbed("quadrotor", kind="full"))
    assert dyn.fused_rollout
    x0, u = system.sample_inputs(8, np.random.default_rng(0))
    dyn.rollout_batch(x0[0], u.reshape(2, 4, -1))
    assert dyn.fused_jacobians(2, 4, 0, dyn.fused_calls) is None


def test_fast_solver_same_plan_with_fused_jacobians() -> None:
    """The fast friction solver reads its Jacobians from the start's and the line search's fused rollouts; the plans
    must be those it finds with NumpyDynamics.jacobians."""
    system = get_system("friction")
    model = perturbed("friction")
    ctrls = []
    for _ in range(2):
        ctrl = make_controller(system, model, "fast")
        assert isinstance(ctrl, SQPShootingMPC)
        ctrls.append(ctrl)
    ctrls[1].dyn.fused_jacobians = lambda k, horizon, i, stamp: None  # type: ignore[method-assign]
    calls = {"jac": 0}
    plain = ctrls[0].dyn.jacobians

    def counted(x: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        calls["jac"] += 1
        return plain(x, u)

    ctrls[0].dyn.jacobians = counted  # type: ignore[method-assign]
    iters = 0
    for p0 in (-1.5, -0.4, 0.3, 1.2):
        x = np.array([p0, 0.0])
        for _ in range(6):
            res = [ctrl.solve(x) for ctrl in ctrls]
            np.testing.assert_allclose(res[0].plan_u, res[1].plan_u, rtol=1e-9, atol=1e-9)
            assert res[0].iterations == res[1].iterations
            iters += res[0].iterations
            x = system.true_step_np(x, res[0].u)
    assert iters > 24 and calls["jac"] == 0  # every Jacobian came from a fused rollout


@pytest.mark.parametrize("scale", [0.5, 4.0, 400.0])
def test_batched_line_search_matches_sequential(scale: float) -> None:
    """The fast solver's line search rolls all step lengths out in one batched call when the model has a fused
    rollout; it must accept the same step length and trial point as the one-by-one search (large steps make it
    backtrack, the largest fails)."""
    system = get_system("friction")
    ctrl = make_controller(system, perturbed("friction"), "fast")
    assert isinstance(ctrl, SQPShootingMPC) and ctrl.dyn.fused_rollout
    rng = np.random.default_rng(0)
    task = ctrl.task
    seen = set()
    for _ in range(20):
        x0 = rng.uniform(-1.0, 1.0, 2)
        u = rng.uniform(-2.0, 2.0, (ctrl.horizon, 1))
        d = scale * rng.normal(size=ctrl.horizon)
        merit = ctrl._merit(ctrl.rollout(x0, u), task, 10.0)[0]
        pred = 0.5 * merit
        got = {}
        for fused in (True, False):
            ctrl.dyn.fused_rollout = fused
            ctrl.stats = {"rollouts": 0}
            got[fused] = ctrl._line_search(x0, u, d, merit, pred, task, 10.0)
        (a1, ok1, t1), (a2, ok2, t2) = got[True], got[False]
        assert (a1, ok1) == (a2, ok2)
        seen.add((a1, ok1))
        for v1, v2 in zip(t1, t2, strict=True):
            np.testing.assert_allclose(np.asarray(v1), np.asarray(v2), rtol=1e-10, atol=1e-12)
    assert len(seen) >= 2  # the problems exercise more than one outcome


def test_ensemble_uses_member_zero_and_rejects_other_systems() -> None:
    system = get_system("friction")
    ens = perturbed("friction", n_models=3)
    x, u = system.sample_inputs(5, np.random.default_rng(0))
    np.testing.assert_allclose(NumpyDynamics(system, ens, base=base_model_np(system)).step(x, u), ens.predict_np(x, u, member=0), atol=1e-12)
    assert not np.allclose(ens.predict_np(x, u, member=0), ens.predict_np(x, u, member=1))
    with pytest.raises(ValueError, match="model is for system"):
        make_controller(get_system("quadrotor"), ens)


# ------------------------------------------------------------------------------------------ QP subproblems
def test_box_qp_matches_lbfgsb() -> None:
    rng = np.random.default_rng(0)
    for _ in range(5):
        m = rng.normal(size=(12, 12))
        hess, grad = m @ m.T / 12 + 1e-3 * np.eye(12), rng.normal(size=12)
        lo, hi = -rng.uniform(0, 1, 12), rng.uniform(0, 1, 12)
        res = solve_box_qp(hess, grad, lo, hi)
        ref = scipy.optimize.minimize(lambda d, h=hess, g=grad: 0.5 * d @ h @ d + g @ d, np.zeros(12),
                                      jac=lambda d, h=hess, g=grad: h @ d + g, bounds=list(zip(lo, hi)),
                                      method="L-BFGS-B",
                                      options={"ftol": 1e-15, "gtol": 1e-12, "maxiter": 10_000})
        assert res.converged
        assert np.all(res.d >= lo) and np.all(res.d <= hi)
        assert 0.5 * res.d @ hess @ res.d + grad @ res.d <= ref.fun + 1e-9


@pytest.mark.parametrize("backend", QP_BACKENDS)
def test_elastic_qp_is_exact_when_feasible_and_prices_violations(backend: str) -> None:
    rng = np.random.default_rng(1)
    n, k = 8, 3
    m = rng.normal(size=(n, n))
    hess, grad = m @ m.T / n + 0.1 * np.eye(n), rng.normal(size=n)
    lo, hi = -np.ones(n), np.ones(n)
    g_mat = rng.normal(size=(k, n))
    h_vec = np.full(k, 0.05)  # d = 0 is feasible: with a large penalty the answer is the constrained optimum
    res = solve_qp(hess, grad, lo, hi, g_mat, h_vec, penalty=1e3, backend=backend)
    ref = scipy.optimize.minimize(lambda d: 0.5 * d @ hess @ d + grad @ d, np.zeros(n), jac=lambda d: hess @ d + grad,
                                  bounds=list(zip(lo, hi)), method="SLSQP",
                                  constraints=[{"type": "ineq", "fun": lambda d: h_vec - g_mat @ d}],
                                  options={"ftol": 1e-14, "maxiter": 500})
    assert res.converged
    np.testing.assert_allclose(res.d, ref.x, atol=1e-5)
    assert np.all(res.slack <= 1e-7) and np.all(res.mult >= 0)
    # infeasible rows (G d <= h with h << 0 beyond the box) are violated, never an error
    res = solve_qp(hess, grad, lo, hi, np.ones((1, n)), np.array([-100.0]), penalty=1.0, backend=backend)
    assert res.converged and res.slack[0] > 90.0


def _elastic_objective(hess: np.ndarray, grad: np.ndarray, g_mat: np.ndarray, h_vec: np.ndarray,
                       pen: np.ndarray, d: np.ndarray) -> float:
    return float(0.5 * d @ hess @ d + grad @ d + pen @ np.maximum(g_mat @ d - h_vec, 0.0))


@pytest.mark.skipif("daqp" not in QP_BACKENDS, reason="daqp not installed")
@pytest.mark.parametrize("hard_first", [True, False])
def test_qp_backends_agree_on_elastic_and_l1_problems(hard_first: bool) -> None:
    """DAQP and the interior point method reach the same optimum of the elastic QP, including rows whose
    price is below their multiplier (violated at the optimum) and exact-l1 LP rows (H = LM term only)."""
    rng = np.random.default_rng(7)
    for trial in range(30):
        n, k = 10, int(rng.integers(1, 12))
        m = rng.normal(size=(n, n))
        lp = trial % 3 == 0  # the friction subproblem: no curvature beyond a small LM term
        hess = 1e-3 * np.eye(n) if lp else m @ m.T / n + 1e-2 * np.eye(n)
        grad = rng.normal(size=n)
        lo, hi = -rng.uniform(0.1, 2, n), rng.uniform(0.1, 2, n)
        g_mat, h_vec = rng.normal(size=(k, n)), rng.normal(scale=0.5, size=k)
        pen = rng.uniform(0.05, 5.0, k)
        a = solve_qp(hess, grad, lo, hi, g_mat, h_vec, pen, backend="daqp", hard_first=hard_first)
        b = solve_qp(hess, grad, lo, hi, g_mat, h_vec, pen, backend="ipm")
        assert np.all(a.d >= lo) and np.all(a.d <= hi)
        fa, fb = (_elastic_objective(hess, grad, g_mat, h_vec, pen, r.d) for r in (a, b))
        assert fa <= fb + 1e-6 * (1 + abs(fb)), (trial, fa, fb)
        assert abs(fa - fb) <= 1e-5 * (1 + abs(fb)), (trial, fa, fb)
        assert np.all(a.mult >= 0) and np.all(a.mult <= pen * (1 + 1e-6))


@pytest.mark.skipif("daqp" not in QP_BACKENDS, reason="daqp not installed")
def test_l1qp_reused_workspace_matches_fresh_solves() -> None:
    """L1QP keeps one DAQP workspace and refreshes only what changed (the Hessian when the damping does, the cost
    vector when the gradient does): a sequence of solves with scalar and matrix Hessians, with and without a
    gradient and with the same damping twice, must give each problem's own optimum (the interior point method's
    on the same model as elastic rows)."""
    rng = np.random.default_rng(11)
    n, t = 10, 10
    for k in (0, 3):
        qp = L1QP(n, t, k)
        for call in range(12):
            j, r = rng.normal(size=(t, n)), rng.normal(size=t)
            lo, hi = -rng.uniform(0.1, 2, n), rng.uniform(0.1, 2, n)
            g_mat, h_vec, pen = rng.normal(size=(k, n)), rng.normal(scale=0.5, size=k), rng.uniform(0.5, 5.0, k)
            damp = (1e-3, 0.5, 0.5, 2.0)[call % 4]  # calls 1 -> 2: the same damping, Hessian not refreshed
            hess_arg: np.ndarray | float = damp if call % 3 else damp * np.eye(n)
            grad = rng.normal(size=n) if call in (4, 5) else None  # 6: back to no gradient
            d = qp.solve(hess_arg, grad, lo, hi, j, r, g_mat, h_vec, pen)
            assert d is not None and np.all(d >= lo) and np.all(d <= hi)
            g0 = np.zeros(n) if grad is None else grad
            ref = solve_qp(damp * np.eye(n), g0, lo, hi, np.vstack((j, -j, g_mat)), np.concatenate((-r, r, h_vec)),
                           np.concatenate((np.ones(2 * t), pen)), backend="ipm").d

            def obj(v: np.ndarray, g0: np.ndarray = g0, j: np.ndarray = j, r: np.ndarray = r, damp: float = damp,
                    g_mat: np.ndarray = g_mat, h_vec: np.ndarray = h_vec, pen: np.ndarray = pen) -> float:
                return float(0.5 * damp * v @ v + g0 @ v + np.abs(r + j @ v).sum()
                             + pen @ np.maximum(g_mat @ v - h_vec, 0.0))

            assert abs(obj(d) - obj(ref)) <= 1e-6 * (1 + abs(obj(ref))), (k, call, obj(d), obj(ref))


def test_l1_convergence_certificate_is_sound() -> None:
    """The fast friction solver skips its first QP when a dual bound proves that the QP's predicted decrease is below
    the threshold: whenever the bound says so, the QP's own prediction must be below it (and the bound must decide
    some of the problems, or it is dead code)."""
    system = get_system("friction")
    ctrl = make_controller(system, perturbed("friction"), "fast")
    assert isinstance(ctrl, SQPShootingMPC)
    ctrl.stats = dict.fromkeys(("daqp_qp", "ipm_qp"), 0)
    rng = np.random.default_rng(5)
    nu = ctrl.horizon
    decided = 0
    for trial in range(300):
        # residuals of all sizes, some tiny (a converged plan), sensitivities of all scales, controls at the bounds
        r1 = rng.normal(size=nu) * 10.0 ** rng.uniform(-6, 0, nu)
        j1 = rng.normal(size=(nu, nu)) * 10.0 ** rng.uniform(-5, -1)
        u_max = float(system.control_high[0])
        u = np.clip(rng.uniform(-1.5, 1.5, nu) * u_max, -u_max, u_max)
        lo, hi = -u_max - u, u_max - u
        damp = 10.0 ** rng.uniform(-3, 1)
        threshold = 3e-4 * (1.0 + float(np.abs(r1).sum()))
        ctrl._l1_rows, ctrl._l1_abs = (j1, r1), float(np.abs(r1).sum())
        _, pred = ctrl._l1_step(damp, lo, hi, np.zeros((0, nu)), np.zeros(0), np.zeros(0))
        if ctrl._l1_converged(damp, lo, hi, threshold):
            decided += 1
            assert pred <= threshold * (1 + 1e-9) + 1e-12, (trial, pred, threshold)
    assert 30 <= decided <= 270, decided


def test_qp_rejects_unknown_backend() -> None:
    with pytest.raises(ValueError, match="unknown QP backend"):
        solve_qp(np.eye(2), np.ones(2), -np.ones(2), np.ones(2), np.ones((1, 2)), np.zeros(1), 1.0, backend="osqp")


# ------------------------------------------------------------------------------------------ bounds, every solver
@pytest.mark.parametrize("name", SYSTEMS)
@pytest.mark.parametrize("solver", ["fast", "slsqp"])
def test_plans_respect_control_bounds(name: str, solver: str) -> None:
    system = get_system(name)
    model = perturbed(name)
    rng = np.random.default_rng(3)
    quad_slsqp = name == "quadrotor" and solver == "slsqp"
    ctrl = make_controller(system, model, solver, **({"max_iter": 15} if quad_slsqp else {}))
    x, _ = system.sample_inputs(1 if quad_slsqp else 3, rng)
    for xi in x:
        if name == "paddle_ball":
            xi[3:6] = (0.3, -0.2, -4.0)
        if name == "quadrotor":
            xi[2] = max(xi[2], 1.0)
        ctrl.reset()
        res = ctrl.solve(xi)
        lo, hi = system.control_low, system.control_high
        assert np.all(res.plan_u >= lo) and np.all(res.plan_u <= hi)
        assert np.all(res.u >= lo) and np.all(res.u <= hi)
        np.testing.assert_array_equal(res.u, res.plan_u[0])
        assert res.plan_u.shape == ((1, 6) if name == "paddle_ball" else (ctrl.horizon, system.control.size))
        assert math.isfinite(res.cost) and res.solve_time > 0 and res.iterations >= 1


# ------------------------------------------------------------------------------------------ friction
def test_friction_mpc_drives_true_system_to_origin() -> None:
    system = get_system("friction")
    out = closed_loop(system, make_controller(system), np.array([1.5, 0.0]), 30)
    assert out.xs.shape == (31, 2) and out.us.shape == (30, 1)
    assert abs(out.xs[-1, 0]) < 0.05 and abs(out.xs[-1, 1]) < 0.2
    assert np.all(np.abs(out.us) <= 10.0)
    np.testing.assert_allclose(out.stage_costs, np.abs(out.xs[1:, 0]))


def test_closed_loop_hook_sees_every_step() -> None:
    """The runner's on_step hook gets each step's state, result and true next state, in order; a controller
    warm-starts from the plan the previous step left (what bench_mpc records through the hook)."""
    system = get_system("friction")
    ctrl = make_controller(system)
    assert isinstance(ctrl, ShootingMPC)
    seen: list[LoopStep] = []
    warm: list[object] = []

    def record(st: LoopStep) -> None:
        seen.append(st)
        warm.append(ctrl.warm_start_plan())

    out = closed_loop(system, ctrl, np.array([1.2, 0.0]), 5, on_step=record)
    assert [st.index for st in seen] == list(range(5))
    for k, st in enumerate(seen):
        np.testing.assert_array_equal(st.x, out.xs[k])
        np.testing.assert_array_equal(st.x_next, out.xs[k + 1])
        np.testing.assert_array_equal(st.x_next, system.true_step_np(st.x, st.result.u))
        np.testing.assert_array_equal(st.result.u, out.us[k])
        assert st.result.cost == out.costs[k] and st.cpu_time == out.cpu_times[k] >= 0.0
        plan = warm[k]
        assert isinstance(plan, tuple)
        np.testing.assert_array_equal(plan[0], st.result.plan_u)
    # paddle ball: x_next is the next pre-impact state, where the ball lands
    system = get_system("paddle_ball")
    steps: list[LoopStep] = []
    run = closed_loop(system, make_controller(system), np.array([0.1, -0.1, 0.0, 0.2, 0.1, -4.0]), 2,
                      on_step=steps.append)
    assert run.landing is not None and len(steps) == len(run.landing) == 2
    for k, st in enumerate(steps):
        np.testing.assert_array_equal(st.x_next[:2], run.landing[k])
        assert st.x_next[2] == st.x[2] and st.x_next[5] < 0.0


def test_friction_learned_model_escapes_stiction() -> None:
    # a model with stiction around u = 0 has no gradient there: the cold start must not stay at rest
    system = get_system("friction")
    x, u, y = system.make_dataset(4000, np.random.default_rng(0))
    model = DynamicsModel(system, seed=0).double()
    model.fit_normalization(x, u, y)
    opt = torch.optim.Adam(model.parameters(), lr=1e-2)
    xt, ut, yt = (torch.as_tensor(a) for a in (x, u, y))
    for _ in range(300):
        opt.zero_grad()
        loss = ((model(xt, ut)[0] - yt) ** 2).sum(-1).mean()
        loss.backward()
        opt.step()
    res = make_controller(system, model).solve(np.array([1.5, 0.0]))
    assert res.u[0] < -5.0 and res.success


def test_fast_and_slsqp_agree_on_friction() -> None:
    system = get_system("friction")
    # base model: the problem is an LP (linear dynamics, l1 cost), solved exactly by linprog; the fast solver
    # must find its optimum, SLSQP (finite differences on a non-smooth cost) at best the same
    T, dt = 10, system.dt
    for p0 in (-1.7, -0.4, 0.9, 1.8):
        x0 = np.array([p0, 0.3])
        fast = make_controller(system, None, "fast").solve(x0)
        ref = make_controller(system, None, "slsqp").solve(x0)
        assert fast.success and ref.success
        # p_t = p0 + t dt v0 + dt^2 sum_{j <= t-2} (t-1-j) u_j;  variables [u (T), e (T)], min sum e, |p_t| <= e_t
        sens = np.array([[dt * dt * max(t - 1 - j, 0) for j in range(T)] for t in range(1, T + 1)])
        free = p0 + dt * x0[1] * np.arange(1, T + 1)
        a_ub = np.block([[sens, -np.eye(T)], [-sens, -np.eye(T)]])
        lp = scipy.optimize.linprog(np.r_[np.zeros(T), np.ones(T)], A_ub=a_ub, b_ub=np.r_[-free, free],
                                    bounds=[(-10, 10)] * T + [(0, None)] * T, method="highs")
        assert abs(fast.cost - lp.fun) <= 5e-4 * (1.0 + lp.fun)  # the SQP stops at tol = 3e-4 (1 + merit)
        assert ref.cost >= lp.fun - 1e-6 and fast.cost <= ref.cost + 5e-4 * (1.0 + lp.fun)
    # a non-convex learned model: the fast solver is never worse than the reference
    model = perturbed("friction", scale=0.1)
    for p0 in (-1.7, -0.4, 0.9, 1.8):
        x0 = np.array([p0, 0.3])
        fast = make_controller(system, model, "fast").solve(x0)
        ref = make_controller(system, model, "slsqp").solve(x0)
        assert fast.success and ref.success
        assert fast.cost <= ref.cost + 0.01 * max(1.0, ref.cost)


# ------------------------------------------------------------------------------------------ quadrotor
def test_quadrotor_lands_and_keeps_height_bound() -> None:
    system = get_system("quadrotor")
    ctrl = make_controller(system)
    ctrl.reset()
    x = system.hover_state((1.0, -1.0, 2.0))  # type: ignore[attr-defined]
    for _ in range(50):
        res = ctrl.solve(x)
        # the height bound holds on every predicted state a control can move (x_1 is fixed by x_0)
        assert res.plan_x[2:, 2].min() >= 0.2 - 1e-4
        assert abs(res.plan_x[-1, 6] - 1.0) <= 0.05 + 1e-4
        assert res.success or "unavoidable" in res.message
        x = system.true_step_np(x, res.u)
    assert np.linalg.norm(x[:3] - np.array([0.0, 0.0, 0.2])) < 0.15


def test_quadrotor_goal_and_reported_violations() -> None:
    system = get_system("quadrotor")
    ctrl = make_controller(system)
    x = system.hover_state((0.0, 0.0, 0.21))  # type: ignore[attr-defined]
    x[5] = -1.0  # pz_1 = 0.11 < 0.2 whatever the controls: reported, not hidden
    res = ctrl.solve(x)
    assert not res.success and "unavoidable" in res.message and res.constraint_violation > 0.08
    assert res.unavoidable  # pz_1 is the only row violated
    assert np.all(res.plan_u >= 0.0) and np.all(res.plan_u <= 10.0)
    x = system.hover_state((0.0, 0.0, 0.6))  # type: ignore[attr-defined]
    x[5] = -4.0  # pz_1 = 0.2 holds, pz_2 breaks it even at full thrust: a row the controls move, not "unavoidable"
    res = make_controller(system).solve(x)
    assert not res.success and not res.unavoidable and "pz_2" in res.message and np.all(res.u == 10.0)
    res = make_controller(system).solve(system.hover_state((1.0, 1.0, 1.0)), goal=np.array([1.0, 1.0, 1.0]))  # type: ignore[attr-defined]
    assert res.success and not res.unavoidable and res.cost < 0.05  # hovering at the goal is (nearly) free


# ------------------------------------------------------------------------------------------ paddle ball
def test_paddle_hits_target_under_the_model() -> None:
    system = get_system("paddle_ball")
    model = perturbed("paddle_ball", scale=0.05)
    ctrl = make_controller(system, model)
    rng = np.random.default_rng(4)
    for _ in range(4):
        x = np.array([rng.uniform(-0.5, 0.5), rng.uniform(-0.5, 0.5), 0.0, rng.uniform(-0.5, 0.5),
                      rng.uniform(-0.5, 0.5), rng.uniform(-5.0, -3.0)])
        goal = paddle_goal(target_xy=rng.uniform(-0.5, 0.5, 2), roll=(-0.3, 0.3), pitch=(-0.35, 0.35),
                           v_rel=(3.0, 5.0))
        res = ctrl.solve(x, goal)
        assert res.success, res.message
        v_post = model.predict_np(x, res.u)  # check independently with the torch model
        land = landing_point(torch.as_tensor(x[None, :3]), torch.as_tensor(v_post[None]), system.g).numpy()[0]  # type: ignore[attr-defined]
        assert np.linalg.norm(land - goal.target_xy) < 0.03
        assert abs(res.cost - np.linalg.norm(land - goal.target_xy)) < 1e-9
        speed = np.linalg.norm(x[3:6] - res.u[:3])
        assert 3.0 - 1e-6 <= speed <= 5.0 + 1e-6
        n = res.u[3:6]
        assert abs(np.linalg.norm(n) - 1.0) < 1e-12
        roll, pitch = math.atan2(-n[1], math.hypot(n[0], n[2])), math.atan2(n[0], n[2])
        assert -0.3 - 1e-9 <= roll <= 0.3 + 1e-9 and -0.35 - 1e-9 <= pitch <= 0.35 + 1e-9
        np.testing.assert_allclose(res.plan_x[0, 3:], v_post, atol=1e-12)


def test_paddle_goal_validation_and_closed_loop() -> None:
    with pytest.raises(ValueError, match="v_rel"):
        paddle_goal(v_rel=(5.0, 3.0))
    with pytest.raises(ValueError, match="no key"):
        paddle_goal({"target": (0, 0)})
    assert paddle_goal({"target_xy": (0.2, 0.1)}).roll == (-0.4, 0.4)
    system = get_system("paddle_ball")
    x0 = np.array([0.1, -0.1, 0.0, 0.2, 0.1, -4.0])
    out = closed_loop(system, make_controller(system), x0, 3, goal={"target_xy": (0.0, 0.0)})
    assert out.landing is not None
    assert out.xs.shape[1] == 6 and out.landing.shape[1] == 2 and not out.dropped
    # the base model's restitution is wrong (0.6 vs 0.8) and the paddle has a hidden tilt: the true ball misses
    assert out.stage_costs.max() > 0.05


# ------------------------------------------------------------------------------------------ hot swap, warm start
def test_set_model_hot_swap_and_warm_start() -> None:
    system = get_system("quadrotor")
    ctrl = make_controller(system)
    assert isinstance(ctrl, ShootingMPC)
    x = system.hover_state((1.0, -1.0, 2.0))  # type: ignore[attr-defined]
    first = ctrl.solve(x)
    again = ctrl.solve(x)  # same state, same model: starts from the converged plan
    assert again.iterations < first.iterations and again.iterations <= 2
    assert abs(again.cost - first.cost) < 1e-3
    model = perturbed("quadrotor", scale=0.5)
    ctrl.set_model(model)
    assert ctrl.warm_start_plan() is not None  # the swap keeps the warm start
    swapped = ctrl.solve(x)
    assert not np.allclose(swapped.plan_u, again.plan_u, atol=1e-3)
    np.testing.assert_allclose(swapped.plan_x, ctrl.rollout(x, swapped.plan_u))
    np.testing.assert_allclose(swapped.plan_x[1], model.predict_np(x, swapped.u), atol=1e-10)
    ctrl.set_model(None)
    back = ctrl.solve(x)
    assert abs(back.cost - first.cost) < 0.05
    ctrl.reset()
    assert ctrl.warm_start_plan() is None


# ------------------------------------------------------------------------------------------ failures
@pytest.mark.parametrize("name", SYSTEMS)
def test_numerical_failure_returns_safe_control(name: str) -> None:
    system = get_system(name)
    ctrl = make_controller(system)
    x, _ = system.sample_inputs(1, np.random.default_rng(0))
    res = ctrl.solve(np.full(system.state.size, np.nan))
    assert not res.success and np.all(np.isfinite(res.u))
    assert np.all(res.u >= system.control_low) and np.all(res.u <= system.control_high)
    bad = perturbed(name)
    with torch.no_grad():
        bad.net.weights[0].fill_(float("nan"))
    ctrl.set_model(bad)
    res = ctrl.solve(x[0])
    assert not res.success and np.all(res.u >= system.control_low) and np.all(res.u <= system.control_high)
    with pytest.raises(ValueError, match="shape"):
        ctrl.solve(np.zeros(system.state.size + 1))


def test_make_controller_rejects_bad_arguments() -> None:
    with pytest.raises(ValueError, match="unknown MPC solver"):
        make_controller(get_system("friction"), solver="ipopt")
    with pytest.raises(TypeError, match="no option"):
        make_controller(get_system("quadrotor"), min_heigth=0.3)
    assert make_controller(get_system("paddle_ball"), horizon=10).horizon == 1  # one-shot: horizon ignored
