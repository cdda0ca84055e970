"""The live model monitor (ROS-free): is the model in use predicting the transitions actually flown worse than the
base model f_hat does? (:class:`LiveErrorMonitor`)

Every control step the active model planned gives one live transition ``(x, u) -> x_next`` (the state the
controller solved from, the command it sent, the next state it received; the guard does not feed it the steps it
planned with f_hat on ensemble disagreement). The monitor keeps the one-step squared errors
``||x_next - model(x, u)||^2`` of the active model and ``||x_next - f_hat(x, u)||^2`` of the base model over the
last ``window`` transitions and says *roll back* once it holds at least ``min_samples`` of them and

    mean(active errors) > ratio * mean(base errors) + margin.

The ``margin`` (squared state units, summed over the target fields) is needed because f_hat is exact wherever the
system has no unmodelled effect (the quadrotor above the ground-effect ceiling): there any learned model has a
larger error than f_hat, however small, and without a margin every good model would be rolled back as soon as
the vehicle climbs out of the ground effect. The default 0.01 is ten times the quadrotor spec's bound
``eps = 0.001`` on the in-region error: a model that satisfies its spec never comes near it, one that sends the
vehicle off (errors of 0.1-10 per step were measured on models trained only on hover data) crosses it within
``min_samples`` steps.

Transitions can come from several *streams* (``stream`` of :meth:`LiveErrorMonitor.add`): two robots whose states
interleave on one topic are two streams, each with its own window, and the monitor says roll back as soon as any
stream's window does. Mixed in one window, a robot on which f_hat is far off (one wired backwards) would hide
that the model is worse than f_hat on the other. At most :data:`MAX_STREAMS` streams are kept (the least recently
added is forgotten).

What happens on a roll back (the previous model, else f_hat) is the caller's
(:class:`saml_ros.core.mpc.guard.GuardedController`).
"""

from __future__ import annotations

import math
from collections import OrderedDict, deque
from dataclasses import dataclass

#: streams whose windows the monitor keeps
MAX_STREAMS = 8


@dataclass(frozen=True)
class MonitorConfig:
    """When :class:`LiveErrorMonitor` says roll back (see the module docstring).

    Attributes:
        window: live transitions the means are taken over (>= 1).
        min_samples: transitions needed in the window before it may say roll back (1..window).
        ratio: the active model must be worse than ``ratio`` times the base model's mean error (> 0).
        margin: plus this (squared state units, >= 0).
    """

    window: int = 5
    min_samples: int = 3
    ratio: float = 1.0
    margin: float = 0.01
    #: the constraint watch (:class:`saml_ros.core.mpc.guard.GuardedController`): roll back once this many of
    #: the last ``window`` steps the model planned (at least ``constraint_strikes``) broke a state constraint of the task by more than
    #: ``constraint_tol`` where the model's ``constraint_steps``-step prediction (the flown commands) kept it and
    #: f_hat's saw it coming; 0 = off (the default: measured, it rolls back the demo's good ensembles in the wind
    #: world as well as the capacity sweep's 4-4 nets, docs/demo.md "The constraint watch")
    constraint_strikes: int = 0
    #: state units of the constrained fields (the quadrotor's height bound: m)
    constraint_tol: float = 0.005
    #: steps from a command to the constrained state (the quadrotor's height: thrust -> vz -> pz, 2)
    constraint_steps: int = 2

    def __post_init__(self) -> None:
        if self.window < 1 or not 1 <= self.min_samples <= self.window:
            raise ValueError(f"monitor: need window >= 1 and 1 <= min_samples <= window, got {self.window}, "
                             f"{self.min_samples}")
        if self.constraint_strikes < 0 or self.constraint_steps < 1 or not (
                self.constraint_tol >= 0 and math.isfinite(self.constraint_tol)):
            raise ValueError(f"monitor: need constraint_strikes >= 0, constraint_steps >= 1 and a finite "
                             f"constraint_tol >= 0, got {self.constraint_strikes}, {self.constraint_steps}, "
                             f"{self.constraint_tol}")
        if not (self.ratio > 0 and math.isfinite(self.ratio)) or not (self.margin >= 0 and math.isfinite(self.margin)):
            raise ValueError(f"monitor: ratio must be > 0 and margin >= 0 (finite), got {self.ratio}, {self.margin}")


class LiveErrorMonitor:
    """Windowed live one-step errors of the active model and of f_hat (see the module docstring)."""

    def __init__(self, config: MonitorConfig | None = None) -> None:
        self.config = config or MonitorConfig()
        #: stream -> (the model's errors, f_hat's errors), the most recently added stream last
        self._windows: OrderedDict[int, tuple[deque[float], deque[float]]] = OrderedDict()
        self._model: deque[float] = deque(maxlen=self.config.window)  # the window of the stream added last
        self._base: deque[float] = deque(maxlen=self.config.window)
        #: the newest pair of errors added (NaN before the first)
        self.last_model = math.nan
        self.last_base = math.nan
        #: the window that last said roll back, ``(mean model error, mean base error, samples)``; kept by
        #: :meth:`reset` (the roll back resets the window before anyone logs why)
        self.verdict: tuple[float, float, int] | None = None

    def reset(self) -> None:
        """Forget every window (a new model became active); :attr:`verdict` stays."""
        self._windows.clear()
        self._model = deque(maxlen=self.config.window)
        self._base = deque(maxlen=self.config.window)

    def describe_verdict(self) -> str:
        """Why the monitor last said roll back, in words (``""`` if it never did)."""
        if self.verdict is None:
            return ""
        mean_model, mean_base, n = self.verdict
        c = self.config
        return (f"its live one-step squared error, mean {mean_model:.4g} over the last {n} steps it planned, exceeded "
                f"f_hat's {mean_base:.4g} on the same steps (x {c.ratio:g} + margin {c.margin:g})")

    @property
    def samples(self) -> int:
        return len(self._model)

    @property
    def mean_model(self) -> float:
        """Mean squared one-step error of the active model over the window (NaN when empty)."""
        return sum(self._model) / len(self._model) if self._model else math.nan

    @property
    def mean_base(self) -> float:
        """Mean squared one-step error of f_hat over the window (NaN when empty)."""
        return sum(self._base) / len(self._base) if self._base else math.nan

    def add(self, err_model: float, err_base: float, stream: int = 0) -> bool:
        """Add one live transition's squared errors to ``stream``'s window; True when that window now says roll
        back. A non-finite ``err_model`` (the model predicted NaN or inf) counts as infinitely wrong; a non-finite
        ``err_base`` (f_hat cannot be wrong by NaN on a finite transition: the transition itself is bad) is
        skipped. :attr:`mean_model`, :attr:`mean_base` and :attr:`samples` are then ``stream``'s."""
        if not math.isfinite(err_base):
            return False
        window = self._windows.pop(stream, None)
        if window is None:
            window = (deque(maxlen=self.config.window), deque(maxlen=self.config.window))
            while len(self._windows) >= MAX_STREAMS:
                self._windows.popitem(last=False)
        self._windows[stream] = window
        self._model, self._base = window
        self.last_model, self.last_base = float(err_model), float(err_base)
        self._model.append(err_model if math.isfinite(err_model) else math.inf)
        self._base.append(err_base)
        c = self.config
        worse = self.samples >= c.min_samples and self.mean_model > c.ratio * self.mean_base + c.margin
        if worse:
            self.verdict = (self.mean_model, self.mean_base, self.samples)
        return worse
