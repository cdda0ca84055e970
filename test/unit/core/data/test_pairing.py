"""Exact stamp pairing (saml_ros.core.data.pairing): no mis-pairing, no loss of good transitions, bounded memory."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from saml_ros.core.data.pairing import COUNTERS, PairingConfig, StampPairer, Transition, total_counts
from saml_ros.core.systems import get_system

DT = 100_000_000  # 0.1 s in ns
T0 = 5 * 10**9


def next_cfg(**kw: Any) -> PairingConfig:
    return PairingConfig(mode="next", n_x=2, n_u=1, n_y=2, dt_ns=DT, **kw)


def same_cfg(**kw: Any) -> PairingConfig:
    return PairingConfig(mode="same", n_x=6, n_u=6, n_y=3, **kw)


def trajectory(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray, list[int]]:
    """n states of the friction system driven by random controls: x (n, 2), u (n, 1), stamps (n,)."""
    sys = get_system("friction")
    rng = np.random.default_rng(seed)
    x = np.zeros((n, 2))
    u = rng.uniform(-3, 3, size=(n, 1))
    x[0] = [0.2, -0.1]
    for k in range(n - 1):
        x[k + 1] = sys.true_step_np(x[k], u[k])
    return x, u, [T0 + k * DT for k in range(n)]


def feed(p: StampPairer, events: list[tuple[str, int, np.ndarray]]) -> list[Transition]:
    out: list[Transition] = []
    for kind, stamp, vec in events:
        out += p.add(kind, stamp, vec).transitions
    return out


def stream(x: np.ndarray, u: np.ndarray, stamps: list[int], cmd_first: bool = False) -> list[tuple[str, int, np.ndarray]]:
    ev: list[tuple[str, int, np.ndarray]] = []
    for k, t in enumerate(stamps):
        pair = [("state", t, x[k]), ("applied_cmd", t, u[k])]
        ev += pair[::-1] if cmd_first else pair
    return ev


Event = tuple[str, int, np.ndarray]


def merge(states: list[Event], cmds: list[Event], rng: np.random.Generator, ahead: float = np.inf,
          lag: float = np.inf) -> list[Event]:
    """The two streams merged at random, each kept in order; commands run at most ``ahead`` steps ahead of the
    states and lag at most ``lag`` steps (a coin decides only where both are possible)."""
    merged: list[Event] = []
    i = j = 0
    while i < len(states) or j < len(cmds):
        if j >= len(cmds) or j - i >= ahead:
            take_state = True
        elif i >= len(states) or i - j >= lag:
            take_state = False
        else:
            take_state = bool(rng.random() < 0.5)
        if take_state:
            merged.append(states[i])
            i += 1
        else:
            merged.append(cmds[j])
            j += 1
    return merged


def check_exact(trs: list[Transition], x: np.ndarray, u: np.ndarray, stamps: list[int]) -> None:
    """Every transition is (x_k, u_k, x_{k+1}) for the k its stamp names."""
    index = {t: k for k, t in enumerate(stamps)}
    for tr in trs:
        k = index[tr.stamp_ns]
        np.testing.assert_array_equal(tr.x, x[k])
        np.testing.assert_array_equal(tr.u, u[k])
        np.testing.assert_array_equal(tr.y, x[k + 1])


# ------------------------------------------------------------------------------------------------ next
@pytest.mark.parametrize("cmd_first", [False, True])
def test_clean_stream_pairs_every_step_exactly(cmd_first: bool) -> None:
    x, u, st = trajectory(50)
    p = StampPairer(next_cfg(), source=3)
    trs = feed(p, stream(x, u, st, cmd_first))
    assert [t.stamp_ns for t in trs] == st[:-1]  # the last state waits for its successor
    assert all(t.source == 3 for t in trs)
    check_exact(trs, x, u, st)
    assert p.counts["paired"] == 49
    assert sum(p.counts[r] for r in ("duplicate", "late", "out_of_order", "unpaired", "nan", "shape")) == 0


def test_any_interleaving_of_kinds_gives_the_same_transitions() -> None:
    x, u, st = trajectory(200, seed=1)
    rng = np.random.default_rng(7)
    states = [("state", t, x[k]) for k, t in enumerate(st)]
    cmds = [("applied_cmd", t, u[k]) for k, t in enumerate(st)]
    for trial in range(20):
        # merge the two streams randomly, keeping each one in order; commands run up to 3 steps ahead of
        # the states or lag up to 15 steps
        ahead, lag = int(rng.integers(0, 4)), int(rng.integers(1, 16))
        merged = merge(states, cmds, rng, ahead, lag)
        p = StampPairer(next_cfg())
        trs = feed(p, merged)
        assert sorted(t.stamp_ns for t in trs) == st[:-1], f"trial {trial}"
        check_exact(trs, x, u, st)


def test_missing_next_state_never_pairs_with_a_later_one() -> None:
    x, u, st = trajectory(10)
    ev = [e for e in stream(x, u, st) if not (e[0] == "state" and e[1] == st[5])]
    p = StampPairer(next_cfg())
    trs = feed(p, ev)
    # steps 4 (needs x_5 as target) and 5 (needs x_5 as x_t) are impossible; all others pair
    assert sorted(t.stamp_ns for t in trs) == [t for k, t in enumerate(st[:-1]) if k not in (4, 5)]
    check_exact(trs, x, u, st)


def test_reset_without_applied_cmd_is_not_paired_across() -> None:
    """The simulator's reset contract: no applied_cmd for the last state before a jump, next state >= 2 dt later."""
    x1, u1, st1 = trajectory(5, seed=1)
    x2, u2, _ = trajectory(5, seed=2)
    st2 = [st1[-1] + 2 * DT + k * DT for k in range(5)]
    ev = stream(x1, u1, st1)[:-1] + stream(x2, u2, st2)  # drop the applied_cmd of the last state of episode 1
    p = StampPairer(next_cfg())
    trs = feed(p, ev)
    assert [t.stamp_ns for t in trs] == st1[:-1] + st2[:-1]
    check_exact([t for t in trs if t.stamp_ns in st1], x1, u1, st1)
    check_exact([t for t in trs if t.stamp_ns in st2], x2, u2, st2)


def test_stamps_within_one_microsecond_are_the_same_stamp() -> None:
    x, u, st = trajectory(6)
    s_jit = [0, 500, -500, 400, -300, 0]  # consecutive states stay within dt +- 1 us
    c_jit = [1000, -1000, 700, 0, -600, 0]  # each command within 1 us of its state
    ev = []
    for k, t in enumerate(st):
        ev += [("state", t + s_jit[k], x[k]), ("applied_cmd", t + s_jit[k] + c_jit[k], u[k])]
    trs = feed(StampPairer(next_cfg()), ev)
    assert [t.stamp_ns for t in trs] == [t + j for t, j in zip(st[:-1], s_jit)]
    # 1.1 us off is another stamp: the command of step 2 finds no state, so only step 2 is not paired
    ev[5] = ("applied_cmd", st[2] + s_jit[2] + 1_100, u[2])
    p = StampPairer(next_cfg())
    trs2 = feed(p, ev)
    assert [t.stamp_ns for t in trs2] == [st[k] + s_jit[k] for k in (0, 1, 3, 4)]


def test_bad_events_are_counted_and_good_ones_still_pair() -> None:
    x, u, st = trajectory(30)
    good = stream(x, u, st)
    bad = {
        4: ("state", st[4], np.array([np.nan, 0.0])),  # before the good x_4: NaN is dropped, x_4 still pairs
        9: ("applied_cmd", st[9], np.array([1.0, 2.0])),  # wrong length
        12: ("state", -5, x[0]),  # negative stamp
        15: ("state", st[15], x[15] + 1.0),  # inserted after the good x_15: duplicate (first one wins)
        20: ("applied_cmd", st[3] + DT // 2, u[3]),  # old command: out of order
    }
    ev: list[tuple[str, int, np.ndarray]] = []
    for k in range(len(st)):
        if k == 4:
            ev.append(bad[4])
        ev += good[2 * k : 2 * k + 2]
        if k in (9, 12, 15, 20):
            ev.append(bad[k])
    ev.append(good[-1])  # exact duplicate of the last command
    p = StampPairer(next_cfg())
    results = [p.add(*e) for e in ev]
    trs = [t for r in results for t in r.transitions]
    assert [t.stamp_ns for t in trs] == st[:-1]
    check_exact(trs, x, u, st)
    c = p.counts
    assert (c["nan"], c["shape"], c["stamp"], c["duplicate"], c["out_of_order"]) == (1, 1, 1, 2, 1)
    reasons = [r.rejected for r in results if r.rejected]
    assert sorted(reasons) == sorted(["nan", "shape", "stamp", "duplicate", "out_of_order", "duplicate"])
    assert all(r.detail for r in results if r.rejected)


def test_late_command_beyond_the_window_is_dropped() -> None:
    x, u, st = trajectory(40)
    p = StampPairer(next_cfg(window=10))  # remembers the newest 10 states
    ev = [e for e in stream(x, u, st) if not (e[0] == "applied_cmd" and e[1] == st[2])]
    trs = feed(p, ev)
    r = p.add("applied_cmd", st[2], u[2])  # arrives 37 steps late
    assert r.rejected == "late" and r.transitions == [] and "older than everything" in r.detail
    assert len(trs) == 38 and st[2] not in [t.stamp_ns for t in trs]
    # x_2 was the target of step 1, so no message was orphaned; slot 2 expired incomplete
    assert p.counts["unpaired"] == 0 and p.counts["expired"] >= 1 and p.counts["late"] == 1


def test_orphaned_command_is_counted_when_it_expires() -> None:
    x, u, st = trajectory(40)
    p = StampPairer(next_cfg(window=5))
    feed(p, stream(x, u, st[:20]))
    feed(p, [("applied_cmd", st[19] + 50_000_000, u[0])])  # a command between two states
    feed(p, stream(x[20:], u[20:], st[20:]))
    assert p.counts["unpaired"] == 1 and p.counts["paired"] == 39


def test_retention_counts_states_not_seconds() -> None:
    """Commands lagging 500 steps behind their states still pair: the window is in states, so it does not
    matter how fast stamps advance (a lockstep simulator may run far faster than real time)."""
    x, u, st = trajectory(1200, seed=4)
    states = [("state", t, x[k]) for k, t in enumerate(st)]
    cmds = [("applied_cmd", t, u[k]) for k, t in enumerate(st)]
    ev = states[:500] + [e for pair in zip(states[500:], cmds) for e in pair] + cmds[700:]
    p = StampPairer(next_cfg(window=600))
    trs = feed(p, ev)
    assert len(trs) == 1199 and p.counts["late"] == 0
    check_exact(trs, x, u, st)


def test_memory_is_bounded_by_the_window_and_the_slot_cap() -> None:
    p = StampPairer(next_cfg(window=10))
    for k in range(5000):  # states only: nothing ever pairs
        p.add("state", T0 + k * DT, np.zeros(2))
    assert p.pending <= 10
    assert p.counts["unpaired"] >= 4980
    q = StampPairer(next_cfg(window=20, max_slots=50))
    rng = np.random.default_rng(0)
    for k in range(2000):  # commands with scattered stamps and no states: only the cap bounds them
        q.add("applied_cmd", T0 + k * DT + int(rng.integers(0, 10**6)), np.zeros(1))
    assert q.pending <= 50 and q.counts["overflow"] >= 1950


def test_bogus_future_stamps_do_not_block_a_source() -> None:
    x, u, st = trajectory(40)
    p = StampPairer(next_cfg())
    trs = feed(p, stream(x[:10], u[:10], st[:10]))
    r = p.add("applied_cmd", st[9] + 10**15, u[0])  # bogus command far in the future
    assert r.rejected is None
    trs += feed(p, stream(x[10:20], u[10:20], st[10:20]))
    # the next commands looked out of order against it; three increasing ones show it to be an outlier: it is
    # dropped and counted, and the commands are used after all: no transition lost
    assert p.counts["outlier"] == 1 and p.counts["out_of_order"] == 0 and p.counts["reanchors"] == 0
    assert [t.stamp_ns for t in trs] == st[:19]
    p.add("state", st[19] + 10**15, x[0])  # bogus state far in the future
    res = [p.add(*e) for e in stream(x[20:], u[20:], st[20:])]
    trs2 = [t for r in res for t in r.transitions]
    # the real states outnumber it: an outlier, not a clock restart; every good transition pairs, 19 -> 20 too
    assert p.counts["time_resets"] == 0 and p.counts["outlier"] == 2 and p.counts["out_of_order"] == 0
    assert any("outlier" in r.detail for r in res)
    assert [t.stamp_ns for t in trs2] == st[19:-1]
    check_exact(trs + trs2, x, u, st)
    assert p.counts["unpaired"] == 0


@pytest.mark.parametrize("n_wild", [1, 2])
def test_wild_state_stamps_lose_no_pending_transition(n_wild: int) -> None:
    """One or two states stamped far in the future while transitions are pending: rejected as outliers, every
    good transition still pairs (the pending ones included), and the wild ones are counted under a reason."""
    x, u, st = trajectory(30)
    p = StampPairer(next_cfg())
    ev = merge(stream(x, u, st)[0::2], stream(x, u, st)[1::2], np.random.default_rng(1), ahead=3, lag=3)
    cut = next(i for i, e in enumerate(ev) if e[:2] == ("state", st[12]))  # commands may be ahead: pending
    trs = feed(p, ev[:cut])
    for i in range(n_wild):
        assert p.add("state", st[-1] + (i + 1) * 10**12, x[0]).rejected is None
    trs += feed(p, ev[cut:])
    assert sorted(t.stamp_ns for t in trs) == st[:-1]
    check_exact(trs, x, u, st)
    assert p.counts["outlier"] == n_wild and p.counts["time_resets"] == 0
    assert p.counts["out_of_order"] == 0 and p.counts["unpaired"] == 0


def test_simulator_restart_with_the_same_stamps_is_a_new_clock() -> None:
    x, u, st = trajectory(30)
    p = StampPairer(next_cfg())
    trs = feed(p, stream(x, u, st))
    x2, u2, _ = trajectory(10, seed=3)
    r = [p.add(*e) for e in stream(x2, u2, st[:10])]  # stamps start again at T0: duplicates at first ...
    trs2 = [t for res in r for t in res.transitions]
    assert p.counts["time_resets"] == 1 and any("restarted" in res.detail for res in r)
    # ... until three increasing ones reveal the restart; they are then used: nothing of the new run is lost
    assert [t.stamp_ns for t in trs2] == st[:9] and p.counts["duplicate"] == 0
    check_exact(trs, x, u, st)
    check_exact(trs2, x2, u2, st[:10])


def test_random_faults_never_mispair_and_keep_every_good_transition() -> None:
    """Drops, duplicates, corrupt vectors and interleavings: emitted == exactly the complete good steps."""
    x, u, st = trajectory(400, seed=5)
    rng = np.random.default_rng(11)
    keep_state = rng.random(400) > 0.05
    keep_cmd = rng.random(400) > 0.05
    ev: list[tuple[str, int, np.ndarray]] = []
    for k, t in enumerate(st):
        pair = []
        if keep_state[k]:
            pair.append(("state", t, x[k]))
        if keep_cmd[k]:
            pair.append(("applied_cmd", t, u[k]))
        if rng.random() < 0.5:
            pair.reverse()
        for e in pair:
            ev.append(e)
            roll = rng.random()
            if roll < 0.05:
                ev.append(e)  # duplicate
            elif roll < 0.08:
                ev.append((e[0], e[1] + DT // 2, np.full_like(e[2], np.inf)))  # corrupt, between steps
    p = StampPairer(next_cfg())
    trs = feed(p, ev)
    expected = [st[k] for k in range(399) if keep_state[k] and keep_cmd[k] and keep_state[k + 1]]
    assert sorted(t.stamp_ns for t in trs) == expected
    check_exact(trs, x, u, st)


@pytest.mark.parametrize("seed", range(5))
def test_fuzz_reordered_and_conflicting_input_never_mispairs(seed: int) -> None:
    """Adjacent swaps within a topic, conflicting duplicates, drops: whatever is emitted is exactly right and
    emitted once, and every step whose three messages arrived cleanly in order is emitted."""
    x, u, st = trajectory(300, seed=seed)
    rng = np.random.default_rng(100 + seed)
    states = [("state", t, x[k]) for k, t in enumerate(st) if rng.random() > 0.03]
    cmds = [("applied_cmd", t, u[k]) for k, t in enumerate(st) if rng.random() > 0.03]
    for seq in (states, cmds):
        for i in range(len(seq) - 1):
            if rng.random() < 0.03:
                seq[i], seq[i + 1] = seq[i + 1], seq[i]
        for i in sorted(rng.choice(len(seq), size=8, replace=False), reverse=True):
            kind, t, v = seq[i]
            seq.insert(i + 1, (kind, t, v + 1.0))  # a conflicting duplicate after the original
    ev = merge(states, cmds, rng)
    p = StampPairer(next_cfg())
    trs = feed(p, ev)
    check_exact(trs, x, u, st)
    stamps = [t.stamp_ns for t in trs]
    assert len(stamps) == len(set(stamps))
    assert p.counts["duplicate"] >= 8 and p.counts["out_of_order"] >= 1
    # a step whose messages arrived in order, undisturbed, is never lost
    order_ok = {t for t in st}
    for seq in (states, cmds):
        seen: set[int] = set()
        newest = -1
        for _, t, _ in seq:
            if t < newest or t in seen:
                order_ok.discard(t)
            seen.add(t)
            newest = max(newest, t)
    have_s = {t for _, t, _ in states}
    have_c = {t for _, t, _ in cmds}
    must = [t for t in st[:-1] if t in have_s and t in have_c and t + DT in have_s and {t, t + DT} <= order_ok]
    assert set(must) <= set(stamps)


# ------------------------------------------------------------------------------------------------ same
def test_same_stamp_mode_pairs_three_messages_in_any_order() -> None:
    rng = np.random.default_rng(2)
    n = 50
    xs, us, ys = rng.normal(size=(n, 6)), rng.normal(size=(n, 6)), rng.normal(size=(n, 3))
    stamps = [T0 + k * 700_000_000 for k in range(n)]
    ev: list[tuple[str, int, np.ndarray]] = []
    for k, t in enumerate(stamps):
        trio = [("state", t, xs[k]), ("applied_cmd", t, us[k]), ("target", t, ys[k])]
        ev += [trio[i] for i in rng.permutation(3)]
    ev.insert(10, ("target", stamps[3], ys[3]))  # a duplicate target after its trio completed
    p = StampPairer(same_cfg())
    trs = feed(p, ev)
    assert [t.stamp_ns for t in trs] == stamps
    for tr, k in zip(trs, range(n)):
        np.testing.assert_array_equal(tr.x, xs[k])
        np.testing.assert_array_equal(tr.u, us[k])
        np.testing.assert_array_equal(tr.y, ys[k])
    assert p.counts["duplicate"] == 1 and p.counts["paired"] == n


def test_same_stamp_mode_needs_identical_stamps() -> None:
    p = StampPairer(same_cfg())
    p.add("state", T0, np.zeros(6))
    p.add("applied_cmd", T0, np.zeros(6))
    assert p.add("target", T0 + 1_500, np.zeros(3)).transitions == []
    t1 = T0 + 10**9
    p.add("applied_cmd", t1, np.zeros(6))
    p.add("target", t1 - 1_000, np.ones(3))
    assert p.add("state", t1 + 800, np.zeros(6)).transitions[0].y.tolist() == [1.0, 1.0, 1.0]
    assert p.counts["paired"] == 1


def test_config_validation_and_target_kind_in_next_mode() -> None:
    with pytest.raises(ValueError, match="dt_ns"):
        PairingConfig(mode="next", n_x=2, n_u=1, n_y=2, dt_ns=0)
    with pytest.raises(ValueError, match="window"):
        PairingConfig(mode="next", n_x=2, n_u=1, n_y=2, dt_ns=DT, window=1)
    with pytest.raises(ValueError, match="max_slots"):
        PairingConfig(mode="next", n_x=2, n_u=1, n_y=2, dt_ns=DT, window=100, max_slots=10)
    with pytest.raises(ValueError, match="mode"):
        PairingConfig(mode="sometimes", n_x=2, n_u=1, n_y=2)
    with pytest.raises(ValueError, match="kind"):
        StampPairer(next_cfg()).add("target", T0, np.zeros(2))
    cfg = PairingConfig.for_system(get_system("friction"), "next")
    assert (cfg.dt_ns, cfg.tolerance_ns, cfg.n_x, cfg.n_u) == (DT, 1000, 2, 1)


def test_total_counts_sums_sources() -> None:
    a, b = StampPairer(next_cfg(), 0), StampPairer(next_cfg(), 1)
    a.add("state", T0, np.zeros(2))
    b.add("state", T0, np.zeros(3))
    tot = total_counts([a.counts, b.counts])
    assert set(COUNTERS) <= set(tot) and tot["received/state"] == 2 and tot["shape"] == 1
