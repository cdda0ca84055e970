"""Pairing for controllers that run at the state's rate (saml_ros.core.data.resampling, issue 27 item 3).

The timing simulator of bench/pairing_timing.py (no ROS) plays a robot, its controller and the learner, and knows
the command the robot really applied over every interval; every transition the pairer emits is checked against
it, for both common timings and several random phases and delays:

* **a controller triggered by each state message** (its answer arrives anywhere in the period, now and then after
  it), with a robot that applies each answer over the interval its state starts (``command: answer``), or a
  free-running zero-order-hold robot that applies it at its next step (``command: answer_next_step``);
* **a controller on its own timer at the state's rate**, random phase, zero-order-hold robot (``command: hold``,
  the default): an interval is lost only where a command reached the learner within the guard of the robot's
  step (the learner cannot know which step applied it), never mis-paired.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import pytest

from bench.pairing_timing import DT, MS, T0, N, config, run, state, timer, triggered
from saml_ros.core.data.resampling import ResamplingPairer


def assert_paired_right(trs: list, truth: Mapping[int, float | None]) -> None:
    """Every transition on the grid, with the robot's states at its stamp and one period later and the command the
    robot applied over that interval (the states compared all at once: one assert_allclose per transition was
    most of these tests' time)."""
    assert trs
    stamps = [tr.stamp_ns for tr in trs]
    assert all((t - T0) % DT == 0 for t in stamps)
    np.testing.assert_allclose(np.stack([tr.x for tr in trs]), np.stack([state(t) for t in stamps]), atol=1e-9)
    np.testing.assert_allclose(np.stack([tr.y for tr in trs]), np.stack([state(t + DT) for t in stamps]), atol=1e-9)
    for tr in trs:
        k = (tr.stamp_ns - T0) // DT
        assert tr.u[0] == truth[k], f"step {k}: paired {tr.u[0]}, the robot applied {truth[k]}"


def conservation(c: dict[str, int]) -> None:
    lost = c["gap"] + c["no_cmd"] + c["stale_cmd"] + c["ambiguous_cmd"] + c["no_answer"]
    assert c["intervals"] == c["paired"] + lost, c


# ------------------------------------------------------------------------------------------ state-triggered
@pytest.mark.parametrize("seed", [1, 2, 3, 4, 5, 6])
def test_state_triggered_answer_applied_at_once_every_interval_paired(seed: int) -> None:
    """``command: answer``: whatever the answer's arrival jitter within the period, every interval gets it."""
    sim = triggered(seed)
    p = ResamplingPairer(config(cmd_rule="answer", stamped_cmd=False))
    trs = run(p, sim.events)
    assert_paired_right(trs, sim.answer)
    c = p.counts
    conservation(c)
    assert sim.latency.max() > 0.8 * DT and np.median(sim.latency) < 0.3 * DT  # jitter over the whole period
    assert c["paired"] == c["intervals"] >= N - 15
    # the zero-order hold would pair every interval with the previous state's answer
    hold = ResamplingPairer(config(stamped_cmd=False))
    assert all(tr.u[0] != sim.answer[(tr.stamp_ns - T0) // DT] for tr in run(hold, sim.events))


@pytest.mark.parametrize("seed", [7, 8, 9])
def test_state_triggered_late_answers_are_dropped_never_mispaired(seed: int) -> None:
    """Answers later than the period (stalls): what the robot applied meanwhile is robot-specific, so those
    intervals and the ones whose window holds a late answer are dropped, and nothing is mis-paired."""
    sim = triggered(seed, stalls=12, max_stall=35 * MS, cap=None)
    p = ResamplingPairer(config(cmd_rule="answer", stamped_cmd=False))
    trs = run(p, sim.events)
    assert_paired_right(trs, sim.answer)
    c = p.counts
    conservation(c)
    late = int(np.sum(sim.latency >= DT))
    assert late >= 12 and c["no_answer"] > 0 and c["ambiguous_cmd"] > 0
    assert c["no_answer"] + c["ambiguous_cmd"] <= 3 * late  # only around the stalls
    assert c["paired"] >= c["intervals"] - 3 * late


@pytest.mark.parametrize("seed", [10, 11])
def test_state_triggered_with_the_states_stamp_is_exact_at_any_latency(seed: int) -> None:
    """A stamped command carrying the stamp of the state it answers pairs exactly, however late it comes."""
    sim = triggered(seed, copy_stamp=True, stalls=10, max_stall=60 * MS, cap=None)
    p = ResamplingPairer(config(cmd_rule="answer"))
    trs = run(p, sim.events)
    assert_paired_right(trs, sim.answer)
    assert int(np.sum(sim.latency >= DT)) >= 10
    assert p.counts["paired"] == p.counts["intervals"] >= N - 15


@pytest.mark.parametrize("fault", ["skip", "double"])
def test_state_triggered_controller_that_skips_or_doubles_answers_never_mispairs(fault: str) -> None:
    """A controller that leaves some states unanswered (a depth-1 queue), or answers some twice with different
    values: what cannot be told apart is counted, never paired wrongly."""
    sim = triggered(12)
    events = list(sim.events)
    rng = np.random.default_rng(0)
    steps = sorted(rng.choice(np.arange(20, N - 20, 25), 20, replace=False).tolist())  # 25 steps apart at least
    applied: dict[int, float | None] = dict(sim.answer)
    if fault == "skip":
        events = [e for i, e in enumerate(events) if not (i % 2 == 1 and (i - 1) // 2 in steps)]
        for k in steps:
            applied[k] = None  # not answered: what the robot applied is its own business
    else:
        for k in steps:
            arr, kind, stamp, vec = events[2 * k + 1]
            events.append((arr + MS // 3, kind, stamp + MS // 3, vec + 0.5))
            applied[k] = None  # which of the two the robot applied is not known
    p = ResamplingPairer(config(cmd_rule="answer", stamped_cmd=False))
    trs = run(p, events)
    assert_paired_right(trs, applied)
    c = p.counts
    conservation(c)
    if fault == "skip":  # the skipped state, and the next ones until latency (0.1 s) says it was skipped
        assert c["no_answer"] == len(steps) and c["ambiguous_cmd"] == 10 * len(steps)
    else:
        assert c["ambiguous_cmd"] == len(steps) and c["no_answer"] == 0
    assert c["paired"] == c["intervals"] - c["no_answer"] - c["ambiguous_cmd"]


@pytest.mark.parametrize("seed", [13, 14, 15, 16])
def test_state_triggered_robot_applying_at_its_next_step(seed: int) -> None:
    """``command: answer_next_step``: a free-running zero-order-hold robot (examples/diff_drive/robot.py) with a
    controller answering each state: each answer is applied at the next step. The plain ``hold`` loses the
    intervals whose answer came within its guard after the state (about half here); this rule knows an answer
    cannot have reached the robot before the state it answers, and loses only where a (late) answer may have
    crossed a step."""
    sim = triggered(seed, stalls=6, cap=None)
    p = ResamplingPairer(config(cmd_rule="answer_next_step", stamped_cmd=False))
    trs = run(p, sim.events)
    assert_paired_right(trs, sim.next_step)
    c = p.counts
    conservation(c)
    hold = ResamplingPairer(config(stamped_cmd=False))
    assert_paired_right(run(hold, sim.events), sim.next_step)
    fast = int(np.sum(sim.latency <= hold.config.cmd_guard_ns))
    assert fast > 0.2 * N and hold.counts["ambiguous_cmd"] >= fast - 5
    late = int(np.sum(sim.latency >= DT - hold.config.cmd_guard_ns))  # may cross the next step
    assert c["ambiguous_cmd"] <= 2 * late + 2
    assert c["paired"] >= c["intervals"] - 2 * late - 3


# ------------------------------------------------------------------------------------------ own timer
@pytest.mark.parametrize("seed", range(8))
def test_timer_controller_at_the_state_rate_any_phase(seed: int) -> None:
    phase = int(np.random.default_rng(100 + seed).integers(0, DT))
    events, truth, rx = timer(seed, phase)
    p = ResamplingPairer(config(stamped_cmd=False))  # the defaults: command: hold, command_guard 2 ms
    trs = run(p, events)
    assert_paired_right(trs, truth)
    c = p.counts
    conservation(c)
    # an interval is lost only where a command reached the learner within the guard of the robot's step
    guard = p.config.cmd_guard_ns
    tau = T0 + np.arange(N) * DT
    near = {int(round((r - T0) / DT)) for r in rx if abs(r - (T0 + round((r - T0) / DT) * DT)) <= guard}
    decided = c["intervals"]
    racing = len([k for k in near if 1 <= k < decided])
    assert c["ambiguous_cmd"] == racing, (phase, racing)
    assert c["paired"] == decided - c["ambiguous_cmd"] - c["no_cmd"]
    assert c["no_cmd"] <= 1
    if not near:
        assert c["ambiguous_cmd"] == 0 and c["paired"] >= decided - 1
    assert len(tau) == N


def test_timer_controller_far_from_the_robots_step_loses_nothing() -> None:
    """Phases a few ms away from the robot's step (where most random phases land): nothing lost."""
    for seed, phase in enumerate((2 * MS + MS // 2, 4 * MS, 5 * MS)):  # arrivals 0-2.5 ms later than the phase
        events, truth, _ = timer(seed, phase)
        p = ResamplingPairer(config(stamped_cmd=False))
        trs = run(p, events)
        assert_paired_right(trs, truth)
        assert p.counts["ambiguous_cmd"] == 0 and p.counts["paired"] >= p.counts["intervals"] - 1


def test_answer_rule_checks_its_period() -> None:
    with pytest.raises(ValueError, match="state period"):
        config(cmd_rule="answer", state_period=0.02)
    with pytest.raises(ValueError, match="cmd_rule"):
        config(cmd_rule="latest")
