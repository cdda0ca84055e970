"""Checkpoint writes that fail (a full or read-only disk, a run directory that went away), ROS-free:
:class:`WriteBackoff` says when the next write may be tried and what ``/diagnostics`` reports meanwhile.

A failed write is retried one checkpoint period after the failure, then 2, 4, ... periods after each further one
(at most :data:`MAX_BACKOFF_PERIODS` periods), never sooner: the training loop does not spend its time on writes
that fail (each attempt costs what a checkpoint costs: the evidence of the whole replay buffer, the file), and the
log gets one line per attempt, so at most one per checkpoint period. The first good write ends the back-off.
Nothing already written is touched by a failed write: a checkpoint file is written to a temporary file and renamed
(:func:`saml_ros.core.model.checkpoint.atomic_write`), so ``latest`` keeps naming the last good checkpoint throughout.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass

#: the longest wait between two attempts, in checkpoint periods
MAX_BACKOFF_PERIODS = 8


@dataclass(frozen=True)
class WriteFailure:
    """One failed checkpoint write.

    Attributes:
        reason: the OS message (``"No space left on device"``), or the exception's text.
        errno: the OS error number (``None`` when the exception had none).
        path: the file or directory the OS named (else the run directory).
        at: when it failed (the :class:`WriteBackoff`'s clock, s).
    """

    reason: str
    errno: int | None
    path: str
    at: float

    @classmethod
    def from_error(cls, exc: OSError, fallback_path: str, at: float) -> WriteFailure:
        """The failure ``exc`` describes (``fallback_path`` when it names no file)."""
        reason = exc.strerror or str(exc) or type(exc).__name__
        return cls(reason, exc.errno, str(exc.filename) if exc.filename else fallback_path, at)


class WriteBackoff:
    """When the next checkpoint write may be tried, after failed ones (see the module docstring).

    Args:
        clock: time source (s); ``time.monotonic`` by default. The last good write starts at its first reading.
        max_periods: the longest wait between two attempts, in checkpoint periods (>= 1).

    Counters (kept as counters: they only grow): :attr:`errors`, the failed writes so far, and :attr:`seconds`, the
    time spent in write attempts, good or failed (what writing takes from training: :meth:`spent`). State:
    :attr:`failures`, the failed writes since the last good one (0 while writes succeed), :attr:`last`, the newest
    failure (``None`` while writes succeed), :attr:`last_good`, when the last good write (or the start) was.
    """

    def __init__(self, clock: Callable[[], float] = time.monotonic, max_periods: int = MAX_BACKOFF_PERIODS) -> None:
        if max_periods < 1:
            raise ValueError(f"max_periods must be >= 1, got {max_periods}")
        self._clock = clock
        self.max_periods = int(max_periods)
        self.failures = 0
        self.errors = 0
        self.last: WriteFailure | None = None
        self.last_good = clock()
        self.seconds = 0.0

    @property
    def failing(self) -> bool:
        """True from a failed write until the next good one."""
        return self.failures > 0

    def delay(self, period_s: float) -> float:
        """Seconds from the newest failure to the next attempt: ``period_s`` times 1, 2, 4, ... (at most
        ``max_periods``) for the 1st, 2nd, 3rd, ... failure in a row; 0 while writes succeed."""
        if self.failures == 0:
            return 0.0
        return period_s * min(2 ** (self.failures - 1), self.max_periods)

    def may_write(self, period_s: float, now: float | None = None) -> bool:
        """True when a write may be tried now (always while writes succeed)."""
        if self.last is None:
            return True
        now = self._clock() if now is None else now
        return now >= self.last.at + self.delay(period_s)

    def failed(self, exc: OSError, fallback_path: str, now: float | None = None) -> WriteFailure:
        """Record a failed write (``fallback_path``: the run directory, used when ``exc`` names no file)."""
        now = self._clock() if now is None else now
        self.failures += 1
        self.errors += 1
        self.last = WriteFailure.from_error(exc, fallback_path, now)
        return self.last

    def succeeded(self, now: float | None = None) -> tuple[int, float]:
        """Record a good write; returns ``(failed writes it ended, seconds since the previous good write)``
        (``(0, ...)`` when writes were not failing)."""
        now = self._clock() if now is None else now
        ended, outage = self.failures, now - self.last_good
        self.failures, self.last, self.last_good = 0, None, now
        return ended, outage

    def spent(self, seconds: float) -> None:
        """Count ``seconds`` of wall time spent in one write attempt (good or failed)."""
        self.seconds += max(0.0, float(seconds))

    def since_good(self, now: float | None = None) -> float:
        """Seconds since the last good write (or the start)."""
        return (self._clock() if now is None else now) - self.last_good

    def describe(self, period_s: float, now: float | None = None) -> str:
        """The ``checkpoint_write_error`` text: the OS message, the path, the failures in a row, the time since the
        last good write and until the next attempt; ``""`` while writes succeed."""
        f = self.last
        if f is None:
            return ""
        now = self._clock() if now is None else now
        code = f" [errno {f.errno}]" if f.errno is not None else ""
        retry = max(0.0, f.at + self.delay(period_s) - now)
        return (f"{f.reason}{code}: {f.path}; {self.failures} failed write(s) in a row, last good checkpoint "
                f"{_seconds(self.since_good(now))} ago, next attempt in {_seconds(retry)}")

    def values(self, now: float | None = None) -> dict[str, float]:
        """The numbers for a status report: ``checkpoint_write_errors`` (failed writes so far),
        ``checkpoint_write_failures`` (in a row, 0 while writes succeed), ``checkpoint_age_s`` (seconds since
        the last good write or the start) and ``checkpoint_write_seconds`` (time spent writing so far, s)."""
        return {"checkpoint_write_errors": float(self.errors), "checkpoint_write_failures": float(self.failures),
                "checkpoint_age_s": self.since_good(now), "checkpoint_write_seconds": self.seconds}


def _seconds(s: float) -> str:
    return f"{s:.0f} s" if math.isfinite(s) and s >= 10 else f"{s:.1f} s"
