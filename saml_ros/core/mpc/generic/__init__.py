"""The generic MPC: plans for any robot described by a system file with an ``mpc:`` section (docs/your_robot.md,
"Control it"; docs/mpc.md, "The generic planner").

* :mod:`.dynamics`: the prediction model f_hat + phi with exact Jacobians (CasADi for f_hat's array-namespace form,
  torch autograd for a plain torch f_hat, the network's own for phi);
* :mod:`.problem`: the task's cost and constraints as numbers;
* :mod:`.sqp`: :class:`GenericSQP`, the Gauss-Newton SQP (the default path);
* :mod:`.nlp`: :class:`CasadiNLP`, the whole problem as one CasADi NLP (IPOPT; the network written symbolically
  with its weights as a parameter vector), the reference path;
* :func:`generic_controllers`: what a robot's registry entry hands :func:`~saml_ros.core.mpc.factory.make_controller`.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from saml_ros.core.mpc.generic.sqp import GenericSQP, system_task


def generic_controllers(planner: str = "sqp") -> Mapping[str, Any]:
    """The controllers of a robot with an ``mpc:`` section, by the MPC node's ``solver`` name: ``fast`` = the path
    its ``mpc.solver`` names (``planner``: ``sqp``, the default, or ``ipopt``), ``slsqp`` = the reference (IPOPT on
    the whole NLP, :class:`~saml_ros.core.mpc.generic.nlp.CasadiNLP`)."""
    from saml_ros.core.mpc.generic.nlp import CasadiNLP

    return {"fast": CasadiNLP if planner == "ipopt" else GenericSQP, "slsqp": CasadiNLP}


__all__ = ["GenericSQP", "generic_controllers", "system_task"]
