"""The training process of the online learner, parent side: a separate, niced interpreter (its side is
:mod:`saml_ros.core.online.child`) owns an :class:`~saml_ros.core.online.learner.OnlineLearner` built from a
picklable :class:`LearnerSetup` and runs :func:`~saml_ros.core.online.loop.run_loop`; :class:`TrainingProcess`
is the parent's handle that starts it, feeds it and restarts it.

Why: ingest in the parent never competes with training for the GIL (the learner node ships raw messages, so
decoding and pairing run in the child too; see docs/learner.md for the measurements). The child is started by
:func:`saml_ros.core.runtime.child_launch.launch_child` (a fresh interpreter running
:func:`saml_ros.core.online.child.child_entry` on its end of a socket pair) and builds everything from the setup.

Socket protocol (``multiprocessing.connection`` messages): first the :class:`LearnerSetup`, then the dataclasses
of :mod:`saml_ros.core.online.messages` both ways (:class:`~saml_ros.core.online.messages.Batch` of paired
transitions, :class:`~saml_ros.core.online.messages.RawMessages` for the setup's decoder, ``Pause`` / ``Resume``
(a managed learner's deactivation and activation), ``SetLoop`` (new pacing, :meth:`TrainingProcess.set_loop`) and
``Stop`` to the child; ``Ready`` (or ``Fatal``), ``Status``, ``Checkpointed``, ``ErrorReport``, ``Log``,
``Paused`` and ``Stopped`` back).
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import os
import signal
import subprocess
import threading
import time
from collections import Counter, deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from saml_ros.core.data.pairing import PairingConfig, Transition, total_counts
from saml_ros.core.data.resampling import ResampleConfig
from saml_ros.core.errors import SamlError
from saml_ros.core.model.checkpoint import CheckpointStore
from saml_ros.core.online.ingest import Decode
from saml_ros.core.online.loop import LoopConfig
from saml_ros.core.online.messages import (
    Batch,
    Checkpointed,
    ErrorReport,
    Fatal,
    Log,
    Pause,
    Paused,
    RawMessages,
    Ready,
    Resume,
    SetLoop,
    Status,
    Stop,
    Stopped,
    ToTrainer,
)
from saml_ros.core.online.options import OnlineConfig
from saml_ros.core.online.resume import ResumeError
from saml_ros.core.runtime.child_launch import LaunchedChild, launch_child
from saml_ros.core.spec import ProblemSpec

if TYPE_CHECKING:
    from saml_ros.core.online.learner import OnlineLearner

log = logging.getLogger("saml_ros.online")

#: ``factory(decoder_args) -> decode``: builds a training process's raw-message decoder (a module-level function,
#: so it pickles by reference; e.g. :func:`msg_schemas.decode.make_decoder`)
DecoderFactory = Callable[[Any], Decode]
#: how often (s) :meth:`TrainingProcess.start` asks its ``cancelled`` predicate while the child starts
CANCEL_POLL_S = 0.1


class StartCancelled(SamlError):
    """:meth:`TrainingProcess.start` gave up because its ``cancelled`` predicate said so (a stop signal arrived
    while the training process was still starting); the child was killed, nothing was written."""


#: what :meth:`TrainingProcess.stop` sends the training process: save now, skip the inbox (see
#: :func:`~saml_ros.core.online.loop.run_loop`)
STOP_SIGNAL = signal.SIGUSR1


@dataclass(frozen=True)
class LearnerSetup:
    """Everything a training process needs to build its :class:`OnlineLearner` (picklable).

    Attributes:
        system, system_params: ``get_system(system, **system_params)``.
        spec: the problem spec as a dict (``ProblemSpec.to_dict()``).
        config: the learner configuration.
        run_dir: checkpoint directory (``None``: no checkpoints).
        resume: resume from the newest valid checkpoint of ``run_dir``.
        loop: pacing of the training loop.
        niceness: added to the training process's nice value, so the OS runs ingest (and simulators, MPC)
            first when CPUs are short; 0 keeps the parent's priority.
        idle: run the training process under ``SCHED_IDLE`` (Linux): it runs only when no other process wants
            the CPU, so a waking controller never waits for it (``niceness`` does not apply then).
        threads: torch intra-op threads of the training process; 0 = torch's default (one per core). One is
            fastest for these small networks on a shared 2-core machine (docs/performance.md).
        flush_denormal: flush subnormal floats to zero in the training process (they can slow training by
            an order of magnitude; docs/performance.md).
        sources: ``(name, pairing)`` of each source, in index order (for raw messages; see below).
        channels: ``(source index, kind)`` of each raw-message channel.
        decoder: a :data:`DecoderFactory`: ``decoder(decoder_args)`` returns ``decode(channel, payload) ->
            (vector, stamp_ns)`` for raw messages (it raises an exception with a ``reason`` attribute, e.g.
            ``msg_schemas.SchemaError``, for a malformed one). The caller passes it, so message formats (and
            rclpy) stay out of the core.
        decoder_args: picklable argument of the decoder factory.
        paused: start without training (data is still buffered) until :meth:`TrainingProcess.resume`.
    """

    system: str
    system_params: dict[str, Any]
    spec: dict[str, Any]
    config: OnlineConfig
    run_dir: str | None = None
    resume: bool = True
    loop: LoopConfig = field(default_factory=LoopConfig)
    niceness: int = 10
    idle: bool = False
    threads: int = 1
    flush_denormal: bool = True
    sources: tuple[tuple[str, PairingConfig | ResampleConfig], ...] = ()
    channels: tuple[tuple[int, str], ...] = ()
    decoder: DecoderFactory | None = None
    decoder_args: Any = None
    paused: bool = False

    def __post_init__(self) -> None:
        if self.threads < 0:
            raise ValueError(f"threads must be >= 0 (0 = torch's default), got {self.threads}")

    def build(self) -> OnlineLearner:
        """The learner (resumed from ``run_dir`` when ``resume``), with its sources registered."""
        from saml_ros.core.online.learner import OnlineLearner
        from saml_ros.core.systems import get_system

        system = get_system(self.system, **self.system_params)
        spec = ProblemSpec.for_system(self.spec, system)
        store = None if self.run_dir is None else CheckpointStore(self.run_dir, keep=self.config.checkpoint_keep)
        learner = OnlineLearner(system, spec, self.config, store=store, resume=self.resume)
        for name, pairing in self.sources:
            learner.add_source(name, pairing)
        return learner

    def make_decoder(self) -> Decode | None:
        """The raw-message decoder (``decoder(decoder_args)``), or None."""
        return None if self.decoder is None else self.decoder(self.decoder_args)


@dataclass
class ReadyInfo:
    """What a training process reported when it was ready.

    Attributes:
        resumed: ``{"path", "version", "updates", "lam", "skipped"}`` of the checkpoint it resumed from, or None.
        hidden: the model's hidden layer sizes.
        status: its first :meth:`OnlineLearner.status`.
        threads: torch intra-op threads the training process runs with.
        flush_denormal: whether it flushes subnormal floats to zero.
    """

    resumed: dict[str, Any] | None
    hidden: list[int]
    status: dict[str, float]
    threads: int
    flush_denormal: bool


def thread_ids(pid: int | None = None) -> list[int]:
    """The ids of the threads of process ``pid`` (None: this process) on Linux. Where ``/proc`` has none: ``[0]``
    (the calling thread) for this process, ``[]`` for another."""
    try:
        return [int(t) for t in os.listdir(f"/proc/{'self' if pid is None else pid}/task")]
    except OSError:
        return [0] if pid is None else []


class TrainingProcess:
    """Runs the training side of an :class:`OnlineLearner` in a child process fed with transitions.

    Why a process: the learner's ingest (rclpy callbacks: decode, pair) and primal-dual training are both
    Python; in one process they share the GIL, and training would take CPU time from ingest (measured: the
    node then loses messages at under a third of a bare subscriber's rate; docs/learner.md). In a child process training runs
    on another CPU when there is one, and at a higher nice value (:attr:`LearnerSetup.niceness`) it yields
    the CPU to ingest when there is not.

    The child owns the buffer, model, trainer, checkpoints and resume (and, for raw messages, the decoding and
    pairing: :class:`RawIngest`); this handle ships paired transitions (:meth:`submit`) or raw messages
    (:meth:`submit_raw`) to it in batches every 5 ms (a shipper thread, so submitting never blocks) and receives
    status, per-source counters, checkpoint announcements, log records and errors (a reader thread, calling the
    callbacks). If the child dies
    unexpectedly it is restarted (resuming from the newest checkpoint) and ``on_error`` is told.

    Args:
        setup: how to build the learner in the child.
        on_status: called with each status dict (:meth:`OnlineLearner.status`).
        on_checkpoint: called with ``(path, version)`` after each checkpoint.
        on_log: called with ``(level, text)`` for the child's log records.
        on_error: called with ``(what, message)`` for training / checkpoint errors and restarts.
        max_queue: transitions held while the child cannot take them; beyond that they are dropped
            (counted in :attr:`dropped`).
    """

    def __init__(
        self,
        setup: LearnerSetup,
        *,
        on_status: Callable[[dict[str, float]], None] | None = None,
        on_checkpoint: Callable[[str, int], None] | None = None,
        on_log: Callable[[int, str], None] | None = None,
        on_error: Callable[[str, str], None] | None = None,
        max_queue: int = 200_000,
    ) -> None:
        self.setup = setup
        self.on_status = on_status or (lambda s: None)
        self.on_checkpoint = on_checkpoint or (lambda p, v: None)
        self.on_log = on_log or (lambda lvl, text: log.log(lvl, text))
        self.on_error = on_error or (lambda what, text: log.error(text))
        self.max_queue = max_queue
        self.status: dict[str, float] = {}
        #: per-source pairing counters of the child, ``{source name: {counter: value}}`` (see pairing.COUNTERS)
        self.source_counts: dict[str, dict[str, int]] = {}
        #: what the running training process reported when it was ready (after a restart: the new one's)
        self.ready: ReadyInfo | None = None
        self.dropped = 0
        self.restarts = 0
        #: errors reported (all kinds) and by kind (``training``, ``checkpoint``, ``process``): counters
        self.errors = 0
        self.error_counts: Counter[str] = Counter()
        #: the text values of the child's last status (``checkpoint_write_error``: "" while writes succeed)
        self.notes: dict[str, str] = {}
        self._outbox: deque[Transition] = deque()
        self._raw: deque[tuple[int, Any]] = deque()
        self._send_lock = threading.Lock()
        self._stopping = threading.Event()
        self._stopped = threading.Event()
        self._final: tuple[str | None, int, int] | None = None
        self._paused = setup.paused
        self._pause_reply: tuple[str | None, int, int] | None = None
        self._pause_done = threading.Event()
        self._proc: subprocess.Popen[bytes] | None = None
        self._conn: Any = None
        self._threads: list[threading.Thread] = []

    # ---------------------------------------------------------------------------------------- lifecycle
    def start(self, timeout: float = 120.0, launched: LaunchedChild | None = None,
              cancelled: Callable[[], bool] | None = None) -> ReadyInfo:
        """Start the child (or use ``launched``, from :func:`launch_child`) and wait until it has built its
        learner (and resumed). ``cancelled`` is asked every :data:`CANCEL_POLL_S` s while waiting: a node that
        received a stop signal during its start-up must not wait for the child's warm-up (seconds of imports, more
        under load) before it can exit.

        Raises:
            ResumeError: the run directory contradicts the configuration.
            RuntimeError: the child could not build its learner or did not answer within ``timeout`` s.
            StartCancelled: ``cancelled()`` became true first (the child is killed).
        """
        ready = self._spawn(self.setup, timeout, launched, cancelled)
        for target, name in ((self._ship, "learner-ship"), (self._read, "learner-read")):
            t = threading.Thread(target=target, name=name, daemon=True)
            t.start()
            self._threads.append(t)
        return ready

    def _spawn(self, setup: LearnerSetup, timeout: float, launched: LaunchedChild | None = None,
               cancelled: Callable[[], bool] | None = None) -> ReadyInfo:
        proc, parent = launched if launched is not None else launch_child()
        parent.send(setup)
        deadline = time.monotonic() + timeout
        while True:
            if cancelled is not None and cancelled():
                proc.kill()
                proc.wait(5)
                raise StartCancelled("stopped while the training process was starting")
            left = deadline - time.monotonic()
            if left <= 0:
                proc.kill()
                proc.wait(5)
                raise RuntimeError(f"the training process did not start within {timeout:.0f} s")
            if not parent.poll(left if cancelled is None else min(left, CANCEL_POLL_S)):
                continue
            try:
                msg = parent.recv()
            except (EOFError, OSError):
                exit_code = proc.wait(5)
                raise RuntimeError(f"the training process exited during start-up (exit code {exit_code})") from None
            match msg:
                case Log(level, text):
                    self.on_log(level, text)
                case Fatal(kind, message):
                    proc.wait(10)
                    raise (ResumeError if kind == "resume" else RuntimeError)(message)
                case Ready(resumed, hidden, status, compute):
                    self._proc, self._conn = proc, parent
                    self.status = status
                    self.ready = ReadyInfo(resumed, hidden, status, compute["threads"], compute["flush_denormal"])
                    return self.ready

    def stop(self, timeout: float = 60.0) -> tuple[str | None, int, int] | None:
        """Ask the child for a final checkpoint now and wait for it to exit.

        What is still queued here or in the child's inbox is dropped (it is not in the buffer yet, so it cannot
        change the final checkpoint): :data:`STOP_SIGNAL` makes the child save at once, however far behind its
        ingest is. Returns ``(path of the final checkpoint or None if nothing was new, model version, updates)``,
        or None if the child did not answer within ``timeout`` s (it is then killed).
        """
        self._stopping.set()
        self._lift_idle_policy()
        if self._proc is not None and self._proc.poll() is None:
            with contextlib.suppress(OSError):
                self._proc.send_signal(STOP_SIGNAL)
        for t in self._threads:
            if t.name == "learner-ship":
                t.join(timeout)
        try:
            with self._send_lock:
                self._conn.send(Stop())
        except (OSError, ValueError):
            pass
        self._stopped.wait(timeout)
        if self._proc is not None:
            try:
                self._proc.wait(5.0 if self._stopped.is_set() else 0.1)
            except subprocess.TimeoutExpired:
                self._proc.kill()
                # a killed process still needs CPU to exit: a starved one is reaped later, never waited for here
                with contextlib.suppress(subprocess.TimeoutExpired):
                    self._proc.wait(5.0)
        return self._final

    def _lift_idle_policy(self) -> None:
        """Best effort, for the final checkpoint and the exit: a ``SCHED_IDLE`` child gets almost no CPU on a busy
        machine (a loaded suite run: no exit within 5 s of its final checkpoint); where the OS allows it (root,
        ``CAP_SYS_NICE`` or a high enough ``RLIMIT_NICE``) its threads return to the normal policy now."""
        if self._proc is None or not self.setup.idle or self._proc.poll() is not None:
            return
        for tid in thread_ids(self._proc.pid):
            with contextlib.suppress(OSError, AttributeError):
                os.sched_setscheduler(tid, os.SCHED_OTHER, os.sched_param(0))

    def pause(self, timeout: float = 30.0) -> tuple[str | None, int, int] | None:
        """Stop training (data is still buffered): the child first writes a checkpoint when it has unsaved
        updates. Returns ``(path of that checkpoint or None, model version, updates)`` once the child has
        paused (after what is already queued for it), or None if it did not answer within ``timeout`` s."""
        self._paused = True
        self._pause_done.clear()
        if not self._send_control(Pause()):
            return None
        return self._pause_reply if self._pause_done.wait(timeout) else None

    def resume(self) -> bool:
        """Train again after :meth:`pause` (or a start with ``setup.paused``); False if the child is gone."""
        self._paused = False
        return self._send_control(Resume())

    @property
    def paused(self) -> bool:
        return self._paused

    def set_loop(self, loop: LoopConfig) -> bool:
        """Pace the running child by ``loop`` from now on (updates per second, telemetry rate, checkpoint period:
        a learner's parameters that apply at once); a restarted child starts with it. False if the child is gone."""
        self.setup = dataclasses.replace(self.setup, loop=loop)
        return self._send_control(SetLoop(loop))

    def _send_control(self, msg: ToTrainer) -> bool:
        try:
            with self._send_lock:
                self._conn.send(msg)
            return True
        except (OSError, ValueError, AttributeError):  # not started, or being restarted (it restarts paused)
            return False

    @property
    def pid(self) -> int | None:
        return None if self._proc is None else int(self._proc.pid)

    # ---------------------------------------------------------------------------------------- data
    def submit(self, tr: Transition) -> None:
        """Queue one transition for the child (never blocks; see ``max_queue``)."""
        if len(self._outbox) >= self.max_queue:
            self.dropped += 1
            return
        self._outbox.append(tr)

    def submit_raw(self, channel: int, payload: Any) -> None:
        """Queue one raw message for the child's decoder (never blocks; see ``max_queue``). Called from one
        thread per channel set (an rclpy callback group), it only appends to a deque."""
        if len(self._raw) >= self.max_queue:
            self.dropped += 1
            return
        self._raw.append((channel, payload))

    @property
    def queued(self) -> int:
        return len(self._outbox) + len(self._raw)

    def counts(self) -> dict[str, int]:
        """The child's pairing counters summed over sources (as of its last status)."""
        return total_counts(self.source_counts.values())

    def _ship(self) -> None:
        """Send queued data in batches every few ms (a blocking pipe write stalls this thread only); returns as
        soon as :meth:`stop` is called (the child no longer reads data then)."""
        while True:
            if self._stopping.is_set():
                return
            n = len(self._raw)
            if n:
                items = [self._raw.popleft() for _ in range(n)]
                try:
                    with self._send_lock:
                        self._conn.send(RawMessages(items))
                except (OSError, ValueError):  # the child is being restarted: keep them
                    self._raw.extendleft(reversed(items))
                    time.sleep(0.1)
            n = len(self._outbox)
            if n:
                trs = [self._outbox.popleft() for _ in range(n)]
                batch = Batch(
                    np.stack([t.x for t in trs]),
                    np.stack([t.u for t in trs]),
                    np.stack([t.y for t in trs]),
                    np.array([t.stamp_ns for t in trs], dtype=np.float64) * 1e-9,
                    np.array([t.source for t in trs], dtype=np.int64),
                )
                try:
                    with self._send_lock:
                        self._conn.send(batch)
                except (OSError, ValueError):  # the child is being restarted: keep the batch
                    self._outbox.extendleft(reversed(trs))
                    time.sleep(0.1)
            time.sleep(0.005)

    def _read(self) -> None:
        while True:
            conn = self._conn
            try:
                msg = conn.recv()
            except (EOFError, OSError):
                if self._stopping.is_set():
                    self._stopped.set()
                    return
                self._restart()
                continue
            match msg:
                case Status(status, counts, notes):
                    self.status = status
                    self.source_counts = counts
                    self.notes = dict(notes)
                    self.on_status(status)
                case Checkpointed(path, version):
                    self.on_checkpoint(path, version)
                case Log(level, text):
                    self.on_log(level, text)
                case ErrorReport(what, message):
                    self.errors += 1
                    self.error_counts[what] += 1
                    self.on_error(what, message)
                case Paused(path, version, updates):
                    self._pause_reply = (path, version, updates)
                    self._pause_done.set()
                case Stopped(path, version, updates):
                    self._final = (path, version, updates)
                    self._stopped.set()
                    return

    def _restart(self) -> None:
        code = None
        if self._proc is not None:
            try:
                code = self._proc.wait(5.0)
            except subprocess.TimeoutExpired:  # its end of the connection broke but it lives on: end it
                self._proc.kill()
                code = self._proc.wait(5.0)
        self.errors += 1
        self.error_counts["process"] += 1
        self.restarts += 1
        self.on_error("process", f"the training process exited unexpectedly (exit code {code}); restarting it "
                                 "from the newest checkpoint (the replay buffer starts empty)")
        time.sleep(0.5)
        setup = dataclasses.replace(self.setup, resume=True, paused=self._paused)
        while not self._stopping.is_set():
            try:
                with self._send_lock:
                    self._spawn(setup, 120.0)
                return
            except Exception as exc:  # noqa: BLE001 - keep trying; ingest goes on meanwhile
                self.on_error("process", f"restarting the training process failed: {exc}; retrying in 5 s")
                time.sleep(5.0)
