"""The drag cart's registry entry: where each of its parts lives (imported when asked for), as a built-in
system's ``entry.py``."""

from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

from saml_ros.core.params import Param
from saml_ros.core.systems.entry import ControllerFactory, SystemEntry

if TYPE_CHECKING:
    from msg_schemas.base import SystemSchema
    from saml_ros.core.dynamics.system import System
    from saml_ros.core.mpc.shooting.tasks import ShootingTask
    from saml_ros.core.worlds.sim_core import SimConfig, SimCore, SteppedModel


def _class() -> type[System]:
    from helpers.toy_system.model import DragCart

    return DragCart


def _schema() -> SystemSchema:
    from helpers.toy_system.schema import SCHEMA

    return SCHEMA


def _controllers() -> Mapping[str, ControllerFactory]:
    from saml_ros.core.mpc.shooting import SLSQPShootingMPC, SQPShootingMPC

    return {"fast": SQPShootingMPC, "slsqp": SLSQPShootingMPC}


def _task(system: System, horizon: int) -> ShootingTask:
    from helpers.toy_system.model import DragCart
    from helpers.toy_system.task import drag_cart_task

    assert isinstance(system, DragCart)
    return drag_cart_task(system, horizon)


def _stepped(system: System) -> SteppedModel:
    from helpers.toy_system.model import DragCart
    from helpers.toy_system.world import drag_cart_model

    assert isinstance(system, DragCart)
    return drag_cart_model(system)


def _simulator(system: System, config: SimConfig, params: Mapping[str, Any]) -> SimCore:
    from saml_ros.core.worlds.sim_core import SteppedSim

    return SteppedSim(_stepped(system), config, publish_clock=params["publish_clock"])


ENTRY = SystemEntry(
    name="toy_drag_cart",
    summary="a cart on a line with quadratic drag (a toy system from the test tree)",
    system_class=_class,
    schema=_schema,
    controllers=_controllers,
    sim_node="",
    simulator=_simulator,
    goal_params=(Param("position", 0.0, "target position p (m)"),),
    goal_fields=("p",),
    mpc_task=_task,
    stepped_model=_stepped,
    paper_samples=2000,
    paper_epochs=20,
)
