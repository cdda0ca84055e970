"""The configuration of an online learner (:class:`OnlineConfig`), without torch: the learner node builds it and
sends it to its training process, which builds the :class:`~saml_ros.core.online.learner.OnlineLearner` (and
imports torch) from it. :mod:`saml_ros.core.online.learner` re-exports it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from saml_ros.core.model.inputs import MODEL_KINDS
from saml_ros.core.online.heldout import HeldoutConfig
from saml_ros.core.training.config import HealthConfig, TrainConfig
from saml_ros.core.training.schedule import schedules_for


@dataclass
class OnlineConfig:
    """Configuration of an :class:`OnlineLearner`.

    Attributes:
        kind: ``"residual"`` (f_hat + phi) or ``"full"`` (phi only).
        hidden: hidden layer sizes; ``None`` = the system's ``paper_hidden``.
        train: primal-dual hyper-parameters (``epochs`` is not used online).
        buffer_capacity: replay buffer rows (>= min_transitions).
        buffer_policy: ``"fifo"`` or ``"reservoir"`` (see docs/buffer.md).
        min_transitions: transitions needed before training starts (normalisation is fitted on the first
            ``min_transitions``); training also pauses while the buffer holds fewer (e.g. right after a resume).
        telemetry_window: most recent transitions the live model error is computed on.
        checkpoint_keep: checkpoint files kept in the run directory (older ones are pruned).
        n_models: ensemble members (each its own initialisation and minibatches from the one buffer).
        plausible_bounds: overrides of the system's plausible ranges (:mod:`saml_ros.core.data.plausibility`) for
            already-paired batches (each source's pairing config carries its own).
        health: the training-health limits (:mod:`saml_ros.core.training.health`).
        heldout: which stretches of the stream are held out (never trained on) and how many are kept
            (:mod:`saml_ros.core.online.heldout`).
        heldout_period: seconds (of the learner's clock) between two evaluations on the held-out set (telemetry,
            /diagnostics); a checkpoint is always evaluated when written.
        updates_per_transition: at most this many updates per training transition that arrived since training
            started (the first ``min_transitions`` included), so a buffer that stops growing is not memorised by
            ever more updates; 0 = no limit (as fast as the CPU allows).
        renormalize: refit the input / output normalisation on the training buffer when it has drifted
            (:data:`RENORM_FACTOR`), keeping the model's function (:meth:`DynamicsModel.renormalize`).
        average_updates: time constant (updates) of an exponential average of the weights kept beside the
            trainer's; at every held-out evaluation the one of the two that does better on the held-out stretches is
            the model checkpoints publish (:meth:`OnlineLearner.evaluate_heldout`). 0 = no average (the trainer's
            weights are published).
    """

    kind: str = "residual"
    hidden: tuple[int, ...] | None = None
    train: TrainConfig = field(default_factory=TrainConfig)
    buffer_capacity: int = 100_000
    buffer_policy: str = "fifo"
    min_transitions: int = 1000
    telemetry_window: int = 1000
    checkpoint_keep: int = 5
    n_models: int = 1
    plausible_bounds: str = ""
    health: HealthConfig = field(default_factory=HealthConfig)
    heldout: HeldoutConfig = field(default_factory=HeldoutConfig)
    heldout_period: float = 1.0
    updates_per_transition: float = 0.0
    renormalize: bool = True
    average_updates: float = 1000.0

    def __post_init__(self) -> None:
        if self.kind not in MODEL_KINDS:
            raise ValueError(f"model kind must be one of {list(MODEL_KINDS)}, got {self.kind!r}")
        if self.hidden is not None:
            self.hidden = tuple(int(h) for h in self.hidden)
            if any(h < 1 for h in self.hidden):
                raise ValueError(f"hidden layer sizes must be >= 1, got {list(self.hidden)}")
        if self.min_transitions < 2:
            raise ValueError(f"min_transitions must be >= 2 (normalisation needs a spread), got {self.min_transitions}")
        if self.buffer_capacity < self.min_transitions:
            raise ValueError(
                f"buffer capacity ({self.buffer_capacity}) must be >= min_transitions ({self.min_transitions})"
            )
        if self.buffer_policy not in ("fifo", "reservoir"):
            raise ValueError(f"buffer policy must be 'fifo' or 'reservoir', got {self.buffer_policy!r}")
        if self.n_models < 1:
            raise ValueError(f"n_models must be >= 1, got {self.n_models}")
        if self.telemetry_window < 1 or self.checkpoint_keep < 1:
            raise ValueError("telemetry_window and checkpoint_keep must be >= 1")
        if not (math.isfinite(self.updates_per_transition) and self.updates_per_transition >= 0):
            raise ValueError(f"updates_per_transition must be >= 0 (0 = no limit), got {self.updates_per_transition}")
        if not (math.isfinite(self.average_updates) and self.average_updates >= 0):
            raise ValueError(f"average_updates must be >= 0 (0 = no average), got {self.average_updates}")
        if not (math.isfinite(self.heldout_period) and self.heldout_period > 0):
            raise ValueError(f"heldout_period must be > 0 s, got {self.heldout_period}")
        schedules_for(self.train, 0)  # online training has no epochs: a schedule needs train.schedule_steps
