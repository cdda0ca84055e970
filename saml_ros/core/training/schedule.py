"""Learning-rate schedules of the primal and the dual step (:class:`LRSchedule`), the same in every engine.

The learning rate of update ``t`` (0-based: ``t`` updates were done before it; a resumed run continues its
count) is ``lr0 * factor(t)`` with horizon ``T`` (:attr:`~saml_ros.core.training.TrainConfig.schedule_steps`,
or ``epochs`` x minibatches per epoch offline):

* ``constant``: ``factor = 1``;
* ``step``: ``factor = gamma ** min(drops, floor(t (drops + 1) / T))``: ``drops`` drops by ``gamma``, evenly
  spaced, the last at ``T drops / (drops + 1)``; the rate stays there after ``T``;
* ``cosine``: ``factor = floor + (1 - floor) (1 + cos(pi min(t, T) / T)) / 2``: from 1 at ``t = 0`` to
  ``floor`` at ``t = T``, then constant.

Factors are Python floats computed from ``t`` alone, so the plain and the fast engine use the same rates.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from saml_ros.core.training.config import TrainConfig


@dataclass(frozen=True)
class LRSchedule:
    """One schedule: ``lr(t)`` for update ``t`` (see the module docstring).

    Attributes:
        kind: ``"constant"``, ``"step"`` or ``"cosine"`` (``"auto"`` already resolved).
        lr0: the starting learning rate.
        horizon: T in updates (ignored by ``constant``; must be > 0 otherwise).
        gamma, drops: the step schedule's factor and number of drops.
        floor: the cosine schedule's final factor.
    """

    kind: str
    lr0: float
    horizon: int = 0
    gamma: float = 0.1
    drops: int = 2
    floor: float = 0.0

    def __post_init__(self) -> None:
        if self.kind not in ("constant", "step", "cosine"):
            raise ValueError(f"unknown learning-rate schedule {self.kind!r}")
        if self.kind != "constant" and self.horizon <= 0:
            raise ValueError(f"the {self.kind} schedule needs a horizon schedule_steps > 0")

    @property
    def constant(self) -> bool:
        return self.kind == "constant"

    def factor(self, t: int) -> float:
        """``lr(t) / lr0``."""
        if self.kind == "constant":
            return 1.0
        if self.kind == "step":
            return self.gamma ** min(self.drops, (t * (self.drops + 1)) // self.horizon)
        c = min(t, self.horizon) / self.horizon
        return self.floor + (1.0 - self.floor) * (1.0 + math.cos(math.pi * c)) / 2.0

    def lr(self, t: int) -> float:
        """The learning rate of update ``t``."""
        return self.lr0 if self.kind == "constant" else self.lr0 * self.factor(t)

    def total(self, n: int) -> float:
        """``sum_{t < n} lr(t)``: how far an optimizer that moves at most ``lr`` per update (Adam) can move in ``n``
        updates."""
        if n <= 0:
            return 0.0
        if self.kind == "constant":
            return self.lr0 * n
        t = np.arange(n, dtype=np.float64)
        if self.kind == "step":
            f = self.gamma ** np.minimum(self.drops, (t * (self.drops + 1)) // self.horizon)
        else:
            f = self.floor + (1.0 - self.floor) * (1.0 + np.cos(np.pi * np.minimum(t, self.horizon) / self.horizon)) / 2
        return float(self.lr0 * f.sum())

    def same_factors(self, other: LRSchedule) -> bool:
        """True when both schedules scale their rates by the same factor at every update."""
        if self.constant and other.constant:
            return True
        return (self.kind, self.horizon, self.gamma, self.drops, self.floor) == (
            other.kind, other.horizon, other.gamma, other.drops, other.floor)


def schedules_for(config: TrainConfig, horizon: int) -> tuple[LRSchedule, LRSchedule]:
    """``(primal, dual)`` schedules of ``config``; ``horizon`` is T when ``config.schedule_steps`` is 0.

    With no horizon at all (``schedule_steps`` and ``horizon`` 0: online training never ends) an ``"auto"``
    schedule is constant.

    Raises:
        ValueError: a schedule other than constant is asked for explicitly without a horizon.
    """
    t = config.schedule_steps or horizon
    out = []
    for which, lr0 in (("primal", config.primal_lr), ("dual", config.dual_lr0)):
        kind = config.schedule(which)
        if t <= 0 and kind != "constant":
            if getattr(config, f"{which}_schedule") != "auto":
                raise ValueError(f"{which}_schedule {kind!r} needs schedule_steps > 0 (the horizon in updates) "
                                 "when training has no fixed number of epochs")
            kind = "constant"
        out.append(LRSchedule(kind, lr0, t, config.lr_gamma, config.lr_drops, config.lr_floor))
    return out[0], out[1]
