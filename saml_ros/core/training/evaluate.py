"""Dataset-level spec values of a model (:func:`evaluate_spec`): what the experiments and the trainer report."""

from __future__ import annotations

import numpy as np
import torch

from saml_ros.core.model.network import DynamicsModel
from saml_ros.core.spec import ProblemSpec
from saml_ros.core.training.dataset import Transitions


@torch.no_grad()
def evaluate_spec(
    model: DynamicsModel, spec: ProblemSpec, data: Transitions, lam: torch.Tensor | None = None,
    chunk: int = 65536,
) -> dict[str, np.ndarray]:
    """Full-dataset spec values for every member (chunked so memory stays bounded).

    Returns objective ``(E,)``, constraints ``(E, K)``, Lagrangian ``(E,)`` (with ``lam`` ``(E, K)``, zeros when
    ``None``) and the lambdas used, in float64. Conditional terms are exact ratios over the whole dataset, not
    means of chunk ratios.
    """
    e, k = model.n_models, spec.n_constraints
    n = len(data)
    terms = [spec.objective, *spec.constraints]
    sums = torch.zeros(e, k + 1, dtype=torch.float64)
    counts = torch.zeros(e, k + 1, dtype=torch.float64)
    for s in range(0, n, chunk):
        sl = slice(s, min(n, s + chunk))
        idx = torch.arange(sl.start, sl.stop).unsqueeze(0).expand(e, -1)
        x, u, y, base = data.take(idx)
        pred = model(x, u, base)
        masks = data.take_masks(idx)
        for j, (t, m) in enumerate(zip(terms, masks)):
            loss = t.per_sample(pred, y).double()
            mm = torch.ones_like(loss) if m is None else m.double().expand_as(loss)
            sums[:, j] += (loss * mm).sum(-1)
            counts[:, j] += mm.sum(-1) if (m is not None and t.mean == "conditional") else loss.shape[-1]
    return spec_values(spec, sums, counts, lam)


def spec_values(spec: ProblemSpec, sums: torch.Tensor, counts: torch.Tensor,
                lam: torch.Tensor | None = None) -> dict[str, np.ndarray]:
    """:func:`evaluate_spec`'s result from the per-term sums and counts ``(E, 1 + K)`` (float64) over the dataset
    (the fused training kernel accumulates them itself at the end of a fit)."""
    e, k = sums.shape[0], spec.n_constraints
    vals = sums / counts.clamp_min(1.0)
    eps = torch.tensor([0.0] + [t.eps for t in spec.constraints], dtype=torch.float64)
    has = counts > 0
    g = torch.where(has, vals - eps, torch.zeros_like(vals))
    lam64 = torch.zeros(e, k, dtype=torch.float64) if lam is None else lam.detach().double()
    obj, cons = g[:, 0], g[:, 1:]
    return {
        "objective": obj.numpy(),
        "constraints": cons.numpy(),
        "lagrangian": (obj + (lam64 * cons).sum(-1)).numpy(),
        "lambdas": lam64.numpy(),
    }
