"""The paddle ball's registry entry: where each of its parts lives (imported when asked for)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

from saml_ros.core.params import Param
from saml_ros.core.systems.entry import ControllerFactory, SystemEntry
from saml_ros.systems.common import _as

if TYPE_CHECKING:
    import numpy as np

    from msg_schemas.base import SystemSchema
    from saml_ros.core.dynamics.system import System
    from saml_ros.core.mpc.dynamics_np import BaseModelNP
    from saml_ros.core.worlds.sim_core import SimConfig, SimCore
    from saml_ros.systems.paddle_ball.mpc import PaddleGoal


# ------------------------------------------------------------------------------------------ paddle ball
def _paddle_class() -> type[System]:
    from saml_ros.systems.paddle_ball.model import PaddleBall

    return PaddleBall


def _paddle_schema() -> SystemSchema:
    from msg_schemas.paddle_ball import SCHEMA

    return SCHEMA


def _paddle_controllers() -> Mapping[str, ControllerFactory]:
    from saml_ros.systems.paddle_ball.mpc import GaussNewtonPaddle, SLSQPPaddle

    return {"fast": GaussNewtonPaddle, "slsqp": SLSQPPaddle}


def _paddle_base_np(system: System) -> BaseModelNP:
    from saml_ros.systems.paddle_ball.dynamics_np import PaddleBaseNP
    from saml_ros.systems.paddle_ball.model import PaddleBall

    return PaddleBaseNP(_as(system, PaddleBall))


def _paddle_true_np(system: System) -> BaseModelNP:
    from saml_ros.systems.paddle_ball.dynamics_np import PaddleTrueNP
    from saml_ros.systems.paddle_ball.model import PaddleBall

    return PaddleTrueNP(_as(system, PaddleBall))


def _paddle_simulator(system: System, config: SimConfig, params: Mapping[str, Any]) -> SimCore:
    from saml_ros.systems.paddle_ball.sim import paddle_ball_simulator

    return paddle_ball_simulator(system, config, params)


def _paddle_goal(entry: SystemEntry, values: Mapping[str, Any]) -> PaddleGoal:
    """:class:`~saml_ros.systems.paddle_ball.mpc.PaddleGoal` from ``goal.target_xy`` and the bound pairs."""
    from saml_ros.systems.paddle_ball.mpc import paddle_goal

    bounds: dict[str, tuple[float, float]] = {}
    for key in ("roll", "pitch", "v_rel"):
        lo, hi = float(values[f"{key}_min"]), float(values[f"{key}_max"])
        if not lo <= hi:
            raise ValueError(f"goal.{key}_min = {values[f'{key}_min']} must be <= goal.{key}_max = "
                             f"{values[f'{key}_max']}")
        bounds[key] = (lo, hi)
    return paddle_goal(target_xy=entry.position_goal(values), roll=bounds["roll"], pitch=bounds["pitch"],
                       v_rel=bounds["v_rel"])


def _paddle_loop_event(system: System, x: np.ndarray, y: np.ndarray,
                       goal: Any) -> tuple[np.ndarray, np.ndarray, float, bool]:
    from saml_ros.systems.paddle_ball.model import PaddleBall
    from saml_ros.systems.paddle_ball.mpc.problem import loop_bounce

    return loop_bounce(_as(system, PaddleBall), x, y, goal)


PADDLE_BALL = SystemEntry(
    name="paddle_ball",
    summary="ball bouncing on a paddle (MuJoCo), one transition per impact: the paddle's velocity and normal set "
            "the ball's post-impact velocity",
    system_class=_paddle_class,
    schema=_paddle_schema,
    controllers=_paddle_controllers,
    sim_node="paddle_ball_sim",
    simulator=_paddle_simulator,
    goal_params=(
        Param("target_xy", [0.0, 0.0], "where the ball should come down, [x, y] (m, world)"),
        Param("roll_min", -0.4, "lower bound of the paddle roll (rad)"),
        Param("roll_max", 0.4, "upper bound of the paddle roll (rad)"),
        Param("pitch_min", -0.4, "lower bound of the paddle pitch (rad)"),
        Param("pitch_max", 0.4, "upper bound of the paddle pitch (rad)"),
        Param("v_rel_min", 3.0, "lower bound of the ball's speed relative to the paddle after impact (m/s)"),
        Param("v_rel_max", 5.0, "upper bound of the ball's speed relative to the paddle after impact (m/s)"),
    ),
    goal_fields=("px", "py"),
    goal_position="target_xy",
    goal_factory=_paddle_goal,
    mpc_horizon=False,  # one-shot: the MPC chooses one impact command
    base_model_np=_paddle_base_np,
    true_model_np=_paddle_true_np,
    paper_samples=20000,
    paper_epochs=200,
    bringup={
        "system": "paddle_ball",
        "sim_time": 300.0,
        "sim": {"mode": "lockstep", "seed": 0, "lockstep_timeout": 5.0},
        "learner": {"min_transitions": 100, "checkpoint_period": 5.0, "updates_per_second": 0.0,
                    "training_niceness": 0},
        "mpc": {"solver": "fast", "poll_period": 0.5, "guard.rollback": True},
    },
    experiment="paddle_ball",
    spec_file="specs/paddle_ball.yaml",
    loop_event=_paddle_loop_event,
)
