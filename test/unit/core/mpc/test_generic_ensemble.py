"""The generic planner with an ensemble (saml_ros.core.mpc.generic; docs/mpc.md, "The generic planner"): planned by
the mean of its members (solver option ``ensemble: mean``) with exact values, Jacobians and whole-horizon rollouts
of that mean; the disagreement cost (``cost.disagreement``: the members' variance of the one-step prediction along
the plan) checked at load naming the key, with the exact gradient in the SQP's model, and a plan that keeps where
the members agree; both off by default."""

from __future__ import annotations

import copy
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
import yaml

from saml_ros.core.model.network import DynamicsModel
from saml_ros.core.mpc.generic import GenericSQP
from saml_ros.core.mpc.generic.dynamics import EnsembleMeanMLP, GenericDynamics, make_base
from saml_ros.core.mpc.generic.section import MPCSectionError, mpc_task
from saml_ros.core.mpc.generic.sqp import _condense
from saml_ros.systems.system_file import FileSystem, SystemFileError, parse_definition
from saml_ros.user_code import resolve_base_model

REPO = Path(__file__).resolve().parents[4]
EXAMPLE = REPO / "examples" / "diff_drive" / "system.yaml"


#: robots these tests load from system files are forgotten after each test (test/conftest.py)
pytestmark = pytest.mark.usefixtures("restore_registry")


def example(**cost: Any) -> dict[str, Any]:
    raw = yaml.safe_load(EXAMPLE.read_text())
    raw["mpc"]["cost"].update(cost)
    return raw


def build(raw: dict[str, Any]) -> FileSystem:
    return FileSystem(parse_definition(raw, "test.yaml", None), "test.yaml", resolve=resolve_base_model)


def ensemble(system: FileSystem, members: int = 4, seed: int = 0, scale: float = 0.3) -> DynamicsModel:
    """A residual ensemble with a fitted normalisation and different (random) last layers: members that disagree."""
    m = DynamicsModel(system, (16, 16), "residual", n_models=members, seed=seed).double()
    rng = np.random.default_rng(seed)
    x, u = system.sample_inputs(2000, rng)
    m.fit_normalization(x, u, system.base_step_np(x, u) + 0.01 * rng.normal(size=x.shape))
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        m.net.weights[-1].copy_(torch.randn(m.net.weights[-1].shape, generator=gen, dtype=torch.float64) * scale)
    return m


def _fd(f: Any, z: np.ndarray, eps: float = 1e-6) -> np.ndarray:
    return np.stack([(f(z + eps * e) - f(z - eps * e)) / (2 * eps) for e in np.eye(z.size)], axis=-1)


def test_ensemble_planned_by_the_mean_of_its_members() -> None:
    s = build(example())
    model = ensemble(s)
    base = make_base(s)
    mean = GenericDynamics(s, base, model, ensemble_mean=True)
    assert isinstance(mean.mlp, EnsembleMeanMLP) and "the mean of the ensemble's 4 members" in mean.describe()
    rng = np.random.default_rng(3)
    x, u = s.sample_inputs(6, rng)
    x[0, 2] = 3.1  # near the wrap of the angle
    want = np.mean([model.predict_np(x, u, i) for i in range(4)], axis=0)
    y, a, b = mean.step_jac(x, u)
    np.testing.assert_allclose(y, want, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(mean.step(x, u), want, rtol=1e-10, atol=1e-12)
    for i in range(len(x)):  # the mean's exact Jacobians
        xi, ui = x[i:i + 1], u[i:i + 1]
        np.testing.assert_allclose(a[i], _fd(lambda z, ui=ui: mean.step(z[None], ui)[0], x[i]), atol=2e-6)
        np.testing.assert_allclose(b[i], _fd(lambda z, xi=xi: mean.step(xi, z[None])[0], u[i]), atol=2e-6)
    # the whole-horizon rollouts (one CasADi call: every member's numbers in its weight vector) predict the mean
    us = rng.uniform(s.control_low, s.control_high, (20, 2))
    steps = [x[1]]
    for t in range(20):
        steps.append(np.mean([model.predict_np(steps[-1], us[t], i) for i in range(4)], axis=0))
    np.testing.assert_allclose(mean.rollout(x[1], us), np.array(steps), rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(mean.rollout_batch(x[1], np.stack([us, us[::-1]]))[0], np.array(steps), rtol=1e-9,
                               atol=1e-12)
    # one member is not the mean, and a model of one member is planned as itself
    one = GenericDynamics(s, base, model, member=2)
    assert np.abs(one.step(x, u) - want).max() > 1e-6
    single = model.member(2).double()
    np.testing.assert_allclose(GenericDynamics(s, base, single, ensemble_mean=True).step(x, u), one.step(x, u),
                               rtol=1e-8, atol=1e-10)
    # the planner option: default the member, 'mean' the mean; a hot swap keeps the mode; anything else is refused
    assert not GenericSQP(s, model).plans_mean
    ctrl = GenericSQP(s, model, ensemble="mean")
    assert ctrl.plans_mean and "mean of the ensemble's 4 members" in ctrl.describe()
    np.testing.assert_allclose(ctrl.dyn.step(x, u), want, rtol=1e-10, atol=1e-12)
    ctrl.set_model(ensemble(s, 3, seed=1))
    assert "mean of the ensemble's 3 members" in ctrl.describe()
    res = ctrl.solve(np.array([1.0, 0.1, 0.2, 0.0, 0.0]))
    assert np.all(np.isfinite(res.plan_x)) and np.all(np.isfinite(res.u))
    with pytest.raises(ValueError, match="solver option ensemble must be one of"):
        GenericSQP(s, model, ensemble="median")
    file_mean = build(_with(example(), solver_options={"ensemble": "mean"}))
    assert GenericSQP(file_mean, model).plans_mean


def _with(raw: dict[str, Any], **mpc: Any) -> dict[str, Any]:
    raw = copy.deepcopy(raw)
    raw["mpc"].update(mpc)
    return raw


@pytest.mark.parametrize("value, message", [
    ({"z": 1.0}, r"mpc.cost.disagreement.z: 'z' is not a state field"),
    ({"x": -1.0}, r"mpc.cost.disagreement.x: must be >= 0"),
    ([1.0], r"mpc.cost.disagreement: expected a mapping of state field -> weight"),
])
def test_bad_disagreement_cost_names_the_key(value: Any, message: str) -> None:
    with pytest.raises((MPCSectionError, SystemFileError), match=message):
        build(example(disagreement=value))


def test_disagreement_cost_exact_gradient_and_a_plan_where_the_members_agree() -> None:
    s = build(example())
    default = mpc_task(s.definition)
    assert default is not None and default.w_disagreement.size == 0  # off by default
    weights = {"x": 3e4, "y": 3e4, "yaw": 30.0}
    sd = build(example(disagreement=weights))
    task = mpc_task(sd.definition)
    assert task is not None
    np.testing.assert_array_equal(task.w_disagreement, [3e4, 3e4, 30.0, 0.0, 0.0])
    model = ensemble(s, scale=0.5)
    x0 = np.array([0.8, 0.05, 0.1, 0.2, 0.0])
    rng = np.random.default_rng(4)
    for mode in ("mean", "member"):
        ctrl = GenericSQP(sd, model, ensemble=mode, smoothing=0.0, max_iter=30)
        assert "disagreement cost on x, y, yaw" in ctrl.describe()
        us = rng.uniform(-0.4, 0.4, (ctrl.horizon, 2))

        def cost(z: np.ndarray, c: GenericSQP = ctrl) -> float:
            u = z.reshape(-1, 2)
            return c._disagreement_cost(c.dyn.rollout(x0, u), u)

        xs = ctrl.dyn.rollout(x0, us)
        dev = ctrl.dyn.deviations(xs[:-1], us)
        assert dev is not None
        w = np.array([3e4, 3e4, 30.0])
        assert cost(us.ravel()) == pytest.approx(float((w * dev[:, :, :3] ** 2).sum()) / 4, rel=1e-12)
        _, a, b = ctrl.dyn.step_jac(xs[:-1], us)
        got = ctrl._disagreement_model(xs, us, _condense(a, b))
        assert got is not None
        r, jac = got
        assert r @ r == pytest.approx(cost(us.ravel()), rel=1e-12)
        grad = 2.0 * jac.T @ r
        np.testing.assert_allclose(grad, _fd(cost, us.ravel()), rtol=1e-5, atol=1e-7 * np.abs(grad).max())
    # the planner trades a little progress for a plan where the members agree: less disagreement than without it
    plain = GenericSQP(s, model, ensemble="mean", max_iter=30)
    penalised = GenericSQP(sd, model, ensemble="mean", max_iter=30)
    p0, p1 = plain.solve(x0), penalised.solve(x0)
    assert p1.cost > 0 and np.isfinite(p0.cost)
    assert penalised._disagreement_cost(p1.plan_x, p1.plan_u) < 0.9 * penalised._disagreement_cost(p0.plan_x, p0.plan_u)
    # a model of one member has nothing to disagree with: the term is 0, and the planner says so
    one = GenericSQP(sd, model.member(0).double())
    assert "disagreement cost off" in one.describe() and one._disagreement_cost(p0.plan_x, p0.plan_u) == 0.0
    # the IPOPT path does not take it yet, and says so
    from saml_ros.core.mpc.generic.nlp import CasadiNLP

    with pytest.raises(ValueError, match="cost.disagreement"):
        CasadiNLP(sd, model)
