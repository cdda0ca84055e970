"""nuPI, a PI controller of the multipliers as a torch optimizer (Sohrabi et al., "On PI controllers for updating
Lagrange multipliers in constrained optimization", ICML 2024; the update of the cooper library's ``nuPI`` with
integral gain K_I = 1 and its "SGD" initialisation).

With error signal ``e_t`` (the parameter's ``grad``; for the multipliers the relative violation g / eps), step
``eta`` (``lr``), proportional gain ``K_P`` and smoothing ``nu``, ascending (``maximize=True``)::

    xi_t        = nu xi_{t-1} + (1 - nu) e_t,  xi_{-1} = e_0  (the first step is plain gradient ascent)
    theta_{t+1} = theta_t + eta (e_t + K_P (xi_t - xi_{t-1}))
                = theta_t + eta (e_t + K_P (1 - nu) (e_t - xi_{t-1}))

so without projection ``theta_t = theta_0 + eta (sum_{s<t} e_s + K_P (xi_{t-1} - e_0))``: an integral term (what
gradient ascent does) plus a proportional one that moves the multiplier as soon as the violation changes, which
damps the oscillation of plain ascent. :func:`nupi_update` is the arithmetic, shared with the fast engine.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from typing import Any

import torch
from torch import Tensor


@torch.no_grad()
def nupi_update(param: Tensor, error: Tensor, xi: Tensor | None, lr: float, kp: float, nu: float,
                maximize: bool) -> Tensor:
    """One nuPI step of ``param`` in place with error ``error``; ``xi`` is the smoothed error of the previous step
    (``None`` on the first step). Returns the new smoothed error (``xi`` updated in place when given)."""
    if xi is None:
        upd = error
        xi = error.clone()
    else:
        upd = torch.sub(error, xi).mul_(kp * (1.0 - nu)).add_(error)
        xi.mul_(nu).add_(error, alpha=1.0 - nu)
    param.add_(upd, alpha=lr if maximize else -lr)
    return xi


class NuPI(torch.optim.Optimizer):
    """The nuPI controller (module docstring) over ``params``; state per parameter: ``xi`` (the smoothed error)
    and ``step``."""

    def __init__(self, params: Iterable[Tensor], lr: float, kp: float = 0.0, nu: float = 0.0,
                 maximize: bool = False) -> None:
        if lr < 0 or kp < 0 or not 0 <= nu < 1:
            raise ValueError(f"nuPI needs lr >= 0, kp >= 0 and 0 <= nu < 1, got {lr}, {kp}, {nu}")
        super().__init__(params, {"lr": lr, "kp": kp, "nu": nu, "maximize": maximize})

    @torch.no_grad()
    def step(self, closure: Callable[[], Any] | None = None) -> None:  # type: ignore[override]
        for group in self.param_groups:
            for p in group["params"]:
                if p.grad is None:
                    continue
                st = self.state[p]
                st["xi"] = nupi_update(p, p.grad, st.get("xi"), float(group["lr"]), float(group["kp"]),
                                       float(group["nu"]), bool(group["maximize"]))
                st["step"] = torch.tensor(float(st.get("step", torch.tensor(0.0))) + 1.0)
