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


def __getattr__(name: str) -> Any:
    """The package's names, each imported on first use (PEP 562): a module that needs only the configuration (the
    learner node's parameter table reads ``TrainConfig``) does not import torch with the rest."""
    if name in ("TrainConfig",):
        from saml_ros.core.training import config

        return getattr(config, name)
    if name in ("Transitions",):
        from saml_ros.core.training import dataset

        return getattr(dataset, name)
    if name in ("FeasibilityDiagnosis", "diagnose"):
        from saml_ros.core.training import diagnosis

        return getattr(diagnosis, name)
    if name in ("DualVariables", "make_dual"):
        from saml_ros.core.training import dual

        return getattr(dual, name)
    if name in ("evaluate_spec",):
        from saml_ros.core.training import evaluate

        return getattr(evaluate, name)
    if name in ("FeasibilityReport", "History", "TrainingLog"):
        from saml_ros.core.training import history

        return getattr(history, name)
    if name in ("LRSchedule",):
        from saml_ros.core.training import schedule

        return getattr(schedule, name)
    if name in ("Selection", "select_members", "take_trainer"):
        from saml_ros.core.training import selection

        return getattr(selection, name)
    if name in ("PrimalDualTrainer",):
        from saml_ros.core.training import trainer

        return getattr(trainer, name)
    if name in ("checkpoint_payload", "resume_trainer", "save_checkpoint"):
        from saml_ros.core.training import trainer_io

        return getattr(trainer_io, name)
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
