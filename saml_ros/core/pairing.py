"""Exact stamp pairing of ``state`` / ``applied_cmd`` / target messages into transitions (ROS-free).

One :class:`StampPairer` serves one source (one robot / simulator namespace). It is fed events
``(kind, stamp_ns, vector)`` with ``kind`` in :data:`KINDS` and emits :class:`Transition` objects
``(x_t, u_t, y)``:

* ``mode="next"`` (time-stepped systems): ``x_t`` = the ``state`` stamped t, ``u_t`` = the ``applied_cmd``
  stamped t, ``y`` = the ``state`` stamped t + dt. ``target`` events are not used in this mode.
* ``mode="same"`` (event systems, the paddle ball): ``state``, ``applied_cmd`` and ``target`` with the same stamp.

Two stamps are "the same" when they differ by at most ``tolerance_ns`` (default 1 us). Events may arrive in
any interleaving across kinds; within one kind stamps must increase. Rules, in the order they are checked
(each rejection is counted under its reason and the event is dropped, never paired):

1. ``stamp``: the stamp is not an int >= 0. ``shape``: the vector has the wrong length. ``nan``: NaN/Inf.
2. ``duplicate``: an event of this kind with the same stamp was already accepted (and is still remembered).
3. A ``state`` stamped more than ``horizon_ns`` before the newest ``state`` means the source's clock was
   restarted (a new simulator run): every pending entry is dropped (counted as ``unpaired`` if it never
   contributed to a transition), ``time_resets`` is incremented and the event is accepted.
4. ``late``: any event stamped more than ``horizon_ns`` before the newest accepted ``state`` of the source
   (its partners have already been forgotten). ``stamp``: an ``applied_cmd`` / ``target`` stamped more than
   ``horizon_ns`` after the newest ``state`` (it answers a state that was never published).
5. ``out_of_order``: the stamp is before the newest accepted stamp of the same kind.

Accepted events are kept in *slots* (one per stamp) until they fall more than ``horizon_ns`` behind the
newest ``state``; then the slot is dropped. The ``state`` stream is the source's clock: a bogus far-future
stamp on another kind only occupies one slot, and a bogus far-future ``state`` is undone by rule 3. Messages in a dropped slot that never became part of a transition are
counted as ``unpaired`` (orphaned), and a dropped slot that was not complete counts in ``stale_slots``. At
most ``max_slots`` slots are kept (the oldest go first, counted in ``overflow_slots``), so memory is bounded
whatever the stamps. A valid transition is emitted exactly once, as soon as its last message arrives.
"""

from __future__ import annotations

import bisect
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np

KINDS: tuple[str, ...] = ("state", "applied_cmd", "target")
MODES: tuple[str, ...] = ("next", "same")

#: reasons a single event is dropped by :meth:`StampPairer.add` (subset of msg_schemas' REJECT_REASONS)
EVENT_REJECTS: tuple[str, ...] = ("stamp", "shape", "nan", "duplicate", "late", "out_of_order")
#: every counter a :class:`StampPairer` keeps (all start at 0)
COUNTERS: tuple[str, ...] = (
    "received/state", "received/applied_cmd", "received/target", "paired",
    *EVENT_REJECTS, "unpaired", "stale_slots", "overflow_slots", "time_resets",
)  # fmt: skip

NS_PER_S = 1_000_000_000


class Transition(NamedTuple):
    """One paired transition.

    Attributes:
        x: ``(n_x,)`` float64 state x_t.
        u: ``(n_u,)`` float64 control applied over [t, t + dt) (or at the impact).
        y: ``(n_y,)`` float64 target: x_{t+dt} (``"next"``) or the target message's vector (``"same"``).
        stamp_ns: stamp of x_t, int nanoseconds.
        source: index of the source (robot / namespace) it came from.
    """

    x: np.ndarray
    u: np.ndarray
    y: np.ndarray
    stamp_ns: int
    source: int


class AddResult(NamedTuple):
    """What one :meth:`StampPairer.add` call did.

    Attributes:
        transitions: transitions completed by this event (0, 1 or 2; 2 when a ``state`` both closes the
            previous step and completes its own).
        rejected: the reason the event was dropped (one of :data:`EVENT_REJECTS`), or ``None`` if accepted.
        detail: a human-readable explanation for a rejection or a clock restart (empty otherwise).
    """

    transitions: list[Transition]
    rejected: str | None = None
    detail: str = ""


@dataclass(frozen=True)
class PairingConfig:
    """Pairing rule and limits for one source.

    Attributes:
        mode: ``"next"`` (time-stepped) or ``"same"`` (identical stamps, event systems).
        n_x, n_u, n_y: vector lengths of ``state``, ``applied_cmd`` and the target.
        dt_ns: sampling period in ns (``"next"`` only; must exceed 2 * tolerance_ns).
        tolerance_ns: two stamps closer than this (inclusive) are the same stamp; default 1 us.
        horizon_ns: how long (in stamp time) an incomplete entry waits for its partners; default 2 s.
        max_slots: hard cap on remembered stamps per source.
    """

    mode: str
    n_x: int
    n_u: int
    n_y: int
    dt_ns: int = 0
    tolerance_ns: int = 1_000
    horizon_ns: int = 2 * NS_PER_S
    max_slots: int = 100_000

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise ValueError(f"pairing mode must be one of {MODES}, got {self.mode!r}")
        if self.n_x < 1 or self.n_u < 0 or self.n_y < 1:
            raise ValueError(f"bad vector sizes n_x={self.n_x}, n_u={self.n_u}, n_y={self.n_y}")
        if self.tolerance_ns < 0:
            raise ValueError(f"tolerance_ns must be >= 0, got {self.tolerance_ns}")
        if self.mode == "next" and self.dt_ns <= 2 * self.tolerance_ns:
            raise ValueError(
                f"pairing mode 'next' needs dt_ns > 2 * tolerance_ns, got dt_ns={self.dt_ns}, "
                f"tolerance_ns={self.tolerance_ns}"
            )
        min_horizon = self.dt_ns + self.tolerance_ns if self.mode == "next" else self.tolerance_ns
        if self.horizon_ns <= min_horizon:
            raise ValueError(
                f"horizon_ns ({self.horizon_ns}) must exceed {'dt + tolerance' if self.mode == 'next' else 'the tolerance'}"
                f" ({min_horizon} ns), or nothing can ever be paired"
            )
        if self.max_slots < 2:
            raise ValueError(f"max_slots must be >= 2, got {self.max_slots}")

    @classmethod
    def for_system(cls, system: Any, target_pairing: str, *, dt: float | None = None, tolerance: float = 1e-6,
                   horizon: float = 2.0, max_slots: int = 100_000) -> PairingConfig:
        """Config for a :class:`~saml_ros.core.systems.base.System` (``dt``, ``tolerance``, ``horizon`` in s).

        ``target_pairing`` is ``SystemSchema.target_pairing``; ``dt`` defaults to ``system.dt``.
        """
        step = float(system.dt if dt is None else dt)
        return cls(
            mode=target_pairing,
            n_x=system.state.size,
            n_u=system.control.size,
            n_y=system.target.size,
            dt_ns=round(step * NS_PER_S) if target_pairing == "next" else 0,
            tolerance_ns=round(tolerance * NS_PER_S),
            horizon_ns=round(horizon * NS_PER_S),
            max_slots=max_slots,
        )


class _Slot:
    """Everything received for one stamp of one source."""

    __slots__ = ("stamp", "x", "u", "y", "x_used", "emitted")

    def __init__(self, stamp: int) -> None:
        self.stamp = stamp
        self.x: np.ndarray | None = None
        self.u: np.ndarray | None = None
        self.y: np.ndarray | None = None
        self.x_used = False  # "next": this state was the target of the previous step
        self.emitted = False  # this slot's own transition (x_t, u_t, ...) was emitted

    def orphans(self, mode: str) -> int:
        """Messages in this slot that never became part of a transition."""
        if mode == "same":
            return 0 if self.emitted else sum(v is not None for v in (self.x, self.u, self.y))
        n = 0 if self.emitted or self.u is None else 1
        if self.x is not None and not (self.emitted or self.x_used):
            n += 1
        return n

    def complete(self, mode: str) -> bool:
        if mode == "same":
            return self.emitted
        return self.emitted and self.x_used


class StampPairer:
    """Pairs one source's events exactly by stamp (see the module docstring for the rules).

    Not thread-safe: feed one pairer from one thread at a time (its counters may be read from any thread).

    Args:
        config: the pairing rule and limits.
        source: index stored in every emitted :class:`Transition`.
        name: label used in rejection details (e.g. the namespace ``"/friction"``).
    """

    def __init__(self, config: PairingConfig, source: int = 0, name: str = "") -> None:
        self.config = config
        self.source = int(source)
        self.name = name or f"source {source}"
        self.counts: dict[str, int] = dict.fromkeys(COUNTERS, 0)
        self._sizes = {"state": config.n_x, "applied_cmd": config.n_u, "target": config.n_y}
        self._keys: list[int] = []  # stamps of the slots, ascending
        self._slots: dict[int, _Slot] = {}
        self._last: dict[str, int | None] = dict.fromkeys(KINDS, None)
        self._newest: int | None = None  # newest accepted state stamp

    # ------------------------------------------------------------------------------------------ public
    @property
    def pending(self) -> int:
        """Remembered stamps (slots), complete or not."""
        return len(self._keys)

    def reject(self, reason: str) -> None:
        """Count an event dropped before it reached the pairer (e.g. a malformed message)."""
        self.counts[reason] = self.counts.get(reason, 0) + 1

    def add(self, kind: str, stamp_ns: int, vector: Any) -> AddResult:
        """Feed one event; returns the transitions it completed, or why it was dropped."""
        cfg = self.config
        if kind not in self._sizes or (kind == "target" and cfg.mode == "next"):
            raise ValueError(f"{self.name}: unknown event kind {kind!r} for pairing mode {cfg.mode!r}")
        self.counts["received/" + kind] += 1
        if isinstance(stamp_ns, bool) or not isinstance(stamp_ns, int | np.integer) or stamp_ns < 0:
            return self._drop("stamp", f"{kind} stamp must be an int >= 0 (ns), got {stamp_ns!r}")
        stamp = int(stamp_ns)
        vec = np.asarray(vector, dtype=np.float64)
        size = self._sizes[kind]
        if vec.shape != (size,):
            return self._drop("shape", f"{kind} at {_fmt(stamp)}: expected {size} values, got shape {vec.shape}")
        if not np.isfinite(vec).all():
            return self._drop("nan", f"{kind} at {_fmt(stamp)}: non-finite value(s) {vec.tolist()}")

        tol = cfg.tolerance_ns
        slot = self._find(stamp)
        if slot is not None and _get(slot, kind) is not None:
            return self._drop("duplicate", f"{kind} at {_fmt(stamp)} was already received")
        detail = ""
        last = self._last[kind]
        if kind == "state" and last is not None and stamp < last - cfg.horizon_ns:
            detail = (
                f"state stamp jumped back from {_fmt(last)} to {_fmt(stamp)}: clock restart, "
                f"{len(self._keys)} pending stamp(s) dropped"
            )
            self._reset()
            self.counts["time_resets"] += 1
            slot, last = None, None
        elif self._newest is not None and stamp < self._newest - cfg.horizon_ns:
            return self._drop(
                "late", f"{kind} at {_fmt(stamp)} is more than the horizon behind the newest state {_fmt(self._newest)}"
            )
        elif kind != "state" and self._newest is not None and stamp > self._newest + cfg.horizon_ns:
            return self._drop(
                "stamp", f"{kind} at {_fmt(stamp)} is more than the horizon ahead of the newest state {_fmt(self._newest)}"
            )
        if kind != "state" and last is not None and self._newest is not None and last > self._newest + cfg.horizon_ns:
            last = None  # accepted before the first state arrived, and implausible now: do not let it block
        if not detail and last is not None and stamp < last - tol:
            return self._drop("out_of_order", f"{kind} at {_fmt(stamp)} arrived after {kind} at {_fmt(last)}")

        if slot is None:
            slot = self._insert(stamp)
        _set(slot, kind, vec)
        self._last[kind] = stamp if last is None else max(last, stamp)
        out = self._pair(slot, kind)
        if kind == "state" and (self._newest is None or stamp > self._newest):
            self._newest = stamp
            self._evict(stamp - cfg.horizon_ns)
        elif len(self._keys) > cfg.max_slots:
            self._evict(None)
        return AddResult(out, None, detail)

    def flush(self) -> None:
        """Forget every pending entry (counting orphans), e.g. at shutdown or when a source goes away."""
        self._reset()

    # ------------------------------------------------------------------------------------------ pairing
    def _pair(self, slot: _Slot, kind: str) -> list[Transition]:
        cfg = self.config
        out: list[Transition] = []
        if cfg.mode == "same":
            if slot.x is not None and slot.u is not None and slot.y is not None and not slot.emitted:
                slot.emitted = True
                out.append(Transition(slot.x, slot.u, slot.y, slot.stamp, self.source))
            self.counts["paired"] += len(out)
            return out
        # "next": this slot's own step (needs x_t, u_t and the state one dt later) ...
        if slot.x is not None and slot.u is not None and not slot.emitted:
            nxt = self._find(slot.stamp + cfg.dt_ns)
            if nxt is not None and nxt.x is not None:
                slot.emitted = True
                nxt.x_used = True
                out.append(Transition(slot.x, slot.u, nxt.x, slot.stamp, self.source))
        # ... and, for a new state, the previous step it closes
        if kind == "state" and slot.x is not None:
            prev = self._find(slot.stamp - cfg.dt_ns)
            if prev is not None and prev.x is not None and prev.u is not None and not prev.emitted:
                prev.emitted = True
                slot.x_used = True
                out.insert(0, Transition(prev.x, prev.u, slot.x, prev.stamp, self.source))
        self.counts["paired"] += len(out)
        return out

    # ------------------------------------------------------------------------------------------ slots
    def _find(self, stamp: int) -> _Slot | None:
        keys, tol = self._keys, self.config.tolerance_ns
        i = bisect.bisect_left(keys, stamp - tol)
        if i < len(keys) and keys[i] <= stamp + tol:
            return self._slots[keys[i]]
        return None

    def _insert(self, stamp: int) -> _Slot:
        slot = _Slot(stamp)
        keys = self._keys
        if not keys or stamp > keys[-1]:
            keys.append(stamp)
        else:
            bisect.insort(keys, stamp)
        self._slots[stamp] = slot
        return slot

    def _evict(self, cutoff: int | None) -> None:
        """Drop slots older than ``cutoff`` (stamp ns) and, beyond ``max_slots``, the oldest ones."""
        keys, n = self._keys, 0
        cap = self.config.max_slots
        while n < len(keys) and ((cutoff is not None and keys[n] < cutoff) or len(keys) - n > cap):
            if cutoff is None or keys[n] >= cutoff:
                self.counts["overflow_slots"] += 1
            self._forget(self._slots.pop(keys[n]))
            n += 1
        if n:
            del keys[:n]

    def _forget(self, slot: _Slot) -> None:
        self.counts["unpaired"] += slot.orphans(self.config.mode)
        if not slot.complete(self.config.mode):
            self.counts["stale_slots"] += 1

    def _reset(self) -> None:
        for key in self._keys:
            self._forget(self._slots[key])
        self._keys.clear()
        self._slots.clear()
        self._last = dict.fromkeys(KINDS, None)
        self._newest = None

    def _drop(self, reason: str, detail: str) -> AddResult:
        self.counts[reason] += 1
        return AddResult([], reason, f"{self.name}: {detail}")


def _get(slot: _Slot, kind: str) -> np.ndarray | None:
    return slot.x if kind == "state" else slot.u if kind == "applied_cmd" else slot.y


def _set(slot: _Slot, kind: str, vec: np.ndarray) -> None:
    if kind == "state":
        slot.x = vec
    elif kind == "applied_cmd":
        slot.u = vec
    else:
        slot.y = vec


def _fmt(stamp: int) -> str:
    return f"{stamp / NS_PER_S:.9f} s"


def total_counts(counters: Iterable[Mapping[str, int]]) -> dict[str, int]:
    """Sum several pairers' :attr:`StampPairer.counts` key by key."""
    out: dict[str, int] = dict.fromkeys(COUNTERS, 0)
    for c in counters:
        for k, v in c.items():
            out[k] = out.get(k, 0) + int(v)
    return out
