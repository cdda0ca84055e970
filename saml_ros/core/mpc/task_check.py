"""The task check (ROS-free): does the controller, with the learned model in use, fail the task's constraints on
states where f_hat's own plan keeps them? (:class:`TaskCheck`)

The live monitor (:mod:`~saml_ros.core.mpc.monitor`) asks whether the model *predicts* worse than f_hat; a model
can predict better and still make the task worse. This check asks the task's own question on the same states,
paired: every step planned while a learned model is in use whose flown plan breaks a constraint of the task that
some control could keep (``MPCResult.success`` False, ``unavoidable`` False) is re-planned by f_hat alone from a
*cold* start (no warm start from the learned model's plans: the task's own starting sequences). When f_hat's own
plan keeps every constraint, the step is a **strike**: f_hat's plan is flown instead, and once ``strikes`` of the
last ``window`` steps planned with the model are strikes, the guard rolls the model back
(:class:`~saml_ros.core.mpc.guard.GuardedController`).

Why (measured on the demo in the wind world, docs/demo.md "The task check"): from a fast descent into the ground
effect a learned ensemble's first plan yawed the vehicle a full turn; the f_hat fallback, warm-started from that
plan, kept the turn, so every plan of the episode broke the terminal attitude bound while f_hat planning on its
own from the same start lands. The one-step monitor saw nothing wrong (the model predicted the flown transitions
better than f_hat). Steps where no control keeps the constraints (the state fixes the violation) are no strike:
f_hat cannot do better there either.

Why it does not roll back good models: a strike needs the model's plan to fail avoidably on a state where f_hat's
plan from scratch succeeds, which a well-trained model does rarely (counted in the demo's evaluation); a single
strike only swaps one step's plan, and the roll back needs ``strikes`` of them within ``window`` steps.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass


@dataclass(frozen=True)
class TaskCheckConfig:
    """When :class:`TaskCheck` strikes and rolls back (see the module docstring).

    Attributes:
        enabled: re-plan with f_hat from a cold start when the plan flown with a learned model in use breaks a
            constraint some control could keep, and fly f_hat's plan when it keeps them (a strike).
        window: steps planned with the model in use the strikes are counted over (>= 1).
        strikes: strikes within the last ``window`` steps that roll the model back (1..window); 0 = never roll
            back (strikes only swap the step's plan).
    """

    enabled: bool = False
    window: int = 10
    strikes: int = 3

    def __post_init__(self) -> None:
        if self.window < 1 or not 0 <= self.strikes <= self.window:
            raise ValueError(f"task check: need window >= 1 and 0 <= strikes <= window, got {self.window}, "
                             f"{self.strikes}")


class TaskCheck:
    """The strikes of the model in use over its last ``window`` steps (see the module docstring)."""

    def __init__(self, config: TaskCheckConfig | None = None) -> None:
        self.config = config or TaskCheckConfig()
        self._window: deque[bool] = deque(maxlen=self.config.window)
        #: ``(strikes, steps)`` of the window that last said roll back; kept by :meth:`reset`
        self.verdict: tuple[int, int] | None = None

    def reset(self) -> None:
        """Forget the window (a new model became active); :attr:`verdict` stays."""
        self._window.clear()

    @property
    def steps(self) -> int:
        return len(self._window)

    @property
    def strikes(self) -> int:
        """Strikes in the window."""
        return sum(self._window)

    def add(self, strike: bool) -> bool:
        """One step planned with the model in use (``strike``: its plan broke an avoidable constraint that f_hat's
        own plan keeps); True when the window now says roll back."""
        self._window.append(bool(strike))
        n = self.config.strikes
        if n > 0 and self.strikes >= n:
            self.verdict = (self.strikes, self.steps)
            return True
        return False

    def describe_verdict(self) -> str:
        """Why the check last said roll back, in words (``""`` if it never did)."""
        if self.verdict is None:
            return ""
        k, n = self.verdict
        return (f"{k} of the last {n} steps planned with it broke a constraint of the task that f_hat's own plan "
                f"from the same state kept")
