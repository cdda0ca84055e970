"""Primal-dual training of dynamics models (the paper's Algorithm 1), offline and one step at a time.

``config`` (:class:`TrainConfig`), ``dataset`` (:class:`Transitions`, a fixed dataset), ``dual`` (the
multipliers of each dual method: :class:`DualVariables` and its subclasses; ``nupi``: the PI controller),
``schedule`` (learning-rate schedules), ``history`` (the training curve and its bookkeeping), ``diagnosis``
(the end-of-run feasibility verdicts), ``engines`` (how ``fit`` runs: plain autograd or the fast hand-written
engine), ``trainer`` (:class:`PrimalDualTrainer`), ``selection`` (restarts: keep the best feasible member),
``evaluate`` (dataset-level spec values), ``trainer_io`` (a trainer into a model checkpoint and back; loading a
model alone is :mod:`saml_ros.core.model.io`, which does not import this package). docs/training.md says which
dual method to use when.
"""

from importlib import import_module
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from saml_ros.core.training.config import TrainConfig
    from saml_ros.core.training.dataset import Transitions
    from saml_ros.core.training.diagnosis import FeasibilityDiagnosis, diagnose
    from saml_ros.core.training.dual import DualVariables, make_dual
    from saml_ros.core.training.evaluate import evaluate_spec
    from saml_ros.core.training.history import FeasibilityReport, History, TrainingLog
    from saml_ros.core.training.schedule import LRSchedule
    from saml_ros.core.training.selection import Selection, select_members, take_trainer
    from saml_ros.core.training.trainer import PrimalDualTrainer
    from saml_ros.core.training.trainer_io import checkpoint_payload, resume_trainer, save_checkpoint

#: the package's names -> the module defining each: imported on first use (PEP 562), so a module that needs only
#: the configuration (the learner node's parameter table reads ``TrainConfig``) does not import torch with the rest
_WHERE = {
    "TrainConfig": "config",
    "Transitions": "dataset",
    "FeasibilityDiagnosis": "diagnosis",
    "diagnose": "diagnosis",
    "DualVariables": "dual",
    "make_dual": "dual",
    "evaluate_spec": "evaluate",
    "FeasibilityReport": "history",
    "History": "history",
    "TrainingLog": "history",
    "LRSchedule": "schedule",
    "Selection": "selection",
    "select_members": "selection",
    "take_trainer": "selection",
    "PrimalDualTrainer": "trainer",
    "checkpoint_payload": "trainer_io",
    "resume_trainer": "trainer_io",
    "save_checkpoint": "trainer_io",
}


def __getattr__(name: str) -> Any:
    """The name from its module (:data:`_WHERE`), imported when first asked for."""
    if name in _WHERE:
        return getattr(import_module(f"{__name__}.{_WHERE[name]}"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = [
    "DualVariables",
    "FeasibilityDiagnosis",
    "FeasibilityReport",
    "History",
    "LRSchedule",
    "PrimalDualTrainer",
    "Selection",
    "TrainConfig",
    "TrainingLog",
    "Transitions",
    "checkpoint_payload",
    "diagnose",
    "evaluate_spec",
    "make_dual",
    "resume_trainer",
    "save_checkpoint",
    "select_members",
    "take_trainer",
]
