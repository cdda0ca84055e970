"""A timing simulator of a robot, its controller and the learner's stamps, for the pairing rules (no ROS).

:mod:`saml_ros.core.data.resampling` decides which command each interval of a robot's stream gets. Whether it is
right depends on timing no single process sees: when the robot received each command, when it applied it, when
the learner received it. This module plays all three with delays modelled on what was measured on the shared
development machine under load (``./dev bench pairing --part ros``: two processes' receive times of one message
differ by up to about 1.8 ms at the 99th percentile; a state-triggered rclpy controller answered in about 2 ms
median, 9 ms at the 99th percentile, now and then after more than a 10 ms period), and knows the command the
robot really applied over every interval. Used by test/test_state_rate_pairing.py and ``./dev bench pairing``.

* :func:`triggered`: a controller answering each state message, in order; ``answer`` is the truth of a robot that
  applies each answer over the interval its state starts, ``next_step`` that of a free-running zero-order-hold
  robot (it applies, at each step, the last command it received).
* :func:`timer`: a controller on its own timer at the state's rate, ``phase`` after the robot's steps, and a
  zero-order-hold robot.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np

from saml_ros.core.data.resampling import ResampleConfig, ResamplingPairer

MS = 1_000_000
DT = 10 * MS  # 100 Hz: state rate = controller rate = grid
T0 = 1_700_000_000 * 1_000_000_000
N = 1500  # robot steps per run


def state(t: int) -> np.ndarray:
    """The robot's (2,) state at stamp ``t`` (linear in time: interpolation is exact)."""
    s = (t - T0) / 1e9
    return np.array([1.0 + 0.5 * s, -2.0 + 0.25 * s])


def config(**kw: Any) -> ResampleConfig:
    """The pairing rule for the simulated robot (100 Hz state, controller and grid), updated with ``kw``."""
    base: dict[str, Any] = dict(n_x=2, n_u=1, dt=DT / 1e9, state_period=DT / 1e9, cmd_period=DT / 1e9)
    base.update(kw)
    return ResampleConfig.from_seconds(**base)


def run(pairer: ResamplingPairer, events: list[tuple[int, str, int, np.ndarray]]) -> list[Any]:
    """Feed ``events`` ``(arrival, kind, stamp, vector)`` in arrival order; the emitted transitions."""
    out = []
    for _, kind, stamp, vec in sorted(events, key=lambda e: (e[0], e[1])):
        out += pairer.add(kind, stamp, vec).transitions
    return out


def dds(rng: np.random.Generator, n: int) -> np.ndarray:
    """One-way delivery delay to one subscriber (ns): median 0.15 ms, heavy tail, at most 0.9 ms."""
    return (np.clip(rng.lognormal(np.log(0.15), 0.9, n), 0.03, 0.9) * MS).astype(np.int64)


def in_order(t: np.ndarray) -> np.ndarray:
    """Receive times of one writer's messages at one reader: in publish order, at least 10 us apart."""
    out = t.copy()
    for i in range(1, len(out)):
        out[i] = max(out[i], out[i - 1] + 10_000)
    return out


class Triggered(NamedTuple):
    events: list[tuple[int, str, int, np.ndarray]]
    answer: dict[int, float]  # the controller's answer to the state of each step
    next_step: dict[int, float | None]  # what a free-running zero-order-hold robot applied at each step
    latency: np.ndarray  # from each state's stamp to the learner's receipt of its answer (ns)


def triggered(seed: int, *, copy_stamp: bool = False, stalls: int = 0, max_stall: int = 25 * MS,
              cap: int | None = int(0.95 * DT)) -> Triggered:
    """A controller answering each state in order, once: the state reaches it after a DDS delay, it answers after
    an executor wake-up and a solve (and now and then a stall of more than a period); the learner and the robot
    receive the answer at slightly different times. ``cap`` bounds the answer's latency (the answer arrives
    within the period), ``copy_stamp`` stamps each command with the state it answers."""
    rng = np.random.default_rng(seed)
    tau = T0 + np.arange(N) * DT
    arrive_ctrl = tau + dds(rng, N)  # the state reaches the controller
    compute = (rng.lognormal(np.log(1.5), 0.7, N) * MS).astype(np.int64)  # executor wake-up and the solve
    stall_at = set(rng.choice(np.arange(50, N - 50), stalls, replace=False).tolist()) if stalls else set()
    done = np.zeros(N, dtype=np.int64)
    busy_until = 0
    for k in range(N):  # one thread, answers in order
        start = max(int(arrive_ctrl[k]), busy_until)
        if k in stall_at:
            start += int(rng.integers(DT, max_stall))  # garbage collection, CPU contention, ...
        done[k] = start + compute[k]
        if cap is not None:
            done[k] = min(done[k], tau[k] + cap - MS)
        busy_until = int(done[k])
    recv = in_order(done + dds(rng, N))  # the learner receives the answers
    robot_rx = in_order(done + dds(rng, N))  # ... and the robot
    if cap is not None:
        recv = np.minimum(recv, tau + cap)
    values = np.round(rng.uniform(-1, 1, N), 6)
    events: list[tuple[int, str, int, np.ndarray]] = []
    for k in range(N):
        events.append((int(tau[k] + dds(rng, 1)[0]), "state", int(tau[k]), state(int(tau[k]))))
        stamp = int(tau[k]) if copy_stamp else int(recv[k])
        events.append((int(recv[k]), "applied_cmd", stamp, np.array([values[k]])))
    next_step: dict[int, float | None] = {}
    for k in range(N):
        got = np.nonzero(robot_rx <= tau[k])[0]
        next_step[k] = float(values[got[-1]]) if len(got) else None
    return Triggered(events, {k: float(values[k]) for k in range(N)}, next_step, recv - tau)


def timer(seed: int, phase: int) -> tuple[list[Any], dict[int, float | None], np.ndarray]:
    """A zero-order-hold robot stepping at its state stamps and a controller on its own timer at the same period,
    ``phase`` ns after the robot's steps. Returns (events, truth by step, the learner's receive stamps)."""
    rng = np.random.default_rng(seed)
    tau = T0 + np.arange(N) * DT
    m = N + 2
    fire = T0 - DT + phase + np.arange(m) * DT + (rng.exponential(0.3, m) * MS).astype(np.int64)  # timers fire late
    robot_rx = in_order(fire + dds(rng, m))
    learner_rx = in_order(fire + dds(rng, m))  # within 0.9 ms of the robot's: inside the 2 ms guard
    values = np.round(rng.uniform(-1, 1, m), 6)
    truth: dict[int, float | None] = {}
    for k in range(N):
        got = np.nonzero(robot_rx <= tau[k])[0]
        truth[k] = float(values[got[np.argmax(robot_rx[got])]]) if len(got) else None
    events: list[tuple[int, str, int, np.ndarray]] = []
    for k in range(N):
        events.append((int(tau[k] + dds(rng, 1)[0]), "state", int(tau[k]), state(int(tau[k]))))
    for j in range(m):  # unstamped: the learner stamps each command with its receive time
        events.append((int(learner_rx[j]), "applied_cmd", int(learner_rx[j]), np.array([values[j]])))
    return events, truth, learner_rx




def mispaired(trs: list[Any], truth: dict[int, float | None]) -> int:
    """How many of ``trs`` have another command than the robot applied (or a step it applied nothing known)."""
    return sum(1 for tr in trs if truth.get((tr.stamp_ns - T0) // DT) != tr.u[0])
