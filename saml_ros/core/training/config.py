"""Hyper-parameters of Algorithm 1 (:class:`TrainConfig`) and the torch optimizers they name."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch

from saml_ros.core.device import resolve_device

#: optimizer names of :attr:`TrainConfig.primal_optimizer` / :attr:`TrainConfig.dual_optimizer`
OPTIMIZERS = ("adam", "sgd")
#: engine names of :attr:`TrainConfig.engine` (the classes are in :mod:`saml_ros.core.training.engines`)
ENGINE_NAMES = ("fast", "plain")


@dataclass
class TrainConfig:
    """Hyper-parameters of Algorithm 1 (defaults: the paper's double-integrator settings).

    Attributes:
        epochs: passes over a fixed dataset (offline mode).
        batch_size: minibatch size M per ensemble member.
        primal_lr: alpha_theta.
        dual_lr: alpha_lambda.
        primal_optimizer / dual_optimizer: ``"adam"`` (the paper) or ``"sgd"`` (plain Algorithm 1).
        log_every: steps between history points (0: once per epoch); values are averaged in between.
        seed: seeds minibatch sampling.
        dtype: ``"float32"`` or ``"float64"`` for parameters and data.
        engine: how :meth:`~saml_ros.core.training.PrimalDualTrainer.fit` runs: ``"fast"`` (hand-written
            forward/backward and flat Adam, :mod:`saml_ros.core.training.engines.fast`; same results up to float
            rounding, falls back to the plain loop where it does not apply) or ``"plain"`` (autograd and
            ``torch.optim``).
        device: ``"cpu"`` (default) or ``"cuda[:N]"``; checked here (:func:`saml_ros.core.device.resolve_device`),
            so a device that cannot be used fails when the configuration is made, not mid-run.
    """

    epochs: int = 200
    batch_size: int = 128
    primal_lr: float = 1e-3
    dual_lr: float = 1e-4
    primal_optimizer: str = "adam"
    dual_optimizer: str = "adam"
    log_every: int = 0
    seed: int = 0
    dtype: str = "float32"
    engine: str = "fast"
    device: str = "cpu"

    def __post_init__(self) -> None:
        if self.primal_optimizer not in OPTIMIZERS or self.dual_optimizer not in OPTIMIZERS:
            raise ValueError(f"optimizers must be one of {OPTIMIZERS}")
        if self.batch_size < 1 or self.epochs < 0:
            raise ValueError("batch_size must be >= 1 and epochs >= 0")
        if not (self.primal_lr > 0 and self.dual_lr >= 0):
            raise ValueError("primal_lr must be > 0 and dual_lr >= 0")
        if self.dtype not in ("float32", "float64"):
            raise ValueError("dtype must be float32 or float64")
        if self.engine not in ENGINE_NAMES:
            raise ValueError(f"engine must be one of {ENGINE_NAMES}")
        resolve_device(self.device)

    @property
    def torch_dtype(self) -> torch.dtype:
        return torch.float32 if self.dtype == "float32" else torch.float64

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> TrainConfig:
        known = set(cls.__dataclass_fields__)
        extra = sorted(set(d) - known)
        if extra:
            raise ValueError(f"unknown training option(s) {extra}; known: {sorted(known)}")
        return cls(**d)


def make_optimizer(kind: str, params: list[torch.nn.Parameter], lr: float, maximize: bool) -> torch.optim.Optimizer:
    """The torch optimizer named ``kind`` (one of :data:`OPTIMIZERS`) over ``params``; ``maximize`` for ascent."""
    if kind == "adam":
        return torch.optim.Adam(params, lr=lr, maximize=maximize, foreach=True)
    if kind == "sgd":
        return torch.optim.SGD(params, lr=lr, maximize=maximize, foreach=True)
    raise ValueError(f"optimizer must be one of {OPTIMIZERS}, got {kind!r}")
