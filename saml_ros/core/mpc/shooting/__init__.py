"""Single-shooting MPC for the time-stepped systems (friction, quadrotor), one module per concept:

* :mod:`.tasks`: the paper's problems as data (:class:`ShootingTask`; :func:`saml_ros.core.mpc.make_task` builds a system's own);
* :mod:`.controller`: :class:`ShootingMPC`, what both solvers share (warm start, rollout, result, failures);
* :mod:`.sqp`: the fast solver :class:`SQPShootingMPC` (exact-derivative SQP);
* :mod:`.slsqp`: the reference :class:`SLSQPShootingMPC` (scipy SLSQP, finite differences);
* :mod:`.qp`: the small dense QP solvers of the SQP subproblems.
"""

from saml_ros.core.mpc.shooting.controller import ShootingMPC
from saml_ros.core.mpc.shooting.slsqp import SLSQPShootingMPC
from saml_ros.core.mpc.shooting.sqp import SQPShootingMPC
from saml_ros.core.mpc.shooting.tasks import ShootingTask

__all__ = ["SLSQPShootingMPC", "SQPShootingMPC", "ShootingMPC", "ShootingTask"]
