"""ROS-free simulator cores: the stepping logic behind the simulator nodes (see docs/simulators.md).

A simulator core turns events (a command arrived, a realtime tick, a lockstep deadline passed, a reset was
requested) into *outputs*: ``(kind, vector, stamp_ns)`` tuples that the rclpy node publishes in order,
``kind`` being one of :data:`STATE`, :data:`APPLIED`, :data:`TARGET`, :data:`FLIGHT` or :data:`CLOCK` (vector
``None``). Nothing here imports rclpy, so every rule below is tested without ROS.

Rules (docs/architecture.md, "Nodes"):

* Stamps: state x_k is stamped ``t_k = t_0 + k dt`` (int ns of simulated time). ``applied_cmd`` carries the u
  applied over ``[t_k, t_{k+1})`` with stamp ``t_k`` and is emitted, right before x_{k+1}, **iff** x_{k+1} is
  ``system.true_step(x_k, u)``: never for the last state before a reset or an episode restart (the next
  state is then stamped 2 dt later) and never for a step changed by ground contact.
* Commands are validated (:class:`CommandValidator`): wrong length / NaN / Inf -> rejected; further outside
  the control box than ``reject_margin`` times its width on either side -> rejected (``bounds``); slightly
  outside -> clipped and counted. :class:`CommandHolder` holds the newest accepted command for
  ``cmd_timeout`` seconds, then the system's safe default applies (counted).
* ``lockstep``: publish x_k, wait for the ``cmd`` stamped ``t_k`` for ``lockstep_timeout`` wall seconds,
  otherwise apply the held command / safe default (a *miss*); commands for other stamps are dropped.
  ``realtime``: every tick applies the newest command.
"""

from __future__ import annotations

import abc
import math
import warnings
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from saml_ros.core.data.plausibility import Plausibility, parse_overrides
from saml_ros.core.dynamics.system import System
from saml_ros.core.errors import SamlError
from saml_ros.core.systems.registry import get_entry

if TYPE_CHECKING:  # imported by FastStep: a simulator that does not step a torch model never loads it
    import torch

NS_PER_S = 1_000_000_000
MODES = ("realtime", "lockstep")

#: output kinds (the node maps each to a topic of the system's schema)
STATE, APPLIED, TARGET, FLIGHT, CLOCK = "state", "applied_cmd", "post_impact", "flight", "clock"

#: lockstep simulated time starts here (ns): 0 means "no clock yet" to ROS nodes with use_sim_time
LOCKSTEP_T0_NS = NS_PER_S

Output = tuple[str, np.ndarray | None, int]


def seconds_to_ns(seconds: float) -> int:
    """``seconds`` (s) -> int nanoseconds, rounded to the nearest ns."""
    return int(round(seconds * NS_PER_S))


# --------------------------------------------------------------------------------------------- commands
class CommandRejected(SamlError, ValueError):
    """A command was refused; ``reason`` is the counter key suffix (``rejected/<reason>``)."""

    def __init__(self, reason: str, detail: str) -> None:
        super().__init__(detail)
        self.reason = reason


class CommandValidator:
    """Checks commands against the control box ``[low, high]``.

    Args:
        low, high: control bounds, shape ``(m,)``.
        reject_margin: a component further than ``reject_margin * (high - low)`` outside the box is refused
            (0.5: anything outside a box twice as wide with the same centre); closer ones are clipped.
    """

    def __init__(self, low: np.ndarray, high: np.ndarray, reject_margin: float = 0.5) -> None:
        self.low = np.asarray(low, dtype=np.float64).copy()
        self.high = np.asarray(high, dtype=np.float64).copy()
        if self.low.shape != self.high.shape or self.low.ndim != 1 or np.any(self.low > self.high):
            raise ValueError("control bounds must be 1-d arrays of equal length with low <= high")
        if not (math.isfinite(reject_margin) and reject_margin >= 0):
            raise ValueError(f"reject_margin must be a finite number >= 0, got {reject_margin}")
        span = (self.high - self.low) * reject_margin
        self.reject_low = self.low - span
        self.reject_high = self.high + span

    @property
    def size(self) -> int:
        return int(self.low.shape[0])

    def check(self, u: Any) -> tuple[np.ndarray, bool]:
        """``u`` -> ``(command within [low, high], clipped?)``; :class:`CommandRejected` if refused."""
        try:
            arr = np.asarray(u, dtype=np.float64)
        except (TypeError, ValueError):
            raise CommandRejected("format", f"command is not numeric: {u!r}") from None
        if arr.shape != (self.size,):
            raise CommandRejected("shape", f"command must have shape ({self.size},), got {arr.shape}")
        clipped = np.clip(arr, self.low, self.high)
        if not (clipped != arr).any():  # the common case: finite and inside the box (NaN != NaN)
            return clipped, False
        if not np.isfinite(arr).all():
            raise CommandRejected("nan", f"command has non-finite values: {arr}")
        if (arr < self.reject_low).any() or (arr > self.reject_high).any():
            raise CommandRejected(
                "bounds", f"command {arr} is far outside the bounds [{self.low}, {self.high}]"
            )
        return clipped, True


class CommandHolder:
    """The newest accepted command, held for ``timeout_ns`` after it arrived, then the safe default.

    Times are the caller's clock in ns (wall time in realtime, simulated time in lockstep).
    ``timeout_ns <= 0`` holds a command forever.
    """

    def __init__(self, safe_default: np.ndarray, timeout_ns: int) -> None:
        self.safe_default = np.asarray(safe_default, dtype=np.float64).copy()
        self.timeout_ns = int(timeout_ns)
        self.u: np.ndarray | None = None
        self.stamp_ns: int | None = None
        self.received_ns = 0

    def accept(self, u: np.ndarray, stamp_ns: int, now_ns: int) -> None:
        """Hold ``u`` (already validated), which answered the state stamped ``stamp_ns``, from ``now_ns``."""
        self.u, self.stamp_ns, self.received_ns = u, stamp_ns, now_ns

    def current(self, now_ns: int) -> tuple[np.ndarray, bool]:
        """``(command, fresh)``; ``fresh`` is False when the safe default applies (none yet or timed out)."""
        if self.u is None or (self.timeout_ns > 0 and now_ns - self.received_ns > self.timeout_ns):
            return self.safe_default, False
        return self.u, True

    def clear(self) -> None:
        self.u, self.stamp_ns = None, None


# ----------------------------------------------------------------------------------------- configuration
@dataclass(frozen=True)
class SimConfig:
    """Options every simulator core shares (the node's parameters of the same names).

    Attributes:
        mode: ``"realtime"`` or ``"lockstep"``.
        cmd_timeout: s a command is held before the safe default applies (0 = forever); wall clock in
            realtime, simulated time in lockstep.
        lockstep_timeout: wall s to wait for the command answering a state in lockstep.
        max_sim_time: s of simulated time after which the run ends (0 = never).
        episode_steps: transitions (impacts for the paddle ball) per episode (0 = one endless episode).
        initial_state: start state of every episode; empty = drawn by the start sampler.
        seed: seed of the start sampler (negative = fresh OS entropy).
        reject_margin: see :class:`CommandValidator`.
        t0_ns: stamp of the first state (ns); lockstep runs use :data:`LOCKSTEP_T0_NS`.
        plausible_bounds: overrides of the system's plausible ranges (:mod:`saml_ros.core.data.plausibility`); a
            time-stepped simulator restarts the episode when its state leaves them (counted ``diverged``).
    """

    mode: str = "realtime"
    cmd_timeout: float = 0.5
    lockstep_timeout: float = 1.0
    max_sim_time: float = 0.0
    episode_steps: int = 0
    initial_state: tuple[float, ...] = ()
    seed: int = 0
    reject_margin: float = 0.5
    t0_ns: int = LOCKSTEP_T0_NS
    plausible_bounds: str = ""

    def __post_init__(self) -> None:
        parse_overrides(self.plausible_bounds)  # ValueError for a malformed mapping
        if self.mode not in MODES:
            raise ValueError(f"mode must be one of {MODES}, got {self.mode!r}")
        for name in ("cmd_timeout", "max_sim_time"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"{name} must be a finite number >= 0 s, got {value}")
        if not (math.isfinite(self.lockstep_timeout) and self.lockstep_timeout > 0):
            raise ValueError(f"lockstep_timeout must be > 0 s, got {self.lockstep_timeout}")
        if self.episode_steps < 0:
            raise ValueError(f"episode_steps must be >= 0, got {self.episode_steps}")
        if self.t0_ns < 0:
            raise ValueError(f"t0_ns must be >= 0, got {self.t0_ns}")

    @property
    def lockstep(self) -> bool:
        return self.mode == "lockstep"

    def rng(self) -> np.random.Generator:
        """The start sampler's generator."""
        return np.random.default_rng(None if self.seed < 0 else self.seed)


def check_initial_state(values: Sequence[float], size: int, what: str = "initial_state") -> np.ndarray | None:
    """``values`` as a float64 ``(size,)`` start state, ``None`` when empty; ``ValueError`` otherwise."""
    if len(values) == 0:
        return None
    arr = np.asarray(values, dtype=np.float64)
    if arr.shape != (size,) or not np.all(np.isfinite(arr)):
        raise ValueError(f"{what} must be empty or {size} finite numbers, got {list(values)}")
    return arr


# ----------------------------------------------------------------------------------------- fast stepping
class FastStep:
    """``system.true_step`` for one state, without per-call tensor allocation.

    The inputs are copied into preallocated ``(1, n)`` / ``(1, m)`` float64 tensors; with ``trace=True`` the
    dynamics are traced once with ``torch.jit.trace`` (about 1.6x faster for the quadrotor: fewer Python
    dispatches per op) and the trace is used only if it reproduces ``true_step`` bit for bit on 64 samples of
    the system's training distribution (the dynamics have no data-dependent Python branches, so it always
    should); otherwise, or if tracing fails, the eager ``true_step`` runs.

    A built-in system (its ``params()`` rebuild it) is traced and checked once per process and set of parameters
    (:data:`_TRACES`): an evaluation builds a fresh plant for every episode of every arm, and the check
    cost ~0.1 s each time, more than a short episode's stepping.
    """

    def __init__(self, system: System, trace: bool = True) -> None:
        import torch

        self._torch = torch
        self.system = system
        self._x = torch.zeros(1, system.state.size, dtype=torch.float64)
        self._u = torch.zeros(1, system.control.size, dtype=torch.float64)
        self._xn = self._x.numpy()
        self._un = self._u.numpy()
        self._fn: Callable[[torch.Tensor, torch.Tensor], torch.Tensor] = system.true_step
        self.traced = False
        if trace:
            self._try_trace()

    def _try_trace(self) -> None:
        key = _trace_key(self.system)
        if key is not None and key in _TRACES:
            traced = _TRACES[key]
            if traced is not None:
                self._fn, self.traced = traced, True
            return
        self._trace_and_check()
        if key is not None:
            _TRACES[key] = self._fn if self.traced else None

    def _trace_and_check(self) -> None:
        torch = self._torch
        try:
            with torch.no_grad(), warnings.catch_warnings():
                # torch.jit is deprecated in favour of torch.compile, which needs a C++ toolchain and tens of
                # seconds at start-up here; if tracing ever fails or disappears, eager is used
                warnings.simplefilter("ignore", DeprecationWarning)
                traced = torch.jit.trace(self.system.true_step, (self._x, self._u), check_trace=False)
                x, u = self.system.sample_inputs(64, np.random.default_rng(0))
                for xi, ui in zip(x, u):
                    xt, ut = torch.from_numpy(xi[None]), torch.from_numpy(ui[None])
                    if not torch.equal(traced(xt, ut), self.system.true_step(xt, ut)):
                        return
        except Exception:  # noqa: BLE001 - tracing is an optimisation; eager is always correct
            return
        self._fn, self.traced = traced, True

    def __call__(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """x_{k+1} = true_step(x_k, u) for ``x`` ``(n,)``, ``u`` ``(m,)``; a new float64 ``(n,)`` array."""
        self._xn[0] = x
        self._un[0] = u
        with self._torch.inference_mode():
            out = self._fn(self._x, self._u)
        return out[0].numpy().copy()


#: :class:`FastStep`'s traces by :func:`_trace_key` (``None``: tracing failed or did not reproduce ``true_step``)
_TRACES: dict[tuple[type, str], Any] = {}


def _trace_key(system: System) -> tuple[type, str] | None:
    """``(type, parameters)`` of a built-in system (a class of the ``saml_ros`` package, whose ``params()`` rebuild
    it: ``type(system)(**params)``), else ``None`` (never cached: a user's system may hold more than its
    ``params()``)."""
    params = getattr(system, "params", None)
    if not type(system).__module__.startswith("saml_ros.") or not callable(params):
        return None
    try:
        return type(system), repr(sorted(params().items()))
    except Exception:  # noqa: BLE001 - no key: traced and checked as before
        return None


# ------------------------------------------------------------------------------------- system bindings
@dataclass(frozen=True)
class SteppedModel:
    """What a time-stepped simulator needs from its system.

    Attributes:
        system: the system (``true_step`` is the simulated dynamics, ``dt`` the period).
        safe_default: command applied when none is fresh, ``(m,)``.
        sample_start: draws an episode start state ``(n,)`` from a generator.
        constrain: maps the integrated next state to the simulated one; returns ``(state, touched)`` with
            ``touched`` True when it changed the state (ground contact); ``None`` = no constraint.
        normalize_start: cleans a user-given start state (e.g. normalises a quaternion); ``None`` = as is.
        step: ``true_step`` for one state in numpy, ``(x (n,), u (m,)) -> new (n,)`` array, equal to it to
            rounding; ``None`` = :class:`FastStep` (torch). A numpy step keeps torch (2-3 CPU-s of start-up) out
            of the simulator's process and is faster per step.
    """

    system: System
    safe_default: np.ndarray
    sample_start: Callable[[np.random.Generator], np.ndarray]
    constrain: Callable[[np.ndarray], tuple[np.ndarray, bool]] | None = None
    normalize_start: Callable[[np.ndarray], np.ndarray] | None = None
    step: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None


# ------------------------------------------------------------------------------------------ core base
class SimCore(abc.ABC):
    """Event-driven simulator logic; every method returns the outputs to publish, in order.

    The node calls :meth:`begin` once, :meth:`on_cmd` for each decoded command (:meth:`reject` for one that
    failed to decode), :meth:`tick` every ``1 / rate_hz`` wall seconds in realtime, :meth:`poll` often in
    lockstep (it applies a miss once the deadline passed) and :meth:`request_reset` from the reset service.
    ``now_ns`` is a monotonic wall clock in ns.

    Shared episode logic: :meth:`begin` starts the first episode once (:meth:`_first_episode`); every advance
    either restarts the episode (a reset was requested or ``episode_steps`` were done: :meth:`_restart`) or
    steps (:meth:`_step`); :meth:`_emit_state` publishes a state (with ``/clock`` when ``publish_clock``), ends
    the run at ``max_sim_time`` and, in lockstep, waits for its command.
    """

    def __init__(self, system: System, config: SimConfig, safe_default: np.ndarray, *,
                 publish_clock: bool = True) -> None:
        self.system = system
        self.config = config
        self.publish_clock = publish_clock
        self.max_sim_ns = seconds_to_ns(config.max_sim_time)
        self.rng = config.rng()
        #: steps (impacts for the paddle ball) in the current episode
        self.episode_step = 0
        self.validator = CommandValidator(system.control_low, system.control_high, config.reject_margin)
        self.holder = CommandHolder(safe_default, seconds_to_ns(config.cmd_timeout))
        self.counters: Counter[str] = Counter()
        #: number and text of the rejections so far (the node logs the newest, throttled)
        self.n_rejections = 0
        self.last_rejection = ""
        self.t0_ns = config.t0_ns
        self.done = False
        self.started = False
        self.pending_reset = False
        #: lockstep: the stamp whose command the core waits for, and the wall deadline of that wait
        self.awaiting: int | None = None
        self.deadline_ns = 0
        self._lockstep_timeout_ns = seconds_to_ns(config.lockstep_timeout)

    # -- command intake ---------------------------------------------------------------------------------
    def reject(self, reason: str, detail: str = "") -> None:
        """Count a refused command as ``rejected/<reason>`` (also used by the node for malformed messages)."""
        self.counters[f"rejected/{reason}"] += 1
        self.n_rejections += 1
        self.last_rejection = detail or reason

    def validate(self, u: Any) -> np.ndarray | None:
        """Validated (possibly clipped, counted) command, or ``None`` if refused (counted)."""
        try:
            cmd, clipped = self.validator.check(u)
        except CommandRejected as exc:
            self.reject(exc.reason, str(exc))
            return None
        self.counters["cmd_clipped"] += int(clipped)
        return cmd

    def on_cmd(self, u: Any, stamp_ns: int, now_ns: int) -> list[Output]:
        """A ``cmd`` message decoded to ``(u, stamp_ns)`` arrived at wall time ``now_ns``."""
        if self.done:
            return []
        if self.config.lockstep:
            if self.awaiting is None or stamp_ns != self.awaiting:
                # an answer to a state we no longer wait for (after a miss or a reset) or never published
                late = self.awaiting is None or stamp_ns < self.awaiting
                self.reject("late" if late else "stamp", f"cmd stamped {stamp_ns} ns does not answer the "
                            f"state the simulator waits for ({self.awaiting} ns)")
                return []
            cmd = self.validate(u)
            if cmd is None:
                return []  # keep waiting: a valid answer may still come before the deadline
            self.counters["cmd_accepted"] += 1
            self.holder.accept(cmd, stamp_ns, self.sim_now_ns())
            self.awaiting = None
            return self._advance(cmd, now_ns)
        if self.holder.stamp_ns is not None and stamp_ns < self.holder.stamp_ns:
            self.reject("out_of_order", f"cmd stamped {stamp_ns} ns is older than the held one")
            return []
        cmd = self.validate(u)
        if cmd is None:
            return []
        self.counters["cmd_accepted"] += 1
        self.holder.accept(cmd, stamp_ns, now_ns)
        return []

    def _held_command(self, now_ns: int) -> np.ndarray:
        """The held command at ``now_ns`` (holder clock), counting safe-default applications."""
        u, fresh = self.holder.current(now_ns)
        if not fresh:
            self.counters["cmd_timeouts"] += 1
        return u

    # -- clock events -----------------------------------------------------------------------------------
    def tick(self, now_ns: int) -> list[Output]:
        """Realtime period elapsed: advance with the newest command (safe default once it timed out)."""
        if self.done or self.config.lockstep or not self.started:
            return []
        return self._advance(self._held_command(now_ns), now_ns)

    def poll(self, now_ns: int) -> list[Output]:
        """Lockstep watchdog: past the deadline, advance with the held command / safe default (a miss)."""
        if self.done or not self.config.lockstep or self.awaiting is None or now_ns < self.deadline_ns:
            return []
        self.counters["lockstep_misses"] += 1
        self.awaiting = None
        return self._advance(self._held_command(self.sim_now_ns()), now_ns)

    def request_reset(self) -> str:
        """Schedule a reset: the next advance starts a new episode instead of stepping."""
        self.pending_reset = True
        return "reset scheduled: the next state starts a new episode"

    def _await(self, stamp_ns: int, now_ns: int) -> None:
        if self.config.lockstep and not self.done:
            self.awaiting = stamp_ns
            self.deadline_ns = now_ns + self._lockstep_timeout_ns

    # -- episodes ---------------------------------------------------------------------------------------
    def begin(self, now_ns: int, t0_ns: int | None = None) -> list[Output]:
        """Start the first episode (once; ``t0_ns`` overrides ``config.t0_ns``); returns its first state."""
        if self.started:
            return []
        self.started = True
        if t0_ns is not None:
            self.t0_ns = t0_ns
        return self._first_episode(now_ns)

    def _episode_complete(self) -> bool:
        """True when the current episode has had its ``episode_steps`` (never with ``episode_steps`` 0)."""
        return bool(self.config.episode_steps and self.episode_step >= self.config.episode_steps)

    def _advance(self, u: np.ndarray, now_ns: int) -> list[Output]:
        """Apply ``u`` (:meth:`_step`), or restart the episode when a reset is pending or it is complete."""
        if self.done:
            return []
        if self.pending_reset or self._episode_complete():
            self.counters["resets" if self.pending_reset else "episodes_completed"] += 1
            return self._restart(now_ns)
        return self._step(u, now_ns)

    def _emit_state(self, x: np.ndarray, stamp_ns: int, now_ns: int, clock_ns: int | None = None) -> list[Output]:
        """Outputs of a new state ``x`` stamped ``stamp_ns``: ``/clock`` (at ``clock_ns``, default the stamp) if
        ``publish_clock``, then the state; ends the run at ``max_sim_time`` and, in lockstep, awaits its cmd."""
        out: list[Output] = [(CLOCK, None, stamp_ns if clock_ns is None else clock_ns)] if self.publish_clock else []
        out.append((STATE, x, stamp_ns))
        if self.max_sim_ns and stamp_ns - self.t0_ns >= self.max_sim_ns:
            self.done = True
        self._await(stamp_ns, now_ns)
        return out

    # -- to implement -----------------------------------------------------------------------------------
    @abc.abstractmethod
    def _first_episode(self, now_ns: int) -> list[Output]:
        """Set up the first episode (``t0_ns`` is final) and return its first state's outputs."""

    @abc.abstractmethod
    def _step(self, u: np.ndarray, now_ns: int) -> list[Output]:
        """Apply ``u`` to the current state and return the outputs (the run is not done, no restart due)."""

    @abc.abstractmethod
    def _restart(self, now_ns: int) -> list[Output]:
        """Start a new episode (clearing ``pending_reset``) and return its first state's outputs."""

    @abc.abstractmethod
    def sim_now_ns(self) -> int:
        """Current simulated time (ns): the stamp of the newest published state."""

    def diagnostics(self) -> dict[str, Any]:
        """Counters and status values for /diagnostics (key -> value)."""
        values: dict[str, Any] = {"mode": self.config.mode, "sim_time": f"{self.sim_now_ns() / NS_PER_S:.3f}"}
        values.update(sorted(self.counters.items()))
        return values


# ---------------------------------------------------------------------------------- time-stepped systems
class SteppedSim(SimCore):
    """A time-stepped simulator (friction, quadrotor): x_{k+1} = constrain(true_step(x_k, u_k)).

    Emits, per step: ``applied_cmd(u_k, t_k)`` (when the step is pure ``true_step``), ``/clock = t_{k+1}``
    (if ``publish_clock``), ``state(x_{k+1}, t_{k+1})``. An episode restart (``episode_steps`` reached or a
    reset requested) replaces the step: no ``applied_cmd``, and the new start state is stamped ``t_k + 2 dt``.
    """

    def __init__(
        self,
        model: SteppedModel,
        config: SimConfig,
        *,
        publish_clock: bool = True,
        step_fn: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None,
    ) -> None:
        system = model.system
        if not system.dt > 0:
            raise ValueError(f"{system.name} is not time-stepped (dt = {system.dt})")
        super().__init__(system, config, model.safe_default, publish_clock=publish_clock)
        self.model = model
        self.step_fn = step_fn or model.step or FastStep(system)
        self.dt_ns = seconds_to_ns(system.dt)
        start = check_initial_state(config.initial_state, system.state.size)
        if start is not None and model.normalize_start is not None:
            start = model.normalize_start(start)
        self.initial_state = start
        self.bounds = Plausibility.for_system(system, config.plausible_bounds).state
        self.k = 0  # stamp index: t_k = t0 + k dt
        self.x = np.zeros(system.state.size)

    def sim_now_ns(self) -> int:
        return self.t0_ns + self.k * self.dt_ns

    def _start_state(self) -> np.ndarray:
        if self.initial_state is not None:
            return self.initial_state.copy()
        return np.asarray(self.model.sample_start(self.rng), dtype=np.float64)

    def _first_episode(self, now_ns: int) -> list[Output]:
        self.x = self._start_state()
        self.counters["episodes"] += 1
        return self._emit_state(self.x, self.sim_now_ns(), now_ns)

    def _step(self, u: np.ndarray, now_ns: int) -> list[Output]:
        x_next = self.step_fn(self.x, u)
        if not np.all(np.isfinite(x_next)):
            self.counters["diverged"] += 1
            return self._restart(now_ns)
        touched = False
        if self.model.constrain is not None:
            x_next, touched = self.model.constrain(x_next)
        if self.bounds.outside(x_next) is not None:  # beyond any physical state: never published
            self.counters["diverged"] += 1
            return self._restart(now_ns)
        out: list[Output] = []
        if touched:
            self.counters["ground_contacts"] += 1
        else:
            out.append((APPLIED, u, self.sim_now_ns()))
        self.counters["steps"] += 1
        self.k += 1
        self.episode_step += 1
        self.x = x_next
        return out + self._emit_state(self.x, self.sim_now_ns(), now_ns)

    def _restart(self, now_ns: int) -> list[Output]:
        """New episode: no applied_cmd for the last state; the start state is stamped 2 dt later."""
        self.pending_reset = False
        self.x = self._start_state()
        self.k += 2
        self.episode_step = 0
        self.counters["episodes"] += 1
        return self._emit_state(self.x, self.sim_now_ns(), now_ns)


def build_stepped_sim(system: System, config: SimConfig, *, publish_clock: bool = True,
                      **options: Any) -> SteppedSim:
    """The :class:`SteppedSim` of a time-stepped system: its registry entry's ``stepped_model`` with ``options``
    (the quadrotor's ``landing_height``, m, default 0.1). ``ValueError`` for an event-based system."""
    model = get_entry(system.name).stepped_model
    if model is None:
        raise ValueError(f"no time-stepped simulator for system {system.name!r}")
    return SteppedSim(model(system, **options), config, publish_clock=publish_clock)
