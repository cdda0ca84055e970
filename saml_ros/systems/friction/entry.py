"""The friction system's registry entry: where each of its parts lives (imported when asked for)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

from saml_ros.core.params import Param
from saml_ros.core.systems.entry import SystemEntry
from saml_ros.systems.common import _as, _shooting_controllers

if TYPE_CHECKING:
    from msg_schemas.base import SystemSchema
    from saml_ros.core.dynamics.system import System
    from saml_ros.core.mpc.dynamics_np import BaseModelNP
    from saml_ros.core.mpc.shooting.tasks import ShootingTask
    from saml_ros.core.worlds.sim_core import SimConfig, SimCore, SteppedModel


# ------------------------------------------------------------------------------------------ friction
def _friction_class() -> type[System]:
    from saml_ros.systems.friction.model import FrictionDoubleIntegrator

    return FrictionDoubleIntegrator


def _friction_schema() -> SystemSchema:
    from msg_schemas.friction import SCHEMA

    return SCHEMA


def _friction_task(system: System, horizon: int) -> ShootingTask:
    from saml_ros.systems.friction.model import FrictionDoubleIntegrator
    from saml_ros.systems.friction.task import friction_task

    return friction_task(_as(system, FrictionDoubleIntegrator), horizon)


def _friction_base_np(system: System) -> BaseModelNP:
    from saml_ros.systems.friction.dynamics_np import FrictionBaseNP
    from saml_ros.systems.friction.model import FrictionDoubleIntegrator

    return FrictionBaseNP(_as(system, FrictionDoubleIntegrator))


def _friction_true_np(system: System) -> BaseModelNP:
    from saml_ros.systems.friction.dynamics_np import FrictionTrueNP
    from saml_ros.systems.friction.model import FrictionDoubleIntegrator

    return FrictionTrueNP(_as(system, FrictionDoubleIntegrator))


def _friction_model(system: System) -> SteppedModel:
    from saml_ros.systems.friction.model import FrictionDoubleIntegrator
    from saml_ros.systems.friction.world import friction_model

    return friction_model(_as(system, FrictionDoubleIntegrator))


def _friction_simulator(system: System, config: SimConfig, params: Mapping[str, Any]) -> SimCore:
    from saml_ros.core.worlds.sim_core import SteppedSim

    return SteppedSim(_friction_model(system), config, publish_clock=params["publish_clock"])


FRICTION = SystemEntry(
    name="friction",
    summary="double integrator with position-dependent friction (1-D cart, dt = 0.1 s)",
    system_class=_friction_class,
    schema=_friction_schema,
    controllers=_shooting_controllers,
    sim_node="friction_sim",
    simulator=_friction_simulator,
    goal_params=(Param("position", 0.0, "target position p (m); the paper drives the cart to the origin"),),
    goal_fields=("p",),
    mpc_task=_friction_task,
    base_model_np=_friction_base_np,
    true_model_np=_friction_true_np,
    stepped_model=_friction_model,
    paper_samples=15000,
    paper_epochs=200,
    bringup={
        "system": "friction",
        "sim_time": 300.0,
        "sim": {"mode": "lockstep", "episode_steps": 100, "seed": 0, "lockstep_timeout": 5.0},
        "learner": {"min_transitions": 200, "checkpoint_period": 5.0, "updates_per_second": 0.0,
                    "training_niceness": 0},
        # the live monitor's roll back (on by default; here as in config/loop_friction.yaml)
        "mpc": {"solver": "fast", "horizon": 10, "poll_period": 0.5, "guard.rollback": True},
    },
    experiment="friction",
    spec_file="specs/friction.yaml",
)
