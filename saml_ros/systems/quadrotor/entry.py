"""The quadrotor's registry entry: where each of its parts lives (imported when asked for)."""

from __future__ import annotations

import math
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


# ------------------------------------------------------------------------------------------ quadrotor
def _quadrotor_class() -> type[System]:
    from saml_ros.systems.quadrotor.model import Quadrotor

    return Quadrotor


def _quadrotor_schema() -> SystemSchema:
    from msg_schemas.quadrotor import SCHEMA

    return SCHEMA


def _quadrotor_task(system: System, horizon: int, **options: float) -> ShootingTask:
    from saml_ros.systems.quadrotor.model import Quadrotor
    from saml_ros.systems.quadrotor.task import quadrotor_task

    return quadrotor_task(_as(system, Quadrotor), horizon, **options)


def _quadrotor_base_np(system: System) -> BaseModelNP:
    from saml_ros.systems.quadrotor.dynamics_np import QuadrotorBaseNP
    from saml_ros.systems.quadrotor.model import Quadrotor

    return QuadrotorBaseNP(_as(system, Quadrotor))


def _quadrotor_true_np(system: System) -> BaseModelNP:
    from saml_ros.systems.quadrotor.dynamics_np import QuadrotorTrueNP
    from saml_ros.systems.quadrotor.model import Quadrotor

    return QuadrotorTrueNP(_as(system, Quadrotor))


def _quadrotor_model(system: System, landing_height: float = 0.1) -> SteppedModel:
    from saml_ros.systems.quadrotor.model import Quadrotor
    from saml_ros.systems.quadrotor.world import quadrotor_model

    return quadrotor_model(_as(system, Quadrotor), landing_height)


def _quadrotor_simulator(system: System, config: SimConfig, params: Mapping[str, Any]) -> SimCore:
    from saml_ros.core.worlds.sim_core import SteppedSim

    return SteppedSim(_quadrotor_model(system, params["landing_height"]), config,
                      publish_clock=params["publish_clock"])


QUADROTOR = SystemEntry(
    name="quadrotor",
    summary="quadrotor with ground effect landing at a target (13-d rigid body, four motor forces, dt = 0.1 s)",
    system_class=_quadrotor_class,
    schema=_quadrotor_schema,
    controllers=_shooting_controllers,
    sim_node="quadrotor_sim",
    simulator=_quadrotor_simulator,
    goal_params=(
        Param("position", [0.0, 0.0, 0.0], "landing target [x, y, z] (m, world); the paper lands at the origin"),
    ),
    goal_fields=("px", "py", "pz"),
    task_params=(
        Param("min_height", 0.2, "lowest allowed height of the centre of mass over the horizon (m)"),
        Param("qw_tol", 0.05, "attitude at the end of the horizon: |qw_T - 1| <= qw_tol"),
        Param("tilt_max", math.inf, "attitude at every step: |qx_t|, |qy_t| <= tilt_max (quaternion components; "
                                    "0.2 = about 23 degrees); inf = no such rows (the paper's problem)", finite=False),
    ),
    mpc_task=_quadrotor_task,
    base_model_np=_quadrotor_base_np,
    true_model_np=_quadrotor_true_np,
    stepped_model=_quadrotor_model,
    paper_samples=10000,
    paper_epochs=3000,
    # the MPC only takes checkpoints whose recorded in-region constraint estimate is <= 0.002 (one-step squared
    # error <= 0.003 where pz <= 1.5 m, eps = 0.001): the first, barely trained models sent some landings metres
    # off target
    bringup={
        "system": "quadrotor",
        "sim_time": 300.0,
        # the world: the paper's ground effect. The capacity sweep and the demo (demo --world wind, its default)
        # add a wind field above the pad's shelter (saml_ros/demo/landing.py WORLDS; docs/demo.md)
        "sim": {"mode": "lockstep", "episode_steps": 50, "seed": 0, "lockstep_timeout": 5.0},
        "learner": {"min_transitions": 200, "checkpoint_period": 5.0, "updates_per_second": 0.0,
                    "training_niceness": 0, "train.batch_size": 128, "model.ensemble": 5},
        "mpc": {"solver": "fast", "horizon": 10, "poll_period": 0.5, "gate.max_constraint": 0.002,
                "goal.position": [0.0, 0.0, 0.2], "task.tilt_max": 0.2,
                "guard.max_disagreement": 0.1, "guard.bound_residual": True, "guard.rollback": True,
                "guard.margin_relative": 0.08, "guard.infeasible": True, "guard.task_check": True},
    },
    experiment="quadrotor",
    spec_file="specs/quadrotor.yaml",
)
