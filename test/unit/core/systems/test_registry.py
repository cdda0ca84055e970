"""The system registry: every built-in system reaches every part from its entry, and the registry is open."""

from __future__ import annotations

import importlib
import inspect
from collections.abc import Callable

import numpy as np
import pytest
import torch
from helpers import REPO

from msg_schemas import get_schema
from msg_schemas.base import DATA_QOS, SystemSchema, TopicSpec
from msg_schemas.codecs import JOINT_STATE, JointStateCodec
from saml_ros.core.dynamics.system import System
from saml_ros.core.layout import make_layout
from saml_ros.core.mpc import make_controller
from saml_ros.core.mpc.dynamics_np import TorchBaseNP
from saml_ros.core.mpc.factory import SOLVERS, base_model_np, make_task
from saml_ros.core.mpc.shooting import SLSQPShootingMPC, SQPShootingMPC
from saml_ros.core.mpc.shooting.tasks import ShootingTask
from saml_ros.core.params import Param
from saml_ros.core.spec import ProblemSpec
from saml_ros.core.systems import (
    SYSTEM_NAMES,
    SystemEntry,
    get_entry,
    get_system,
    register_system,
    system_names,
)
from saml_ros.core.worlds.sim_core import SimConfig, SimCore
from saml_ros.executables import EXECUTABLES
from saml_ros.experiments import EXPERIMENT_NAMES
from saml_ros.experiments import cli as experiment_cli


# ---------------------------------------------------------------------------------------- built-in systems
@pytest.mark.parametrize("name", SYSTEM_NAMES)
def test_every_part_of_a_builtin_system_is_reached_from_its_entry(name: str) -> None:
    entry = get_entry(name)
    assert entry.name == name and entry.summary
    cls = entry.system_class()
    assert issubclass(cls, System) and cls.name == name
    system = get_system(name)
    assert type(system) is cls
    # topic schema: the same layouts as the dynamics
    schema = entry.schema()
    assert schema.system == name and get_schema(name) is schema
    assert schema.state.field_names == system.state.names and schema.control.field_names == system.control.names
    # numpy twin: a real one (not the autograd fallback), equal to base_step
    twin = base_model_np(system)
    assert not isinstance(twin, TorchBaseNP)
    x, u = system.sample_inputs(5, np.random.default_rng(0))
    np.testing.assert_allclose(twin.step(x, u), system.base_step_np(x, u), rtol=1e-9, atol=1e-9)
    # MPC: a controller per solver; goals from the default goal parameters; the task for horizon systems
    assert set(entry.controllers()) == set(SOLVERS)
    goal = entry.make_goal({})
    for solver in SOLVERS:
        assert make_controller(system, None, solver, horizon=3) is not None
    if entry.mpc_horizon:
        assert entry.mpc_task is not None
        task = make_task(system, 3)
        assert task.horizon == 3 and task.target.shape == entry.position_goal({}).shape
        signature = inspect.signature(entry.mpc_task).parameters
        assert set(signature) >= {"system", "horizon"}
    res = make_controller(system, None, "fast", horizon=3).solve(x[0], goal)
    assert res.u.shape == (system.control.size,) and np.all(np.isfinite(res.u))
    # goal and task parameters are declared parameters; the goal position is compared with state fields
    assert entry.goal_position in [g.name for g in entry.goal_params]
    assert all(f in system.state.names for f in entry.goal_fields)
    assert np.isfinite(entry.task_error(x[0], entry.position_goal({})))
    # safe command within the bounds
    safe = system.safe_control()
    assert safe.shape == (system.control.size,)
    assert np.all(safe >= system.control_low) and np.all(safe <= system.control_high)
    # spec file = the paper's spec
    assert entry.spec_file is not None
    spec = ProblemSpec.from_yaml(REPO / "config" / entry.spec_file, system)
    assert spec.to_dict() == ProblemSpec.for_system(system.paper_spec(), system).to_dict()
    # training budget, bringup defaults, experiment, simulator executable
    assert entry.paper_samples > 0 and entry.paper_epochs > 0
    assert entry.bringup["system"] == name and set(entry.bringup) >= {"sim_time", "sim", "learner", "mpc"}
    assert entry.experiment in EXPERIMENT_NAMES and entry.experiment in experiment_cli.SETTINGS
    assert EXECUTABLES[entry.sim_node] == f"sim_nodes.{entry.sim_node}:main"


@pytest.mark.parametrize("name", SYSTEM_NAMES)
def test_the_simulator_core_is_built_from_the_sim_nodes_default_parameters(name: str) -> None:
    entry = get_entry(name)
    binding = importlib.import_module(f"sim_nodes.{entry.sim_node}").BINDING
    assert binding.system == name and binding.node_name == entry.sim_node
    params = {p.name: p.default for p in binding.all_params()}
    from sim_nodes.binding import config_from_params

    core = entry.simulator(get_system(name), config_from_params({**params, "mode": "lockstep"}), params)
    assert isinstance(core, SimCore)
    np.testing.assert_array_equal(core.holder.safe_default, get_system(name).safe_control())
    assert core.begin(0)  # the first state (and /clock) come out
    if entry.stepped_model is not None:
        from saml_ros.core.worlds.sim_core import build_stepped_sim

        assert build_stepped_sim(get_system(name), SimConfig()).system.name == name


def test_task_parameters_default_to_the_task_functions_defaults() -> None:
    """The MPC node declares ``task.*`` with these defaults: they must be what the task itself uses."""
    from saml_ros.systems.friction.task import friction_task
    from saml_ros.systems.quadrotor.task import quadrotor_task

    #: each in its system's folder
    task_functions: dict[str, Callable[..., object]] = {"friction": friction_task, "quadrotor": quadrotor_task}
    for name in SYSTEM_NAMES:
        entry = get_entry(name)
        if entry.mpc_task is None:
            assert entry.task_params == ()
            continue
        fn = task_functions[name]
        defaults = {k: p.default for k, p in inspect.signature(fn).parameters.items() if k not in ("system", "horizon")}
        assert {p.name: p.default for p in entry.task_params} == defaults


# ---------------------------------------------------------------------------------------------- errors
def test_unknown_names_give_a_clear_error_listing_the_registered_ones() -> None:
    for call in (lambda: get_entry("pendulum"), lambda: get_system("pendulum"), lambda: get_schema("pendulum")):
        with pytest.raises(ValueError, match=r"unknown system 'pendulum'; valid names are \['friction', "
                                             r"'quadrotor', 'paddle_ball'\]"):
            call()
    with pytest.raises(ValueError, match="has no parameter"):
        get_system("quadrotor", masss=2.0)


def test_bad_entries_are_refused() -> None:
    friction = get_entry("friction")
    with pytest.raises(ValueError, match="already registered"):
        register_system(friction)
    with pytest.raises(ValueError, match="must start with a letter"):
        register_system(SystemEntry(**{**vars(friction), "name": "bad/name"}))
    with pytest.raises(ValueError, match="goal_position 'where'"):
        register_system(SystemEntry(**{**vars(friction), "name": "other", "goal_position": "where"}))
    with pytest.raises(TypeError, match="wants a SystemEntry"):
        register_system("friction")  # type: ignore[arg-type]
    assert system_names() == SYSTEM_NAMES


def test_goal_values_are_validated_with_the_parameter_named() -> None:
    with pytest.raises(ValueError, match="goal.position must be 3 finite"):
        get_entry("quadrotor").make_goal({"position": [1.0, 2.0]})
    with pytest.raises(ValueError, match="goal.v_rel_min = 6.0 must be <= goal.v_rel_max"):
        get_entry("paddle_ball").make_goal({"v_rel_min": 6.0})
    goal = get_entry("paddle_ball").make_goal({"target_xy": [0.5, -0.5]})
    np.testing.assert_array_equal(goal.target_xy, [0.5, -0.5])


# ---------------------------------------------------------------------------------------------- open table
class Cart(System):
    """A frictionless cart whose velocity is the command: x' = x + dt u (base model exact)."""

    name = "cart"
    state = make_layout("cart_state", [("x", "m", "position")])
    control = make_layout("cart_control", [("u", "m/s", "velocity command")])
    target = state
    dt = 0.1
    paper_hidden = (4,)

    def __init__(self, *, u_max: float = 1.0) -> None:
        self.u_max = u_max

    @property
    def control_low(self) -> np.ndarray:
        return np.array([-self.u_max])

    @property
    def control_high(self) -> np.ndarray:
        return np.array([self.u_max])

    def true_step(self, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        return x + self.dt * u

    def base_step(self, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        return x + self.dt * u

    def sample_inputs(self, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        return rng.uniform(-1, 1, (n, 1)), rng.uniform(-1, 1, (n, 1))

    def paper_spec(self) -> dict:
        return {"objective": {"loss": "l2"}}


CART_CODEC = JointStateCodec([("x", "m", "cart", "position")], "cart position")
CART_CMD = JointStateCodec([("u", "m/s", "cart", "velocity")], "cart velocity command")
CART_SCHEMA = SystemSchema(
    system="cart", state=CART_CODEC, control=CART_CMD, target=CART_CODEC, target_topic="state",
    target_pairing="next",
    topics=(TopicSpec("state", JOINT_STATE, DATA_QOS, "sim", "mpc", "x", codec=CART_CODEC),
            TopicSpec("cmd", JOINT_STATE, DATA_QOS, "mpc", "sim", "u", codec=CART_CMD),
            TopicSpec("applied_cmd", JOINT_STATE, DATA_QOS, "sim", "learner", "u", codec=CART_CMD)),
)


def cart_task(system: System, horizon: int, max_x: float = 10.0) -> ShootingTask:
    return ShootingTask(name="cart", horizon=horizon, u_low=system.control_low, u_high=system.control_high,
                        res_idx=np.array([0]), target=np.zeros(1), u_default=np.zeros(1),
                        cons_t=np.arange(1, horizon + 1), cons_idx=np.zeros(horizon, dtype=int),
                        cons_sign=np.ones(horizon), cons_bound=np.full(horizon, max_x))


def unavailable(*args: object) -> SimCore:
    raise NotImplementedError("the cart has no simulator")


def test_a_system_registered_at_run_time_gets_an_mpc_and_its_schema(restore_registry: None) -> None:
    entry = register_system(SystemEntry(
        name="cart", summary="a velocity-commanded cart", system_class=lambda: Cart, schema=lambda: CART_SCHEMA,
        controllers=lambda: {"fast": SQPShootingMPC, "slsqp": SLSQPShootingMPC}, sim_node="cart_sim",
        simulator=unavailable, goal_params=(Param("position", 0.0, "target x (m)"),), goal_fields=("x",),
        task_params=(Param("max_x", 10.0, "upper bound of x (m)"),), mpc_task=cart_task,
    ))
    assert get_entry("cart") is entry and system_names() == (*SYSTEM_NAMES, "cart")
    assert get_schema("cart") is CART_SCHEMA
    system = get_system("cart", u_max=2.0)
    assert isinstance(system, Cart) and system.u_max == 2.0
    assert isinstance(base_model_np(system), TorchBaseNP)  # no numpy twin: the exact autograd fallback
    with pytest.raises(TypeError, match="cart MPC has no option"):
        make_task(system, 5, min_height=1.0)
    # the fast MPC drives the cart from 1 m to the goal 0.5 m at full speed, then holds it
    ctrl = make_controller(system, None, "fast", horizon=5, max_x=10.0)
    x = np.array([1.0])
    goal = entry.make_goal({"position": 0.5})
    for _ in range(6):
        x = system.true_step_np(x, ctrl.solve(x, goal).u)
    np.testing.assert_allclose(x, [0.5], atol=1e-3)
    with pytest.raises(ValueError, match="goal.position must be 1 finite"):
        entry.make_goal({"position": [0.5, 1.0]})
