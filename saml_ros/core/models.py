"""Residual and full dynamics models: ensembles of small PReLU MLPs evaluated in one batched pass.

A single model is an ensemble of one. Ensembles exist so that many seeds or configurations (the paper's
convergence grid) train in one pass with one optimizer: Adam is element-wise, so stacking E models'
parameters gives exactly E independent Adam runs.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch
from torch import nn

from saml_ros.core.systems.base import System

MODEL_KINDS = ("residual", "full")


def _finite_float(what: str, value: Any) -> float:
    """``value`` as a Python float (an int such as ``-1`` included: a PReLU slope tensor must be floating point),
    or ``ValueError`` naming ``what`` when it is not a finite real number."""
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise ValueError(f"{what} must be a finite real number, got {value!r}")
    out = float(value)
    if not math.isfinite(out):
        raise ValueError(f"{what} must be finite, got {value!r}")
    return out


class EnsembleMLP(nn.Module):
    """E independent MLPs ``in_dim -> hidden... -> out_dim`` with PReLU activations.

    Weights are stored stacked: ``weights[l]`` has shape ``(E, d_in, d_out)``, ``biases[l]``
    ``(E, 1, d_out)``, PReLU slopes ``(E, 1, 1)`` (one learnable slope per layer, as ``nn.PReLU()``).
    Hidden layers use PyTorch's ``nn.Linear`` default initialisation; the output layer starts at zero; the PReLU
    slopes start at 0.25 (``nn.PReLU``'s default), the first hidden layer's at ``first_slope``.
    """

    def __init__(
        self,
        n_models: int,
        in_dim: int,
        hidden: Sequence[int],
        out_dim: int,
        generator: torch.Generator | None = None,
        first_slope: float = 0.25,
    ) -> None:
        super().__init__()
        first_slope = _finite_float("first_slope", first_slope)
        if n_models < 1 or in_dim < 1 or out_dim < 1 or any(h < 1 for h in hidden):
            raise ValueError(f"bad MLP shape: E={n_models}, {in_dim} -> {list(hidden)} -> {out_dim}")
        self.n_models, self.in_dim, self.out_dim = n_models, in_dim, out_dim
        self.hidden = tuple(int(h) for h in hidden)
        dims = [in_dim, *self.hidden, out_dim]
        self.weights = nn.ParameterList()
        self.biases = nn.ParameterList()
        self.slopes = nn.ParameterList()
        for i, (a, b) in enumerate(zip(dims[:-1], dims[1:])):
            last = i == len(dims) - 2
            w = torch.zeros(n_models, a, b)
            bias = torch.zeros(n_models, 1, b)
            if not last:
                bound = 1.0 / math.sqrt(a)
                w.uniform_(-bound, bound, generator=generator)
                bias.uniform_(-bound, bound, generator=generator)
                self.slopes.append(nn.Parameter(torch.full((n_models, 1, 1), first_slope if i == 0 else 0.25)))
            self.weights.append(nn.Parameter(w))
            self.biases.append(nn.Parameter(bias))

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        """``(E, B, in_dim) -> (E, B, out_dim)``."""
        h = z
        n = len(self.weights)
        for i in range(n):
            h = torch.baddbmm(self.biases[i], h, self.weights[i])
            if i < n - 1:
                h = torch.where(h >= 0, h, self.slopes[i] * h)
        return h

    def flops_per_sample(self) -> int:
        """Multiply-adds x2 of one forward pass of one member (matmuls only)."""
        dims = [self.in_dim, *self.hidden, self.out_dim]
        return sum(2 * a * b for a, b in zip(dims[:-1], dims[1:]))


class DynamicsModel(nn.Module):
    """x_{t+1} ~ f_hat(x, u) + phi(x, u) (``kind="residual"``) or ~ phi(x, u) (``kind="full"``).

    The network sees ``[x, u]`` normalised by ``in_mean``/``in_std`` and its output is scaled by
    ``out_std`` (no offset, so a fresh residual model predicts exactly f_hat). The statistics are fitted from
    data with :meth:`fit_normalization` and stored with the weights.

    Buffers: ``in_mean``, ``in_std`` ``(E, 1, n_x + n_u)``; ``out_std`` ``(E, 1, n_y)``.

    ``prelu_init``: the first hidden layer's initial PReLU slope (0.25, PyTorch's default; -1 starts it as
    ``|h|``, an even feature of the inputs, which finds the good optima of sign-symmetric residuals such as
    Coulomb friction far more often: docs/training.md, "Restarts and selection"). Only the initialisation: the
    slope is learned, and a checkpoint stores it.
    """

    def __init__(
        self,
        system: System,
        hidden: Sequence[int] | None = None,
        kind: str = "residual",
        n_models: int = 1,
        seed: int | None = None,
        prelu_init: float = 0.25,
    ) -> None:
        super().__init__()
        prelu_init = _finite_float("prelu_init (the first hidden layer's starting PReLU slope)", prelu_init)
        if kind not in MODEL_KINDS:
            raise ValueError(f"model kind must be one of {MODEL_KINDS}, got {kind!r}")
        self.system = system
        self.kind = kind
        self.hidden = tuple(system.paper_hidden if hidden is None else hidden)
        n_in = system.state.size + system.control.size
        n_out = system.target.size
        gen = None if seed is None else torch.Generator().manual_seed(int(seed))
        self.net = EnsembleMLP(n_models, n_in, self.hidden, n_out, generator=gen, first_slope=prelu_init)
        self.register_buffer("in_mean", torch.zeros(n_models, 1, n_in))
        self.register_buffer("in_std", torch.ones(n_models, 1, n_in))
        self.register_buffer("out_std", torch.ones(n_models, 1, n_out))

    in_mean: torch.Tensor
    in_std: torch.Tensor
    out_std: torch.Tensor

    @property
    def n_models(self) -> int:
        return self.net.n_models

    # ------------------------------------------------------------------------------------- data
    def base(self, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        """f_hat(x, u) for residual models, zeros for full models; ``(..., B, n_y)``."""
        if self.kind == "full":
            return x.new_zeros((*x.shape[:-1], self.system.target.size))
        lead = x.shape[:-1]
        out = self.system.base_step(x.reshape(-1, x.shape[-1]), u.reshape(-1, u.shape[-1]))
        return out.reshape(*lead, -1)

    @torch.no_grad()
    def fit_normalization(self, x: Any, u: Any, y: Any, min_std: float = 1e-6) -> None:
        """Fit input mean/std and output scale from data (numpy or torch).

        ``(N, .)`` arrays fit every member alike; ``(E, N, .)`` arrays fit each member on its own dataset.
        A system with a ``fit_base(x, u, y)`` method (a system file's ``linear`` base model) fits its base
        model here first, on the same data, once. The output scale is the std of what the network must
        produce (y - f_hat, or y); a field the base
        model already predicts exactly (std below ``min_std``) keeps the tiny scale, so the network cannot
        disturb it.
        """
        xt, ut, yt = (torch.as_tensor(np.asarray(a), dtype=torch.float64) for a in (x, u, y))
        fit_base = getattr(self.system, "fit_base", None)
        if self.kind == "residual" and callable(fit_base) and xt.dim() == 2:
            fit_base(xt.numpy(), ut.numpy(), yt.numpy())  # a base model fitted from data (system files' 'linear')
        z = torch.cat([xt, ut], -1)
        resid = yt - self.base(xt, ut) if self.kind == "residual" else yt
        if z.shape[-2] < 2:
            raise ValueError("fit_normalization needs at least 2 samples")
        mean = z.mean(-2, keepdim=True)
        std = z.std(-2, keepdim=True).clamp_min(min_std)
        ostd = resid.std(-2, keepdim=True).clamp_min(min_std)
        dt = self.in_mean.dtype
        self.in_mean.copy_(mean.expand_as(self.in_mean).to(dt))
        self.in_std.copy_(std.expand_as(self.in_std).to(dt))
        self.out_std.copy_(ostd.expand_as(self.out_std).to(dt))

    # ------------------------------------------------------------------------------------- forward
    def correction(self, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        """phi(x, u) only: ``(E, B, n_y)``; ``x, u`` are ``(B, .)`` (shared) or ``(E, B, .)``."""
        z = torch.cat([x, u], -1)
        if z.dim() == 2:
            z = z.unsqueeze(0).expand(self.n_models, -1, -1)
        z = (z - self.in_mean) / self.in_std
        return self.net(z) * self.out_std

    def forward(self, x: torch.Tensor, u: torch.Tensor, base: torch.Tensor | None = None) -> torch.Tensor:
        """Predicted target ``(E, B, n_y)``. ``base`` may carry a precomputed f_hat(x, u)."""
        phi = self.correction(x, u)
        if self.kind == "full":
            return phi
        return phi + (self.base(x, u) if base is None else base)

    @torch.no_grad()
    def predict_np(self, x: np.ndarray, u: np.ndarray, member: int = 0) -> np.ndarray:
        """Prediction of one member on numpy inputs ``(B, .)`` or a single ``(n,)`` sample."""
        single = np.ndim(x) == 1
        dt = self.in_mean.dtype
        xt = torch.as_tensor(np.atleast_2d(x), dtype=dt)
        ut = torch.as_tensor(np.atleast_2d(u), dtype=dt)
        y = self.forward(xt, ut)[member].numpy().astype(np.float64)
        return y[0] if single else y

    # ------------------------------------------------------------------------------------- metadata
    def architecture(self) -> dict[str, Any]:
        """JSON-serialisable description; with the state dict it rebuilds the model."""
        return {
            "system": self.system.name,
            "kind": self.kind,
            "hidden": list(self.hidden),
            "n_models": self.n_models,
            "in_dim": self.net.in_dim,
            "out_dim": self.net.out_dim,
            "activation": "prelu",
        }

    @torch.no_grad()
    def member(self, i: int) -> DynamicsModel:
        """A standalone single-model copy of ensemble member ``i``."""
        m = DynamicsModel(self.system, self.hidden, self.kind, n_models=1)
        src = self.state_dict()
        m.load_state_dict({k: v[i : i + 1].clone() for k, v in src.items()})
        return m.to(self.in_mean.dtype)
