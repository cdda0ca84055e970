"""The generic MPC of a robot described by a system file (saml_ros.core.mpc.generic; docs/your_robot.md, "Control
it"): the ``mpc:`` section is checked at load naming the key, f_hat's array-namespace forms equal the torch base
models, the planner's derivatives are exact (finite differences), it plans what the task asks (goal, angles the short
way, constraints), a hot swap changes the plan without rebuilding anything, the reference path agrees with it, goals
and references from messages are checked, and the MPC service answers a stale state with the safe command."""

from __future__ import annotations

import copy
import math
import sys
import textwrap
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
import yaml

from msg_schemas import RCLPY
from saml_ros.core.dynamics.base_forms import NUMPY, TORCH, builtin_form
from saml_ros.core.model.network import DynamicsModel
from saml_ros.core.mpc.generic import GenericSQP
from saml_ros.core.mpc.generic.dynamics import GenericDynamics, SymbolicBase, TorchBase, make_base
from saml_ros.core.mpc.generic.goals import GoalRefused, GoalTracker
from saml_ros.core.mpc.generic.section import mpc_task
from saml_ros.systems.system_file import FileSystem, SystemFileError, parse_definition
from saml_ros.user_code import load_system_file, resolve_base_model

REPO = Path(__file__).resolve().parents[4]
EXAMPLE = REPO / "examples" / "diff_drive" / "system.yaml"


#: robots these tests load from system files are forgotten after each test (test/conftest.py)
pytestmark = pytest.mark.usefixtures("restore_registry")


def example() -> dict[str, Any]:
    return yaml.safe_load(EXAMPLE.read_text())


def build(raw: dict[str, Any], tmp: Path | None = None) -> FileSystem:
    return FileSystem(parse_definition(raw, "test.yaml", tmp), "test.yaml", resolve=resolve_base_model)


def mutate(path: str, value: Any) -> dict[str, Any]:
    raw = copy.deepcopy(example())
    *keys, last = path.split(".")
    node: Any = raw
    for k in keys:
        node = node[int(k)] if k.isdigit() else node[k]
    if value is KeyError:
        del node[int(last) if last.isdigit() else last]
    elif last.isdigit():
        node[int(last)] = value
    else:
        node[last] = value
    return raw


def fitted_model(system: FileSystem, hidden: tuple[int, ...] = (32, 32), members: int = 1, seed: int = 0,
                 scale: float = 0.3) -> DynamicsModel:
    """A residual model with a fitted normalisation and a non-trivial (random) last layer."""
    m = DynamicsModel(system, hidden, "residual", n_models=members, seed=seed).double()
    rng = np.random.default_rng(seed)
    x, u = system.sample_inputs(2000, rng)
    y = system.base_step_np(x, u) + 0.01 * rng.normal(size=x.shape)
    m.fit_normalization(x, u, y)
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        m.net.weights[-1].copy_(torch.randn(m.net.weights[-1].shape, generator=gen, dtype=torch.float64) * scale)
    return m


# ------------------------------------------------------------------------------------------ the section
BAD: list[tuple[str, Any, str]] = [
    ("mpc.horizon", 0, r"mpc.horizon: expected an integer in \[1, 200\]"),
    ("mpc.horizon", 2.5, r"mpc.horizon: expected an integer"),
    ("mpc.rate", "fast", r"mpc.rate: expected a finite number, got 'fast'"),
    ("mpc.rate", -5, r"mpc.rate: must be > 0"),
    ("mpc.state_timeout", 0, r"mpc.state_timeout: must be > 0"),
    ("mpc.colour", "red", r"mpc: unknown key\(s\) \['colour'\]"),
    ("mpc.goal", KeyError, r"mpc: missing key\(s\) \['goal'\]"),
    ("mpc.goal.fields", ["x", "yw"], r"mpc.goal.fields\[1\]: 'yw' is not a state field \(did you mean 'yaw'\?\)"),
    ("mpc.goal.fields", ["x", "x"], r"mpc.goal.fields\[1\]: field 'x' is listed twice"),
    ("mpc.goal.default", [1.5, 0.0], r"mpc.goal.default: expected 5 value\(s\), one per goal field"),
    ("mpc.goal.default", [9.0, 0.0, 0.0, 0.0, 0.0], r"mpc.goal.default\[0\]: x = 9 is outside its bounds"),
    ("mpc.goal.default", [1.0, math.nan, 0.0, 0.0, 0.0], r"mpc.goal.default\[1\]: expected a finite number"),
    ("mpc.goal.bounds", {"x": [-3.0, 1.0]}, r"mpc.goal.bounds.x: \[-3, 1\] goes beyond the bounds \[-2.5, 2.5\]"),
    ("mpc.goal.bounds", {"x": [-1.0, 1.0]}, r"mpc.goal.default\[0\]: x = 1.5 is outside its bounds \[-1, 1\]"),
    ("mpc.goal.type", "geometry_msgs/msg/PoseStampd", r"mpc.goal.type: .*unknown message type"),
    ("mpc.goal.paths", {"x": "pose.positon.x"}, r"mpc.goal.paths.x: .*no field 'positon'"),
    ("mpc.goal.paths", {"yaw": "pose.position.z"}, r"mpc.goal.paths.yaw: field 'yaw' is in 'rad', but "
                                                   r"pose.position.z of geometry_msgs/msg/PoseStamped is in 'm'"),
    ("mpc.goal.paths", {"speed": "pose.position.x"}, r"mpc.goal.paths.speed: 'speed' is not a goal field"),
    ("mpc.goal.topic", "goal pose", r"mpc.goal.topic: 'goal pose' is not a valid ROS topic name"),
    ("mpc.cost.stage", {"x": -1.0}, r"mpc.cost.stage.x: must be >= 0"),
    ("mpc.cost.stage", {"z": 1.0}, r"mpc.cost.stage.z: 'z' is not a goal field"),
    ("mpc.cost.effort", {"v": 1.0}, r"mpc.cost.effort.v: 'v' is not a control field; control fields are \['v_cmd', 'w_cmd'\]"),
    ("mpc.cost.rate", {"w_cmd": "a lot"}, r"mpc.cost.rate.w_cmd: expected a finite number"),
    ("mpc.cost.smoothness", {}, r"mpc.cost: unknown key\(s\) \['smoothness'\]"),
    ("mpc.cost", {"stage": {"x": 0.0}, "terminal": {"x": 0.0}}, r"mpc.cost: every stage and terminal weight is 0"),
    ("mpc.constraints.0", {"box": {"v": [0.5, -0.5]}}, r"mpc.constraints\[0\].box.v: low \(0.5\) must be below"),
    ("mpc.constraints.0", {"box": {"v": [2.0, 3.0]}}, r"mpc.constraints\[0\].box.v: \[2, 3\] lies outside the "
                                                      r"bounds \[-0.8, 0.8\]"),
    ("mpc.constraints.0", {"box": {"yaw": [-1.0, 1.0]}}, r"mpc.constraints\[0\].box.yaw: 'yaw' is an angle field"),
    ("mpc.constraints.0", {"box": {"v": [None, None]}}, r"mpc.constraints\[0\].box.v: both sides are open"),
    ("mpc.constraints.0", {"norm": {"fields": ["v", "w"]}}, r"mpc.constraints\[0\].norm: missing key\(s\) \['max'\]"),
    ("mpc.constraints.0", {"norm": {"fields": ["v", "w"], "max": 0}}, r"mpc.constraints\[0\].norm.max: must be > 0"),
    ("mpc.constraints.0", {"keep_out": {"fields": ["x", "y"], "center": [1.0], "radius": 0.2}},
     r"mpc.constraints\[0\].keep_out.center: expected 2 value\(s\)"),
    ("mpc.constraints.0", {"keep_out": {"fields": ["x", "y"], "center": [1.0, 0.0], "radius": -0.2}},
     r"mpc.constraints\[0\].keep_out.radius: must be > 0"),
    ("mpc.constraints.0", {"box": {"v": [0, 1]}, "norm": {"fields": ["v"], "max": 1}},
     r"mpc.constraints\[0\]: give exactly one of"),
    ("mpc.constraints.0", {"circle": {}}, r"mpc.constraints\[0\]: unknown key\(s\) \['circle'\]"),
    ("mpc.solver", "acados", r"mpc.solver: expected one of \['sqp', 'ipopt'\]"),
    ("mpc.solver_options", {"max_iters": 3}, r"mpc.solver_options: unknown option\(s\) \['max_iters'\] for solver"),
    ("mpc.penalty", 0, r"mpc.penalty: must be > 0"),
    ("mpc.reference", {"topic": "plan", "type": "geometry_msgs/msg/PoseStamped", "paths": {"x": "pose.position.x"}},
     r"mpc.reference.type: a reference needs a message with an array 'poses'"),
    ("mpc.reference", {"topic": "plan", "type": "nav_msgs/msg/Path", "paths": {"x": "pose.position.q"}},
     r"mpc.reference.paths.x: .*no field 'q'"),
]


@pytest.mark.parametrize("path, value, message", BAD, ids=[b[0] + "=" + str(b[1])[:24] for b in BAD])
def test_bad_mpc_section_names_the_key(path: str, value: Any, message: str) -> None:
    with pytest.raises(SystemFileError, match=r"system file test.yaml: " + message):
        build(mutate(path, value))


def test_mpc_section_from_a_task_file_and_round_trip(tmp_path: Path) -> None:
    raw = example()
    section = raw.pop("mpc")
    (tmp_path / "task.yaml").write_text(yaml.safe_dump(section))
    raw["mpc_file"] = "task.yaml"
    s = build(raw, tmp_path)
    task = mpc_task(s.definition)
    assert task is not None and task.horizon == 20 and task.goal_fields == ("x", "y", "yaw", "v", "w")
    assert task.goal_angle == (False, False, True, False, False) and task.rate == 0.0
    np.testing.assert_array_equal(task.u_low, [-0.5, -1.5])
    # the normalised section re-parses to itself (a checkpoint stores it)
    again = parse_definition(s.params()["definition"], "stored")
    assert again["mpc"] == s.definition["mpc"]
    section["goal"]["fields"] = ["x", "nope"]
    (tmp_path / "task.yaml").write_text(yaml.safe_dump(section))
    with pytest.raises(SystemFileError, match=r"mpc \(from task.yaml\).goal.fields\[1\]: 'nope'"):
        build(raw, tmp_path)
    raw["mpc"] = section
    with pytest.raises(SystemFileError, match=r"mpc_file: give either 'mpc' or 'mpc_file'"):
        build(raw, tmp_path)


def test_robot_without_mpc_section_says_what_to_add() -> None:
    raw = example()
    del raw["mpc"]
    from saml_ros.core.systems.registry import get_entry
    from saml_ros.systems.robot_entry import register_robot

    register_robot(build(raw))
    with pytest.raises(ValueError, match="without an 'mpc:' section: add one"):
        get_entry("diff_drive").controllers()


# ------------------------------------------------------------------------------------------ f_hat forms
AXES = {"axes": [{"position": "x", "velocity": "v"}]}


@pytest.mark.parametrize("base", [
    {"builtin": "unicycle", "params": {"x": "x", "y": "y", "yaw": "yaw", "v": "v_cmd", "w": "w_cmd",
                                       "v_state": "v", "w_state": "w", "tau": 0.12}},
    {"builtin": "unicycle", "params": {"x": "x", "y": "y", "yaw": "yaw", "v": "v_cmd", "w": "w_cmd"}},
    {"builtin": "constant_velocity", "params": AXES},
    {"builtin": "zero"}, {"builtin": "hold"},
    {"builtin": "linear", "params": {"A": np.eye(5).tolist(), "B": np.ones((5, 2)).tolist(), "c": [0.1] * 5}},
], ids=["unicycle", "unicycle_kinematic", "constant_velocity", "zero", "hold", "linear"])
def test_forms_equal_the_torch_base_models(base: dict[str, Any]) -> None:
    s = build(mutate("base_model", base))
    form = builtin_form(s.base_model)
    x, u = s.sample_inputs(64, np.random.default_rng(3))
    want = s.base_step_np(x, u)
    np.testing.assert_allclose(form(x, u, dt=s.dt, xp=NUMPY), want, rtol=1e-13, atol=1e-14)
    np.testing.assert_allclose(form(torch.from_numpy(x), torch.from_numpy(u), dt=s.dt, xp=TORCH).numpy(), want,
                               rtol=1e-13, atol=1e-14)
    b = make_base(s)
    assert isinstance(b, SymbolicBase) and b.scalar
    y, a, bm = b.step_jac(x[:7], u[:7])
    np.testing.assert_allclose(y, want[:7], rtol=1e-13, atol=1e-14)
    np.testing.assert_allclose([b.step1_list(xi.tolist(), ui.tolist()) for xi, ui in zip(x[:7], u[:7])], want[:7],
                               rtol=1e-13, atol=1e-14)


def test_double_integrator_form() -> None:
    raw = example()
    raw["state"]["fields"] = [
        {"name": "p", "unit": "m", "bounds": [-1, 1], "path": "pose.pose.position.x"},
        {"name": "v", "unit": "m/s", "bounds": [-1, 1], "path": "twist.twist.linear.x"}]
    raw["control"] = {"topic": "accel", "type": "geometry_msgs/msg/AccelStamped", "fields": [
        {"name": "a", "unit": "m/s^2", "bounds": [-2, 2], "path": "accel.linear.x"}]}
    raw["base_model"] = {"builtin": "double_integrator", "params": {"axes": [{"position": "p", "velocity": "v",
                                                                                 "acceleration": "a"}]}}
    raw["spec"] = {"objective": {"loss": "l2"}}
    raw["mpc"] = {"goal": {"fields": ["p", "v"], "default": [0.5, 0.0]},
                  "cost": {"stage": {"p": 10.0, "v": 0.1}, "terminal": {"p": 100.0, "v": 10.0}, "effort": {"a": 0.001}}}
    s = build(raw)
    x, u = s.sample_inputs(16, np.random.default_rng(4))
    np.testing.assert_allclose(builtin_form(s.base_model)(x, u, dt=s.dt, xp=NUMPY), s.base_step_np(x, u),
                               rtol=1e-13, atol=1e-14)
    ctrl = GenericSQP(s)
    state = np.zeros(2)
    for _ in range(250):
        state = s.base_step_np(state[None], ctrl.solve(state).u[None])[0]
    assert abs(state[0] - 0.5) < 0.01 and abs(state[1]) < 0.02


def _fd_jac(f: Any, x: np.ndarray, u: np.ndarray, h: float = 1e-6) -> tuple[np.ndarray, np.ndarray]:
    """Central finite differences of ``f(x (1, n), u (1, m)) -> (1, n)``."""
    n, m = x.shape[1], u.shape[1]
    ja, jb = np.zeros((n, n)), np.zeros((n, m))
    for i in range(n):
        e = np.zeros((1, n))
        e[0, i] = h
        ja[:, i] = (f(x + e, u) - f(x - e, u))[0] / (2 * h)
    for i in range(m):
        e = np.zeros((1, m))
        e[0, i] = h
        jb[:, i] = (f(x, u + e) - f(x, u - e))[0] / (2 * h)
    return ja, jb


@pytest.fixture
def user_module(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[str]:
    (tmp_path / "gm_user_models.py").write_text(textwrap.dedent("""
        import torch

        def drag(x, u, *, dt, xp, k=0.5):
            # an array-namespace form: written once, run by torch (learner), numpy and CasADi (planner)
            v = x[:, 3]
            vn = v + (u[:, 0] - k * v * xp.abs(v)) * dt
            return xp.stack([x[:, 0] + v * xp.cos(x[:, 2]) * dt, x[:, 1] + v * xp.sin(x[:, 2]) * dt,
                             x[:, 2] + u[:, 1] * dt, vn, x[:, 4]])

        def drag_torch(x, u, *, dt, k=0.5):
            # the same in plain torch (differentiated by autograd)
            out = x.clone()
            v = x[:, 3]
            out[:, 0] = x[:, 0] + v * torch.cos(x[:, 2]) * dt
            out[:, 1] = x[:, 1] + v * torch.sin(x[:, 2]) * dt
            out[:, 2] = x[:, 2] + u[:, 1] * dt
            out[:, 3] = v + (u[:, 0] - k * v * v.abs()) * dt
            return out
        """))
    monkeypatch.syspath_prepend(str(tmp_path))
    yield "gm_user_models"
    sys.modules.pop("gm_user_models", None)


@pytest.mark.parametrize("fn, kind", [(None, SymbolicBase), ("drag", SymbolicBase), ("drag_torch", TorchBase)])
def test_derivatives_are_exact(user_module: str, fn: str | None, kind: type) -> None:
    raw = example() if fn is None else mutate("base_model", {"function": f"{user_module}:{fn}",
                                                              "params": {"k": 0.7}})
    s = build(raw)
    base = make_base(s)
    assert isinstance(base, kind)
    for model in (None, fitted_model(s, members=3)):
        dyn = GenericDynamics(s, base, model, member=1)
        rng = np.random.default_rng(5)
        x, u = s.sample_inputs(6, rng)
        x[0, 2] = 3.1  # near the wrap of the angle
        y, a, b = dyn.step_jac(x, u)
        np.testing.assert_allclose(y, dyn.step(x, u), rtol=1e-12, atol=1e-12)
        if model is not None:
            with torch.no_grad():
                want = model(torch.from_numpy(x), torch.from_numpy(u))[1].numpy()
            np.testing.assert_allclose(y, want, rtol=1e-10, atol=1e-12)
        for i in range(len(x)):
            fa, fb = _fd_jac(dyn.step, x[i:i + 1], u[i:i + 1])
            np.testing.assert_allclose(a[i], fa, atol=2e-6)
            np.testing.assert_allclose(b[i], fb, atol=2e-6)
        np.testing.assert_allclose(dyn.rollout(x[0], u), _steps(dyn, x[0], u), rtol=1e-12, atol=1e-12)


def test_rounded_kinks_keep_the_networks_values_and_round_only_its_jacobians() -> None:
    s = build(example())
    model = fitted_model(s, members=2)
    exact = GenericDynamics(s, make_base(s), model, member=1)
    smooth = GenericDynamics(s, make_base(s), model, member=1, smoothing=0.5)
    tiny = GenericDynamics(s, make_base(s), model, member=1, smoothing=1e-12)
    x, u = s.sample_inputs(6, np.random.default_rng(9))
    y_s, a_s, b_s = smooth.step_jac(x, u)
    y_e, a_e, b_e = exact.step_jac(x, u)
    # the values are the network's own: no offset in what the plan predicts (the rounded values biased the dock)
    np.testing.assert_allclose(y_s, y_e, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(smooth.step(x, u), exact.step(x, u), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(smooth.rollout(x[0], u), exact.rollout(x[0], u), rtol=1e-12, atol=1e-12)
    # the Jacobians are rounded near the kinks, and tend to the exact ones as the rounding goes to 0
    assert np.abs(a_s - a_e).max() > 0
    _, a_t, b_t = tiny.step_jac(x, u)
    np.testing.assert_allclose(a_t, a_e, atol=1e-9)
    np.testing.assert_allclose(b_t, b_e, atol=1e-9)
    assert "Jacobians with the PReLU kinks rounded by 0.5" in smooth.describe()


def _steps(dyn: GenericDynamics, x0: np.ndarray, us: np.ndarray) -> np.ndarray:
    xs = [x0]
    for u in us:
        xs.append(dyn.step(xs[-1][None], u[None])[0])
    return np.array(xs)


def test_learner_calls_a_form_with_torch(user_module: str) -> None:
    s = build(mutate("base_model", {"function": f"{user_module}:drag", "params": {"k": 0.7}}))
    t = build(mutate("base_model", {"function": f"{user_module}:drag_torch", "params": {"k": 0.7}}))
    x, u = s.sample_inputs(8, np.random.default_rng(6))
    np.testing.assert_allclose(s.base_step_np(x, u), t.base_step_np(x, u), rtol=1e-13)


# ------------------------------------------------------------------------------------------ the planner
def test_planner_reaches_the_goal_the_short_way_and_keeps_constraints() -> None:
    sys.path.insert(0, str(EXAMPLE.parent))
    try:
        from dynamics import DiffDrive  # type: ignore[import-not-found]
    finally:
        sys.path.remove(str(EXAMPLE.parent))
    raw = example()
    raw["mpc"]["constraints"].append({"name": "pillar", "keep_out": {"fields": ["x", "y"], "center": [0.8, 0.15],
                                                                    "radius": 0.2}})
    s = build(raw)
    ctrl = GenericSQP(s)
    robot = DiffDrive(0.0, 0.0, 0.0)
    worst, unconverged = 0.0, 0
    for _ in range(400):
        res = ctrl.solve(robot.state())
        # soft constraints: f_hat moves the robot at the commanded speed, the robot's wheels lag, so a plan may
        # start a few mm inside the disc it skirts
        assert res.constraint_violation < 0.01, res.message
        unconverged += not res.converged
        assert np.all(res.u >= [-0.5, -1.5]) and np.all(res.u <= [0.5, 1.5])
        robot.step(res.u, s.dt)
        p = robot.state()
        worst = max(worst, 0.2 - math.hypot(p[0] - 0.8, p[1] - 0.15))
        assert abs(p[3]) <= 0.45 + 0.02  # the speed box (a measured speed: the lag lets it overshoot slightly)
    # f_hat knows neither the wheels' lag nor the slip on the wet patch beside the disc: the robot skirts it with a
    # centimetre of model error at most
    assert worst <= 0.02, f"entered the keep-out disc by {worst:.3f} m"
    final = robot.state()
    assert math.hypot(final[0] - 1.5, final[1]) < 0.05 and abs(final[2]) < 0.1, final
    assert unconverged <= 20, f"{unconverged} of 400 solves stopped at max_iter"
    # an angle goal across pi: the goal yaw -3.0 from yaw 3.0 is 0.28 rad away, not 6 rad
    ctrl.reset()
    x = np.array([1.5, 0.0, 3.0, 0.0, 0.0])
    res = ctrl.solve(x, np.array([1.5, 0.0, -3.0, 0.0, 0.0]))
    assert res.plan_x[-1, 2] > 3.0 and res.u[1] > 0  # turns left, through pi


def test_hot_swap_changes_the_plan_not_the_solver() -> None:
    s = build(example())
    ctrl = GenericSQP(s, fitted_model(s, seed=1))
    x = np.array([0.2, 0.3, 0.4, 0.1, 0.0])
    first = ctrl.solve(x)
    jac_fn = ctrl.dyn.base._jac  # type: ignore[union-attr]
    ctrl.reset()
    ctrl.set_model(fitted_model(s, seed=2))
    second = ctrl.solve(x)
    assert ctrl.dyn.base._jac is jac_fn  # type: ignore[union-attr]
    # f_hat's CasADi Jacobian was not rebuilt
    assert np.abs(first.plan_u - second.plan_u).max() > 1e-3  # the new weights plan differently
    ctrl.reset()
    ctrl.set_model(fitted_model(s, seed=1))
    np.testing.assert_allclose(ctrl.solve(x).plan_u, first.plan_u, atol=1e-9)


def test_reference_path_agrees_on_a_smooth_model() -> None:
    from saml_ros.core.mpc.generic.nlp import CasadiNLP

    s = build(example())
    sqp, nlp = GenericSQP(s, max_iter=60, tol=1e-12), CasadiNLP(s)
    for x in (np.array([0.0, 0.5, 0.3, 0.0, 0.0]), np.array([1.0, -0.5, 2.8, 0.2, 0.1])):
        a, b = sqp.solve(x), nlp.solve(x)
        assert a.converged and b.converged, (a.message, b.message)
        assert a.cost == pytest.approx(b.cost, rel=1e-6)
        sqp.reset()
        nlp.reset()
    nlp.set_model(fitted_model(s, scale=0.01))
    assert nlp.solve(x).success


def test_guarded_generic_planner_falls_back_where_the_ensemble_disagrees() -> None:
    from saml_ros.core.mpc.guard import GuardConfig, make_guarded_controller

    s = build(example())
    from saml_ros.systems.robot_entry import register_robot

    register_robot(s)
    g = make_guarded_controller(s, "fast", GuardConfig(max_disagreement=1e-6, bound_residual=True), member=0,
                                horizon=20)
    model = fitted_model(s, members=5)
    g.set_model(model, tag=3, meta={"learner": {"residual_bound": [0.01] * 5}})
    res = g.solve(np.array([0.2, 0.3, 0.4, 0.1, 0.0]))
    assert res.success and g.counters["fallbacks"] >= 1 and g.last_source == "base"
    assert g.learned.dyn.bound is not None  # type: ignore[attr-defined]
    # the generic planner clips phi itself
    g2 = make_guarded_controller(s, "fast", GuardConfig(max_disagreement=1e6), horizon=20)
    g2.set_model(model, tag=3)
    assert g2.solve(np.array([0.2, 0.3, 0.4, 0.1, 0.0])).success and g2.last_source == "learned"


def test_casadi_model_equals_the_model() -> None:
    import casadi as ca

    from saml_ros.core.mpc.generic.casadi_model import casadi_dynamics, mlp_theta

    s = build(example())
    model = fitted_model(s, members=2)
    f = casadi_dynamics(s, "residual", model.hidden)
    x, u = s.sample_inputs(50, np.random.default_rng(8))
    with torch.no_grad():
        want = model(torch.from_numpy(x), torch.from_numpy(u))[1].numpy()
    got = np.asarray(f.map(50)(x.T, u.T, mlp_theta(model, 1), np.full(5, np.inf))).T
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12)
    assert isinstance(f, ca.Function)


# ------------------------------------------------------------------------------------------ goals
def _pose(x: float, y: float, yaw: float, stamp_ns: int = 0) -> Any:
    msg = RCLPY.cls("geometry_msgs/msg/PoseStamped")()
    msg.pose.position.x, msg.pose.position.y = x, y
    msg.pose.orientation.z, msg.pose.orientation.w = math.sin(yaw / 2), math.cos(yaw / 2)
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp_ns, 1_000_000_000)
    return msg


def test_goal_messages_are_checked_and_the_last_goal_kept() -> None:
    s = build(example())
    task = mpc_task(s.definition)
    assert task is not None
    tr = GoalTracker(task, s.dt)
    np.testing.assert_allclose(tr.goal_message(_pose(1.0, -0.5, 0.5)), [1.0, -0.5, 0.5, 0.0, 0.0], atol=1e-12)
    for bad, why in ((_pose(math.nan, 0.0, 0.0), "nan"), (_pose(2.4, 0.0, 0.0), "outside its bounds")):
        with pytest.raises(GoalRefused, match=why):
            tr.goal_message(bad)
    np.testing.assert_allclose(tr(np.zeros(5), 0, 20), [1.0, -0.5, 0.5, 0.0, 0.0], atol=1e-12)


def test_reference_path_timed_and_untimed() -> None:
    raw = example()
    raw["mpc"]["reference"] = {"topic": "plan", "type": "nav_msgs/msg/Path",
                               "paths": {"x": "pose.position.x", "y": "pose.position.y",
                                         "yaw": "yaw(pose.orientation)"}, "timeout": 0.5}
    s = build(raw)
    task = mpc_task(s.definition)
    assert task is not None and task.reference is not None
    tr = GoalTracker(task, s.dt)
    path = RCLPY.cls("nav_msgs/msg/Path")()
    path.poses = [_pose(0.1 * i, 0.0, 3.1 + 0.02 * i) for i in range(10)]  # untimed, yaw through pi
    assert tr.reference_message(path, now_ns=0) == 10
    ref = tr(np.array([0.22, 0.0, 3.1, 0.0, 0.0]), 0, 5)
    np.testing.assert_allclose(ref[:, 0], [0.3, 0.4, 0.5, 0.6, 0.7], atol=1e-12)  # from the nearest pose on
    assert np.all(np.diff(ref[:, 2]) > 0) and ref[-1, 2] > math.pi  # unwrapped, the short way
    timed = RCLPY.cls("nav_msgs/msg/Path")()
    timed.poses = [_pose(0.0, 0.0, 0.0, 1_000_000_000), _pose(1.0, 0.0, 0.0, 2_000_000_000)]
    tr.reference_message(timed, now_ns=1_000_000_000)
    ref = tr(np.zeros(5), 1_000_000_000, 3)
    np.testing.assert_allclose(ref[:, 0], [0.02, 0.04, 0.06], atol=1e-12)
    goal = tr(np.zeros(5), 3_000_000_000, 3)  # 1 s after its last pose (timeout 0.5 s): the last pose is the goal
    assert goal.shape == (5,) and goal[0] == pytest.approx(1.0) and not tr.tracking
    bad = RCLPY.cls("nav_msgs/msg/Path")()
    bad.poses = [_pose(0.0, 0.0, 0.0), _pose(math.nan, 0.0, 0.0)]
    with pytest.raises(GoalRefused, match="pose 1"):
        tr.reference_message(bad, now_ns=0)


# ------------------------------------------------------------------------------------------ the service
class _Log:
    def __init__(self) -> None:
        self.lines: list[str] = []

    def info(self, text: str) -> None:
        self.lines.append(text)

    def warning(self, text: str) -> None:
        self.lines.append(text)


def test_service_stale_state_and_goals() -> None:
    from saml_ros.core.mpc.config import MPCConfig
    from saml_ros.core.mpc.service import MPCService

    load_system_file(EXAMPLE)
    sent: list[tuple[np.ndarray, int]] = []
    config = MPCConfig.from_params({"system": "diff_drive"})
    assert config.state_timeout == 0.25 and config.mode == "lockstep" and config.horizon == 20
    svc = MPCService(config, lambda u, stamp: sent.append((u.copy(), stamp)), _Log())
    x = np.array([0.0, 0.0, 0.0, 0.0, 0.0])
    stamp, values = svc.receive(x, 1_000_000_000, 0.0, now_ns=1_010_000_000)  # type: ignore[misc]
    assert values["safe"] == 0.0 and sent[-1][0][0] > 0.1  # drives towards the dock
    stamp, values = svc.receive(x, 1_020_000_000, 0.0, now_ns=2_000_000_000)  # type: ignore[misc]
    assert values["safe"] == 1.0 and np.all(sent[-1][0] == 0.0) and svc.counters["safe_commands/stale"] == 1
    # the watchdog: no state for longer than the timeout
    assert svc.watchdog(0.1) is None
    assert svc.watchdog(1.0) is not None and svc.counters["safe_commands/stale"] == 2
    assert svc.watchdog(1.1) is None  # at most once per timeout
    assert svc.goal_message(_pose(math.nan, 0.0, 0.0)) is False and svc.counters["rejected/goal"] == 1
    assert svc.goal_message(_pose(1.0, 0.2, 0.0)) is True
    diag = svc.diagnostic_values()
    assert diag["goal"].startswith("x=1, y=0.2") and diag["rejected/goal"] == 1 and "Gauss-Newton" in diag["planner"]
    with pytest.raises(ValueError, match=r"goal.setpoint: goal field 'x' = 7 is outside its bounds"):
        MPCConfig.from_params({"system": "diff_drive", "goal.setpoint": [7.0, 0.0, 0.0, 0.0, 0.0]})


# ------------------------------------------------------------------------------------------ CasADi export
def test_casadi_export_equals_the_model_and_solves_an_ocp(tmp_path: Path) -> None:
    """``./dev export`` writes model.casadi + theta.npy; loaded back, it predicts what the model predicts, and an
    OCP built once on it takes another checkpoint's weights as new parameter values (no rebuild)."""
    import json

    import casadi as ca

    from saml_ros.export import export_model

    s = build(example())
    model = fitted_model(s, members=2, scale=0.05).float()  # the learner's dtype
    res = export_model(model, tmp_path / "out", ["casadi"], member=1)
    meta = json.loads((tmp_path / "out" / "model.json").read_text())
    assert meta["casadi_base_exported"] and res.max_abs_error["casadi"] < 1e-5
    assert meta["casadi"]["theta_size"] == np.load(tmp_path / "out" / "theta.npy").size
    theta = np.load(tmp_path / "out" / "theta.npy")
    # a small OCP for IPOPT (the kinks of the network rounded by 1e-3: it does not converge on the exact ones):
    # drive from the origin to (0.08, 0) in 15 steps, the exported model as the dynamics
    smooth = ca.Function.load(str(tmp_path / "out" / "model_smooth.casadi"))
    opti = ca.Opti()
    T, x0 = 15, np.zeros(5)
    xs, us, th = opti.variable(5, T + 1), opti.variable(2, T), opti.parameter(theta.size)
    opti.subject_to(xs[:, 0] == x0)
    for t in range(T):
        opti.subject_to(xs[:, t + 1] == smooth(xs[:, t], us[:, t], th, 1e-3)[0])
        opti.subject_to(opti.bounded(-0.5, us[0, t], 0.5))
        opti.subject_to(opti.bounded(-1.5, us[1, t], 1.5))
    opti.minimize(100 * ca.sumsqr(xs[:2, T] - np.array([0.08, 0.0])) + 1e-2 * ca.sumsqr(us))
    opti.solver("ipopt", {"ipopt.print_level": 0, "print_time": False, "ipopt.sb": "yes", "expand": True})
    opti.set_value(th, theta)
    sol = opti.solve()
    plan_u, plan_x = np.asarray(sol.value(us)).T, np.asarray(sol.value(xs)).T
    assert np.hypot(plan_x[-1, 0] - 0.08, plan_x[-1, 1]) < 0.01
    # the plan's states are the model's own predictions (float32 model; the rounding moves them by < 1e-4)
    xt = x0
    for u in plan_u:
        with torch.no_grad():
            xt = model(torch.tensor(xt[None], dtype=torch.float32), torch.tensor(u[None], dtype=torch.float32))[1]
        xt = xt.double().numpy()[0]
    np.testing.assert_allclose(xt, plan_x[-1], atol=1e-4)
    # another member's weights: new numbers for the same OCP
    from saml_ros.core.mpc.generic.casadi_model import mlp_theta

    opti.set_value(th, mlp_theta(model, 0))
    other = np.asarray(opti.solve().value(us)).T
    assert np.abs(other - plan_u).max() > 1e-4



# ------------------------------------------------------------------------------------------ evaluation
def test_robot_evaluation_pairs_starts_and_reports_headroom(tmp_path: Path) -> None:
    """The closed-loop evaluation on the example robot's own simulator: base, oracle (its true dynamics, torch) and
    a model, on the same starts; paired statistics, the report, the figure."""
    sys.path.insert(0, str(EXAMPLE.parent))
    try:
        import dynamics as dd
    finally:
        sys.path.remove(str(EXAMPLE.parent))
    from saml_ros.experiments.robot_eval import evaluate_robot

    s = build(example())
    starts = dd.sample_starts(2, np.random.default_rng(0))
    ev = evaluate_robot(s, dd.make_robot, {"m": fitted_model(s, scale=0.0)}, starts, 30, oracle=dd.true_step)
    assert set(ev.errors) == {"base", "oracle", "m", "pooled"} and ev.errors["base"].shape == (2,)
    # a model whose residual is zero plans exactly as f_hat: the same episodes
    np.testing.assert_allclose(ev.errors["m"], ev.errors["base"], atol=1e-9)
    assert ev.stats["m"].n == 2 and ev.stats["m"].diff == pytest.approx(0.0, abs=1e-9)
    assert math.isfinite(ev.headroom) and "headroom (base - oracle)" in ev.report()
    ev.figure(tmp_path / "e.png")
    assert (tmp_path / "e.png").stat().st_size > 1000


def test_evaluation_task_file_is_checked_and_completed_like_the_section(tmp_path: Path) -> None:
    """``robot_eval --task FILE``: a task file's ``mpc:`` mapping (the example's dock task) is checked and completed
    against the system file (goal bounds, penalty) as the file's own section is, and a wrong key is named."""
    from saml_ros.core.mpc.generic.section import MPCSectionError
    from saml_ros.experiments.robot_eval import task_from_file

    s = load_system_file(EXAMPLE)
    task = task_from_file(s, EXAMPLE.parent / "dock_task.yaml")
    assert task.w_stage.tolist() == [10.0, 100.0, 0.5, 0.05, 0.01] and task.w_rate.tolist() == [0.5, 1.0]
    assert task.horizon == 20 and task.goal_topic is not None
    assert task.goal_low.tolist() == [-2.3, -2.3, -3.14159266, -0.8, -2.0] and task.penalty == 1000.0
    bad = tmp_path / "bad.yaml"
    bad.write_text(yaml.safe_dump({"mpc": {"goal": {"fields": ["x"], "default": [1.0]}, "cost": {"stage": {"yw": 1.0}}}}))
    with pytest.raises(MPCSectionError, match=r"bad.yaml: mpc.cost.stage.yw"):
        task_from_file(s, bad)


def test_nested_evaluation_flies_each_seed_from_its_own_starts() -> None:
    """Starts nested in seeds: each model flies its own starts beside base and oracle (the wet ramp: the oracle's
    slide), and the seed is the unit of the interval; the true dynamics with ``slide`` equal the simulator's."""
    sys.path.insert(0, str(EXAMPLE.parent))
    try:
        import dynamics as dd
    finally:
        sys.path.remove(str(EXAMPLE.parent))
    from saml_ros.experiments.robot_eval import evaluate_nested

    rng = np.random.default_rng(3)
    x0 = np.array([1.2, 0.1, 0.4, 0.2, -0.3])
    robot, u = dd.make_robot_on_ramp(x0), np.array([0.3, 0.5])
    np.testing.assert_allclose(robot.state(), x0, atol=1e-12)
    robot.step(u, 0.02)
    np.testing.assert_allclose(np.asarray(dd.true_step_on_ramp(x0[None], u[None], dt=0.02, xp=np)).ravel(),
                               robot.state(), atol=1e-12)
    s = build(example())
    models = {"a": fitted_model(s, scale=0.0), "b": fitted_model(s, scale=0.0)}
    ev = evaluate_nested(s, dd.make_robot_on_ramp, models, dd.sample_approach_starts, 2, 8, seed=int(rng.integers(9)),
                         oracle=dd.true_step_on_ramp)
    assert set(ev.runs) == {"a", "b"}
    assert not np.allclose(ev.runs["a"].starts, ev.runs["b"].starts)  # each seed its own starts
    assert ev.seed_level.n == 2 and ev.pooled.n == 4
    assert ev.seed_level.diff == pytest.approx(0.0, abs=1e-9)  # zero residuals plan as f_hat
    base, oracle, rel = ev.headroom()
    assert math.isfinite(oracle) and "seed level (unit: the training seed, n = 2)" in ev.report()


def test_guarded_evaluation_flies_the_nodes_guard_and_acceptance_refuses_a_wild_model() -> None:
    """``guard=node_guard()``: the learned model flies inside the MPC node's default guard (live monitor fed every
    transition; counters reported), the same episodes as the bare planner while the monitor keeps it; the node's
    acceptance passes a model near its data and refuses one that predicts far beyond any residual the data showed."""
    sys.path.insert(0, str(EXAMPLE.parent))
    try:
        import dynamics as dd
    finally:
        sys.path.remove(str(EXAMPLE.parent))
    from saml_ros.core.spec import ProblemSpec
    from saml_ros.experiments.robot_eval import acceptance, evaluate_robot, node_guard

    s = build(example())
    guard = node_guard()
    assert guard.rollback and not math.isfinite(guard.max_disagreement) and not guard.bound_residual
    starts = dd.sample_approach_starts(1, np.random.default_rng(0))
    model = fitted_model(s, scale=0.0)
    ev = evaluate_robot(s, dd.make_robot_on_ramp, {"m": model}, starts, 12, guard=guard)
    c = ev.guard["m"]
    assert c["solves"] == 12 and c.get("rollbacks", 0) == 0 and c.get("solves_base", 0) == 0
    np.testing.assert_allclose(ev.errors["m"], ev.errors["base"], atol=1e-9)
    assert "planned with the learned model" in ev.report()
    spec = ProblemSpec.for_system(s.paper_spec(), s)
    rng = np.random.default_rng(1)
    x, u = s.sample_inputs(300, rng)
    y = s.base_step_np(x, u) + 1e-3 * rng.normal(size=x.shape)
    assert acceptance(s, model, spec, x, u, y) is None
    wild = fitted_model(s, scale=0.0)
    with torch.no_grad():
        wild.net.biases[-1].fill_(50.0)  # phi = 50 output scales everywhere
    refused = acceptance(s, wild, spec, x, u, y)
    assert refused is not None and refused[0] in ("residual", "implausible")


def test_norm_cost_and_a_terminal_constraint() -> None:
    """``cost.norm``: each step's goal term is the (smoothed) distance, and the SQP's gradient is its exact one; a
    constraint ``at: terminal`` binds x_T only; both are checked at load naming the key."""
    from saml_ros.core.mpc.generic.problem import GenericProblem
    from saml_ros.core.mpc.generic.section import MPCSectionError

    raw = mutate("mpc.cost.norm", True)
    raw["mpc"]["constraints"].append({"name": "stop", "norm": {"fields": ["v"], "max": 0.05}, "at": "terminal"})
    task = mpc_task(build(raw).definition)
    assert task is not None and task.norm_cost and task.constraints[-1].terminal
    pb = GenericProblem(task, 5, 2)
    rng = np.random.default_rng(2)
    xs, us = rng.normal(size=(pb.T + 1, 5)), rng.normal(size=(pb.T, 2))
    ref = pb.reference(xs[0], None)
    r = pb.state_residuals(xs, ref)
    ru = pb.control_residuals(us, None)
    want = np.sqrt((r * r).sum(1) + task.norm_eps ** 2).sum() + ru @ ru
    assert pb.cost(xs, us, ref, None) == pytest.approx(want, rel=1e-12)
    c = pb.constraints(xs)
    assert np.all(c[:-1, -1] == -1.0) and c[-1, -1] == pytest.approx(abs(xs[-1, 3]) - 0.05)
    cj = pb.constraint_jac(xs)
    assert np.all(cj[:-1, -1] == 0.0) and cj[-1, -1, 3] == pytest.approx(np.sign(xs[-1, 3]))
    # the planner reaches a plan whose x_T keeps the terminal bound, from rest towards the dock
    ctrl = GenericSQP(build(raw), None, task=task, max_iter=30)
    res = ctrl.solve(np.array([1.2, 0.0, 0.0, 0.0, 0.0]))
    assert np.isfinite(res.cost) and abs(res.plan_x[-1, 3]) <= 0.05 + 1e-3
    for path, value, key in (("mpc.cost.norm", "yes", "mpc.cost.norm"), ("mpc.cost.norm_eps", -1.0, "norm_eps")):
        with pytest.raises((MPCSectionError, SystemFileError), match=key):
            build(mutate(path, value))
    bad = copy.deepcopy(example())
    bad["mpc"]["constraints"][0]["at"] = "first"
    with pytest.raises((MPCSectionError, SystemFileError), match="constraints\\[0\\].at"):
        build(bad)
