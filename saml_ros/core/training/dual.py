"""The dual variables of a primal-dual run: multipliers lambda ``(E, K)`` >= 0, their update and their state.

One class per dual method (:data:`~saml_ros.core.training.config.DUAL_METHODS`, :func:`make_dual`); per step the
primal step descends on :meth:`DualVariables.lagrangian`, then :meth:`DualVariables.step` moves lambda with the
detached minibatch constraint estimates ``g`` ``(E, K)`` and projects it onto ``lambda >= 0``. With
``eps`` ``(K,)`` the constraint bounds:

* :class:`DualVariables` (``"paper"``, Algorithm 1 steps 3-4): primal loss ``f + sum_k lambda_k g_k``; lambda
  ascends on ``g`` with a torch optimizer (Adam as in the paper, or SGD).
* :class:`LagrangianDual` (``"lagrangian"``): the same arithmetic under its own name, for the recommended recipe
  (Adam on lambda at a fast rate, both rates cosine-decayed: the ``"auto"`` schedules are the paper's constant
  ones only for ``"paper"``).
* :class:`NuPIDual` (``"nupi"``): the same Lagrangian; lambda is driven by the PI controller
  :class:`~saml_ros.core.training.nupi.NuPI` on the relative violation ``g / eps``.
* :class:`AugmentedDual` (``"augmented"``, the augmented Lagrangian method, the method of multipliers as the
  cooper library's ``AugmentedLagrangian`` runs it): primal loss
  ``f + sum_k (relu(lambda_k + rho_k g_k)^2 - lambda_k^2) / (2 rho_k)``, whose gradient weights ``g_k`` by
  ``relu(lambda_k + rho_k g_k)``; ``lambda <- relu(lambda + s_t rho_k g_k)``, an SGD step on ``rho g`` at learning
  rate ``s_t`` = the dual schedule's factor (1 with a constant schedule), so the penalty ``rho_k = penalty /
  eps_k`` is the multiplier's step as well as the penalty's weight. ``dual_optimizer`` and ``dual_lr`` are not
  used: an adaptive optimizer (Adam) would divide the scale of ``rho g`` out of the step, leaving the Lagrangian
  with a penalty weight ``rho g`` that is negligible at useful step sizes.
* :class:`ResilientDual` (``"resilient"``, Hounie et al. 2023, "Resilient constrained learning"): each
  constraint may be relaxed to ``g_k <= u_k`` at a cost ``h(u) = alpha f / 2 sum_k (u_k / eps_k)^2`` added to the
  objective, with ``f`` the objective's minibatch estimate (so the price ``alpha`` is dimensionless: relaxing
  ``eps_k`` by a fraction ``r`` costs ``alpha r^2 / 2`` times the objective). The relaxation takes its exact
  minimiser for the current lambda, ``u_k = lambda_k eps_k^2 / (alpha f)`` (``h'(u) = lambda``), and lambda
  ascends on the relaxed violation ``g_k - u_k``. At a saddle point the relative relaxation is
  ``u_k / eps_k = (lambda_k eps_k / f) / alpha``: the constraint's elasticity (the relative objective gain per
  relative relaxation of eps) over the price, so a constraint is relaxed only where it is expensive, and lambda
  stays bounded when ``eps`` is out of reach.

What an engine needs from the dual variables is :meth:`~DualVariables.primal_weights` (the weights of ``g`` in
the primal gradient), :meth:`~DualVariables.ascent` (what the optimizer ascends on), :attr:`~DualVariables.value`
and the optimizer (its state is in checkpoints). The fast engine implements each class's arithmetic in flat form
(:mod:`saml_ros.core.training.engines.fast`).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from typing import Any, ClassVar

import torch

from saml_ros.core.spec import SpecValues
from saml_ros.core.training.config import TrainConfig, make_optimizer
from saml_ros.core.training.nupi import NuPI


class DualVariables:
    """Multipliers lambda ``(E, K)`` (one row per ensemble member), projected gradient ascent with a torch optimizer:
    the paper's method.

    Args:
        n_models: E.
        n_constraints: K (0: nothing to update; the run is Uniformly Accurate).
        dtype: of lambda (the run's dtype).
        optimizer: ``"adam"`` or ``"sgd"`` (see :data:`~saml_ros.core.training.config.OPTIMIZERS`).
        lr: alpha_lambda.
        eps: the constraint bounds ``(K,)`` (methods that scale by them need them; ones when omitted).

    Attributes:
        param: lambda as a torch Parameter (what :attr:`optimizer` updates; lambda starts at 0).
        optimizer: the dual optimizer (``maximize=True``: its step ascends along ``param.grad``).
        eps: the constraint bounds ``(K,)`` in lambda's dtype.
    """

    method: ClassVar[str] = "paper"

    def __init__(self, n_models: int, n_constraints: int, dtype: torch.dtype, optimizer: str = "adam",
                 lr: float = 1e-4, eps: Sequence[float] | None = None) -> None:
        self.param = torch.nn.Parameter(torch.zeros(n_models, n_constraints, dtype=dtype))
        self.optimizer = self._make_optimizer(optimizer, lr)
        e = [1.0] * n_constraints if eps is None else [float(v) for v in eps]
        if len(e) != n_constraints:
            raise ValueError(f"eps has {len(e)} entries for {n_constraints} constraints")
        self.eps = torch.tensor(e, dtype=dtype)

    def _make_optimizer(self, kind: str, lr: float) -> torch.optim.Optimizer:
        return make_optimizer(kind, [self.param], lr, maximize=True)

    @classmethod
    def for_config(cls, config: TrainConfig, n_models: int, n_constraints: int,
                   eps: Sequence[float] | None = None) -> DualVariables:
        """The dual variables ``config`` asks for (its ``dual_method``, dtype, ``dual_optimizer``, ``dual_lr`` and
        the method's parameters); ``eps`` ``(K,)`` are the constraint bounds."""
        return make_dual(config, n_models, n_constraints, eps)

    @property
    def n_constraints(self) -> int:
        return int(self.param.shape[1])

    @property
    def value(self) -> torch.Tensor:
        """lambda ``(E, K)``, always >= 0 (a detached view: it changes with every :meth:`step`)."""
        return self.param.detach()

    def primal_weights(self, g: torch.Tensor) -> torch.Tensor:
        """Weights ``(E, K)`` of the constraint estimates ``g`` in the primal gradient (lambda here)."""
        return self.value

    def lagrangian(self, vals: SpecValues) -> torch.Tensor:
        """The primal loss per member ``(E,)``: ``objective + sum_k lambda_k g_k`` with lambda held fixed."""
        return vals.lagrangian(self.value)

    def ascent(self, g: torch.Tensor, f: torch.Tensor | None = None) -> torch.Tensor:
        """What the optimizer ascends on, from the detached minibatch estimates of the constraints ``g`` ``(E, K)``
        and of the objective ``f`` ``(E,)`` (``g`` here)."""
        return g.clone()

    def relaxation(self, f: torch.Tensor | None = None) -> torch.Tensor:
        """How far each constraint is relaxed at objective ``f`` ``(E,)``: ``u`` ``(E, K)`` in the constraint's
        units (0 but for resilient constraints)."""
        return torch.zeros_like(self.value)

    def step(self, g: torch.Tensor, f: torch.Tensor | None = None) -> None:
        """Ascend on :meth:`ascent` of the detached minibatch estimates ``g`` ``(E, K)`` and ``f`` ``(E,)``, then
        project."""
        if not self.n_constraints:
            return
        self.param.grad = self.ascent(g, f)
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

    @property
    def lr(self) -> float:
        """The optimizer's current learning rate."""
        return float(self.optimizer.param_groups[0]["lr"])

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


class LagrangianDual(DualVariables):
    """The Lagrangian with lambda moved by ``optimizer`` (Adam or SGD): the paper's arithmetic (:class:`DualVariables`)
    under the name of the recommended recipe (``dual_method="lagrangian"``)."""

    method: ClassVar[str] = "lagrangian"


class NuPIDual(DualVariables):
    """lambda driven by a nuPI controller (:class:`~saml_ros.core.training.nupi.NuPI`, step ``lr``, gain ``kp``,
    smoothing ``nu``) on the relative violation ``g / eps``."""

    method: ClassVar[str] = "nupi"

    def __init__(self, n_models: int, n_constraints: int, dtype: torch.dtype, lr: float = 1e-3,
                 eps: Sequence[float] | None = None, kp: float = 10.0, nu: float = 0.0) -> None:
        self._kp, self._nu = float(kp), float(nu)
        super().__init__(n_models, n_constraints, dtype, "nupi", lr, eps)

    def _make_optimizer(self, kind: str, lr: float) -> torch.optim.Optimizer:
        return NuPI([self.param], lr=lr, kp=self._kp, nu=self._nu, maximize=True)

    def ascent(self, g: torch.Tensor, f: torch.Tensor | None = None) -> torch.Tensor:
        return torch.div(g, self.eps)


class AugmentedDual(DualVariables):
    """The augmented Lagrangian method (see the module docstring): ``rho_k = penalty / eps_k``; lambda moved by SGD
    at learning rate ``lr`` (the dual schedule's factor, 1 at the start) along ``rho g``: the method of multipliers
    ``lambda <- relu(lambda + rho g)``."""

    method: ClassVar[str] = "augmented"
    #: the multipliers' optimizer (its step along rho g is the method of multipliers' only with SGD)
    OPTIMIZER: ClassVar[str] = "sgd"

    def __init__(self, n_models: int, n_constraints: int, dtype: torch.dtype, eps: Sequence[float] | None = None,
                 penalty: float = 1.0, lr: float = 1.0) -> None:
        super().__init__(n_models, n_constraints, dtype, self.OPTIMIZER, lr, eps)
        self.penalty = float(penalty)
        self.rho = torch.div(torch.full_like(self.eps, self.penalty), self.eps)

    def primal_weights(self, g: torch.Tensor) -> torch.Tensor:
        """``relu(lambda + rho g)``: the gradient of the augmented term w.r.t. ``g``."""
        return torch.addcmul(self.value, self.rho, g).clamp_(min=0.0)

    def lagrangian(self, vals: SpecValues) -> torch.Tensor:
        """``f + sum_k w_k g_k`` with ``w = relu(lambda + rho g)`` held fixed: the augmented Lagrangian's gradient."""
        w = self.primal_weights(vals.constraints.detach())
        return vals.objective + (w * vals.constraints).sum(-1)

    def ascent(self, g: torch.Tensor, f: torch.Tensor | None = None) -> torch.Tensor:
        return torch.mul(g, self.rho)


class ResilientDual(DualVariables):
    """Resilient constraints (see the module docstring): relaxation ``u = lambda eps^2 / (alpha f)``, ascent on
    ``g - u``; ``relax_cost`` is alpha (dimensionless)."""

    method: ClassVar[str] = "resilient"
    #: the objective estimate is clamped to at least this (a perfect minibatch must not make the relaxation infinite)
    F_MIN = 1e-12

    def __init__(self, n_models: int, n_constraints: int, dtype: torch.dtype, optimizer: str = "adam",
                 lr: float = 1e-4, eps: Sequence[float] | None = None, relax_cost: float = 100.0) -> None:
        super().__init__(n_models, n_constraints, dtype, optimizer, lr, eps)
        self.relax_cost = float(relax_cost)
        self.eps2 = torch.div(torch.mul(self.eps, self.eps), self.relax_cost)  # eps^2 / alpha

    def decay(self, f: torch.Tensor) -> torch.Tensor:
        """``eps^2 / (alpha f)`` ``(E, K)``: the relaxation per unit of lambda at objective ``f`` ``(E,)``."""
        return torch.div(self.eps2, f.clamp_min(self.F_MIN).unsqueeze(-1))

    def relaxation(self, f: torch.Tensor | None = None) -> torch.Tensor:
        if f is None:
            raise ValueError("the resilient relaxation depends on the objective f")
        return torch.mul(self.value, self.decay(f.to(self.value.dtype)))

    def ascent(self, g: torch.Tensor, f: torch.Tensor | None = None) -> torch.Tensor:
        if f is None:
            raise ValueError("resilient constraints need the objective's minibatch estimate f")
        return torch.sub(g, torch.mul(self.value, self.decay(f)))


log = logging.getLogger("saml_ros.trainer")
_WARNED: list[str] = []  # the once-per-process warning about 'augmented' and an optimizer it does not use

#: ``TrainConfig.dual_method`` -> class
DUAL_CLASSES: dict[str, type[DualVariables]] = {
    "paper": DualVariables, "lagrangian": LagrangianDual, "nupi": NuPIDual, "augmented": AugmentedDual,
    "resilient": ResilientDual,
}


def make_dual(config: TrainConfig, n_models: int, n_constraints: int,
              eps: Sequence[float] | None = None) -> DualVariables:
    """The dual variables of ``config.dual_method`` for ``n_models`` members and constraints with bounds ``eps``."""
    dt, m = config.torch_dtype, config.dual_method
    if m in ("paper", "lagrangian"):
        return DUAL_CLASSES[m](n_models, n_constraints, dt, config.dual_optimizer, config.dual_lr, eps)
    if m == "nupi":
        return NuPIDual(n_models, n_constraints, dt, config.dual_lr, eps, config.nupi_kp, config.nupi_ema)
    if m == "augmented":
        if config.dual_optimizer != AugmentedDual.OPTIMIZER and not _WARNED:
            _WARNED.append(m)
            log.warning("dual_method 'augmented' is the augmented Lagrangian method: lambda <- relu(lambda + rho g), "
                        "rho = penalty / eps (penalty %g); dual_optimizer %r and dual_lr are not used. A configuration "
                        "written for the former 'augmented' (the multipliers moved by Adam, in effect the Lagrangian) "
                        "gets that arithmetic as 'lagrangian', the default (docs/training.md). dual_optimizer: sgd "
                        "(what 'augmented' uses) silences this.", config.penalty, config.dual_optimizer)
        return AugmentedDual(n_models, n_constraints, dt, eps, config.penalty, config.dual_lr0)
    if m == "resilient":
        return ResilientDual(n_models, n_constraints, dt, config.dual_optimizer, config.dual_lr, eps,
                             config.relax_cost)
    raise ValueError(f"unknown dual method {m!r}")
