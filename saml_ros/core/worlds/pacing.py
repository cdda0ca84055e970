"""A speed limit for lockstep simulation (:class:`Pacer`): at most ``max_speed`` simulated seconds per wall second.

In lockstep the loop runs as fast as its slowest participant, so whatever else shares the CPU (the learners'
training processes beside the demo's loop) gets less of it per simulated second the faster the controller is.
A limit makes that share a property of the run's settings, like Gazebo's real-time factor. The limit never
makes up for lost time: after a slow step the next one is not hurried (no bursts).
"""

from __future__ import annotations

import math


class Pacer:
    """How long to wait before stepping to simulated time ``sim_ns`` (``wait_s``).

    Args:
        max_speed: simulated seconds per wall second at most; 0 = no limit.
    """

    def __init__(self, max_speed: float) -> None:
        if not (math.isfinite(max_speed) and max_speed >= 0.0):
            raise ValueError(f"max_speed must be >= 0 (0 = no limit), got {max_speed}")
        self.max_speed = float(max_speed)
        self._origin: tuple[int, int] | None = None  # (simulated ns, wall ns) the schedule counts from
        #: wall seconds waited so far
        self.waited_s = 0.0

    def set_speed(self, max_speed: float) -> None:
        """A new limit (``max_speed`` as in the constructor), counted from the next step."""
        if not (math.isfinite(max_speed) and max_speed >= 0.0):
            raise ValueError(f"max_speed must be >= 0 (0 = no limit), got {max_speed}")
        self.max_speed, self._origin = float(max_speed), None

    def wait_s(self, sim_ns: int, wall_ns: int) -> float:
        """Wall seconds to wait (>= 0) before the step at simulated time ``sim_ns`` when the wall clock reads
        ``wall_ns`` (monotonic ns): zero while the run is slower than the limit (then the schedule restarts from
        this step) or when simulated time went back (a reset)."""
        if self.max_speed <= 0.0:
            return 0.0
        origin = self._origin
        if origin is None or sim_ns < origin[0]:
            self._origin = (sim_ns, wall_ns)
            return 0.0
        due_ns = origin[1] + (sim_ns - origin[0]) / self.max_speed
        wait = (due_ns - wall_ns) * 1e-9
        if wait <= 0.0:
            self._origin = (sim_ns, wall_ns)
            return 0.0
        self.waited_s += wait
        return wait
