"""What the saml_ros rclpy executables (learner, mpc, play, record) share around their ``main``.

SIGINT and SIGTERM only set a stop flag, and rclpy starts without its own signal handlers (which would raise
inside a callback): the executable leaves its spin loop, finishes its shutdown work (a final checkpoint, closing
a bag) and exits 0 (docs/architecture.md, "Nodes"). Any number of further signals during that work only set the
flag again: under ``ros2 launch`` a terminal's Ctrl-C reaches every node twice (from the terminal's process group,
then from launch), and launch sends SIGTERM 5 s later. :func:`process_main` then ends the process at once
instead of running the interpreter's teardown (see :func:`exit_process`). Imports rclpy only inside the functions
that need it.
"""

from __future__ import annotations

import functools
import logging
import os
import signal
import sys
import time
from collections.abc import Callable, Sequence
from types import FrameType
from typing import Any, TypeVar

#: ``{"signal": number of the newest SIGINT / SIGTERM received, 0 = none yet}``
StopFlag = dict[str, int]
#: ``[True]`` while an executable runs as the process entry (:func:`process_main`), which ends with ``os._exit``
_ENDING_PROCESS = [False]


def catch_stop_signals() -> StopFlag:
    """Route SIGINT and SIGTERM of this process to a new :data:`StopFlag` and return it."""
    stop: StopFlag = {"signal": 0}

    def on_signal(signum: int, frame: FrameType | None) -> None:
        stop["signal"] = signum

    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)
    return stop


def full_argv(name: str, argv: Sequence[str] | None) -> list[str]:
    """``[program, *arguments]``: ``sys.argv`` when ``argv`` is None, else ``[name, *argv]``."""
    return list(sys.argv) if argv is None else [name, *argv]


def wants_help(args: Sequence[str]) -> bool:
    """True for ``-h`` / ``--help`` among ``args[1:]`` when there are no ROS arguments."""
    return any(a in ("-h", "--help") for a in args[1:]) and "--ros-args" not in args


def init_rclpy(args: Sequence[str]) -> None:
    """``rclpy.init(args)`` without rclpy's signal handlers (pair it with :func:`catch_stop_signals`)."""
    import rclpy
    from rclpy.signals import SignalHandlerOptions

    rclpy.init(args=list(args), signal_handler_options=SignalHandlerOptions.NO)


def spin_until_stopped(node: Any, stop: StopFlag, keep_going: Callable[[], bool] | None = None, *,
                       period: float = 0.1, announce: bool = True, executor: str = "single",
                       drain: Callable[[], int] | None = None, drain_timeout: float = 2.0,
                       drain_quiet: float = 0.3) -> None:
    """Spin ``node`` on :func:`make_executor`'s executor until a stop signal arrives or ``keep_going()`` is False.

    Args:
        period: longest wait (s) between two looks at the flag.
        announce: log ``received SIGINT: shutting down`` (or SIGTERM) on the node's logger when a signal ended it.
        executor: see :func:`make_executor`.
        drain: after the stop, keep spinning while this count (e.g. messages written) still grows, until it has
            not grown for ``drain_quiet`` s or ``drain_timeout`` s have passed: what the middleware already
            delivered (acknowledged to its publishers) is taken, not dropped with the process. While the robot
            keeps publishing the count never stops growing, so ``drain_timeout`` bounds the stop: 2 s leaves the
            rest of ``ros2 launch``'s 5 s grace period for closing the bag (at 5 s a recorder beside a 50 Hz
            simulator outlived the grace period under load).
    """
    spinner = make_executor(executor)
    spinner.add_node(node)
    while not stop["signal"] and (keep_going is None or keep_going()):
        spinner.spin_once(timeout_sec=period)
    if announce and stop["signal"]:
        node.get_logger().info(f"received {signal.Signals(stop['signal']).name}: shutting down")
    if drain is not None:
        now = time.monotonic()
        deadline, quiet_since, last = now + drain_timeout, now, drain()
        while now < deadline and now - quiet_since < drain_quiet:
            spinner.spin_once(timeout_sec=min(period, drain_quiet))
            now, count = time.monotonic(), drain()
            if count != last:
                last, quiet_since = count, now
    spinner.shutdown()  # drops its callback generator, a reference cycle (see shutdown())


#: executors :func:`make_executor` knows (environment variable ``SAML_EXECUTOR``; docs/performance.md)
EXECUTORS = ("single", "events")


def make_executor(kind: str = "single") -> Any:
    """An executor: ``"single"`` (rclpy's ``SingleThreadedExecutor``) or ``"events"`` (the experimental
    ``EventsExecutor``: 2-7x more lockstep steps per second in ``bench sim``, but it fails in the recorder's
    generic subscriptions, docs/performance.md, so only the simulator node uses it by default). The environment
    variable ``SAML_EXECUTOR``, when set, overrides ``kind`` (for measurements)."""
    kind = os.environ.get("SAML_EXECUTOR", kind)
    if kind not in EXECUTORS:
        raise ValueError(f"executor (or SAML_EXECUTOR) must be one of {EXECUTORS}, got {kind!r}")
    if kind == "events":
        from rclpy.experimental import EventsExecutor

        return EventsExecutor()
    from rclpy.executors import SingleThreadedExecutor

    return SingleThreadedExecutor()


def single_torch_thread() -> None:
    """One intra-op torch thread in this process, whether torch is imported already or only later (the MPC's first
    checkpoint, a simulator world stepping ``true_step`` in torch): a node that never needs torch never pays its
    2-3 CPU-s import. Before the import, ``OMP_NUM_THREADS=1`` is what torch reads for its thread count (checked by
    test_torch_free_imports)."""
    if "torch" in sys.modules:
        sys.modules["torch"].set_num_threads(1)
    else:
        os.environ["OMP_NUM_THREADS"] = "1"


def shutdown(node: Any | None) -> None:
    """Destroy ``node`` (if any) and shut rclpy down (if it is still up).

    Executors, timers and clocks register weak methods among the context's shutdown callbacks; one freed after
    ``rclpy.shutdown()`` (which empties that list) makes rclpy print an ignored ``ValueError`` traceback from
    ``Context._remove_callback`` on the node's output (seen in the suite on the MPC node, freed by the cycle
    collector in the moment between shutdown and the process's end). So garbage is collected before the shutdown,
    and in a process that :func:`process_main` is about to end the cycle collector is then off (it ends with
    ``os._exit``, nothing is left to free); called in-process (a test) the collector stays on.
    """
    import gc

    import rclpy

    if node is not None:
        node.destroy_node()
    gc.collect()
    if _ENDING_PROCESS[0]:
        gc.disable()
    if rclpy.ok():
        rclpy.shutdown()


def log_at(logger: Any, level: int, text: str) -> None:
    """``text`` on an rclpy ``logger`` at Python logging ``level`` (error, warning, else info); one call site per
    severity, as rclpy refuses a call site whose severity changes between calls."""
    if level >= logging.ERROR:
        logger.error(text)
    elif level >= logging.WARNING:
        logger.warning(text)
    else:
        logger.info(text)


def exit_process(code: int) -> None:
    """End this process now with ``code``: flush stdout, stderr and Python logging, then ``os._exit``.

    Only for the end of an executable whose shutdown work is done (checkpoint written, bag closed, rclpy shut
    down). The interpreter's own teardown is what it skips: with torch imported it takes about 1 s on an idle
    2-core machine and over 5 s under load (torch's library finalizers), longer than ``ros2 launch`` waits
    before SIGTERM; and a SIGINT arriving in it (the terminal's second one) would print a ``KeyboardInterrupt``
    traceback, because Python resets the handlers to their defaults while finalizing.
    """
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    logging.shutdown()
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError, AttributeError):  # closed or replaced stream: nothing left to flush
            pass
    os._exit(code)


_Main = TypeVar("_Main", bound=Callable[..., Any])


def process_main(main: _Main) -> _Main:
    """Decorate an executable's ``main(argv=None)``: run as the process entry (``argv`` None, as the console
    script and ``python -m saml_ros.executables`` call it), it ends the process with :func:`exit_process` once
    ``main`` returned its exit code; called with an explicit ``argv`` (in-process, e.g. from a test) it just
    returns the code. An exception propagates as usual (traceback, exit code 1)."""

    @functools.wraps(main)
    def wrapper(argv: Sequence[str] | None = None) -> Any:
        _ENDING_PROCESS[0] = argv is None
        code = main(argv)
        if argv is None:
            if isinstance(code, str):  # as sys.exit(message): the message on stderr, status 1
                print(code, file=sys.stderr)
            exit_process(code if isinstance(code, int) else (0 if code is None else 1))
        return code

    return wrapper  # type: ignore[return-value]
