"""The training process of the online learner, child side: :func:`child_entry` runs in the fresh interpreter
:func:`saml_ros.core.runtime.child_launch.launch_child` starts; it receives the
:class:`~saml_ros.core.online.process.LearnerSetup`, builds the learner (and the raw-message decoder the setup
carries), reports :class:`~saml_ros.core.online.messages.Ready` and runs :func:`~saml_ros.core.online.loop.run_loop` until the parent says stop
(the messages are :mod:`saml_ros.core.online.messages`)."""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import sys
import threading
import time
from typing import Any

import torch

from saml_ros.core.online.ingest import RawIngest
from saml_ros.core.online.loop import Send, run_loop
from saml_ros.core.online.messages import Fatal, FromTrainer, Log, Ready
from saml_ros.core.online.process import STOP_SIGNAL, LearnerSetup, thread_ids
from saml_ros.core.online.resume import ResumeError

log = logging.getLogger("saml_ros.online")


class _PipeLogHandler(logging.Handler):
    """Ships ``saml_ros.*`` log records of the training process to its parent as :class:`Log` messages."""

    def __init__(self, send: Send) -> None:
        super().__init__()
        self._send = send

    def emit(self, record: logging.LogRecord) -> None:
        with contextlib.suppress(Exception):
            self._send(Log(record.levelno, self.format(record)))


def _die_with_parent() -> None:
    """Linux: SIGKILL this process when its parent dies (a killed learner never leaves a trainer behind that
    keeps writing checkpoints into the run directory)."""
    with contextlib.suppress(Exception):
        import ctypes

        libc = ctypes.CDLL("libc.so.6", use_errno=True)
        pr_set_pdeathsig = 1
        libc.prctl(pr_set_pdeathsig, signal.SIGKILL)
        if os.getppid() == 1:  # the parent died before prctl took effect
            os._exit(0)


def child_entry(fd: int) -> None:
    """Entry point of a training process started for a :class:`~saml_ros.core.online.process.TrainingProcess`: ``fd`` is its end of a socket
    pair; the first message on it is the :class:`LearnerSetup`."""
    from multiprocessing.connection import Connection

    conn = Connection(fd)
    try:
        setup = conn.recv()
    except (EOFError, OSError):
        _exit_now()
    _child_main(conn, setup)
    _exit_now()


def _exit_now() -> None:
    """End the training process without the interpreter's teardown: its work is saved and reported (or there was
    none), and torch's teardown takes 1-5 s on a loaded 2-core machine, which the node's shutdown would wait for."""
    logging.shutdown()
    with contextlib.suppress(Exception):
        sys.stdout.flush()
        sys.stderr.flush()
    os._exit(0)


def apply_compute_settings(threads: int, flush_denormal: bool) -> dict[str, Any]:
    """Set this process's torch intra-op ``threads`` (0 = leave torch's default) and subnormal flushing.

    Returns what torch reports afterwards: ``{"threads": torch.get_num_threads(), "flush_denormal": bool}``
    (``flush_denormal`` is False where the CPU cannot flush, e.g. without SSE3).
    """
    if threads > 0:
        torch.set_num_threads(threads)
    flushing = bool(torch.set_flush_denormal(flush_denormal)) and flush_denormal
    return {"threads": torch.get_num_threads(), "flush_denormal": flushing}


def warm_up() -> dict[str, Any]:
    """Pay the training's one-time costs before the process reports ready, not in its first update: the first
    torch optimizer imports ``torch._dynamo`` (2-3 s here, more under load), and the fused kernel is loaded
    from its cache (a kernel not built yet is built by the first update that needs it, as before: a build takes
    about a minute, longer than a start-up should wait). Returns ``{"seconds": float, "kernel": what became of the
    kernel, for the log}``."""
    from saml_ros.core.training.engines.fused import kernel_reason, load_kernel, switched_off

    t0 = time.perf_counter()
    torch.optim.Adam([torch.zeros(1, requires_grad=True)])
    if load_kernel(build=False) is not None:
        kernel = "loaded"
    elif switched_off():
        kernel = f"not used: {kernel_reason()}"
    else:
        kernel = "not built yet: the first update that uses it builds it, about a minute"
    return {"seconds": time.perf_counter() - t0, "kernel": kernel}


def set_priority(niceness: int, idle: bool) -> str:
    """Lower the CPU priority of this process's threads (those started later inherit it): ``SCHED_IDLE`` when
    ``idle`` (where the OS has it), else ``niceness`` added to the nice value. Returns what was applied, for the
    log. Both are per thread on Linux, and imports may already have started threads: each one is set."""
    if idle:
        try:
            for tid in thread_ids():
                os.sched_setscheduler(tid, os.SCHED_IDLE, os.sched_param(0))
            return "SCHED_IDLE"
        except (AttributeError, OSError) as exc:  # not Linux: niceness instead
            log.warning("training process: SCHED_IDLE unavailable (%s); using niceness %d", exc, niceness)
    if niceness:
        with contextlib.suppress(OSError):
            base = os.getpriority(os.PRIO_PROCESS, 0)
            for tid in thread_ids():
                os.setpriority(os.PRIO_PROCESS, tid, min(19, base + niceness))
    return f"nice {os.getpriority(os.PRIO_PROCESS, 0)}"


def _child_main(conn: Any, setup: LearnerSetup) -> None:
    _die_with_parent()
    # the terminal's Ctrl-C reaches the whole process group: the parent decides when training stops, and tells
    # this process with STOP_SIGNAL (then the Stop message) so that it stops without working off its inbox
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    stop_flag: list[int] = []
    signal.signal(STOP_SIGNAL, lambda signum, frame: stop_flag.append(signum))
    compute = apply_compute_settings(setup.threads, setup.flush_denormal)
    lock = threading.Lock()

    def send(msg: FromTrainer) -> None:
        with lock:
            conn.send(msg)

    handler = _PipeLogHandler(send)
    root = logging.getLogger("saml_ros")
    root.addHandler(handler)
    root.setLevel(logging.INFO)
    try:
        try:
            learner = setup.build()
            decode = setup.make_decoder()
        except ResumeError as exc:
            send(Fatal("resume", str(exc)))
            return
        except Exception as exc:  # noqa: BLE001 - reported to the parent, which exits with a message
            send(Fatal("error", f"{type(exc).__name__}: {exc}"))
            return
        r = learner.resumed
        info = None if r is None else {"path": str(r.path), "version": r.version, "updates": r.updates,
                                       "lam": r.lam, "skipped": [(str(p), why) for p, why in r.skipped]}
        raw = None if decode is None else RawIngest(learner, setup.channels, decode)
        warm = warm_up()
        # lowered only now, for training: under SCHED_IDLE on a busy machine the one-time start-up (learner, kernel,
        # warm-up) starved past the node's 120 s start timeout (a loaded suite run); every thread so far is covered
        priority = set_priority(setup.niceness, setup.idle)
        log.info("training process warmed up in %.1f s (fused kernel %s)", warm["seconds"], warm["kernel"])
        log.info("training process: %d torch intra-op thread(s), subnormal floats %s, CPU priority %s",
                 compute["threads"], "flushed to zero" if compute["flush_denormal"] else "not flushed", priority)
        send(Ready(info, list(learner.model.hidden), learner.status(), compute))
        run_loop(learner, setup.loop, conn, send, raw, stop_requested=lambda: bool(stop_flag),
                 paused=setup.paused)
    except (EOFError, OSError):
        return  # the parent is gone
