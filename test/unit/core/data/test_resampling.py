"""Asynchronous pairing (saml_ros.core.data.resampling): jitter, drops, duplicates, unstamped commands, restarts.

Every test drives a ResamplingPairer with a known ground truth: the state is linear in time (so linear
interpolation is exact) with an angle that wraps, commands are piecewise constant with known switch times.
Every emitted transition is checked against the truth (x(t_k), the command in effect at t_k, x(t_k + dt)):
no transition may be mis-paired, and the counters must add up as the module docstring says.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from saml_ros.core.data.resampling import ResampleConfig, ResamplingPairer, wrap_angle

MS = 1_000_000
DT = 20 * MS  # 50 Hz grid
T0 = 1_700_000_000 * 1_000_000_000  # an epoch-like start, as a wall-clock stamp
VEL = np.array([0.5, 2.0])  # p (m/s) and theta (rad/s): theta wraps every ~3.1 s


def truth(t_ns: int) -> np.ndarray:
    s = (t_ns - T0) / 1e9
    return np.array([1.0 + VEL[0] * s, float(wrap_angle(0.3 + VEL[1] * s))])


def cmd_at(t_ns: int, switches: list[int], values: list[float]) -> float | None:
    i = int(np.searchsorted(np.asarray(switches), t_ns, side="right")) - 1
    return None if i < 0 else values[i]


def config(**kw: object) -> ResampleConfig:
    base = dict(n_x=2, n_u=1, dt=DT / 1e9, angle_indices=(1,), cmd_guard=0.003)
    base.update(kw)
    return ResampleConfig.from_seconds(**base)  # type: ignore[arg-type]


def feed(pairer: ResamplingPairer, events: list[tuple[int, str, int, np.ndarray]]) -> list:
    """Events ``(arrival order key, kind, stamp, vector)`` fed in arrival order."""
    out = []
    for _, kind, stamp, vec in sorted(events, key=lambda e: e[0]):
        out += pairer.add(kind, stamp, vec).transitions
    return out


def check_all(trs: list, switches: list[int], values: list[float], guard: int, mixed_drop: bool) -> None:
    assert trs, "no transition formed"
    for tr in trs:
        t = tr.stamp_ns
        np.testing.assert_allclose(tr.x, truth(t), atol=1e-9)
        want_y = truth(t + DT)
        want_y[1] = tr.x[1] + wrap_angle(want_y[1] - tr.x[1])  # targets are unwrapped relative to x
        np.testing.assert_allclose(tr.y, want_y, atol=1e-9)
        assert abs(tr.y[1] - tr.x[1]) < 0.1, "angle target not unwrapped"
        assert tr.u[0] == cmd_at(t, switches, values), f"mis-paired command at {t}"
        # no switch within the guard of t_k, and none inside the interval when mixed intervals are dropped
        sw = np.asarray(switches)
        assert not np.any(np.abs(sw[1:] - t) <= guard)
        if mixed_drop:
            assert not np.any((sw[1:] > t) & (sw[1:] < t + DT - guard))


def assert_conservation(c: dict[str, int], mixed_drop: bool) -> None:
    lost = c["gap"] + c["no_cmd"] + c["stale_cmd"] + c["ambiguous_cmd"] + (c["mixed_cmd"] if mixed_drop else 0)
    assert c["intervals"] == c["paired"] + lost, c


def stream(n_states: int, state_period: int = DT, jitter: float = 0.0, cmd_period: int = 100 * MS,
           seed: int = 0, cmd_phase: int = 7 * MS) -> tuple[list, list[int], list[float]]:
    rng = np.random.default_rng(seed)
    events = []
    stamps = T0 + np.arange(n_states) * state_period
    if jitter:
        stamps = stamps + np.round(rng.uniform(-jitter, jitter, n_states) * state_period).astype(np.int64)
        stamps[0] = T0
    for s in stamps:
        events.append((int(s) + 2 * MS, "state", int(s), truth(int(s))))  # arrives 2 ms after its stamp
    switches = list(range(T0 - 100 * MS + cmd_phase, int(stamps[-1]), cmd_period))
    values = [float(v) for v in np.round(rng.uniform(-1, 1, len(switches)), 3)]
    for sw, v in zip(switches, values, strict=True):
        events.append((sw + 1 * MS, "applied_cmd", sw, np.array([v])))
    return events, switches, values


@pytest.mark.parametrize("mixed", ["hold", "drop"])
def test_regular_streams_pair_every_unambiguous_interval(mixed: str) -> None:
    events, switches, values = stream(500)
    p = ResamplingPairer(config(mixed=mixed))
    trs = feed(p, events)
    check_all(trs, switches, values, 3 * MS, mixed == "drop")
    c = p.counts
    assert c["received/state"] == 500 and c["received/applied_cmd"] == len(switches)
    assert c["gap"] == 0 and c["missing/state"] == 0 and c["jitter/state"] == 0
    # commands switch at 7 ms past a grid point every 100 ms: inside an interval (mixed), never ambiguous
    assert c["ambiguous_cmd"] == 0 and c["mixed_cmd"] == pytest.approx(c["intervals"] / 5, abs=2)
    assert c["paired"] == c["intervals"] - (c["mixed_cmd"] if mixed == "drop" else 0)
    assert_conservation(c, mixed == "drop")


def test_jitter_is_counted_and_interpolated_exactly() -> None:
    events, switches, values = stream(600, jitter=0.4, seed=3)
    p = ResamplingPairer(config())
    trs = feed(p, events)
    check_all(trs, switches, values, 3 * MS, False)
    stamps = np.array(sorted(e[2] for e in events if e[1] == "state"))
    d = np.diff(stamps)
    want_missing = sum(max(0, round(x / DT) - 1) for x in d if x > 1.5 * DT)
    want_jitter = int(np.sum((d <= 1.5 * DT) & (np.abs(d - DT) > 0.25 * DT)))
    assert want_jitter > 50
    assert p.counts["jitter/state"] == want_jitter and p.counts["missing/state"] == want_missing
    assert p.counts["max_interval_us/state"] == int(d.max()) // 1000
    assert p.counts["gap"] == 0  # every bracket is shorter than the 2.5 dt tolerance
    assert_conservation(p.counts, False)


def test_dropped_states_are_counted_and_gaps_never_paired() -> None:
    events, switches, values = stream(800, seed=5)
    rng = np.random.default_rng(1)
    states = [i for i, e in enumerate(events) if e[1] == "state"]
    single = set(rng.choice(states[10:300], 25, replace=False).tolist())
    single = {i for i in single if i - 1 not in single and i + 1 not in single}
    block = set(states[400:412])  # 12 consecutive states: a gap the 2.5 dt tolerance cannot bridge
    kept = [e for i, e in enumerate(events) if i not in single | block]
    p = ResamplingPairer(config())
    trs = feed(p, kept)
    check_all(trs, switches, values, 3 * MS, False)
    c = p.counts
    assert c["missing/state"] == len(single) + len(block)
    assert c["gap"] > 0
    t_block = (events[states[400]][2], events[states[411]][2])
    assert not any(t_block[0] - DT < tr.stamp_ns < t_block[1] for tr in trs), "a transition spans the gap"
    # single drops are bridged by interpolation: only the block loses intervals
    assert c["gap"] == pytest.approx(12 + 1, abs=2)
    assert_conservation(c, False)


def test_duplicates_are_counted_and_change_nothing() -> None:
    events, switches, values = stream(300, seed=7)
    ref = ResamplingPairer(config())
    want = feed(ref, events)
    dup = [(e[0] + 0.5, e[1], e[2], e[3]) for e in events[::7]]  # re-delivered right after the original
    p = ResamplingPairer(config())
    got = feed(p, events + dup)
    assert p.counts["duplicate"] == len(dup)
    assert len(got) == len(want)
    for a, b in zip(got, want, strict=True):
        assert a.stamp_ns == b.stamp_ns and np.array_equal(a.u, b.u) and np.array_equal(a.y, b.y)


def test_unstamped_commands_stamped_on_receipt_never_mispair() -> None:
    """The robot applies each command from when it received it; the learner stamps it on its own receipt, up to
    1.5 ms off. The guard (3 ms) drops the intervals where that could matter; none is mis-paired."""
    rng = np.random.default_rng(11)
    events, switches, values = stream(1000, seed=11, cmd_period=97 * MS)  # drifts through every phase
    noisy = []
    for e in events:
        if e[1] == "applied_cmd":
            recv = e[2] + int(rng.uniform(-1.5, 1.5) * MS)
            noisy.append((recv, "applied_cmd", recv, e[3]))
        else:
            noisy.append(e)
    p = ResamplingPairer(config(stamped_cmd=False))
    trs = feed(p, noisy)
    check_all(trs, switches, values, 3 * MS - 2 * MS, False)  # against the *true* switch times
    for tr in trs:
        assert tr.u[0] == cmd_at(tr.stamp_ns, switches, values)
    c = p.counts
    assert c["unstamped/applied_cmd"] == len(switches) and c["unstamped/state"] == 0
    assert c["ambiguous_cmd"] > 0
    assert_conservation(c, False)


def test_nearest_rule_and_stale_commands() -> None:
    events, switches, values = stream(400, seed=2)
    # the robot stops getting commands after 3 s: with a 0.5 s timeout the rest is stale, not paired
    cut = T0 + 3_000 * MS
    events = [e for e in events if e[1] == "state" or e[2] < cut]
    sent = [s for s in switches if s < cut]
    p = ResamplingPairer(config(state_rule="nearest", cmd_timeout=0.5))
    trs = feed(p, events)
    check_all(trs, sent, values[: len(sent)], 3 * MS, False)
    assert max(tr.stamp_ns for tr in trs) < cut + 500 * MS
    assert p.counts["stale_cmd"] > 100
    assert_conservation(p.counts, False)


@pytest.mark.parametrize("latency", [0.1, 0.4])
def test_commands_lagging_more_than_latency_are_counted_late(latency: float) -> None:
    """Commands that reach the pairer 0.3 s after states of the same time: with latency 0.4 s every interval
    waits for them and all transitions are right; with 0.1 s they are counted late (the documented sign that
    ``latency`` is too short)."""
    events, switches, values = stream(300, seed=4)
    lagged = [(e[0] + 300 * MS, *e[1:]) if e[1] == "applied_cmd" else e for e in events]
    p = ResamplingPairer(config(latency=latency))
    trs = feed(p, lagged)
    if latency < 0.3:
        assert p.counts["late"] > 0
    else:
        assert p.counts["late"] == 0
        check_all(trs, switches, values, 3 * MS, False)
    assert_conservation(p.counts, False)


def test_clock_restart_reanchors() -> None:
    events, switches, values = stream(200, seed=9)
    p = ResamplingPairer(config())
    first = feed(p, events)
    assert first
    # the robot restarts: its stamps begin again 10 s earlier (a new clock); 3 increasing states re-anchor
    restart = [(1e20 + i, "state", T0 - 10_000 * MS + i * DT, truth(T0 + i * DT)) for i in range(5)]
    for _, kind, stamp, vec in restart:
        p.add(kind, stamp, vec)
    assert p.counts["time_resets"] == 1
    assert p.counts["out_of_order"] == 0


def test_bad_messages_are_rejected_with_reasons() -> None:
    p = ResamplingPairer(config())
    assert p.add("state", -1, [0, 0]).rejected == "stamp"
    assert p.add("state", T0, [0, 0, 0]).rejected == "shape"
    assert p.add("applied_cmd", T0, [math.nan]).rejected == "nan"
    assert p.add("state", T0, [0, 0]).rejected is None
    assert p.add("state", T0 - DT, [0, 0]).rejected == "out_of_order"
    with pytest.raises(ValueError, match="unknown event kind"):
        p.add("target", T0, [0, 0])


def test_config_validation() -> None:
    with pytest.raises(ValueError, match="state_rule"):
        config(state_rule="cubic")
    with pytest.raises(ValueError, match="cmd_guard"):
        config(cmd_guard=0.015)
    with pytest.raises(ValueError, match="latency"):
        config(latency=0.01)
    with pytest.raises(ValueError, match="angle_indices"):
        config(angle_indices=(5,))
