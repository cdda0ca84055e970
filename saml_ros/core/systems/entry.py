"""What one system is made of: :class:`SystemEntry`, the record the registry (:mod:`.registry`) holds per system.

Each field is a value or a factory that imports what it builds only when called, so building an entry (and
importing this module) imports neither torch, MuJoCo nor the MPC.
"""

from __future__ import annotations

import inspect
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from saml_ros.core.params import Param

if TYPE_CHECKING:
    import numpy as np

    from saml_ros.core.dynamics.system import System

#: a controller class (or factory): ``(system, model | None, **options) -> saml_ros.core.mpc.contract.Controller``
ControllerFactory = Callable[..., Any]
#: what the factories build belongs to layers above the table (message schemas, the MPC, the simulator worlds), which
#: import the table: the fields name those types in their descriptions and are typed ``Any`` here, so the table
#: imports none of them (test_layers.py)
SystemSchema = Any  #: ``msg_schemas.base.SystemSchema``
BaseModelNP = Any  #: ``saml_ros.core.mpc.dynamics_np.BaseModelNP``
ShootingTask = Any  #: ``saml_ros.core.mpc.shooting.tasks.ShootingTask``
SimConfig = Any  #: ``saml_ros.core.worlds.sim_core.SimConfig``
SimCore = Any  #: ``saml_ros.core.worlds.sim_core.SimCore``
SteppedModel = Any  #: ``saml_ros.core.worlds.sim_core.SteppedModel``


@dataclass(frozen=True)
class SystemEntry:
    """Everything saml_ros knows about one system; each field is a value or a factory importing on call.

    Attributes:
        name: registry name, used in parameters, topics (namespace ``/<name>``), specs and checkpoints.
        summary: one line saying what the system is.
        system_class: ``() -> type[System]``: the dynamics (true and base model, layouts, bounds, paper spec,
            safe command :meth:`System.safe_control`).
        schema: ``() -> SystemSchema``: topics and message conversions (``msg_schemas``).
        controllers: ``() -> {solver: factory}`` with a factory ``(system, model, **options) -> Controller`` for
            every solver name of :data:`saml_ros.core.mpc.factory.SOLVERS`.
        sim_node: executable (and ROS node) name of the simulator node, e.g. ``"friction_sim"``.
        simulator: ``(system, config, params) -> SimCore``: the simulator core from the simulator node's
            parameter values ``params`` (by parameter name).
        goal_params: the MPC's goal parameters (declared as ``goal.<name>``); the first one named
            :attr:`goal_position` is the target position.
        goal_fields: the state fields the target position is compared with (the task error, m).
        goal_position: name of the goal parameter holding the target position.
        goal_factory: ``(entry, values) -> goal`` builds the ``goal`` argument of ``Controller.solve`` from the
            ``goal.*`` values; ``None``: the target position as a float64 vector (:meth:`position_goal`).
        task_params: MPC task options (declared as ``task.<name>``) forwarded to the controller.
        mpc_horizon: whether the MPC plans over a horizon (the ``horizon`` parameter applies); False for a
            one-shot problem.
        mpc_task: ``(system, horizon, **task options) -> ShootingTask`` for a single-shooting MPC; None if the
            system's controllers are not shooting controllers.
        base_model_np: ``(system) -> BaseModelNP``: numpy twin of ``base_step`` with exact Jacobians; None =
            torch autograd (exact but slow).
        true_model_np: ``(system) -> BaseModelNP``: numpy twin of ``true_step`` (the MPC's oracle model,
            ``make_controller(system, "oracle")``) with Jacobians exact where ``true_step`` is differentiable;
            None = torch autograd of ``true_step``.
        stepped_model: ``(system, **options) -> SteppedModel`` for a time-stepped simulator core; None for an
            event-based system.
        paper_samples, paper_epochs: the paper's offline dataset size and epochs (``train`` defaults).
        bringup: default bringup configuration (``system``, ``sim_time`` and the sections ``sim``, ``learner``,
            ``mpc`` of node parameters).
        experiment: name of the paper experiment reproducing this system's results (``saml_ros.experiments``).
        spec_file: the paper's spec as YAML, relative to the repository's ``config/`` directory.
        mpc_defaults: defaults of the MPC node's parameters this system sets (a system file's ``mpc:`` section:
            ``horizon``, ``mode``, ``rate_hz``, ``state_timeout``), by parameter name.
        loop_event: for an event-based system, one step of the closed-loop runner
            (:func:`saml_ros.core.mpc.loop.closed_loop`): ``(system, x, y, goal) -> (landing point, next state,
            stage cost, stop)`` from the true model's output ``y``; None for a time-stepped system (``y`` is the
            next state).
    """

    name: str
    summary: str
    system_class: Callable[[], type[System]]
    schema: Callable[[], SystemSchema]
    controllers: Callable[[], Mapping[str, ControllerFactory]]
    sim_node: str
    simulator: Callable[[System, SimConfig, Mapping[str, Any]], SimCore]
    goal_params: tuple[Param, ...]
    goal_fields: tuple[str, ...]
    goal_position: str = "position"
    goal_factory: Callable[[SystemEntry, Mapping[str, Any]], Any] | None = None
    task_params: tuple[Param, ...] = ()
    mpc_horizon: bool = True
    mpc_task: Callable[..., ShootingTask] | None = None
    base_model_np: Callable[[System], BaseModelNP] | None = None
    true_model_np: Callable[[System], BaseModelNP] | None = None
    stepped_model: Callable[..., SteppedModel] | None = None
    paper_samples: int = 10_000
    paper_epochs: int = 200
    bringup: Mapping[str, Any] = field(default_factory=dict)
    experiment: str | None = None
    spec_file: str | None = None
    mpc_defaults: Mapping[str, Any] = field(default_factory=dict)
    loop_event: Callable[[System, np.ndarray, np.ndarray, Any], tuple[np.ndarray, np.ndarray, float, bool]] | None = None

    # ------------------------------------------------------------------------------------------ dynamics
    def default_params(self) -> dict[str, Any]:
        """The system's constructor parameters with their (paper) defaults."""
        sig = inspect.signature(self.system_class().__init__)
        return {k: p.default for k, p in sig.parameters.items() if p.kind is inspect.Parameter.KEYWORD_ONLY}

    def make_system(self, **overrides: Any) -> System:
        """The system with physical parameters ``overrides``; ``ValueError`` for an unknown parameter (listing
        the valid ones) or an invalid value."""
        valid = self.default_params()
        unknown = sorted(set(overrides) - set(valid))
        if unknown:
            raise ValueError(f"system {self.name!r} has no parameter(s) {unknown}; valid parameters are "
                             f"{sorted(valid)}")
        system = self.system_class()(**overrides)
        if system.name != self.name:
            raise ValueError(f"system entry {self.name!r} built a system named {system.name!r}")
        return system

    # ------------------------------------------------------------------------------------------ goals
    def goal_defaults(self) -> dict[str, Any]:
        """``{name: default}`` of the goal parameters."""
        return {g.name: g.default for g in self.goal_params}

    def goal_vector(self, name: str, value: Any, size: int) -> np.ndarray:
        """``value`` of goal parameter ``name`` as ``size`` finite float64 numbers; ``ValueError`` otherwise."""
        import numpy as np  # here, not at the top: `import saml_ros` (every executable's first step) stays light

        arr = np.atleast_1d(np.asarray(value, dtype=np.float64))
        if arr.shape != (size,) or not np.all(np.isfinite(arr)):
            raise ValueError(f"goal.{name} must be {size} finite number(s), got {value!r}")
        return arr

    def position_goal(self, values: Mapping[str, Any]) -> np.ndarray:
        """The target position (one number per :attr:`goal_fields`) from goal values (defaults filled in)."""
        value = {**self.goal_defaults(), **values}[self.goal_position]
        return self.goal_vector(self.goal_position, value, len(self.goal_fields))

    def make_goal(self, values: Mapping[str, Any]) -> Any:
        """The ``goal`` argument of ``Controller.solve`` from ``goal.*`` values (by name, without the prefix;
        defaults filled in). ``ValueError`` for a value of the wrong size, not finite or an inverted bound."""
        full = {**self.goal_defaults(), **values}
        if self.goal_factory is None:
            return self.position_goal(full)
        return self.goal_factory(self, full)

    def task_error(self, x: np.ndarray, goal: np.ndarray, fields: int | None = None) -> float:
        """Euclidean distance (m) of state ``x``'s :attr:`goal_fields` (the first ``fields`` of them) from the
        target position ``goal``."""
        layout = self.system_class().state
        names = self.goal_fields[:fields]
        import numpy as np

        pos = np.array([x[layout.index(f)] for f in names], dtype=np.float64)
        return float(np.linalg.norm(pos - np.asarray(goal, dtype=np.float64)[: len(names)]))
