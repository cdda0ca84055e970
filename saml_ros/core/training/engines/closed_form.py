"""Spec terms in closed form for the fast engine: terms that share a loss and fields form a :class:`TermGroup`;
:func:`group_step_fn` computes a group's minibatch estimates and their gradient w.r.t. the prediction without
autograd (one ``bmm`` each way with the region masks).

Shapes: ``E`` ensemble members, ``B`` minibatch size, ``T = 1 + K`` spec terms (objective first), ``Tg`` terms
of one group.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor

from saml_ros.core.spec import LOSS_TYPES, Term

#: losses with a closed-form gradient here (all of :data:`saml_ros.core.spec.LOSS_TYPES`)
SUPPORTED_LOSSES = frozenset(LOSS_TYPES)
# Below this l2 norm the l2 / normalized loss gradient e / ||e|| is taken as 0 (PyTorch masks exactly ||e|| = 0;
# a float32 error this small cannot occur unless the error is exactly zero).
_TINY = 1e-30


@dataclass
class TermGroup:
    """Spec terms sharing loss, fields and Huber delta; ``cols`` are their indices among the T terms."""

    loss: str
    fields: tuple[int, ...]
    delta: float
    cols: list[int]
    terms: list[Term]


def term_groups(terms: list[Term]) -> list[TermGroup]:
    """``terms`` (objective first) grouped by loss, fields and Huber delta, in order of first appearance."""
    out: dict[tuple[str, tuple[int, ...], float], TermGroup] = {}
    for j, t in enumerate(terms):
        key = (t.loss, tuple(t.fields), float(t.huber_delta) if t.loss == "huber" else 0.0)
        if key not in out:
            out[key] = TermGroup(key[0], key[1], key[2], [], [])
        out[key].cols.append(j)
        out[key].terms.append(t)
    return list(out.values())


@dataclass
class StepGroup:
    """One group's tensors for one minibatch: masks ``(E, B, Tg)``, estimator denominators ``den`` and
    gradient-weight denominators ``wden`` ``(E, Tg)``, ``-eps`` (0 for an empty conditional region) and, for the
    normalized loss, ``||y||`` ``(E, B, 1)``."""

    mk: Tensor
    den: Tensor
    wden: Tensor
    negeps: Tensor
    ny: Tensor | None


#: ``values(err, step_group, row) -> context``: writes a group's term values into ``row`` ``(E, T)``
GroupValues = Callable[[Tensor, "StepGroup", Tensor], tuple[Tensor, Tensor, Tensor]]
#: ``grad(context, step_group, coef) -> dL/dpred contribution`` of ``sum_t coef_t * value_t``
GroupGrad = Callable[[tuple[Tensor, Tensor, Tensor], "StepGroup", Tensor], Tensor]


def group_step_fn(g: TermGroup, n_y: int, single: bool) -> tuple[GroupValues, GroupGrad]:
    """``(values, grad)`` for one group: ``values(err, step_group, row)`` writes the group's term values into
    ``row`` ``(E, T)`` and returns a context; ``grad(context, step_group, coef)`` returns the gradient of
    ``sum_t coef_t * value_t`` w.r.t. ``pred``. Every group's values come first, so the coefficients may depend
    on this minibatch's values (the augmented Lagrangian's do).

    Per-sample gradients are the closed forms of autograd's: l2 ``e / ||e||`` (0 at e = 0), squared_l2 ``2 e``,
    l1 ``sign(e)``, huber ``clamp(e, -delta, delta)``, normalized ``e / (||e|| ||y||)``.
    """
    loss, delta = g.loss, g.delta
    all_fields = g.fields == tuple(range(n_y))
    fidx = torch.tensor(g.fields, dtype=torch.long)
    cols = g.cols
    lo, hi = cols[0], cols[-1] + 1
    contiguous = cols == list(range(lo, hi))
    col_idx = torch.tensor(cols, dtype=torch.long)
    bmm, div = torch.bmm, torch.div

    def values(err: Tensor, sg: StepGroup, row: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        eg = err if all_fields else err.index_select(-1, fidx)
        nrm = eg  # placeholder for the norms of l2 / normalized
        if loss == "l2":
            nrm = torch.linalg.vector_norm(eg, dim=-1, keepdim=True)
            lval = nrm
        elif loss == "squared_l2":
            lval = (eg * eg).sum(-1, keepdim=True)
        elif loss == "normalized":
            assert sg.ny is not None
            nrm = torch.linalg.vector_norm(eg, dim=-1, keepdim=True)
            lval = nrm / sg.ny
        elif loss == "l1":
            lval = eg.abs().sum(-1, keepdim=True)
        else:
            ab = eg.abs()
            lval = torch.where(ab <= delta, 0.5 * eg * eg, delta * (ab - 0.5 * delta)).sum(-1, keepdim=True)
        sums = bmm(lval.transpose(1, 2), sg.mk).squeeze(1)  # (E, Tg)
        if single:
            torch.addcdiv(sg.negeps, sums, sg.den, out=row)
        elif contiguous:
            torch.addcdiv(sg.negeps, sums, sg.den, out=row[:, lo:hi])
        else:
            row[:, col_idx] = torch.addcdiv(sg.negeps, sums, sg.den)
        return err, eg, nrm

    def grad(ctx: tuple[Tensor, Tensor, Tensor], sg: StepGroup, coef: Tensor) -> Tensor:
        err, eg, nrm = ctx
        if single:
            cw = div(coef, sg.wden)
        elif contiguous:
            cw = div(coef[:, lo:hi], sg.wden)
        else:
            cw = div(coef.index_select(1, col_idx), sg.wden)
        wgt = bmm(sg.mk, cw.unsqueeze(-1))  # (E, B, 1): dL/dl per sample
        if loss == "l2":
            contrib = eg * (wgt / nrm.clamp_min(_TINY))
        elif loss == "squared_l2":
            contrib = eg * wgt  # the factor 2 is in wden
        elif loss == "normalized":
            assert sg.ny is not None
            contrib = eg * (wgt / sg.ny / nrm.clamp_min(_TINY))
        elif loss == "l1":
            contrib = torch.sign(eg) * wgt
        else:
            contrib = eg.clamp(-delta, delta) * wgt
        if all_fields:
            return contrib
        return torch.zeros_like(err).index_copy_(-1, fidx, contrib)

    return values, grad
