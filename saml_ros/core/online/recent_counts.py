"""How much cumulative counters grew over a recent time window (ROS-free): :class:`RecentCounts`.

A node's ``/diagnostics`` reports its counters as counters (they only grow, so a monitor can difference them), but
its level says how the node is *now*: "messages were rejected in the last minute", not "a message was rejected an
hour ago". :class:`RecentCounts` is fed the counters at every report and returns each one's increase over the last
``window_s`` seconds; a counter that goes down (a restarted process counts from 0 again) counts its new value as the
increase, so nothing is lost across a restart.
"""

from __future__ import annotations

import math
import time
from collections import deque
from collections.abc import Callable, Mapping

#: the default window (s) of the levels on /diagnostics
LEVEL_WINDOW_S = 60.0


class RecentCounts:
    """Increases of cumulative counters over the last ``window_s`` seconds (see the module docstring).

    Args:
        window_s: the window (s, > 0).
        clock: time source (s); ``time.monotonic`` by default (steady: simulated time does not move it).

    The counters seen at construction count from 0: what a new node counted before its first report is recent.
    """

    def __init__(self, window_s: float = LEVEL_WINDOW_S, clock: Callable[[], float] = time.monotonic) -> None:
        if not (window_s > 0 and math.isfinite(window_s)):
            raise ValueError(f"window_s must be > 0 s, got {window_s}")
        self.window_s = float(window_s)
        self._clock = clock
        self._last: dict[str, float] = {}  # the counters as last seen
        self._total: dict[str, float] = {}  # their growth so far (monotone, across resets)
        self._history: deque[tuple[float, dict[str, float]]] = deque([(clock(), {})])

    def update(self, counters: Mapping[str, float], now: float | None = None) -> dict[str, float]:
        """Take the counters' current values; returns each one's increase over the last ``window_s`` seconds."""
        now = self._clock() if now is None else now
        for key, value in counters.items():
            v = float(value)
            prev = self._last.get(key, 0.0)
            self._total[key] = self._total.get(key, 0.0) + (v - prev if v >= prev else v)
            self._last[key] = v
        self._history.append((now, dict(self._total)))
        # the baseline is the newest snapshot at least window_s old (or the oldest one there is)
        while len(self._history) >= 2 and self._history[1][0] <= now - self.window_s:
            self._history.popleft()
        base = self._history[0][1]
        return {key: self._total[key] - base.get(key, 0.0) for key in counters}
