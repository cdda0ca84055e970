"""Online Sufficiently Accurate model learning, ROS-free: ingest -> replay buffer -> primal-dual updates.

``learner`` (:class:`OnlineLearner`, the learner's state: buffer, model, trainer, counters), ``ingest`` (the
ingest path: decode -> pairing -> buffer and recent window), ``telemetry`` (what ``learner/model_error``
reports), ``resume`` (the newest valid checkpoint of a run directory), ``loop`` (:func:`run_loop`: update pacing,
telemetry and checkpoint periods), ``heldout`` (the held-out stretches of the stream and the errors read on
them), ``process`` (:class:`TrainingProcess`, the parent's handle on the training
interpreter, and the socket protocol) and ``child`` (what runs in that interpreter).
"""

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from saml_ros.core.online.heldout import HeldoutConfig, HeldoutReport
    from saml_ros.core.online.ingest import RawIngest
    from saml_ros.core.online.learner import OnlineConfig, OnlineLearner
    from saml_ros.core.online.loop import LoopConfig, run_loop
    from saml_ros.core.online.process import LearnerSetup, ReadyInfo, StartCancelled, TrainingProcess
    from saml_ros.core.online.resume import ResumeError, ResumeInfo
    from saml_ros.core.online.telemetry import assemble_telemetry

#: name -> module of this package; imported on first use (PEP 562), so that importing one module of the package
#: (the learner node imports ``config``) does not import torch through the others
_EXPORTS = {
    "HeldoutConfig": "heldout",
    "HeldoutReport": "heldout",
    "LearnerSetup": "process",
    "LoopConfig": "loop",
    "OnlineConfig": "learner",
    "OnlineLearner": "learner",
    "RawIngest": "ingest",
    "ReadyInfo": "process",
    "ResumeError": "resume",
    "ResumeInfo": "resume",
    "StartCancelled": "process",
    "TrainingProcess": "process",
    "assemble_telemetry": "telemetry",
    "run_loop": "loop",
}


def __getattr__(name: str) -> Any:
    module = _EXPORTS.get(name)
    if module == "heldout":
        from saml_ros.core.online import heldout

        return getattr(heldout, name)
    elif module == "ingest":
        from saml_ros.core.online import ingest

        return getattr(ingest, name)
    elif module == "learner":
        from saml_ros.core.online import learner

        return getattr(learner, name)
    elif module == "loop":
        from saml_ros.core.online import loop

        return getattr(loop, name)
    elif module == "process":
        from saml_ros.core.online import process

        return getattr(process, name)
    elif module == "resume":
        from saml_ros.core.online import resume

        return getattr(resume, name)
    elif module == "telemetry":
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
