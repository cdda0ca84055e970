"""The messages between the online learner's node process and its training process (one frozen dataclass per kind).

:class:`~saml_ros.core.online.process.TrainingProcess` (the parent) and
:func:`~saml_ros.core.online.loop.run_loop` in the training process (the child,
:mod:`saml_ros.core.online.child`) exchange these over a ``multiprocessing.connection`` socket, pickled; each side
dispatches on the type (``match msg: case Batch(): ...``). The first message of the parent is the
:class:`~saml_ros.core.online.process.LearnerSetup`; after it:

* parent -> child (:data:`ToTrainer`): :class:`Batch`, :class:`RawMessages`, :class:`Pause`, :class:`Resume`,
  :class:`SetLoop` and finally :class:`Stop`;
* child -> parent (:data:`FromTrainer`): :class:`Ready` once built (or :class:`Fatal`, and the child exits), then
  :class:`Status`, :class:`Checkpointed`, :class:`ErrorReport`, :class:`Log`, after a pause :class:`Paused` and,
  after a stop, :class:`Stopped`.

Both interpreters import this module by name when they unpickle a message; it imports no torch (the learner node
imports it before its training interpreter has started), only numpy for the batch's arrays.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

import numpy as np


# ------------------------------------------------------------------------------------------ parent -> child
@dataclass(frozen=True, eq=False)
class Batch:
    """Paired transitions for the buffer (``OnlineLearner.add_batch``'s arguments).

    Attributes:
        x, u, y: states ``(B, n)``, controls ``(B, m)`` and targets ``(B, p)``.
        stamp_s: stamps of the states ``(B,)``, s.
        source: index of the source of each transition ``(B,)``, int64.
    """

    x: np.ndarray
    u: np.ndarray
    y: np.ndarray
    stamp_s: np.ndarray
    source: np.ndarray


@dataclass(frozen=True)
class RawMessages:
    """Serialized messages for the setup's decoder: ``(channel index, payload)`` in arrival order."""

    items: list[tuple[int, Any]]


@dataclass(frozen=True)
class Pause:
    """Stop training (a managed learner's deactivation); answered with :class:`Paused`."""


@dataclass(frozen=True)
class Resume:
    """Train again after :class:`Pause` (a managed learner's activation)."""


@dataclass(frozen=True)
class SetLoop:
    """Pace the training loop by ``loop`` (a :class:`~saml_ros.core.online.loop.LoopConfig`, typed ``Any`` here:
    the loop module imports this one) from now on (a parameter changed on the running node)."""

    loop: Any


@dataclass(frozen=True)
class Stop:
    """Write a final checkpoint (when there are unsaved updates) and exit; answered with :class:`Stopped`."""


#: what the parent sends after the setup
ToTrainer = Batch | RawMessages | Pause | Resume | SetLoop | Stop


# ------------------------------------------------------------------------------------------ child -> parent
@dataclass(frozen=True)
class Ready:
    """The training process has built its learner (and resumed).

    Attributes:
        resumed: ``{"path", "version", "updates", "lam", "skipped"}`` of the checkpoint it resumed from, or None.
        hidden: the model's hidden layer sizes.
        status: its first ``OnlineLearner.status()``.
        compute: ``{"threads": int, "flush_denormal": bool}`` as torch reports them
            (:func:`~saml_ros.core.online.child.apply_compute_settings`).
    """

    resumed: dict[str, Any] | None
    hidden: list[int]
    status: dict[str, float]
    compute: dict[str, Any]


@dataclass(frozen=True)
class Fatal:
    """The training process could not build its learner and exits: ``kind`` ``"resume"`` (the run directory
    contradicts the configuration) or ``"error"`` (anything else); ``message`` says why."""

    kind: Literal["resume", "error"]
    message: str


@dataclass(frozen=True)
class Status:
    """A status report, at the telemetry rate.

    Attributes:
        status: ``OnlineLearner.status()``.
        counts: per-source pairing counters, ``{source name: {counter: value}}``.
        notes: text values such as ``checkpoint_write_error`` (``""`` while writes succeed;
            :func:`~saml_ros.core.online.loop.status_notes`).
    """

    status: dict[str, float]
    counts: dict[str, dict[str, int]]
    notes: dict[str, str]


@dataclass(frozen=True)
class Checkpointed:
    """A checkpoint was written: its ``path`` and model ``version``."""

    path: str
    version: int


@dataclass(frozen=True)
class ErrorReport:
    """A training step or a checkpoint write failed (training goes on): ``what`` is ``"training"`` or
    ``"checkpoint"``, ``message`` says why."""

    what: str
    message: str


@dataclass(frozen=True)
class Log:
    """A ``saml_ros.*`` log record of the training process: its ``level`` (``logging`` levels) and text."""

    level: int
    text: str


@dataclass(frozen=True)
class Paused:
    """The answer to :class:`Pause`: the checkpoint written first (``path``, None when nothing was unsaved), the
    model ``version`` and the ``updates`` so far."""

    path: str | None
    version: int
    updates: int


@dataclass(frozen=True)
class Stopped:
    """The answer to :class:`Stop`: the final checkpoint (``path``, None when nothing was new), the model
    ``version`` and the ``updates``; the training process exits after it."""

    path: str | None
    version: int
    updates: int


#: what the training process sends
FromTrainer = Ready | Fatal | Status | Checkpointed | ErrorReport | Log | Paused | Stopped
