"""Asynchronous pairing: resample a robot's own state and command streams onto a fixed period (ROS-free).

The exact-stamp rule of :mod:`saml_ros.core.data.pairing` needs a simulator that stamps the applied command like the
state it was applied from. A real robot publishes its state (``nav_msgs/Odometry``, ``sensor_msgs/JointState``)
at its own rate and takes commands (``geometry_msgs/Twist`` on ``cmd_vel``) at another, unsynchronised and often
unstamped. One :class:`ResamplingPairer` per source turns those two streams into transitions
``(x(t_k), u_k, x(t_k + dt))`` on the grid ``t_k = t_0 + k dt`` (``t_0`` = the first state's stamp):

* **state at a grid time** (``state_rule``): ``interpolate`` linearly between the two state messages around
  ``t_k`` when they are at most ``state_tolerance`` apart (angle fields the short way round), or ``nearest``: the
  closer of the two when it is at most ``state_tolerance`` from ``t_k``. Otherwise ``t_k`` is a **gap** and the
  transitions that need it are not formed (counted ``gap``).
* **command**: zero-order hold. ``u_k`` is the last command stamped at or before ``t_k`` (stamps shifted by
  ``cmd_delay``, the robot's command latency). Unstamped messages (no ``header``) are stamped on receipt by
  the caller and counted under ``unstamped/<kind>``. No command yet, or the last one older than
  ``cmd_timeout`` (the robot has stopped following it): ``no_cmd`` / ``stale_cmd``, no transition.
* **command changes near a grid time**: a command that changes the value within ``cmd_guard`` of ``t_k`` makes it
  unknown whether the robot applied the old or the new one over ``[t_k, t_k + dt)``: the transition is dropped
  (``ambiguous_cmd``). A change strictly inside the interval is counted ``mixed_cmd``; with ``mixed="hold"``
  (default: the robot samples commands when it samples its state, as most base controllers do) the transition
  keeps ``u_k``, with ``mixed="drop"`` it is dropped. A repeated command with the same value is no change.

**Which command an interval gets** (``cmd_rule``) depends on when the robot applies a command it receives:

* ``"hold"`` (default): at its control step, which is the stamp of the state it publishes (a free-running driver
  loop: read the sensors, publish the state, apply the last command received). ``u_k`` is the command held at
  ``t_k`` (above). Right for a controller at any rate and phase, including one on its own timer at the state's
  rate. A change within ``cmd_guard`` of ``t_k`` (either side: the learner's stamp of a command is not the
  robot's) is ``ambiguous_cmd``: a controller whose timer runs in phase with the robot's loop races it, and no
  one can tell which step applied the commands that arrived within the stamps' uncertainty of a step.
* ``"answer_next_step"``: the same robot with a controller **triggered by each state message**: the answer to
  ``x_k`` arrives after ``t_k`` and is applied at the next step, over ``[t_{k+1}, t_{k+2})``. The rule is
  ``"hold"``, but a command stamped just after ``t_k`` is known to be that answer (it cannot have reached the
  robot before the state it answers was published) when every earlier state has been answered (counted as for
  ``"answer"`` below), the last one before ``t_k - cmd_guard``: the guard applies only before ``t_k`` then.
  While the controller lags (answers owed), or where a late answer may have crossed a step, the guard applies
  on both sides, as for ``"hold"``.
* ``"answer"``: a controller triggered by each state message and a robot that applies the answer to the state
  stamped ``t_k`` over ``[t_k, t_k + dt)`` (a simulator in lockstep, a loop that waits for the controller, a
  driver that applies commands as they arrive with answers much faster than ``dt``). It needs one state message
  per grid interval (``dt`` = the state period). ``u_k`` is the command stamped in the interval's *window*
  ``[s_k, s_{k+1})`` between the state messages at ``t_k`` and ``t_{k+1}``, wherever in the window it came
  (arrival jitter does not matter; a command stamped with the stamp of the state it answers falls in it at any
  latency): one command (or several with one value) is ``u_k``; several different commands are
  ``ambiguous_cmd``; an empty window is ``no_answer`` (not answered within the period: what the robot applied
  instead is its own business). The controller answers each state once, in order, so after an empty window the
  first commands to come answer the unanswered states: the windows are ``ambiguous_cmd`` (or ``no_answer``)
  until one holds one command more than there are unanswered states (the answers caught up; its last command
  is its state's answer, paired). Answers owed for longer than ``latency`` are taken as never coming (a
  controller that skipped a state) and the next window pairs again: an answer later than ``latency`` looks like
  the next state's. An interval whose state message is
  missing (bridged by interpolation) is a ``gap``.

* **angle fields** (``angle_indices``): the target is unwrapped relative to ``x(t_k)``
  (``y = x + wrap(x' - x)``), so a yaw crossing +-pi is a small step, not a 2 pi jump.

A grid interval ``[t_k, t_k + dt]`` is decided once a state stamped at least ``latency`` after its end has
arrived (the newest state stamp is the clock), so commands that arrive a little after the states still count.
A command stamped before an interval that was already decided is counted ``late`` (it is still used from then on;
raise ``latency`` if this happens).

Each event is checked like :class:`~saml_ros.core.data.pairing.StampPairer` does: ``stamp`` (not an int >= 0),
``shape``, ``nan``, ``bounds`` (outside the config's plausible ranges), ``duplicate`` (the same stamp as the previous message of that kind, within 1 us),
``out_of_order`` (older than the previous one of that kind). ``reanchor`` consecutive out-of-order states whose
stamps increase among themselves are a new clock (a restarted robot or simulator): everything pending is
dropped (``time_resets``) and the grid restarts at the first of them.

Every decided grid interval is counted once in ``intervals`` and is exactly one of: ``paired``, ``gap``,
``no_cmd``, ``stale_cmd``, ``ambiguous_cmd``, ``no_answer`` (``answer`` only), or (with ``mixed="drop"``)
``mixed_cmd``; so ``intervals == paired + gap + no_cmd + stale_cmd + ambiguous_cmd + no_answer (+ mixed_cmd when
dropped)``.

Stream statistics (for /diagnostics): ``missing/<kind>`` estimates messages that never came from the intervals
between consecutive stamps (``round(interval / period) - 1`` when an interval exceeds 1.5 periods),
``jitter/<kind>`` counts the other intervals off the nominal period by more than ``jitter_tolerance`` of it,
``max_interval_us/<kind>`` is the longest interval seen. The nominal periods are ``state_period`` (default ``dt``)
and ``cmd_period`` (0 = not counted for commands).

The same pairer serves live topics (the learner) and bags (where an unstamped message's receipt time is its
log time), so a bag yields exactly the transitions the learner paired.
"""

from __future__ import annotations

import bisect
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from saml_ros.core.data.pairing import NS_PER_S, AddResult, Transition
from saml_ros.core.data.plausibility import Plausibility

KINDS: tuple[str, ...] = ("state", "applied_cmd")
STATE_RULES: tuple[str, ...] = ("interpolate", "nearest")
MIXED_POLICIES: tuple[str, ...] = ("hold", "drop")
#: which command an interval gets (see the module docstring)
COMMAND_RULES: tuple[str, ...] = ("hold", "answer_next_step", "answer")
#: every counter a :class:`ResamplingPairer` keeps (all start at 0); see the module docstring
COUNTERS: tuple[str, ...] = (
    "received/state", "received/applied_cmd", "unstamped/state", "unstamped/applied_cmd", "intervals", "paired",
    "stamp", "shape", "nan", "bounds", "duplicate", "out_of_order", "late",
    "gap", "no_cmd", "stale_cmd", "ambiguous_cmd", "mixed_cmd", "no_answer",
    "missing/state", "missing/applied_cmd", "jitter/state", "jitter/applied_cmd",
    "max_interval_us/state", "max_interval_us/applied_cmd", "time_resets",
)  # fmt: skip
_SAME_NS = 1_000  # two stamps within 1 us are the same stamp


@dataclass(frozen=True)
class ResampleConfig:
    """The resampling rule for one source; times in int nanoseconds (see :meth:`from_seconds`).

    Attributes:
        n_x, n_u: state and command vector sizes (the target is the next state, ``n_x``).
        dt_ns: grid period.
        state_rule: ``"interpolate"`` or ``"nearest"``.
        state_tolerance_ns: interpolate: the longest span between the two states around a grid time;
            nearest: the largest distance of the nearest state from it.
        cmd_guard_ns: a command change this close to a grid time makes its interval ambiguous.
        cmd_timeout_ns: a held command older than this is stale (0 = commands never go stale).
        cmd_delay_ns: command latency added to every command stamp.
        mixed: ``"hold"`` or ``"drop"`` for intervals with a command change inside (``cmd_rule="hold"``).
        cmd_rule: ``"hold"`` (zero-order hold at the grid time), ``"answer_next_step"`` (the same for a
            controller triggered by each state) or ``"answer"`` (the command answering the state that starts the
            interval; needs ``state_period_ns`` 0 or ``dt_ns``).
        latency_ns: how far (in state stamps) the newest state must be past an interval before it is decided.
        angle_indices: state fields that are angles in rad (wrapped interpolation, unwrapped targets).
        state_period_ns, cmd_period_ns: nominal message periods for the missing / jitter counters
            (``state_period_ns`` 0 = ``dt_ns``; ``cmd_period_ns`` 0 = commands not counted).
        jitter_tolerance: fraction of the period an interval may deviate before it counts as jitter.
        stamped_state, stamped_cmd: whether the messages carry a header stamp (else stamped on receipt).
        reanchor: consecutive increasing out-of-order states that restart the clock (>= 2).
        bounds: plausible ranges of the vectors (:mod:`saml_ros.core.data.plausibility`); an event outside them is
            rejected as ``bounds``; ``None``: no range check.
    """

    n_x: int
    n_u: int
    dt_ns: int
    state_rule: str = "interpolate"
    state_tolerance_ns: int = 0
    cmd_guard_ns: int = 2_000_000
    cmd_timeout_ns: int = 0
    cmd_delay_ns: int = 0
    mixed: str = "hold"
    cmd_rule: str = "hold"
    latency_ns: int = 100_000_000
    angle_indices: tuple[int, ...] = ()
    state_period_ns: int = 0
    cmd_period_ns: int = 0
    jitter_tolerance: float = 0.25
    stamped_state: bool = True
    stamped_cmd: bool = True
    reanchor: int = 3
    bounds: Plausibility | None = None

    def __post_init__(self) -> None:
        if self.n_x < 1 or self.n_u < 0:
            raise ValueError(f"bad vector sizes n_x={self.n_x}, n_u={self.n_u}")
        if self.dt_ns <= 2 * _SAME_NS:
            raise ValueError(f"dt_ns must exceed {2 * _SAME_NS} ns, got {self.dt_ns}")
        if self.state_rule not in STATE_RULES:
            raise ValueError(f"state_rule must be one of {STATE_RULES}, got {self.state_rule!r}")
        if self.mixed not in MIXED_POLICIES:
            raise ValueError(f"mixed must be one of {MIXED_POLICIES}, got {self.mixed!r}")
        if self.cmd_rule not in COMMAND_RULES:
            raise ValueError(f"cmd_rule must be one of {COMMAND_RULES}, got {self.cmd_rule!r}")
        if self.cmd_rule != "hold" and self.state_period_ns and abs(self.state_period_ns - self.dt_ns) > 0.01 * self.dt_ns:
            raise ValueError(f"cmd_rule {self.cmd_rule!r} pairs each state message with its answer: the state period "
                             f"({self.state_period_ns / NS_PER_S:g} s) must equal dt ({self.dt_ns / NS_PER_S:g} s)")
        for name in ("state_tolerance_ns", "cmd_guard_ns", "cmd_timeout_ns", "latency_ns", "state_period_ns",
                     "cmd_period_ns"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")
        if 2 * self.cmd_guard_ns >= self.dt_ns:
            raise ValueError(f"cmd_guard_ns ({self.cmd_guard_ns}) must be less than half of dt_ns ({self.dt_ns})")
        if any(not 0 <= i < self.n_x for i in self.angle_indices):
            raise ValueError(f"angle_indices {list(self.angle_indices)} outside the state (size {self.n_x})")
        if not 0 < self.jitter_tolerance < 1:
            raise ValueError(f"jitter_tolerance must be in (0, 1), got {self.jitter_tolerance}")
        if self.reanchor < 2:
            raise ValueError(f"reanchor must be >= 2, got {self.reanchor}")
        if self.latency_ns < self.state_tolerance_ns:
            raise ValueError(f"latency_ns ({self.latency_ns}) must be >= state_tolerance_ns "
                             f"({self.state_tolerance_ns}): the state after a grid time must have arrived")

    @classmethod
    def from_seconds(cls, n_x: int, n_u: int, dt: float, *, state_tolerance: float | None = None,
                     cmd_guard: float = 0.002, cmd_timeout: float = 0.0, cmd_delay: float = 0.0,
                     latency: float | None = None, state_period: float = 0.0, cmd_period: float = 0.0,
                     **rest: Any) -> ResampleConfig:
        """Build from times in seconds; ``state_tolerance`` defaults to ``2.5 * (state_period or dt)`` for
        ``interpolate`` (one missing message is bridged) and ``0.5 * (state_period or dt)`` for ``nearest``;
        ``latency`` to ``max(0.1, state_tolerance)``."""
        period = state_period or dt
        if state_tolerance is None:
            state_tolerance = (0.5 if rest.get("state_rule") == "nearest" else 2.5) * period
        if latency is None:
            latency = max(0.1, state_tolerance)

        def ns(v: float) -> int:
            return round(float(v) * NS_PER_S)

        return cls(n_x=n_x, n_u=n_u, dt_ns=ns(dt), state_tolerance_ns=ns(state_tolerance), cmd_guard_ns=ns(cmd_guard),
                   cmd_timeout_ns=ns(cmd_timeout), cmd_delay_ns=ns(cmd_delay), latency_ns=ns(latency),
                   state_period_ns=ns(state_period), cmd_period_ns=ns(cmd_period), **rest)


def wrap_angle(a: np.ndarray | float) -> Any:
    """Angle(s) wrapped into [-pi, pi)."""
    return (np.asarray(a) + math.pi) % (2.0 * math.pi) - math.pi


class _Stream:
    """The messages of one kind: stamps ascending and their vectors, plus arrival statistics."""

    def __init__(self, kind: str, period_ns: int) -> None:
        self.kind = kind
        self.period_ns = period_ns
        self.stamps: list[int] = []
        self.values: list[np.ndarray] = []

    def last(self) -> int | None:
        return self.stamps[-1] if self.stamps else None

    def append(self, stamp: int, vec: np.ndarray) -> None:
        self.stamps.append(stamp)
        self.values.append(vec)

    def drop_before(self, index: int) -> None:
        if index > 0:
            del self.stamps[:index]
            del self.values[:index]


class ResamplingPairer:
    """Pairs one source's state and command streams on a fixed period (see the module docstring).

    Same interface as :class:`~saml_ros.core.data.pairing.StampPairer`: :meth:`add` takes ``(kind, stamp_ns, vector)``
    with ``kind`` ``"state"`` or ``"applied_cmd"`` and returns the transitions it completed; :attr:`counts` holds
    :data:`COUNTERS`. Not thread-safe.

    Args:
        config: the rule.
        source: index stored in every emitted :class:`~saml_ros.core.data.pairing.Transition`.
        name: label used in messages (e.g. the namespace).
    """

    def __init__(self, config: ResampleConfig, source: int = 0, name: str = "") -> None:
        self.config = config
        self.source = int(source)
        self.name = name or f"source {source}"
        self.counts: dict[str, int] = dict.fromkeys(COUNTERS, 0)
        self._sizes = {"state": config.n_x, "applied_cmd": config.n_u}
        self._stamped = {"state": config.stamped_state, "applied_cmd": config.stamped_cmd}
        self._angles = np.array(config.angle_indices, dtype=np.int64)
        self._run: list[tuple[int, np.ndarray]] = []
        self._reset()

    def _reset(self) -> None:
        cfg = self.config
        self._states = _Stream("state", cfg.state_period_ns or cfg.dt_ns)
        self._cmds = _Stream("applied_cmd", cfg.cmd_period_ns)
        self._last_stamp: dict[str, int | None] = dict.fromkeys(KINDS, None)
        self._t0: int | None = None
        self._k = 0  # next grid interval to decide: [t0 + k dt, t0 + (k + 1) dt]
        # cmd_rule "answer": stamps of earlier states whose answer has not come yet (answers come in order)
        self._unanswered: list[int] = []
        self._owed_since = 0  # the window where the answers started to be owed

    # ------------------------------------------------------------------------------------------ public
    @property
    def pending(self) -> int:
        """Messages held for intervals not decided yet."""
        return len(self._states.stamps) + len(self._cmds.stamps)

    def reject(self, reason: str, kind: str | None = None) -> None:
        """Count a message of ``kind`` dropped before it reached the pairer (e.g. malformed) under ``reason``."""
        if kind in self._sizes:
            self.counts["received/" + kind] += 1
        self.counts[reason] = self.counts.get(reason, 0) + 1

    def flush(self) -> None:
        """Forget everything pending (the source went away); undecided intervals are not formed."""
        self._reset()

    def add(self, kind: str, stamp_ns: int, vector: Any) -> AddResult:
        """Feed one message; returns the transitions it completed, or why it was dropped."""
        if kind not in self._sizes:
            raise ValueError(f"{self.name}: unknown event kind {kind!r}; expected one of {KINDS}")
        self.counts["received/" + kind] += 1
        if not self._stamped[kind]:
            self.counts["unstamped/" + kind] += 1
        if isinstance(stamp_ns, bool) or not isinstance(stamp_ns, int | np.integer) or stamp_ns < 0:
            return self._drop("stamp", f"{kind} stamp must be an int >= 0 (ns), got {stamp_ns!r}")
        stamp = int(stamp_ns)
        vec = np.asarray(vector, dtype=np.float64)
        if vec.shape != (self._sizes[kind],):
            return self._drop("shape", f"{kind} at {_fmt(stamp)}: expected {self._sizes[kind]} values, got "
                                       f"shape {vec.shape}")
        if not np.isfinite(vec).all():
            return self._drop("nan", f"{kind} at {_fmt(stamp)}: non-finite value(s) {vec.tolist()}")
        bounds = self.config.bounds
        if bounds is not None and (why := bounds.outside(kind, vec)) is not None:
            return self._drop("bounds", f"{kind} at {_fmt(stamp)}: outside the plausible range: {why}")
        last = self._last_stamp[kind]
        if last is not None and abs(stamp - last) <= _SAME_NS:
            return self._drop("duplicate", f"{kind} at {_fmt(stamp)} has the stamp of the previous {kind}")
        if last is not None and stamp < last:
            return self._out_of_order(kind, stamp, vec, last)
        if kind == "state":
            self._run.clear()
        return AddResult(self._accept(kind, stamp, vec))

    # ------------------------------------------------------------------------------------------ rules
    def _out_of_order(self, kind: str, stamp: int, vec: np.ndarray, last: int) -> AddResult:
        result = self._drop("out_of_order", f"{kind} at {_fmt(stamp)} arrived after {kind} at {_fmt(last)}")
        if kind != "state":
            return result
        if self._run and stamp <= self._run[-1][0] + _SAME_NS:
            self._run.clear()
        self._run.append((stamp, vec))
        if len(self._run) < self.config.reanchor:
            return result
        run, self._run = self._run, []
        pending = self.pending
        self._reset()
        self.counts["time_resets"] += 1
        self.counts["out_of_order"] -= len(run)
        out: list[Transition] = []
        for s, v in run:
            out += self._accept("state", s, v)
        return AddResult(out, None, f"{self.name}: state stamps restarted at {_fmt(run[0][0])} (before "
                                    f"{_fmt(last)}): new clock, {pending} pending message(s) dropped")

    def _accept(self, kind: str, stamp: int, vec: np.ndarray) -> list[Transition]:
        cfg = self.config
        stream = self._states if kind == "state" else self._cmds
        prev = self._last_stamp[kind]
        if prev is not None:
            self._interval_stats(stream, stamp - prev)
        self._last_stamp[kind] = stamp
        if kind == "applied_cmd":
            eff = stamp + cfg.cmd_delay_ns
            if self._t0 is not None and self._k and eff < self._t0 + self._k * cfg.dt_ns - cfg.cmd_guard_ns:
                self.counts["late"] += 1  # an interval it belongs to was already decided
            stream.append(eff, vec)
            return []
        stream.append(stamp, vec)
        if self._t0 is None:
            self._t0 = stamp
        return self._decide(stamp)

    def _interval_stats(self, stream: _Stream, interval: int) -> None:
        kind = stream.kind
        key = "max_interval_us/" + kind
        self.counts[key] = max(self.counts[key], interval // 1000)
        period = stream.period_ns
        if period <= 0:
            return
        if interval > 1.5 * period:
            self.counts["missing/" + kind] += max(0, round(interval / period) - 1)
        elif abs(interval - period) > self.config.jitter_tolerance * period:
            self.counts["jitter/" + kind] += 1

    def _decide(self, newest: int) -> list[Transition]:
        cfg = self.config
        assert self._t0 is not None
        out: list[Transition] = []
        dt = cfg.dt_ns
        while True:
            t_a = self._t0 + self._k * dt
            t_b = t_a + dt
            if t_b > newest - cfg.latency_ns:
                break
            # skip straight over long outages: no state within reach of t_a means nothing to form until then
            first_after = self._first_state_near(t_a)
            if first_after is not None and first_after > t_b + cfg.state_tolerance_ns:
                skip = max(1, (first_after - cfg.state_tolerance_ns - t_a) // dt)
                self.counts["gap"] += int(skip)
                self.counts["intervals"] += int(skip)
                self._k += int(skip)
                self._unanswered = []
                continue
            tr = self._form(t_a, t_b)
            self.counts["intervals"] += 1
            if tr is not None:
                out.append(tr)
            self._k += 1
        self.counts["paired"] += len(out)
        self._prune(self._t0 + self._k * dt)
        return out

    def _first_state_near(self, t: int) -> int | None:
        """Stamp of the first state at or after ``t - tolerance`` (``None`` if there is none)."""
        st = self._states.stamps
        i = bisect.bisect_left(st, t - self.config.state_tolerance_ns)
        return st[i] if i < len(st) else None

    def _form(self, t_a: int, t_b: int) -> Transition | None:
        cfg = self.config
        xa = self._state_at(t_a)
        xb = self._state_at(t_b) if xa is not None else None
        if xa is None or xb is None:
            self.counts["gap"] += 1
            self._unanswered = []
            return None
        if cfg.cmd_rule == "answer":
            u = self._answer(t_a, t_b)
            return None if u is None else Transition(xa, u, self._target(xa, xb), t_a, self.source)
        # "answer_next_step": a change stamped just after t_a is the answer to the state at t_a, which the robot
        # cannot have applied at t_a, when every earlier state's answer came before t_a - guard
        after = cfg.cmd_guard_ns
        if cfg.cmd_rule == "answer_next_step" and self._answered_before(t_a):
            after = 0
        cs, cv = self._cmds.stamps, self._cmds.values
        i = bisect.bisect_right(cs, t_a) - 1  # last command at or before t_a
        if i < 0:
            self.counts["no_cmd"] += 1
            return None
        if cfg.cmd_timeout_ns and t_a - cs[i] > cfg.cmd_timeout_ns:
            self.counts["stale_cmd"] += 1
            return None
        g = cfg.cmd_guard_ns
        # value changes with stamps in [t_a - g, t_b + g): which one the robot applied over [t_a, t_b) is unclear
        j = bisect.bisect_left(cs, t_a - g)
        mixed = False
        while j < len(cs) and cs[j] < t_b - g:
            if j > 0 and not np.array_equal(cv[j], cv[j - 1]):
                if cs[j] <= t_a + after:
                    self.counts["ambiguous_cmd"] += 1
                    return None
                mixed = True
            j += 1
        if mixed:
            self.counts["mixed_cmd"] += 1
            if cfg.mixed == "drop":
                return None
        return Transition(xa, cv[i].copy(), self._target(xa, xb), t_a, self.source)

    def _target(self, xa: np.ndarray, xb: np.ndarray) -> np.ndarray:
        """``x(t_k + dt)`` with its angle fields unwrapped relative to ``x(t_k)``."""
        y = xb.copy()
        if len(self._angles):
            a = self._angles
            y[a] = xa[a] + wrap_angle(xb[a] - xa[a])
        return y

    # ------------------------------------------------------------------------------------------ "answer"
    def _anchor(self, t: int) -> int | None:
        """Stamp of the state message at grid time ``t`` (the nearest, within half a period), else ``None``."""
        st = self._states.stamps
        half = (self.config.state_period_ns or self.config.dt_ns) // 2
        i = bisect.bisect_left(st, t - half)
        best = None
        for j in (i, i + 1):
            if j < len(st) and abs(st[j] - t) <= half and (best is None or abs(st[j] - t) < abs(best - t)):
                best = st[j]
        return best

    def _window(self, start: int, end: int) -> list[int]:
        """Indices of the commands stamped in ``[start, end)``."""
        cs = self._cmds.stamps
        return list(range(bisect.bisect_left(cs, start), bisect.bisect_left(cs, end)))

    def _answer(self, t_a: int, t_b: int) -> np.ndarray | None:
        """The command answering the state at ``t_a`` (rules in the module docstring), or ``None`` (counted)."""
        wa, wb = self._anchor(t_a), self._anchor(t_b)
        if wa is None or wb is None:  # a state message is missing: whose window is whose is unknown
            self.counts["gap"] += 1
            self._unanswered = []
            return None
        index, reason = self._account(wa, wb)
        if index is None:
            self.counts[reason] += 1
            return None
        return self._cmds.values[index].copy()

    def _account(self, start: int, end: int) -> tuple[int | None, str]:
        """Book the commands stamped in the window ``[start, end)`` of the state stamped ``start`` as answers
        (each state is answered once, in order; the first commands answer states still owed an answer). Returns
        the index of the command answering this state, or ``None`` and why (``no_answer``, ``ambiguous_cmd``)."""
        cv = self._cmds.values
        now = self._window(start, end)
        if self._unanswered and start - self._owed_since > self.config.latency_ns:
            self._unanswered = []  # owed for longer than an answer may take: a state was skipped, not answered late
        owed, self._unanswered = self._unanswered, []
        if owed:  # the first commands here answer earlier states
            if len(now) == len(owed) + 1:  # caught up: the last one answers this state
                return now[-1], ""
            if len(now) <= len(owed):
                self._unanswered = owed[len(now):] + [start]
            return None, "ambiguous_cmd" if now else "no_answer"
        if not now:
            self._unanswered, self._owed_since = [start], start
            return None, "no_answer"
        if any(not np.array_equal(cv[j], cv[now[0]]) for j in now[1:]):
            return None, "ambiguous_cmd"  # several answers to one state
        return now[0], ""

    def _answered_before(self, t: int) -> bool:
        """``"answer_next_step"``: whether every state before ``t`` has been answered, the last one before
        ``t - cmd_guard`` (then a command stamped just after ``t`` is the answer to the state at ``t``)."""
        prev, cur = self._anchor(t - self.config.dt_ns), self._anchor(t)
        if prev is None or cur is None:
            self._unanswered = []
            return False
        index, _ = self._account(prev, cur)
        return index is not None and self._cmds.stamps[index] < t - self.config.cmd_guard_ns

    def _state_at(self, t: int) -> np.ndarray | None:
        cfg = self.config
        st, sv = self._states.stamps, self._states.values
        i = bisect.bisect_right(st, t + _SAME_NS) - 1  # last state at or before t (within 1 us)
        if i >= 0 and abs(st[i] - t) <= _SAME_NS:
            return sv[i].copy()
        if i < 0 or i + 1 >= len(st):
            return None
        (sa, va), (sb, vb) = (st[i], sv[i]), (st[i + 1], sv[i + 1])
        if cfg.state_rule == "nearest":
            s, v = (sa, va) if t - sa <= sb - t else (sb, vb)
            return v.copy() if abs(s - t) <= cfg.state_tolerance_ns else None
        if sb - sa > cfg.state_tolerance_ns:
            return None
        w = (t - sa) / (sb - sa)
        x = va + w * (vb - va)
        if len(self._angles):
            a = self._angles
            x[a] = wrap_angle(va[a] + w * wrap_angle(vb[a] - va[a]))
        return x

    def _prune(self, t_next: int) -> None:
        """Drop what no undecided interval (starting at ``t_next``) can use."""
        cfg = self.config
        st = self._states.stamps
        reach = cfg.state_tolerance_ns
        if cfg.cmd_rule != "hold":  # the state messages anchoring the windows of t_next and the interval before it
            reach = max(reach, cfg.dt_ns + (cfg.state_period_ns or cfg.dt_ns) // 2)
        keep = bisect.bisect_right(st, t_next - reach) - 1
        self._states.drop_before(max(0, keep))
        cs = self._cmds.stamps
        # the held command at t_next and every change that may still matter to the guard checks
        keep_c = bisect.bisect_right(cs, t_next - cfg.cmd_guard_ns - 1) - 1
        if cfg.cmd_rule != "hold":  # and the windows of the states at t_next and one period before
            keep_c = min(keep_c, bisect.bisect_left(cs, t_next - cfg.dt_ns - cfg.dt_ns // 2))
        self._cmds.drop_before(max(0, keep_c))

    def _drop(self, reason: str, detail: str) -> AddResult:
        self.counts[reason] += 1
        return AddResult([], reason, f"{self.name}: {detail}")


def _fmt(stamp: int) -> str:
    return f"{stamp / NS_PER_S:.9f} s"


