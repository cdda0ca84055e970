"""The paddle ball's one-shot MPC (paper eq. ball_paddle_opt), one module per concept:

* :mod:`.problem`: the goal parameters (:class:`PaddleGoal`, :func:`paddle_goal`) and the problem at one state;
* :mod:`.controller`: the controllers, :class:`GaussNewtonPaddle` (fast) and :class:`SLSQPPaddle` (reference);
* :mod:`.multistart`: the fast solver's multi-start strategy (probe, Newton runs, valley hop);
* :mod:`.projected_newton`: one run of projected Gauss-Newton / Newton iterations from one start;
* :mod:`.feasible_set`: the box and speed bounds, projection and active constraints;
* :mod:`.landing_error`: the landing error and its exact first and second derivatives.
"""

from saml_ros.systems.paddle_ball.mpc.controller import GaussNewtonPaddle, PaddleController, SLSQPPaddle
from saml_ros.systems.paddle_ball.mpc.problem import PaddleGoal, PaddleProblem, paddle_goal

__all__ = ["GaussNewtonPaddle", "PaddleController", "PaddleGoal", "PaddleProblem", "SLSQPPaddle", "paddle_goal"]
