"""Online Sufficiently Accurate model learning, ROS-free: ingest -> replay buffer -> primal-dual updates.

``learner`` (:class:`OnlineLearner`, the learner's state: buffer, model, trainer, counters), ``ingest`` (the
ingest path: decode -> pairing -> buffer and recent window), ``telemetry`` (what ``learner/model_error``
reports), ``resume`` (the newest valid checkpoint of a run directory), ``loop`` (:func:`run_loop`: update pacing,
telemetry and checkpoint periods), ``heldout`` (the held-out stretches of the stream and the errors read on
them), ``process`` (:class:`TrainingProcess`, the parent's handle on the training
interpreter), ``messages`` (the dataclasses the two processes exchange) and ``child`` (what runs in that
interpreter).
"""

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from saml_ros.core.online.heldout import HeldoutConfig, HeldoutReport
    from saml_ros.core.online.ingest import RawIngest
    from saml_ros.core.online.learner import OnlineLearner
    from saml_ros.core.online.loop import LoopConfig, run_loop
    from saml_ros.core.online.options import OnlineConfig
    from saml_ros.core.online.process import LearnerSetup, ReadyInfo, StartCancelled, TrainingProcess
    from saml_ros.core.online.resume import ResumeError, ResumeInfo
    from saml_ros.core.online.telemetry import assemble_telemetry

def __getattr__(name: str) -> Any:
    """The package's names, each imported on first use (PEP 562): importing one module of the package (the learner
    node imports ``config``) does not import torch through the others."""
    if name in ("HeldoutConfig", "HeldoutReport"):
        from saml_ros.core.online import heldout

        return getattr(heldout, name)
    if name in ("RawIngest",):
        from saml_ros.core.online import ingest

        return getattr(ingest, name)
    if name == "OnlineConfig":
        from saml_ros.core.online import options

        return options.OnlineConfig
    if name == "OnlineLearner":
        from saml_ros.core.online import learner

        return learner.OnlineLearner
    if name in ("LoopConfig", "run_loop"):
        from saml_ros.core.online import loop

        return getattr(loop, name)
    if name in ("LearnerSetup", "ReadyInfo", "StartCancelled", "TrainingProcess"):
        from saml_ros.core.online import process

        return getattr(process, name)
    if name in ("ResumeError", "ResumeInfo"):
        from saml_ros.core.online import resume

        return getattr(resume, name)
    if name in ("assemble_telemetry",):
        from saml_ros.core.online import telemetry

        return getattr(telemetry, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = [
    "HeldoutConfig",
    "HeldoutReport",
    "LearnerSetup",
    "LoopConfig",
    "OnlineConfig",
    "OnlineLearner",
    "RawIngest",
    "ReadyInfo",
    "ResumeError",
    "ResumeInfo",
    "StartCancelled",
    "TrainingProcess",
    "assemble_telemetry",
    "run_loop",
]
