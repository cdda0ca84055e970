"""ROS-free MPC for the paper's three tasks (see ``docs/mpc.md``).

``make_controller(system, model=None, solver="fast" | "slsqp", **options) -> Controller`` builds the
controller; ``controller.solve(x0, goal) -> MPCResult``; ``controller.set_model(model)`` hot-swaps the
learned model between solves; ``closed_loop(system, controller, x0, steps)`` runs it on the true system.
"""

from saml_ros.core.mpc.factory import SOLVERS, make_controller
from saml_ros.core.mpc.loop import closed_loop
from saml_ros.core.mpc.paddle import GaussNewtonPaddle, PaddleGoal, SLSQPPaddle, paddle_goal
from saml_ros.core.mpc.shooting import SLSQPShootingMPC, SQPShootingMPC
from saml_ros.core.mpc.tasks import ShootingTask, make_task
from saml_ros.core.mpc.types import Controller, MPCResult

__all__ = [
    "SOLVERS",
    "Controller",
    "GaussNewtonPaddle",
    "MPCResult",
    "PaddleGoal",
    "SLSQPPaddle",
    "SLSQPShootingMPC",
    "SQPShootingMPC",
    "ShootingTask",
    "closed_loop",
    "make_controller",
    "make_task",
    "paddle_goal",
]
