"""Exact stamp pairing of ``state`` / ``applied_cmd`` / target messages into transitions (ROS-free).

One :class:`StampPairer` serves one source (one robot / simulator namespace). It is fed events
``(kind, stamp_ns, vector)`` with ``kind`` in :data:`KINDS` and emits :class:`Transition` objects
``(x_t, u_t, y)``:

* ``mode="next"`` (time-stepped systems): ``x_t`` = the ``state`` stamped t, ``u_t`` = the ``applied_cmd``
  stamped t, ``y`` = the ``state`` stamped t + dt. ``target`` events are not used in this mode.
* ``mode="same"`` (event systems, the paddle ball): ``state``, ``applied_cmd`` and ``target`` with the same stamp.

Two stamps are "the same" when they differ by at most ``tolerance_ns`` (default 1 us). Events of different
kinds may arrive in any interleaving; within one kind, stamps must increase (DDS keeps each topic in publish
order). A transition is emitted exactly once, as soon as its last message arrives, whatever the order.

Retention (bounded memory): the pairer remembers the stamps of the newest ``window`` accepted states and every
entry not older than the oldest of them; older entries are dropped. Retention counts states, not seconds, so
it does not depend on how fast stamps advance (a lockstep simulator may run far faster than real time) and
covers any backlog between topics shorter than ``window`` steps (a DDS reader queue holds at most its depth).
At most ``max_slots`` stamps are remembered in total (the oldest go first), whatever the stamps.

Each event is checked in this order; a rejected event is counted under its reason and dropped, never paired:

1. ``stamp``: not an int >= 0. ``shape``: wrong vector length. ``nan``: NaN or Inf in the vector. ``bounds``: a
   value outside the system's plausible range (:class:`~saml_ros.core.data.plausibility.Plausibility`, when the
   config has one).
2. ``duplicate``: an event of this kind with the same stamp is already remembered.
3. ``late``: stamped at or before the newest dropped entry (its partners were forgotten).
4. ``out_of_order``: stamped before the newest accepted event of the same kind.

Re-anchoring: ``reanchor`` (default 3) consecutive rejected events of one kind (``duplicate``, ``late`` or
``out_of_order``) whose stamps increase among themselves are not noise. They mean one of two things:

* **an outlier**: fewer remembered events of that kind are newer than the run's first stamp than the run is
  long, and none of them was paired yet: those few (typically one bogus far-future stamp that every later event
  looks "out of order" against) are removed and counted ``outlier``; nothing else is touched, so no good pending
  transition is lost;
* **a new clock** otherwise (a restarted simulator, a bag played again): for ``state`` everything pending is
  dropped (``time_resets``; every transition whose messages had all arrived was already emitted); for another
  kind only that kind's order reference is forgotten (``reanchors``).

Either way the events of the run are then fed again (and removed from the rejection counters if they are
accepted), so a restart loses nothing but the steps spanning it.

Counters (:attr:`StampPairer.counts`, see :data:`COUNTERS`): ``received/<kind>`` every event of that kind,
``paired`` transitions emitted, one counter per rejection reason, ``unpaired`` messages dropped from memory
without ever being part of a transition (orphans: a command whose state never came, a state with neither a
command nor a predecessor), ``expired`` incomplete stamps dropped (informational: the last state before an
episode reset is one), ``overflow`` stamps dropped by the ``max_slots`` cap, ``outlier`` events accepted at
first and removed when later events showed their stamp to be out of pattern, ``time_resets``, ``reanchors``.
"""

from __future__ import annotations

import bisect
from collections import deque
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np

from saml_ros.core.data.plausibility import Plausibility

KINDS: tuple[str, ...] = ("state", "applied_cmd", "target")
MODES: tuple[str, ...] = ("next", "same")

#: reasons a single event is dropped by :meth:`StampPairer.add` (a subset of msg_schemas' REJECT_REASONS);
#: ``outlier`` events are dropped by a later call (see "Re-anchoring")
EVENT_REJECTS: tuple[str, ...] = ("stamp", "shape", "nan", "bounds", "duplicate", "late", "out_of_order", "outlier")
#: rejections that may reveal a new clock (see "Re-anchoring" in the module docstring)
_ORDER_REJECTS = frozenset({"duplicate", "late", "out_of_order"})
#: every counter a :class:`StampPairer` keeps (all start at 0)
COUNTERS: tuple[str, ...] = (
    "received/state", "received/applied_cmd", "received/target", "paired",
    *EVENT_REJECTS, "unpaired", "expired", "overflow", "time_resets", "reanchors",
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
        transitions: transitions completed by this event (usually 0 or 1; a ``state`` may close the previous
            step and complete its own, and a re-anchoring may complete several).
        rejected: the reason the event was dropped (one of :data:`EVENT_REJECTS`), or ``None`` if accepted.
        detail: explanation of a rejection or of a re-anchoring (empty otherwise).
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
        window: newest accepted states whose stamps (and everything newer) are remembered.
        max_slots: hard cap on remembered stamps.
        reanchor: consecutive increasing rejected events of one kind that re-anchor its clock (>= 2).
        bounds: plausible ranges of the vectors (events outside them are rejected as ``bounds``); ``None``: no
            range check.
    """

    mode: str
    n_x: int
    n_u: int
    n_y: int
    dt_ns: int = 0
    tolerance_ns: int = 1_000
    window: int = 1000
    max_slots: int = 10_000
    reanchor: int = 3
    bounds: Plausibility | None = None

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
        if self.window < 2:
            raise ValueError(f"window must be >= 2 states (x_t and x_t+dt), got {self.window}")
        if self.max_slots < self.window:
            raise ValueError(f"max_slots ({self.max_slots}) must be >= window ({self.window})")
        if self.reanchor < 2:
            raise ValueError(f"reanchor must be >= 2, got {self.reanchor}")

    @classmethod
    def for_system(cls, system: Any, target_pairing: str, *, dt: float | None = None, tolerance: float = 1e-6,
                   window: int = 1000, max_slots: int = 10_000, reanchor: int = 3,
                   plausible_bounds: Mapping[str, Any] | str | None = None) -> PairingConfig:
        """Config for a :class:`~saml_ros.core.dynamics.system.System` (``dt``, ``tolerance`` in s).

        ``target_pairing`` is ``SystemSchema.target_pairing``; ``dt`` defaults to ``system.dt``; the bounds are the
        system's plausible ranges with ``plausible_bounds`` overrides (:meth:`Plausibility.for_system`).
        """
        step = float(system.dt if dt is None else dt)
        return cls(
            mode=target_pairing,
            n_x=system.state.size,
            n_u=system.control.size,
            n_y=system.target.size,
            dt_ns=round(step * NS_PER_S) if target_pairing == "next" else 0,
            tolerance_ns=round(tolerance * NS_PER_S),
            window=window,
            max_slots=max_slots,
            reanchor=reanchor,
            bounds=Plausibility.for_system(system, plausible_bounds),
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
        return self.emitted and (mode == "same" or self.x_used)


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
        self._states: deque[int] = deque()  # stamps of the newest accepted states, ascending
        self._floor: int | None = None  # newest stamp dropped from memory
        self._last: dict[str, int | None] = dict.fromkeys(KINDS, None)
        self._runs: dict[str, list[tuple[int, np.ndarray, str]]] = {k: [] for k in KINDS}

    # ------------------------------------------------------------------------------------------ public
    @property
    def pending(self) -> int:
        """Remembered stamps (slots), complete or not."""
        return len(self._keys)

    def reject(self, reason: str, kind: str | None = None) -> None:
        """Count an event of ``kind`` dropped before it reached the pairer (e.g. a malformed message) under
        ``reason``; ``received/<kind>`` counts it too, so it counts every message of that kind."""
        if kind in self._sizes:
            self.counts["received/" + kind] += 1
        self.counts[reason] = self.counts.get(reason, 0) + 1

    def add(self, kind: str, stamp_ns: int, vector: Any) -> AddResult:
        """Feed one event; returns the transitions it completed, or why it was dropped."""
        if kind not in self._sizes or (kind == "target" and self.config.mode == "next"):
            raise ValueError(f"{self.name}: unknown event kind {kind!r} for pairing mode {self.config.mode!r}")
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
        bounds = self.config.bounds
        if bounds is not None:
            why = bounds.outside(kind, vec)
            if why is not None:
                return self._drop("bounds", f"{kind} at {_fmt(stamp)}: outside the plausible range: {why}")
        reason, detail = self._classify(kind, stamp)
        run = self._runs[kind]
        if reason is None:
            run.clear()
            return AddResult(self._accept(kind, stamp, vec))
        result = self._drop(reason, detail)
        if run and stamp <= run[-1][0] + self.config.tolerance_ns:
            run.clear()  # not increasing: noise, not a new clock
        run.append((stamp, vec, reason))
        if len(run) >= self.config.reanchor:
            return self._reanchor(kind)
        return result

    def flush(self) -> None:
        """Forget every pending entry (counting orphans), e.g. when a source goes away."""
        self._reset()

    # ------------------------------------------------------------------------------------------ rules
    def _classify(self, kind: str, stamp: int) -> tuple[str | None, str]:
        tol = self.config.tolerance_ns
        slot = self._find(stamp)
        if slot is not None and _get(slot, kind) is not None:
            return "duplicate", f"{kind} at {_fmt(stamp)} was already received"
        if slot is None and self._floor is not None and stamp <= self._floor + tol:
            return "late", (f"{kind} at {_fmt(stamp)} is older than everything still remembered (up to "
                            f"{_fmt(self._floor)}; pairing window = {self.config.window} states)")
        last = self._last[kind]
        if last is not None and stamp < last - tol:
            return "out_of_order", f"{kind} at {_fmt(stamp)} arrived after {kind} at {_fmt(last)}"
        return None, ""

    def _accept(self, kind: str, stamp: int, vec: np.ndarray) -> list[Transition]:
        slot = self._find(stamp) or self._insert(stamp)
        _set(slot, kind, vec)
        last = self._last[kind]
        self._last[kind] = stamp if last is None else max(last, stamp)
        out = self._pair(slot, kind)
        if kind == "state":
            self._states.append(stamp)
            if len(self._states) > self.config.window:
                self._evict(self._states.popleft())
        if len(self._keys) > self.config.max_slots:
            self._evict(None)
        return out

    def _reanchor(self, kind: str) -> AddResult:
        outliers = self._outliers(kind, self._runs[kind])
        kinds = list(KINDS) if kind == "state" and outliers is None else [kind]
        runs = {k: self._runs[k] for k in kinds}
        self._runs.update({k: [] for k in kinds})
        if outliers is not None:
            for slot in outliers:
                self._remove(slot, kind)
            newest = [s.stamp for s in self._slots.values() if _get(s, kind) is not None]
            self._last[kind] = max(newest) if newest else None
            self.counts["outlier"] += len(outliers)
            detail = (f"{self.name}: {kind} at {', '.join(_fmt(s.stamp) for s in outliers)} out of pattern "
                      f"(later {kind} stamps continue at {_fmt(runs[kind][0][0])}): dropped as outlier(s)")
        elif kind == "state":
            first = runs["state"][0][0]
            detail = (f"{self.name}: state stamps restarted at {_fmt(first)} (before {_fmt(self._last['state'] or 0)}):"
                      f" new clock, {len(self._keys)} pending stamp(s) dropped")
            self._reset()
            self.counts["time_resets"] += 1
        else:
            detail = (f"{self.name}: {kind} stamps continue at {_fmt(runs[kind][0][0])}, before the {kind} at "
                      f"{_fmt(self._last[kind] or 0)}: that one was bogus; {kind} order re-anchored")
            self._last[kind] = None
            self.counts["reanchors"] += 1
        out: list[Transition] = []
        for k in kinds:
            for stamp, vec, reason in runs[k]:
                self.counts[reason] -= 1  # counted as rejected when it arrived; decided again now
                again, _ = self._classify(k, stamp)
                if again is None:
                    out += self._accept(k, stamp, vec)
                else:
                    self.counts[again] += 1
        return AddResult(out, None, detail)

    def _outliers(self, kind: str, run: list[tuple[int, np.ndarray, str]]) -> list[_Slot] | None:
        """The remembered ``kind`` events newer than the run's first stamp, if they are outliers (fewer than the
        run and none paired yet), else ``None`` (the run is a new clock)."""
        first = run[0][0] + self.config.tolerance_ns
        newer = [self._slots[k] for k in self._keys[bisect.bisect_right(self._keys, first):]]
        newer = [s for s in newer if _get(s, kind) is not None]
        if not newer or len(newer) >= len(run) or any(s.emitted or s.x_used for s in newer):
            return None
        return newer

    def _remove(self, slot: _Slot, kind: str) -> None:
        """Take the ``kind`` message out of ``slot`` (and the slot out of memory once it is empty)."""
        _set(slot, kind, None)
        if kind == "state" and slot.stamp in self._states:
            self._states.remove(slot.stamp)
        if slot.x is None and slot.u is None and slot.y is None:
            del self._slots[slot.stamp]
            self._keys.remove(slot.stamp)

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
        """Drop slots stamped at or before ``cutoff`` and, beyond ``max_slots``, the oldest ones."""
        keys, n = self._keys, 0
        cap = self.config.max_slots
        while n < len(keys) and ((cutoff is not None and keys[n] <= cutoff) or len(keys) - n > cap):
            if cutoff is None or keys[n] > cutoff:
                self.counts["overflow"] += 1
            self._forget(self._slots.pop(keys[n]))
            n += 1
        if n:
            self._floor = max(keys[n - 1], self._floor if self._floor is not None else keys[n - 1])
            del keys[:n]
        while self._states and self._floor is not None and self._states[0] <= self._floor:
            self._states.popleft()

    def _forget(self, slot: _Slot) -> None:
        self.counts["unpaired"] += slot.orphans(self.config.mode)
        if not slot.complete(self.config.mode):
            self.counts["expired"] += 1

    def _reset(self) -> None:
        for key in self._keys:
            self._forget(self._slots[key])
        self._keys.clear()
        self._slots.clear()
        self._states.clear()
        self._floor = None
        self._last = dict.fromkeys(KINDS, None)

    def _drop(self, reason: str, detail: str) -> AddResult:
        self.counts[reason] += 1
        return AddResult([], reason, f"{self.name}: {detail}")


def _get(slot: _Slot, kind: str) -> np.ndarray | None:
    return slot.x if kind == "state" else slot.u if kind == "applied_cmd" else slot.y


def _set(slot: _Slot, kind: str, vec: np.ndarray | None) -> None:
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
