"""The friction MPC's initial guess (ShootingMPC._warm_start, shooting.tasks.push_brake_sequences): a model with a dead
zone (friction holds the cart at rest for small |u|, so the predicted cost is flat around u = 0) must not trap
either solver at rest, neither on a cold start nor when the previous plan rests."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from saml_ros.core.model.network import DynamicsModel
from saml_ros.core.mpc import closed_loop, make_controller
from saml_ros.core.mpc.factory import make_task
from saml_ros.core.mpc.shooting import ShootingMPC
from saml_ros.core.mpc.shooting.sqp import SQPShootingMPC
from saml_ros.core.mpc.shooting.tasks import push_brake_sequences
from saml_ros.core.systems import get_system
from saml_ros.systems.friction.model import FrictionDoubleIntegrator

SYSTEM = FrictionDoubleIntegrator()
#: friction deceleration of the dead-zone model (m/s^2): the true sticky patch near p = 0.3 m has ~3
MU = 3.0


def dead_zone_model(mu: float = MU) -> DynamicsModel:
    """A residual 2-unit ReLU model that is exactly Coulomb friction of ``mu`` m/s^2 everywhere:
    ``v' = sign(w) max(|w| - b, 0)`` with ``w = v + dt u``, ``b = dt mu``, i.e. ``phi_v = -clip(w, -b, b)``
    ``= relu(w - b) - relu(w + b) + b``. At rest, ``|u| < mu`` leaves the cart where it is with dv'/du = 0."""
    b = SYSTEM.dt * mu
    model = DynamicsModel(SYSTEM, hidden=(2,), kind="residual").double()
    net = model.net
    with torch.no_grad():
        for p in net.parameters():
            p.zero_()  # slope 0: ReLU
        net.weights[0][0, 1, :] = 1.0  # input [p, v, u] -> both units see w = v + dt u
        net.weights[0][0, 2, :] = SYSTEM.dt
        net.biases[0][0, 0] = torch.tensor([b, -b], dtype=torch.float64)
        net.weights[1][0, 0, 1] = -1.0
        net.weights[1][0, 1, 1] = 1.0
        net.biases[1][0, 0, 1] = b
    return model


def rest_cost(ctrl: ShootingMPC, x0: np.ndarray) -> float:
    """Predicted cost of u = 0 for the whole horizon."""
    return ctrl.task.cost(ctrl.rollout(x0, np.zeros((ctrl.horizon, 1))))


def test_dead_zone_model_is_a_dead_zone() -> None:
    model = dead_zone_model()
    x = np.tile([0.15, 0.0], (5, 1))
    u = np.array([[0.0], [0.9 * MU], [-0.9 * MU], [5.0], [-10.0]])
    pred = model.predict_np(x, u)
    np.testing.assert_allclose(pred[:3], np.tile([0.15, 0.0], (3, 1)), atol=1e-12)
    np.testing.assert_allclose(pred[3:, 1], [0.1 * (5.0 - MU), 0.1 * (-10.0 + MU)], atol=1e-12)


@pytest.mark.parametrize("solver", ["fast", "slsqp"])
@pytest.mark.parametrize("p0", [0.15, -0.15])
def test_cold_start_leaves_the_dead_zone(solver: str, p0: float) -> None:
    # from rest the constant guesses {0, +-5, +-10} all predict more cost than staying (they overshoot), so the
    # old start was u = 0 and both solvers stopped there at once
    ctrl = make_controller(SYSTEM, dead_zone_model(), solver)
    assert isinstance(ctrl, ShootingMPC)
    x0 = np.array([p0, 0.0])
    res = ctrl.solve(x0)
    assert res.success
    assert -np.sign(p0) * res.u[0] > MU  # pushes toward the goal, out of the dead zone
    assert res.cost < 0.5 * rest_cost(ctrl, x0)
    assert abs(res.plan_x[-1, 0]) < 0.5 * abs(p0)


@pytest.mark.parametrize("solver", ["fast", "slsqp"])
def test_resting_previous_plan_does_not_trap(solver: str) -> None:
    # closed loop: the cart came to rest in the dead zone and the previous plan rests too (shifted: still rest)
    ctrl = make_controller(SYSTEM, dead_zone_model(), solver)
    assert isinstance(ctrl, ShootingMPC)
    x0 = np.array([0.15, 0.0])
    ctrl.set_warm_start(np.zeros((ctrl.horizon, 1)), np.tile(x0, (ctrl.horizon + 1, 1)))
    res = ctrl.solve(x0)
    assert res.u[0] < -MU and res.cost < 0.5 * rest_cost(ctrl, x0)


@pytest.mark.parametrize("solver", ["fast", "slsqp"])
def test_closed_loop_from_dead_zone_reaches_goal(solver: str) -> None:
    out = closed_loop(SYSTEM, make_controller(SYSTEM, dead_zone_model(), solver), np.array([0.15, 0.0]), 30)
    assert abs(out.xs[-1, 0]) < 0.05
    assert np.all(np.abs(out.us) <= SYSTEM.u_max)


def test_converged_plan_wins_the_start_of_a_re_solve() -> None:
    # the previous (converged) plan is never worse than the candidates it started from: a re-solve of the same
    # state starts there and stops at once
    ctrl = make_controller(SYSTEM, dead_zone_model())
    x0 = np.array([0.4, 0.0])
    first = ctrl.solve(x0)
    again = ctrl.solve(x0)
    assert again.iterations <= 2 and again.cost <= first.cost + 1e-9
    np.testing.assert_allclose(again.plan_u, first.plan_u, atol=1e-6)


def test_push_brake_candidates() -> None:
    u_max = SYSTEM.u_max
    seqs = push_brake_sequences(u_max, 10)[:, :, 0]
    assert seqs.shape == (41, 10) and np.all(np.abs(seqs) <= u_max)
    assert np.all(seqs[0] == 0.0)  # rest first: ties go to staying
    assert len({tuple(s) for s in seqs}) == len(seqs)
    rows = {tuple(s) for s in seqs}
    for c in (0.5, -0.5, 1.0, -1.0):
        assert tuple(np.full(10, c * u_max)) in rows
    # push 2 steps at -u_max/4, brake 2 steps at +u_max/4, then rest
    assert tuple(np.r_[[-2.5, -2.5, 2.5, 2.5], np.zeros(6)]) in rows
    assert push_brake_sequences(u_max, 1).shape == (7, 1, 1)  # 0, +-5, +-10, +-2.5 (duplicates dropped)
    for horizon in (1, 3, 20):
        task = make_task(SYSTEM, horizon)
        assert task.u_starts.shape[1:] == (horizon, 1) and task.starts_every_solve
    # the quadrotor keeps its single hover start, used only without a previous plan (its solve stays as fast)
    quad = get_system("quadrotor")
    qtask = make_task(quad, 10)
    assert qtask.u_starts.shape == (1, 10, 4) and not qtask.starts_every_solve
    np.testing.assert_allclose(qtask.u_starts[0], np.tile(quad.hover_thrust(), (10, 1)))  # type: ignore[attr-defined]


def test_start_scores_match_cost_and_violations() -> None:
    # the batched rollout + score of the warm start equals one rollout, cost and check per sequence
    quad = get_system("quadrotor")
    ctrl = make_controller(quad, horizon=5)
    assert isinstance(ctrl, ShootingMPC)
    task = ctrl.task
    x0 = quad.hover_state((0.5, 0.0, 0.25))  # type: ignore[attr-defined]
    seqs = np.random.default_rng(0).uniform(0.0, 6.0, (4, 5, 4))
    seqs[0] = 0.0  # falls below the 0.2 m height bound
    seqs[1, :, :2] = 10.0  # tilts: violates the attitude bound
    xs = np.stack([ctrl.rollout(x0, s) for s in seqs])
    want = [task.cost(x) + 100.0 * np.maximum(task.violations(x), 0.0).sum() for x in xs]
    np.testing.assert_allclose(task.start_scores(xs), want, rtol=1e-12)
    np.testing.assert_allclose(task.start_scores(ctrl._rollout_batch(x0, seqs)), want, rtol=1e-9)
    assert task.violations(xs[0])[:-1].max() > 0 and task.violations(xs[1])[-1] > 0  # penalties exercised


def test_l1_certificate_keeps_the_plans() -> None:
    """The fast solver skips its first QP when a dual bound proves convergence (SQPShootingMPC._l1_converged): with a
    dead-zone model (flat predicted cost at rest, where it decides) closed loops must plan as well as without it (the
    same cost: the model's flat regions make the optimal controls not unique, and the QP workspace's warm start
    differs when a QP is skipped)."""
    ctrls = []
    for _ in range(2):
        ctrl = make_controller(SYSTEM, dead_zone_model(), "fast")
        assert isinstance(ctrl, SQPShootingMPC)
        ctrls.append(ctrl)
    ctrls[1]._l1_converged = lambda damp, lo, hi, threshold: False  # type: ignore[method-assign]
    certified = 0
    for p0 in (-1.5, -0.4, 0.3, 1.2):
        x = np.array([p0, 0.0])
        for _ in range(15):
            res = [ctrl.solve(x) for ctrl in ctrls]
            certified += ctrls[0].stats["certified"]
            assert res[0].success and res[1].success
            assert abs(res[0].cost - res[1].cost) <= 1e-8 * (1.0 + res[1].cost), (p0, res[0].cost, res[1].cost)
            x = SYSTEM.true_step_np(x, res[0].u)
    assert certified >= 5
