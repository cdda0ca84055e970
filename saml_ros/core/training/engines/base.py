"""What a training engine is: :class:`Engine` runs epochs of Algorithm 1 over a fixed dataset on a
:class:`RunState` (the trainer's public state), and nothing else of the trainer."""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable
from typing import Any, ClassVar, Protocol

import torch

from saml_ros.core.model.network import DynamicsModel
from saml_ros.core.spec import ProblemSpec
from saml_ros.core.training.config import TrainConfig
from saml_ros.core.training.dataset import Transitions
from saml_ros.core.training.dual import DualVariables
from saml_ros.core.training.health import TrainingHealth
from saml_ros.core.training.history import TrainingLog
from saml_ros.core.training.schedule import LRSchedule


class RunState(Protocol):
    """The state of a primal-dual run that engines read and update (:class:`~saml_ros.core.training.
    PrimalDualTrainer` has exactly these public attributes)."""

    model: DynamicsModel
    spec: ProblemSpec
    config: TrainConfig
    primal_opt: torch.optim.Optimizer
    dual: DualVariables
    rng: torch.Generator
    log: TrainingLog
    schedules: tuple[LRSchedule, LRSchedule] | None
    health: TrainingHealth
    steps: int
    epochs_done: float


def minibatch_plan(batch_size: int, n: int) -> tuple[int, int]:
    """``(minibatch size, minibatches per epoch)`` for ``n`` samples: the batch is at most ``n``, and an epoch is
    ``n // batch`` minibatches (at least one; the remainder of the shuffle is not used)."""
    bsz = min(batch_size, n)
    return bsz, max(1, n // bsz)


class Engine(ABC):
    """One way to run offline epochs of Algorithm 1.

    Contract of :meth:`fit`, for every engine: every member sees its own shuffle per epoch, drawn from
    ``run.rng`` with ``torch.rand(E, N)`` per epoch (so engines can be mixed and resumed); ``run.steps`` and
    ``run.epochs_done`` advance; the model, ``run.primal_opt``'s state and ``run.dual`` (value and optimizer state)
    hold the result when it returns and whenever ``on_epoch`` is called (after each epoch); ``run.log`` gets a row
    every ``config.log_every`` steps (0: once per epoch) and one for the rest at the end; ``bar`` (a progress bar
    or None) advances by one per step.
    """

    name: ClassVar[str]

    def unsupported_reason(self, run: RunState, data: Transitions) -> str | None:
        """Why this engine cannot run ``run`` on ``data`` exactly like the plain loop, or ``None`` if it can."""
        return None

    @abstractmethod
    def fit(self, run: RunState, data: Transitions, epochs: int, bar: Any = None,
            on_epoch: Callable[[], None] | None = None) -> None:
        """Run ``epochs`` passes over ``data`` (see the class docstring)."""
