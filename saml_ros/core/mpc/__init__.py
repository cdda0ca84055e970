"""ROS-free MPC for the paper's three tasks (see ``docs/mpc.md``).

``make_controller(system, model=None, solver="fast" | "slsqp", **options) -> Controller`` builds the
controller; ``controller.solve(x0, goal) -> MPCResult``; ``controller.set_model(model)`` hot-swaps the
learned model between solves; ``closed_loop(system, controller, x0, steps, on_step=hook) -> ClosedLoopRun``
runs it on the true system.

Modules: :mod:`.contract` (``MPCResult``, the ``Controller`` protocol), :mod:`.factory` (``make_controller``),
:mod:`.loop` (the closed-loop runner), :mod:`.dynamics_np` / :mod:`.mlp_np` (the numpy prediction model
``f_hat + phi`` with exact Jacobians), :mod:`.shooting` (time-stepped systems) and :mod:`.generic` (robots'
system files). A system's own planner parts (its numpy twins, its shooting task, the paddle ball's one-shot
planner ``saml_ros.systems.paddle_ball.mpc``) live in its folder, ``saml_ros.systems.<name>``, reached through
its registry entry.
"""

from saml_ros.core.mpc.contract import Controller, MPCResult
from saml_ros.core.mpc.factory import SOLVERS, base_model_np, make_controller, make_task
from saml_ros.core.mpc.loop import ClosedLoopRun, LoopStep, StepHook, closed_loop
from saml_ros.core.mpc.shooting import ShootingMPC, ShootingTask, SLSQPShootingMPC, SQPShootingMPC

__all__ = [
    "SOLVERS",
    "ClosedLoopRun",
    "Controller",
    "LoopStep",
    "MPCResult",
    "SLSQPShootingMPC",
    "SQPShootingMPC",
    "ShootingMPC",
    "ShootingTask",
    "StepHook",
    "closed_loop",
    "base_model_np",
    "make_controller",
    "make_task",
]
