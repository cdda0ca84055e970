"""The dual variables of a primal-dual run: multipliers lambda ``(E, K)`` >= 0, their update and their state.

:class:`DualVariables` is the paper's method (Algorithm 1, steps 3-4): the primal step descends on the Lagrangian
``f + sum_k lambda_k g_k`` with lambda held fixed, then lambda ascends on the detached minibatch constraint
estimates ``g`` with a torch optimizer (Adam as in the paper, or SGD) and is projected onto ``lambda >= 0``.

What a run asks of its dual variables is :meth:`DualVariables.lagrangian` (the primal loss per member),
:meth:`DualVariables.step` (the dual update after the primal one), :attr:`DualVariables.value` and
:meth:`DualVariables.state_dict`; a method that changes how the Lagrangian is formed or how lambda moves is a
subclass that overrides those (an augmented Lagrangian: ``lagrangian`` and ``step``; slack variables for
resilient constraints: extra state in ``step`` / ``state_dict``), and a multiplier controller that is a torch
optimizer (PI control) is just another ``optimizer``. Engines that run their own update of the paper's method
(the fast engine) accept exactly :class:`DualVariables` and fall back to the plain loop for a subclass.
"""

from __future__ import annotations

from typing import Any

import torch

from saml_ros.core.spec import SpecValues
from saml_ros.core.training.config import TrainConfig, make_optimizer


class DualVariables:
    """Multipliers lambda ``(E, K)`` (one row per ensemble member), projected gradient ascent with a torch optimizer.

    Args:
        n_models: E.
        n_constraints: K (0: nothing to update; the run is Uniformly Accurate).
        dtype: of lambda (the run's dtype).
        optimizer: ``"adam"`` or ``"sgd"`` (see :data:`~saml_ros.core.training.config.OPTIMIZERS`).
        lr: alpha_lambda.

    Attributes:
        param: lambda as a torch Parameter (what :attr:`optimizer` updates; lambda starts at 0).
        optimizer: the dual optimizer (``maximize=True``: its step ascends along ``param.grad``).
    """

    def __init__(self, n_models: int, n_constraints: int, dtype: torch.dtype, optimizer: str = "adam",
                 lr: float = 1e-4) -> None:
        self.param = torch.nn.Parameter(torch.zeros(n_models, n_constraints, dtype=dtype))
        self.optimizer = make_optimizer(optimizer, [self.param], lr, maximize=True)

    @classmethod
    def for_config(cls, config: TrainConfig, n_models: int, n_constraints: int) -> DualVariables:
        """The dual variables ``config`` asks for (its dtype, ``dual_optimizer`` and ``dual_lr``)."""
        return cls(n_models, n_constraints, config.torch_dtype, config.dual_optimizer, config.dual_lr)

    @property
    def n_constraints(self) -> int:
        return int(self.param.shape[1])

    @property
    def value(self) -> torch.Tensor:
        """lambda ``(E, K)``, always >= 0 (a detached view: it changes with every :meth:`step`)."""
        return self.param.detach()

    def lagrangian(self, vals: SpecValues) -> torch.Tensor:
        """The primal loss per member ``(E,)``: ``objective + sum_k lambda_k g_k`` with lambda held fixed."""
        return vals.lagrangian(self.value)

    def step(self, g: torch.Tensor) -> None:
        """Ascend on the detached minibatch constraint estimates ``g`` ``(E, K)``, then project."""
        if not self.n_constraints:
            return
        self.param.grad = g.clone()
        self.optimizer.step()
        self.project_()

    @torch.no_grad()
    def project_(self) -> None:
        """``lambda <- max(lambda, 0)``."""
        self.param.clamp_(min=0.0)

    @torch.no_grad()
    def assign_(self, lam: Any) -> None:
        """Set lambda to ``lam`` ``(E, K)`` (e.g. from a checkpoint; the optimizer state is left as it is)."""
        self.param.copy_(torch.as_tensor(lam, dtype=self.param.dtype))

    def set_lr(self, lr: float) -> None:
        """Use learning rate ``lr`` from now on (a torch optimizer restores the one saved with its state)."""
        for group in self.optimizer.param_groups:
            group["lr"] = lr

    def state_dict(self) -> dict[str, Any]:
        """``{"lam": (E, K) copy, "optimizer": the optimizer's state_dict}``."""
        return {"lam": self.value.clone(), "optimizer": self.optimizer.state_dict()}

    def load_state_dict(self, st: dict[str, Any]) -> None:
        self.assign_(st["lam"])
        self.optimizer.load_state_dict(st["optimizer"])
