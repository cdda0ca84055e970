"""Robots described by a system file (:mod:`.system_file`) as entries of the open registry.

:func:`register_robot` registers a loaded :class:`~saml_ros.systems.system_file.FileSystem` under its name,
so everything that looks a system up by name (the learner node's configuration, ``msg_schemas.get_schema``, the bag
tools, ``train``, checkpoint loading) reaches it like a built-in. A process that never read the file (a training
process, a script loading a checkpoint) meets the robot as ``get_system(name, definition=...)`` with the definition
the checkpoint or the learner stored: :func:`load_stored_robot`, installed as the registry's loader of unknown
names, rebuilds and registers it from that alone.

A robot has its own topics and base model but no simulator inside saml_ros: its entry's ``simulator`` raises
``ValueError`` saying so. A robot whose file has an ``mpc:`` section (:mod:`saml_ros.core.mpc.generic.section`) is controlled by the
generic planner (``saml_ros.core.mpc.generic``): its entry's controllers are that planner's, its goal parameter
``goal.setpoint`` (the goal fields' default) and its MPC node defaults (horizon, rate, state timeout) the section's.
Without one, ``controllers`` raise ``ValueError`` naming what to add (the MPC node then exits with a configuration
error).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

from saml_ros.core.params import Param
from saml_ros.core.systems.entry import SystemEntry
from saml_ros.core.systems.registry import find_entry, register_loader, register_system

if TYPE_CHECKING:
    from saml_ros.systems.system_file import FileSystem


def _no_mpc(name: str) -> Any:
    raise ValueError(f"system {name!r} is a robot described by a system file without an 'mpc:' section: add one "
                     "(its goal, cost, constraints; docs/your_robot.md, 'Control it') to plan for it, or use its "
                     "exported model in your own controller")


def _generic_controllers(planner: str) -> Any:
    from saml_ros.core.mpc.generic import generic_controllers

    return generic_controllers(planner)


def _setpoint_goal(task: Any) -> Any:
    def make(entry: SystemEntry, values: Mapping[str, Any]) -> Any:
        try:
            return task.check_goal(values["setpoint"])
        except ValueError as exc:
            raise ValueError(f"goal.setpoint: {exc}") from None

    return make


def _no_simulator(name: str) -> Any:
    raise ValueError(f"system {name!r} is a robot described by a system file: saml_ros has no simulator of it, "
                     "its data comes from its own topics")


def robot_entry(system: FileSystem) -> SystemEntry:
    """The registry entry of ``system``: ``entry.make_system()`` rebuilds it (keyword ``definition`` = another
    stored definition of the same robot, ``base_function`` = its user base model function)."""
    name = system.name
    definition = system.params()["definition"]
    function = system.user_function
    base = type(system)

    class Robot(base):  # type: ignore[valid-type, misc]
        def __init__(self, *, definition: Mapping[str, Any] = definition, base_function: Any = function) -> None:
            base.__init__(self, base.parse(definition, f"system {name!r}"), f"system {name!r}",
                          function=base_function)

    Robot.__name__ = Robot.__qualname__ = f"Robot_{name}"
    from saml_ros.core.mpc.generic.section import mpc_task

    task = mpc_task(definition)
    if task is None:
        first = system.state.names[0]
        return SystemEntry(
            name=name,
            summary=system.description or f"a robot described by a system file ({system.where})",
            system_class=lambda: Robot,
            schema=system.schema,
            controllers=lambda: _no_mpc(name),
            sim_node="",
            simulator=lambda *_: _no_simulator(name),
            goal_params=(Param("position", [0.0], "not used: this robot's system file has no 'mpc:' section"),),
            goal_fields=(first,),
            paper_samples=0,
            paper_epochs=200,
        )
    fields = task.goal_fields
    return SystemEntry(
        name=name,
        summary=system.description or f"a robot described by a system file ({system.where})",
        system_class=lambda: Robot,
        schema=system.schema,
        controllers=lambda: _generic_controllers(task.planner),
        sim_node="",
        simulator=lambda *_: _no_simulator(name),
        goal_params=(Param("setpoint", [float(v) for v in task.goal_default],
                           f"goal of the state fields {list(fields)} (the system file's mpc.goal.default; a goal "
                           f"topic replaces it)"),),
        goal_fields=fields,
        goal_position="setpoint",
        goal_factory=_setpoint_goal(task),
        paper_samples=0,
        paper_epochs=200,
        mpc_defaults={"horizon": task.horizon, "mode": "realtime" if task.rate > 0 else "lockstep",
                      "rate_hz": task.rate if task.rate > 0 else 10.0, "state_timeout": task.state_timeout},
    )


def register_robot(system: FileSystem) -> SystemEntry:
    """Register ``system`` (replacing an earlier robot of the same name); ``ValueError`` if the name is a
    built-in system's."""
    known = find_entry(system.name)
    if known is not None and known.sim_node:
        raise ValueError(f"system file {system.where}: name {system.name!r} is the built-in system of that name; "
                         "choose another name")
    return register_system(robot_entry(system), replace=True)


def load_stored_robot(name: str, overrides: Mapping[str, Any]) -> SystemEntry | None:
    """Registry loader: a robot ``name`` not registered in this process, rebuilt from the ``definition`` (and
    ``base_function``) it is asked with; ``None`` when ``overrides`` hold no definition of ``name``."""
    definition = overrides.get("definition")
    if not isinstance(definition, Mapping) or definition.get("name") != name:
        return None
    from saml_ros.systems.system_file import system_from_params

    return register_robot(system_from_params(overrides))


register_loader(load_stored_robot)
