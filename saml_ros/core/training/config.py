"""Hyper-parameters of a primal-dual run (:class:`TrainConfig`) and the torch optimizers they name.

A run is the paper's Algorithm 1 (``dual_method="paper"``) or one of the dual methods of
:mod:`saml_ros.core.training.dual` (:data:`DUAL_METHODS`), with learning-rate schedules for the primal and the
dual step (:mod:`saml_ros.core.training.schedule`). docs/training.md says which method to use when.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from saml_ros.core.runtime.device import check_device

if TYPE_CHECKING:
    import torch

#: optimizer names of :attr:`TrainConfig.primal_optimizer` / :attr:`TrainConfig.dual_optimizer`
OPTIMIZERS = ("adam", "sgd")
#: engine names of :attr:`TrainConfig.engine` (the classes are in :mod:`saml_ros.core.training.engines`)
ENGINE_NAMES = ("fast", "fast_torch", "plain")
#: dual methods of :attr:`TrainConfig.dual_method` (the classes are in :mod:`saml_ros.core.training.dual`)
DUAL_METHODS = ("paper", "lagrangian", "nupi", "augmented", "resilient")
#: learning-rate schedules of :attr:`TrainConfig.primal_schedule` / :attr:`TrainConfig.dual_schedule`; ``"auto"``
#: is ``"constant"`` for ``dual_method="paper"`` and :data:`AUTO_SCHEDULE` for every other method
SCHEDULES = ("auto", "constant", "step", "cosine")
#: what ``"auto"`` means for a method other than the paper's
AUTO_SCHEDULE = "cosine"


@dataclass
class TrainConfig:
    """Hyper-parameters of a primal-dual run.

    ``TrainConfig()`` is the recommended recipe, chosen by measurement (``bench/bench_dual.py``,
    ``bench/bench_cooper.py``, docs/training.md): the Lagrangian with Adam 3e-3 on the network and 1e-2 on the
    multipliers (fast multipliers: an early push inside the constraint's region), both rates cosine-decayed,
    batch 128.
    ``TrainConfig.paper()`` is the paper's Algorithm 1 with the paper's double-integrator settings.

    Attributes:
        epochs: passes over a fixed dataset (offline mode).
        batch_size: minibatch size M per ensemble member.
        primal_lr: alpha_theta (the schedule's starting value).
        dual_lr: alpha_lambda (the schedule's starting value; the controller's step for ``"nupi"``; not used by
            ``"augmented"``, whose step is its penalty: :attr:`dual_lr0`).
        primal_optimizer / dual_optimizer: ``"adam"`` (the paper) or ``"sgd"`` (plain Algorithm 1); the dual
            optimizer is not used by ``"nupi"``, which is its own controller, nor by ``"augmented"``, whose
            multiplier step is the method of multipliers' (SGD along ``rho g``: :attr:`dual_optimizer_used`).
        log_every: steps between history points (0: once per epoch); values are averaged in between.
        seed: seeds minibatch sampling.
        dtype: ``"float32"`` or ``"float64"`` for parameters and data.
        engine: how :meth:`~saml_ros.core.training.PrimalDualTrainer.fit` runs: ``"fast"`` (hand-written
            forward/backward and flat Adam, :mod:`saml_ros.core.training.engines.fast`, its steps in the fused C++
            kernel of :mod:`saml_ros.core.training.engines.fused` where that is built and not switched off with
            ``SAML_FUSED_KERNEL=0``; same results up to float rounding, falls back to the plain loop where it does
            not apply), ``"fast_torch"`` (the fast engine's torch path, never the kernel) or ``"plain"``
            (autograd and ``torch.optim``).
        dual_method: how the multipliers move (:data:`DUAL_METHODS`, :mod:`saml_ros.core.training.dual`):
            ``"paper"`` (Algorithm 1: projected ascent on g with ``dual_optimizer``), ``"lagrangian"`` (the same
            arithmetic; its ``"auto"`` schedules are cosine), ``"nupi"`` (a PI controller on the relative violation
            g / eps), ``"augmented"`` (the augmented Lagrangian method: penalty ``penalty``, multipliers by the
            method of multipliers ``lambda <- relu(lambda + rho g)``), ``"resilient"`` (constraints relaxed at
            price ``relax_cost``).
        nupi_kp: nuPI's proportional gain K_P (the integral gain is 1, the step ``dual_lr``).
        nupi_ema: nuPI's smoothing nu of the error signal (0: none), in [0, 1).
        penalty: augmented Lagrangian's penalty c, in objective units: rho_k = c / eps_k, the weight of the
            quadratic penalty and the multiplier's step (times the dual schedule's factor).
        relax_cost: resilient constraints' price alpha (dimensionless) of relaxing eps_k by u_k:
            h(u) = alpha f / 2 * sum_k (u_k / eps_k)^2 with f the objective (relaxing eps by a fraction r costs
            alpha r^2 / 2 times the objective).
        primal_schedule / dual_schedule: learning-rate schedule (:data:`SCHEDULES`) over the update count:
            ``"constant"``, ``"step"`` (times ``lr_gamma`` at each of ``lr_drops`` evenly spaced drops) or
            ``"cosine"`` (cosine decay to ``lr_floor`` times the starting value); ``"auto"``: constant for the
            paper's method, :data:`AUTO_SCHEDULE` otherwise. Exact formulas: :mod:`saml_ros.core.training.schedule`.
        schedule_steps: the schedules' horizon T in updates; 0: ``epochs`` times the minibatches per epoch of
            the dataset being fitted (online training needs T > 0 for a schedule other than constant).
        lr_gamma: factor of each step-schedule drop, in (0, 1].
        lr_drops: number of step-schedule drops (at T k / (drops + 1), k = 1..drops), >= 1.
        lr_floor: the cosine schedule's final learning rate as a fraction of the starting one, in [0, 1].
        device: ``"cpu"`` (default) or ``"cuda[:N]"``; checked here (:func:`saml_ros.core.runtime.device.check_device`),
            so a device that cannot be used fails when the configuration is made, not mid-run.
    """

    epochs: int = 200
    batch_size: int = 128
    primal_lr: float = 3e-3
    dual_lr: float = 1e-2
    primal_optimizer: str = "adam"
    dual_optimizer: str = "adam"
    log_every: int = 0
    seed: int = 0
    dtype: str = "float32"
    engine: str = "fast"
    dual_method: str = "lagrangian"
    nupi_kp: float = 10.0
    nupi_ema: float = 0.0
    penalty: float = 0.01
    relax_cost: float = 100.0
    primal_schedule: str = "auto"
    dual_schedule: str = "auto"
    schedule_steps: int = 0
    lr_gamma: float = 0.1
    lr_drops: int = 2
    lr_floor: float = 0.0
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
        if self.dual_method not in DUAL_METHODS:
            raise ValueError(f"dual_method must be one of {DUAL_METHODS}, got {self.dual_method!r}")
        for name in ("primal_schedule", "dual_schedule"):
            if getattr(self, name) not in SCHEDULES:
                raise ValueError(f"{name} must be one of {SCHEDULES}, got {getattr(self, name)!r}")
        checks = [
            (self.nupi_kp >= 0, "nupi_kp must be >= 0"),
            (0 <= self.nupi_ema < 1, "nupi_ema must be in [0, 1)"),
            (self.penalty > 0, "penalty must be > 0"),
            (self.relax_cost > 0, "relax_cost must be > 0"),
            (self.schedule_steps >= 0, "schedule_steps must be >= 0"),
            (0 < self.lr_gamma <= 1, "lr_gamma must be in (0, 1]"),
            (self.lr_drops >= 1, "lr_drops must be >= 1"),
            (0 <= self.lr_floor <= 1, "lr_floor must be in [0, 1]"),
        ]
        for ok, msg in checks:
            if not ok:
                raise ValueError(msg)
        check_device(self.device)

    @property
    def torch_dtype(self) -> torch.dtype:
        import torch

        return torch.float32 if self.dtype == "float32" else torch.float64

    @property
    def dual_lr0(self) -> float:
        """The dual optimizer's starting learning rate (the dual schedule's ``lr0``): :attr:`dual_lr`, but 1 for
        ``"augmented"``, whose SGD step along ``rho g`` is then the method of multipliers' (the schedule scales it
        by its factor)."""
        return 1.0 if self.dual_method == "augmented" else self.dual_lr

    @property
    def dual_optimizer_used(self) -> str:
        """What moves the multipliers: ``"nupi"`` (the controller), ``"sgd"`` for ``"augmented"``, else
        :attr:`dual_optimizer`."""
        if self.dual_method == "nupi":
            return "nupi"
        return "sgd" if self.dual_method == "augmented" else self.dual_optimizer

    def schedule(self, which: str) -> str:
        """The schedule ``"auto"`` resolves to for ``which`` (``"primal"`` or ``"dual"``)."""
        name = str(getattr(self, f"{which}_schedule"))
        if name != "auto":
            return name
        return "constant" if self.dual_method == "paper" else AUTO_SCHEDULE

    @classmethod
    def paper(cls, **overrides: Any) -> TrainConfig:
        """The paper's Algorithm 1 with its double-integrator settings (Adam 1e-3 / 1e-4, batch 128, 200 epochs,
        constant learning rates); ``overrides`` replace fields."""
        base: dict[str, Any] = {"epochs": 200, "batch_size": 128, "primal_lr": 1e-3, "dual_lr": 1e-4,
                                "primal_optimizer": "adam", "dual_optimizer": "adam", "dual_method": "paper",
                                "primal_schedule": "constant", "dual_schedule": "constant"}
        return cls(**{**base, **overrides})

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> TrainConfig:
        known = set(cls.__dataclass_fields__)
        extra = sorted(set(d) - known)
        if extra:
            raise ValueError(f"unknown training option(s) {extra}; known: {sorted(known)}")
        return cls(**d)


def make_optimizer(kind: str, params: list[torch.nn.Parameter], lr: float, maximize: bool) -> torch.optim.Optimizer:
    """The torch optimizer named ``kind`` (one of :data:`OPTIMIZERS`) over ``params``; ``maximize`` for ascent."""
    import torch

    if kind == "adam":
        return torch.optim.Adam(params, lr=lr, maximize=maximize, foreach=True)
    if kind == "sgd":
        return torch.optim.SGD(params, lr=lr, maximize=maximize, foreach=True)
    raise ValueError(f"optimizer must be one of {OPTIMIZERS}, got {kind!r}")


@dataclass(frozen=True)
class HealthConfig:
    """Limits of :class:`~saml_ros.core.training.health.TrainingHealth` (imported from here by that module).

    Attributes:
        explode_ratio: a minibatch objective or gradient norm this many times its running mean is exploding (> 1).
        max_weight: a network weight or multiplier larger than this in magnitude is exploding.
        warmup: healthy steps before the ratio tests apply (their values start the running means).
        smoothing: weight of the newest healthy step in the running means, in (0, 1].
        snapshot_every: healthy steps between two snapshots of the healthy state (the plain step).
        check_every: steps per health check of the fast engine.
        error_after: consecutive skipped steps from which the learner reports ERROR.
        rebase_after: consecutive skipped steps after which the running means start again (a new scale).
    """

    explode_ratio: float = 1e4
    max_weight: float = 1e6
    warmup: int = 20
    smoothing: float = 0.05
    snapshot_every: int = 10
    check_every: int = 10
    error_after: int = 100
    rebase_after: int = 50

    def __post_init__(self) -> None:
        if not (self.explode_ratio > 1 and self.max_weight > 0):
            raise ValueError(f"health: explode_ratio must be > 1 and max_weight > 0, got {self}")
        if not 0 < self.smoothing <= 1 or min(self.warmup, 0) < 0:
            raise ValueError(f"health: smoothing must be in (0, 1] and warmup >= 0, got {self}")
        if min(self.snapshot_every, self.check_every, self.error_after, self.rebase_after) < 1:
            raise ValueError(f"health: snapshot_every, check_every, error_after and rebase_after must be >= 1, "
                             f"got {self}")


def parse_margin(margin: str | float | None) -> str | float | None:
    """The ``margin`` option of offline training (:func:`saml_ros.offline.pipelines.train_models`, which
    re-exports this): ``"auto"``, a fraction of eps in [0, 0.5], or None (``"none"``, 0: no margin); ``ValueError`` otherwise."""
    if margin is None or (isinstance(margin, str) and margin.strip().lower() in ("none", "off", "0")):
        return None
    if isinstance(margin, str) and margin.strip().lower() == "auto":
        return "auto"
    try:
        f = float(margin)
    except (TypeError, ValueError):
        raise ValueError(f"margin must be 'auto', 'none' or a fraction of eps in [0, 0.5], got {margin!r}") from None
    if not 0.0 <= f <= 0.5:
        raise ValueError(f"margin must be 'auto', 'none' or a fraction of eps in [0, 0.5], got {margin!r}")
    return None if f == 0.0 else f
