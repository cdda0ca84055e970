"""Primal-dual training of dynamics models (the paper's Algorithm 1), offline and one step at a time.

``config`` (:class:`TrainConfig`), ``dataset`` (:class:`Transitions`, a fixed dataset), ``dual`` (the
multipliers: :class:`DualVariables`), ``history`` (the training curve and its bookkeeping), ``engines`` (how
``fit`` runs: plain autograd or the fast hand-written engine), ``trainer`` (:class:`PrimalDualTrainer`),
``evaluate`` (dataset-level spec values), ``trainer_io`` (a trainer into a model checkpoint and back; loading a
model alone is :mod:`saml_ros.core.model_io`, which does not import this package).
"""

from saml_ros.core.training.config import TrainConfig
from saml_ros.core.training.dataset import Transitions
from saml_ros.core.training.dual import DualVariables
from saml_ros.core.training.evaluate import evaluate_spec
from saml_ros.core.training.history import FeasibilityReport, History, TrainingLog
from saml_ros.core.training.trainer import PrimalDualTrainer
from saml_ros.core.training.trainer_io import checkpoint_payload, resume_trainer, save_checkpoint

__all__ = [
    "DualVariables",
    "FeasibilityReport",
    "History",
    "PrimalDualTrainer",
    "TrainConfig",
    "TrainingLog",
    "Transitions",
    "checkpoint_payload",
    "evaluate_spec",
    "resume_trainer",
    "save_checkpoint",
]
