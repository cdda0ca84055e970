"""The contract every system implements (double integrator with friction, quadrotor, paddle ball).

One implementation of each system's dynamics serves the simulator (``true_step``), the learner's base
model (``base_step``, the f_hat of the paper) and the MPC. Dynamics are batched torch functions:

* ``x``: state, shape ``(B, state.size)``; ``u``: control, shape ``(B, control.size)``;
* return: the *target* of one transition, shape ``(B, target.size)``. For time-stepped systems the target
  is x_{t+1} (``target is state``); for the paddle ball it is the ball's post-impact velocity.

They accept float32 or float64 tensors, keep the input dtype, are differentiable with torch autograd,
and contain no Python-level branching on tensor values (``torch.where`` instead), so they also run
under ``torch.func.vmap`` / ``jacrev``.
"""

from __future__ import annotations

import abc
from typing import TYPE_CHECKING, Any

import numpy as np

from saml_ros.core.layout import VectorLayout, schema_hash

if TYPE_CHECKING:
    import torch

#: a command further outside the control box than this fraction of the box's width is implausible (the
#: simulators' default ``cmd_reject_margin`` is the same fraction: between the box and this margin they clip)
PLAUSIBLE_CONTROL_MARGIN = 0.5


class System(abc.ABC):
    """A dynamical system with a true model and an imperfect first-principles base model f_hat."""

    #: registry name used in parameters, specs and checkpoints ("friction", "quadrotor", "paddle_ball")
    name: str
    state: VectorLayout
    control: VectorLayout
    #: what one transition predicts; ``state`` for time-stepped systems
    target: VectorLayout
    #: sampling period in seconds (0.0 for event-based systems such as the paddle-ball impact)
    dt: float
    #: hidden layer sizes the paper uses for this system's residual network
    paper_hidden: tuple[int, ...]

    @property
    @abc.abstractmethod
    def control_low(self) -> np.ndarray:
        """Lower control bound, shape ``(control.size,)``."""

    @property
    @abc.abstractmethod
    def control_high(self) -> np.ndarray:
        """Upper control bound, shape ``(control.size,)``."""

    @abc.abstractmethod
    def true_step(self, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        """Ground-truth transition f(x, u) used by the simulator; ``(B, n), (B, m) -> (B, target.size)``."""

    @abc.abstractmethod
    def base_step(self, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        """First-principles base model f_hat(x, u); same shapes as :meth:`true_step`."""

    @abc.abstractmethod
    def sample_inputs(self, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """Draw ``n`` (x_t, u_t) pairs from the paper's training distribution; float64 ``(n, n_x), (n, m)``."""

    @abc.abstractmethod
    def paper_spec(self) -> dict[str, Any]:
        """The paper's Sufficiently Accurate problem for this system, as a spec dict (see ``core.spec``)."""

    def safe_control(self) -> np.ndarray:
        """The command applied when no valid one is at hand, float64 ``(control.size,)``: what a simulator holds
        once the last command timed out and what the MPC sends when its solve fails. Zero, clipped into the
        control bounds, unless the system overrides it (quadrotor: hover thrust; paddle: level, at rest)."""
        return np.clip(np.zeros(self.control.size), self.control_low, self.control_high)

    def plausible_state(self) -> dict[str, tuple[float, float]]:
        """Plausible range ``{field: (low, high)}`` of each state field, in the field's unit: a value outside it is
        not a physical state of this system but a fault (a broken sensor, a bad driver, a hostile sender), and
        every receiver rejects it (counted ``rejected/bounds``). Generous by design: orders of magnitude beyond
        the paper's training distribution are outside, anything a real run reaches is inside. A field that is not
        listed is unbounded. Node parameter ``plausible_bounds`` overrides these (:mod:`saml_ros.core.data.plausibility`).
        """
        return {}

    def plausible_target(self) -> dict[str, tuple[float, float]]:
        """Plausible range of each target field (see :meth:`plausible_state`); the state's ranges when the target
        is the next state."""
        return self.plausible_state() if self.target is self.state else {}

    def plausible_control(self) -> dict[str, tuple[float, float]]:
        """Plausible range of each control field: the control box widened by :data:`PLAUSIBLE_CONTROL_MARGIN`
        times its width on either side (what the simulators reject rather than clip)."""
        low, high = np.asarray(self.control_low, float), np.asarray(self.control_high, float)
        span = PLAUSIBLE_CONTROL_MARGIN * (high - low)
        return {f: (float(lo), float(hi)) for f, lo, hi in zip(self.control.names, low - span, high + span)}

    # ----------------------------------------------------------------- conveniences (not overridden)
    def schema_hash(self) -> str:
        """Hash of the state, control and target layouts; checkpoints store it, the MPC compares it."""
        return schema_hash(self.state, self.control, self.target)

    def true_step_np(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """:meth:`true_step` on float64 numpy arrays; accepts a single ``(n,)`` state or a batch."""
        return _np_call(self.true_step, x, u)

    def base_step_np(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """:meth:`base_step` on float64 numpy arrays; accepts a single ``(n,)`` state or a batch."""
        return _np_call(self.base_step, x, u)

    def make_dataset(
        self, n: int, rng: np.random.Generator, noise: dict[str, float] | None = None
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Sample ``n`` transitions (x, u, y) with y = true_step(x, u).

        ``noise`` maps target field names to the std-dev of zero-mean Gaussian noise added to y
        (the convergence experiment adds sigma = 0.2 to ``v``).
        """
        x, u = self.sample_inputs(n, rng)
        y = self.true_step_np(x, u)
        for name, sigma in (noise or {}).items():
            y[:, self.target.index(name)] += rng.normal(0.0, sigma, size=n)
        return x, u, y


def _np_call(fn: Any, x: np.ndarray, u: np.ndarray) -> np.ndarray:
    import torch

    single = np.ndim(x) == 1
    xt = torch.as_tensor(np.atleast_2d(np.asarray(x, dtype=np.float64)))
    ut = torch.as_tensor(np.atleast_2d(np.asarray(u, dtype=np.float64)))
    with torch.no_grad():
        y = fn(xt, ut).numpy()
    return y[0] if single else y
