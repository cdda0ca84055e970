"""The live model monitor (ROS-free): is the model in use predicting the transitions actually flown worse than the
base model f_hat does? (:class:`LiveErrorMonitor`)

Every control step the active model planned gives one live transition ``(x, u) -> x_next`` (the state the
controller solved from, the command it sent, the next state it received; the guard does not feed it the steps it
planned with f_hat on ensemble disagreement). The monitor keeps the one-step squared errors
``||x_next - model(x, u)||^2`` of the active model and ``||x_next - f_hat(x, u)||^2`` of the base model over the
last ``window`` transitions and says *roll back* once it holds at least ``min_samples`` of them and

    mean(active errors) > ratio * mean(base errors) + margin + margin_relative * scale.

A margin is needed because f_hat is exact wherever the system has no unmodelled effect (the quadrotor above the
ground-effect ceiling, any robot at rest on a dry floor): there any learned model has a larger error than f_hat,
however small, and without a margin every good model would be rolled back as soon as the vehicle leaves the
region where the model helps. How large "small" is depends on the robot (squared one-step errors of 1e-1 on the
quadrotor's 13 fields in the ground effect, 1e-5 on a diff-drive base's pose), so the default margin is relative:
``margin_relative`` times ``scale``, f_hat's mean squared one-step error (summed over the target fields) over the
data the model was trained on (the checkpoint's evidence, ``meta["evidence"]["residual_rms"]``, which the learner
and the offline trainer write; :func:`data_scale`), or, for a model without evidence, over the live transitions
the controller has seen so far (:meth:`LiveErrorMonitor.note_base`). A learned model may then be worse than f_hat on
the steps it planned by at most a fraction of how wrong f_hat typically is on the robot's data. The default
``margin_relative = 0.02`` rolls back, on the example diff-drive base (f_hat's mean squared error over its data
about 6e-4), a model whose error on the steps it planned at the goal was 3.8e-5 against f_hat's 3.1e-8, which the
absolute 0.01 the monitor had let fly. The quadrotor's bringup sets 0.08 (about 0.12 over the demo learner's data:
a threshold near that 0.01), since its SA models err up to about 0.01 per step in free flight and a roll back there
lands worse (docs/mpc.md, "Guarded MPC"). ``margin`` (absolute, squared state units, default 0) is added to it: set
``margin_relative = 0`` and ``margin`` for a fixed threshold.

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
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

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
        margin_relative: plus this times the monitor's ``scale``, f_hat's mean squared one-step error over the
            model's data (>= 0; see the module docstring).
    """

    window: int = 5
    min_samples: int = 3
    ratio: float = 1.0
    margin: float = 0.0
    margin_relative: float = 0.02
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
        if not (self.margin_relative >= 0 and math.isfinite(self.margin_relative)):
            raise ValueError(f"monitor: margin_relative must be >= 0 (finite), got {self.margin_relative}")


def data_scale(meta: Mapping[str, Any] | None) -> float:
    """f_hat's mean squared one-step error (summed over the target fields) over a model's training data, from its
    checkpoint meta (``meta["evidence"]["residual_rms"]``, :class:`~saml_ros.core.model.evidence.DataEvidence`);
    NaN when the meta records none (or a malformed one)."""
    ev = meta.get("evidence") if isinstance(meta, Mapping) else None
    rms = ev.get("residual_rms") if isinstance(ev, Mapping) else None
    try:
        values = [float(v) for v in rms]  # type: ignore[union-attr]
    except (TypeError, ValueError):
        return math.nan
    total = math.fsum(v * v for v in values)
    return total if values and math.isfinite(total) else math.nan


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
        self._verdict_margin = math.nan  # the margin in use when :attr:`verdict` was given
        #: f_hat's mean squared one-step error over the active model's data (:func:`data_scale`); NaN: unknown,
        #: then :attr:`live_base_mean` stands in
        self.data_scale = math.nan
        self._live_base = (0.0, 0)  # sum and count of every f_hat error noted (:meth:`note_base`); kept by reset

    def note_base(self, err_base: float) -> None:
        """One live transition's squared error of f_hat, whoever planned it: the live stand-in for the data's scale
        (a model without evidence). Non-finite values are skipped."""
        if math.isfinite(err_base):
            total, n = self._live_base
            self._live_base = (total + err_base, n + 1)

    def sibling(self, data_scale: float) -> LiveErrorMonitor:
        """A fresh monitor of the same config and live f_hat errors, for a model whose data has ``data_scale``
        (scoring a model before it flies)."""
        other = LiveErrorMonitor(self.config)
        other.data_scale = data_scale
        other._live_base = self._live_base
        return other

    @property
    def live_base_mean(self) -> float:
        """Mean of the f_hat errors given to :meth:`note_base` (NaN before the first)."""
        total, n = self._live_base
        return total / n if n else math.nan

    @property
    def scale(self) -> float:
        """The scale ``margin_relative`` multiplies: :attr:`data_scale`, else :attr:`live_base_mean`, else 0."""
        for s in (self.data_scale, self.live_base_mean):
            if math.isfinite(s):
                return s
        return 0.0

    @property
    def margin(self) -> float:
        """The margin in use: ``margin + margin_relative * scale`` (squared state units)."""
        return self.config.margin + self.config.margin_relative * self.scale

    def reset(self) -> None:
        """Forget every window (a new model became active); :attr:`verdict`, :attr:`data_scale` and the live f_hat
        errors noted stay."""
        self._windows.clear()
        self._model = deque(maxlen=self.config.window)
        self._base = deque(maxlen=self.config.window)

    def describe_verdict(self) -> str:
        """Why the monitor last said roll back, in words (``""`` if it never did)."""
        if self.verdict is None:
            return ""
        mean_model, mean_base, n = self.verdict
        return (f"its live one-step squared error, mean {mean_model:.4g} over the last {n} steps it planned, exceeded "
                f"f_hat's {mean_base:.4g} on the same steps (x {self.config.ratio:g} + margin {self._verdict_margin:.3g})")

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
        margin = self.margin
        worse = self.samples >= c.min_samples and self.mean_model > c.ratio * self.mean_base + margin
        if worse:
            self.verdict = (self.mean_model, self.mean_base, self.samples)
            self._verdict_margin = margin
        return worse


def main(argv: list[str] | None = None) -> int:
    """``python -m saml_ros.core.mpc.monitor CHECKPOINT_OR_RUN_DIR ...``: the margin the live monitor's default
    (``guard.margin_relative``, ``guard.margin``) gives each checkpoint (a run directory: its ``latest``)."""
    import argparse
    from pathlib import Path

    from saml_ros.core.model.checkpoint import CheckpointStore, read_checkpoint

    p = argparse.ArgumentParser(prog="python -m saml_ros.core.mpc.monitor", description=main.__doc__)
    p.add_argument("paths", nargs="+", type=Path)
    p.add_argument("--margin-relative", type=float, default=MonitorConfig.margin_relative,
                   help="guard.margin_relative (the quadrotor's bringup: 0.08)")
    p.add_argument("--margin", type=float, default=MonitorConfig.margin, help="guard.margin")
    args = p.parse_args(argv)
    config = MonitorConfig(margin=args.margin, margin_relative=args.margin_relative)
    for path in args.paths:
        if path.is_dir():
            found = CheckpointStore(path / "checkpoints" if (path / "checkpoints").is_dir() else path).latest()
            if found is None:
                print(f"{path}: no checkpoint")
                continue
            path = found[0]
        _, meta = read_checkpoint(path)
        monitor = LiveErrorMonitor(config)
        monitor.data_scale = scale = data_scale(meta)
        margin = monitor.margin
        print(f"{path}: f_hat's mean squared one-step error over the model's data {scale:.4g}; margin "
              f"{margin:.4g} (guard.margin_relative {config.margin_relative:g} x that + guard.margin {config.margin:g})"
              + ("" if math.isfinite(scale) else "; no evidence: the live transitions set the scale"))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
