"""A fixed dataset of transitions as tensors (:class:`Transitions`), what offline training and evaluation read."""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from saml_ros.core.model.network import DynamicsModel
from saml_ros.core.spec import ProblemSpec


class Transitions:
    """A fixed dataset of transitions as tensors, with f_hat and region masks precomputed.

    ``x, u, y`` are ``(N, .)`` (shared by every member) or ``(E, N, .)`` (one dataset per member, equal N), in the
    model's dtype; ``base`` is f_hat(x, u) (computed in float64, then cast); ``masks`` holds one ``(N,)`` /
    ``(E, N)`` boolean mask per spec term (objective first), ``None`` for a term without a region.
    """

    def __init__(self, model: DynamicsModel, spec: ProblemSpec, x: Any, u: Any, y: Any) -> None:
        dt = model.in_mean.dtype
        x64, u64, y64 = (torch.as_tensor(np.asarray(a), dtype=torch.float64) for a in (x, u, y))
        if not (x64.shape[:-1] == u64.shape[:-1] == y64.shape[:-1]):
            raise ValueError(f"x, u, y disagree on the number of samples: {x64.shape}, {u64.shape}, {y64.shape}")
        with torch.no_grad():
            base = model.base(x64, u64)  # f_hat in float64, then cast
        self.x, self.u, self.y, self.base = (t.to(dt) for t in (x64, u64, y64, base))
        self.per_member = self.x.dim() == 3
        self.masks = [None if m is None else m for m in spec.masks(x64, u64, y64)]

    def __len__(self) -> int:
        return int(self.x.shape[-2])

    def take(self, idx: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """Gather ``idx`` ``(E, B)``: returns x, u, y, base as ``(E, B, .)``."""
        if self.per_member:
            rows = torch.arange(idx.shape[0]).unsqueeze(1)
            return tuple(t[rows, idx] for t in (self.x, self.u, self.y, self.base))
        return tuple(t[idx] for t in (self.x, self.u, self.y, self.base))

    def take_masks(self, idx: torch.Tensor) -> list[torch.Tensor | None]:
        """The region masks of ``idx`` ``(E, B)``, one ``(E, B)`` mask (or ``None``) per spec term."""
        if self.per_member:
            rows = torch.arange(idx.shape[0]).unsqueeze(1)
            return [None if m is None else m[rows, idx] for m in self.masks]
        return [None if m is None else m[idx] for m in self.masks]
