"""The online learner's ingest path: (decode ->) pairing -> replay buffer and recent window.

:class:`Ingest` pairs each source's ``(kind, stamp, vector)`` events with its own
:class:`~saml_ros.core.data.pairing.StampPairer` and adds the paired transitions to the shared
:class:`~saml_ros.core.data.buffer.ReplayBuffer` and to a :class:`RecentWindow` (what the live model error is computed
on). :class:`RawIngest` is the training process's front: it decodes raw (serialized) messages first, and counts
and logs (throttled, :class:`Throttle`) every rejection.

Threads: one thread may feed each source while another samples the buffer or reads the window.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable, Sequence
from typing import Any, Protocol

import numpy as np

from msg_schemas.telemetry import REJECT_REASONS
from saml_ros.core.data.buffer import ReplayBuffer
from saml_ros.core.data.pairing import AddResult, PairingConfig, StampPairer, Transition, total_counts
from saml_ros.core.data.plausibility import Plausibility
from saml_ros.core.data.resampling import ResampleConfig, ResamplingPairer
from saml_ros.core.online.heldout import HeldoutSet, heldout_mask

log = logging.getLogger("saml_ros.online")

#: ``decode(channel, payload) -> (vector, stamp_ns)`` of a raw message; raises an exception with a ``reason``
#: attribute (e.g. :class:`msg_schemas.SchemaError`) for a malformed one
Decode = Callable[[int, Any], tuple[Any, int]]


class RecentWindow:
    """Ring of the ``size`` most recent transitions (thread-safe); rows are ``[x, u, y]``, float64."""

    def __init__(self, size: int, n_x: int, n_u: int, n_y: int) -> None:
        self._rows = np.zeros((size, n_x + n_u + n_y))
        self._split = (n_x, n_x + n_u)
        self._n = 0
        self._lock = threading.Lock()

    def add(self, x: np.ndarray, u: np.ndarray, y: np.ndarray) -> None:
        with self._lock:
            row = self._rows[self._n % len(self._rows)]
            a, b = self._split
            row[:a], row[a:b], row[b:] = x, u, y
            self._n += 1

    def add_batch(self, x: np.ndarray, u: np.ndarray, y: np.ndarray) -> None:
        rows = np.concatenate([x, u, y], axis=1)[-len(self._rows):]
        with self._lock:
            idx = (self._n + np.arange(len(rows))) % len(self._rows)
            self._rows[idx] = rows
            self._n += len(rows)

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Copies of the window's ``x (W, n_x)``, ``u (W, n_u)``, ``y (W, n_y)`` (``W`` <= size)."""
        with self._lock:
            rows = self._rows[: min(self._n, len(self._rows))].copy()
        a, b = self._split
        return rows[:, :a], rows[:, a:b], rows[:, b:]


class Ingest:
    """One pairer per source (robot / namespace), feeding one replay buffer and one recent window.

    ``bounds``: the plausible ranges already-paired batches (:meth:`add_batch`) are checked against (rows with a
    non-finite or implausible value are dropped and counted as ``nan`` / ``bounds``); each source's pairer checks
    single events with its own config's bounds.

    ``heldout``: where transitions of the held-out stretches go instead of the buffer
    (:func:`~saml_ros.core.online.heldout.heldout_mask` of their stamps); None: every transition is training data.
    The recent window gets every transition.
    """

    def __init__(self, buffer: ReplayBuffer, recent: RecentWindow, bounds: Plausibility | None = None,
                 heldout: HeldoutSet | None = None) -> None:
        self.buffer, self.recent = buffer, recent
        self.bounds = bounds
        self.heldout = heldout
        self._sources: list[StampPairer | ResamplingPairer] = []
        self._batch_rejects: dict[str, int] = {"nan": 0, "bounds": 0}

    def add_source(self, name: str, pairing: PairingConfig | ResampleConfig) -> int:
        """Register a source with its pairing rule (exact stamps, or resampling onto a fixed period for a robot's
        own unsynchronised topics); returns its index."""
        p: StampPairer | ResamplingPairer
        if isinstance(pairing, ResampleConfig):
            p = ResamplingPairer(pairing, source=len(self._sources), name=name)
        else:
            p = StampPairer(pairing, source=len(self._sources), name=name)
        for reason in REJECT_REASONS:
            p.counts.setdefault(reason, 0)
        self._sources.append(p)
        return p.source

    @property
    def sources(self) -> list[StampPairer | ResamplingPairer]:
        return list(self._sources)

    def ingest(self, source: int, kind: str, stamp_ns: int, vector: Any) -> AddResult:
        """Feed one event of ``source`` (see :meth:`StampPairer.add`); completed transitions are added."""
        res = self._sources[source].add(kind, stamp_ns, vector)
        for tr in res.transitions:
            self.add(tr)
        return res

    def reject(self, source: int, reason: str, kind: str | None = None) -> None:
        """Count a ``kind`` message of ``source`` dropped before pairing (``reason``: a SchemaError reason)."""
        self._sources[source].reject(reason, kind)

    def add(self, tr: Transition) -> None:
        """Add one paired transition to the buffer (or the held-out set) and the recent window."""
        stamp = tr.stamp_ns * 1e-9
        if self.heldout is not None and heldout_mask(stamp, self.heldout.config)[0]:
            self.heldout.add_batch(np.asarray(tr.x)[None], np.asarray(tr.u)[None], np.asarray(tr.y)[None],
                                   stamp, tr.source)
        else:
            self.buffer.add(tr.x, tr.u, tr.y, stamp=stamp, source=tr.source)
        self.recent.add(tr.x, tr.u, tr.y)

    def add_batch(self, x: np.ndarray, u: np.ndarray, y: np.ndarray, stamp: Any = 0.0, source: Any = 0) -> None:
        """Add ``B`` paired transitions at once: ``x (B, n_x)``, ``u (B, n_u)``, ``y (B, n_y)``, ``stamp`` in s and
        ``source`` scalars or ``(B,)`` (much cheaper per row than :meth:`add`). Rows with a non-finite value or one
        outside :attr:`bounds` are dropped (counted ``nan`` / ``bounds``)."""
        if len(x) == 0:
            return
        x, u, y = (np.asarray(a, np.float64) for a in (x, u, y))
        finite = np.isfinite(x).all(1) & np.isfinite(u).all(1) & np.isfinite(y).all(1)
        keep = finite
        if self.bounds is not None:
            keep = finite & self.bounds.state.inside(x) & self.bounds.control.inside(u) & self.bounds.target.inside(y)
        if not keep.all():
            self._batch_rejects["nan"] += int((~finite).sum())
            self._batch_rejects["bounds"] += int((finite & ~keep).sum())
            log.warning("dropped %d of %d paired transition(s): non-finite or outside the plausible range",
                        int((~keep).sum()), len(x))
            x, u, y = x[keep], u[keep], y[keep]
            stamp = np.asarray(stamp)[keep] if np.ndim(stamp) else stamp
            source = np.asarray(source)[keep] if np.ndim(source) else source
            if len(x) == 0:
                return
        held = None if self.heldout is None else heldout_mask(np.broadcast_to(stamp, len(x)), self.heldout.config)
        if held is not None and held.any():
            st, so = np.broadcast_to(stamp, len(x)), np.broadcast_to(source, len(x))
            self.heldout.add_batch(x[held], u[held], y[held], stamp=st[held], source=so[held])  # type: ignore[union-attr]
            keep = ~held
            if keep.any():
                self.buffer.add_batch(x[keep], u[keep], y[keep], stamp=st[keep], source=so[keep])
        else:
            self.buffer.add_batch(x, u, y, stamp=stamp, source=source)
        self.recent.add_batch(x, u, y)

    def counts(self) -> dict[str, int]:
        """All sources' pairing and rejection counters, summed (with the batches' rejections)."""
        return total_counts([*(dict(list(p.counts.items())) for p in self._sources), dict(self._batch_rejects)])


class EventSink(Protocol):
    """Where :class:`RawIngest` delivers decoded events (:class:`Ingest` or an online learner)."""

    def ingest(self, source: int, kind: str, stamp_ns: int, vector: Any) -> AddResult: ...

    def reject(self, source: int, reason: str, kind: str | None = None) -> None: ...

    def counts(self) -> dict[str, int]: ...


class Throttle:
    """Per-key log throttling: the first event of each key is logged at once, later ones at most every
    ``period`` seconds with the number suppressed in between."""

    def __init__(self, emit: Callable[[str], Any], period: float = 5.0) -> None:
        self._emit, self._period = emit, period
        self._state: dict[str, tuple[float, int]] = {}

    def __call__(self, key: str, message: str) -> None:
        now = time.monotonic()
        last, suppressed = self._state.get(key, (-math.inf, 0))
        if now - last < self._period:
            self._state[key] = (last, suppressed + 1)
            return
        self._state[key] = (now, 0)
        more = f" ({suppressed} more '{key}' since the last report)" if suppressed else ""
        self._emit(f"rejected/{key}: {message}{more}")


class RawIngest:
    """Decodes raw (serialized) messages and feeds them to ``sink``'s pairers; every rejection is counted and
    logged (throttled per reason).

    Args:
        sink: an :class:`Ingest` (or an online learner).
        channels: ``(source index, kind)`` of each raw-message channel.
        decode: see :data:`Decode`.
    """

    def __init__(self, sink: EventSink, channels: Sequence[tuple[int, str]], decode: Decode) -> None:
        self.sink, self.channels, self.decode = sink, list(channels), decode
        self.throttle = Throttle(log.warning)
        self._unpaired = 0

    def feed(self, items: Sequence[tuple[int, Any]]) -> None:
        """``[(channel, payload), ...]`` in arrival order."""
        sink = self.sink
        for channel, payload in items:
            src, kind = self.channels[channel]
            try:
                vec, stamp = self.decode(channel, payload)
            except Exception as exc:  # noqa: BLE001 - any malformed message is counted, never fatal
                reason = getattr(exc, "reason", None) or "format"
                sink.reject(src, reason, kind)
                self.throttle(reason, str(exc) if reason != "format" else f"{type(exc).__name__}: {exc}")
                continue
            res = sink.ingest(src, kind, stamp, vec)
            if res.rejected is not None:
                self.throttle(res.rejected, res.detail)
            elif res.detail:
                log.warning(res.detail)

    def check_orphans(self) -> None:
        """Log (throttled) when messages left the pairing window without ever being paired."""
        unpaired = self.sink.counts().get("unpaired", 0)
        if unpaired > self._unpaired:
            self.throttle("unpaired", f"{unpaired - self._unpaired} message(s) left the pairing window without "
                                      "ever being paired")
        self._unpaired = unpaired
