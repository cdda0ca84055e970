"""ROS-free tests of the simulator cores (saml_ros.core.worlds.sim_core, the paddle-ball core): stamping, pairing rule,
command validation / holding / timeouts, lockstep waiting and misses, episodes, resets, ground contact."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest

from saml_ros.core.params import coerce_param
from saml_ros.core.systems import get_entry, get_system
from saml_ros.core.worlds.sim_core import (
    APPLIED,
    CLOCK,
    LOCKSTEP_T0_NS,
    STATE,
    CommandHolder,
    CommandRejected,
    CommandValidator,
    FastStep,
    SimConfig,
    SteppedSim,
    build_stepped_sim,
)
from saml_ros.systems.friction.model import FrictionDoubleIntegrator
from saml_ros.systems.friction.world import friction_model, friction_start
from saml_ros.systems.quadrotor.model import Quadrotor
from saml_ros.systems.quadrotor.world import ground_contact, quadrotor_start

DT_NS = 100_000_000  # both time-stepped systems use dt = 0.1 s
QUAD_START = (0.0, 0.0, 2.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)


def kinds(outputs: list) -> list[str]:
    return [k for k, _, _ in outputs]


def only(outputs: list, kind: str) -> tuple[np.ndarray, int]:
    found = [(v, t) for k, v, t in outputs if k == kind]
    assert len(found) == 1, (kind, kinds(outputs))
    return found[0]


# ------------------------------------------------------------------------------------------ validation
def test_validator_rejects_malformed_and_far_commands_and_clips_near_ones() -> None:
    v = CommandValidator(np.array([-10.0]), np.array([10.0]), reject_margin=0.5)  # reject beyond +-20
    for bad, reason in (([np.nan], "nan"), ([np.inf], "nan"), ([1.0, 2.0], "shape"), ([], "shape"),
                        ([20.5], "bounds"), ([-25.0], "bounds"), (["x"], "format")):
        with pytest.raises(CommandRejected) as exc:
            v.check(bad)
        assert exc.value.reason == reason, bad
    u, clipped = v.check([3.0])
    assert u.tolist() == [3.0] and not clipped
    u, clipped = v.check([12.0])
    assert u.tolist() == [10.0] and clipped
    u, clipped = v.check([-19.9])
    assert u.tolist() == [-10.0] and clipped


def test_validator_margin_is_relative_to_each_components_range() -> None:
    quad = Quadrotor()
    v = CommandValidator(quad.control_low, quad.control_high, reject_margin=0.5)  # [0, 10] -> accept [-5, 15]
    assert v.check([14.9, 0.0, -4.9, 5.0])[1]
    with pytest.raises(CommandRejected):
        v.check([15.1, 0.0, 0.0, 5.0])


def test_holder_holds_for_the_timeout_then_gives_the_safe_default() -> None:
    h = CommandHolder(np.array([0.0]), timeout_ns=500)
    u, fresh = h.current(0)
    assert not fresh and u.tolist() == [0.0]
    h.accept(np.array([2.0]), stamp_ns=7, now_ns=1000)
    assert h.current(1500) == (h.u, True)
    u, fresh = h.current(1501)
    assert not fresh and u.tolist() == [0.0]
    forever = CommandHolder(np.array([0.0]), timeout_ns=0)
    forever.accept(np.array([1.0]), 0, 0)
    assert forever.current(10**15)[1]


# ------------------------------------------------------------------------------------ lockstep stepping
def test_lockstep_waits_for_the_stamped_cmd_and_applies_exactly_that_command() -> None:
    quad = Quadrotor()
    sim = build_stepped_sim(quad, SimConfig(mode="lockstep", initial_state=QUAD_START))
    out = sim.begin(now_ns=0)
    assert kinds(out) == [CLOCK, STATE]
    x, t = only(out, STATE)
    assert t == LOCKSTEP_T0_NS and only(out, CLOCK)[1] == t
    rng = np.random.default_rng(1)
    for _ in range(20):
        u = quad.hover_thrust() + rng.uniform(-0.5, 0.5, 4)
        # answers to other stamps are dropped and nothing moves
        assert sim.on_cmd(u, t - DT_NS, now_ns=0) == [] and sim.on_cmd(u, t + 1, now_ns=0) == []
        out = sim.on_cmd(u, t, now_ns=0)
        assert kinds(out) == [APPLIED, CLOCK, STATE]
        applied, t_applied = only(out, APPLIED)
        x_next, t_next = only(out, STATE)
        assert t_applied == t and t_next == t + DT_NS and only(out, CLOCK)[1] == t_next
        np.testing.assert_array_equal(applied, u)
        np.testing.assert_allclose(x_next, quad.true_step_np(x, u), rtol=0, atol=1e-12)
        x, t = x_next, t_next
    assert sim.counters["rejected/late"] == 20 and sim.counters["rejected/stamp"] == 20
    assert sim.counters["steps"] == 20 and sim.counters["lockstep_misses"] == 0


def test_lockstep_rejects_bad_commands_keeps_waiting_and_clips_near_ones() -> None:
    fr = get_system("friction")
    sim = build_stepped_sim(fr, SimConfig(mode="lockstep", initial_state=(1.0, 0.0)))
    _, t = only(sim.begin(0), STATE)
    for bad in ([np.nan], [1.0, 2.0], [100.0]):
        assert sim.on_cmd(bad, t, 0) == []
    assert sim.counters["rejected/nan"] == 1 and sim.counters["rejected/shape"] == 1
    assert sim.counters["rejected/bounds"] == 1 and sim.awaiting == t
    out = sim.on_cmd([11.0], t, 0)
    assert only(out, APPLIED)[0].tolist() == [10.0] and sim.counters["cmd_clipped"] == 1


def test_lockstep_miss_holds_the_last_command_then_the_safe_default() -> None:
    fr = get_system("friction")
    cfg = SimConfig(mode="lockstep", initial_state=(0.0, 0.0), lockstep_timeout=0.5, cmd_timeout=0.25)
    sim = build_stepped_sim(fr, cfg)
    _, t = only(sim.begin(now_ns=0), STATE)
    out = sim.on_cmd([4.0], t, now_ns=10)
    assert only(out, APPLIED)[0].tolist() == [4.0]
    assert sim.poll(now_ns=10 + 499_999_999) == []  # still waiting
    applied = []
    now = 10
    for _ in range(4):  # misses at sim ages 0.1, 0.2 (held), 0.3, 0.4 s (> cmd_timeout: safe default)
        now += 500_000_001
        out = sim.poll(now)
        applied.append(only(out, APPLIED)[0][0])
    assert applied == [4.0, 4.0, 0.0, 0.0]
    assert sim.counters["lockstep_misses"] == 4 and sim.counters["cmd_timeouts"] == 2


def test_episode_restart_and_reset_skip_applied_cmd_and_two_dt() -> None:
    fr = get_system("friction")
    sim = build_stepped_sim(fr, SimConfig(mode="lockstep", episode_steps=3, seed=5))
    out = sim.begin(0)
    stamps, applied, starts = [only(out, STATE)[1]], [], [only(out, STATE)[0]]
    for i in range(9):
        if i == 5:
            sim.request_reset()
        out = sim.on_cmd([1.0], stamps[-1], 0)
        x, t = only(out, STATE)
        if APPLIED in kinds(out):
            applied.append(only(out, APPLIED)[1])
        else:
            starts.append(x)
        stamps.append(t)
    gaps = np.diff(stamps) // DT_NS
    # 3 steps, restart (+2 dt), 1 step, reset at the next advance (+2 dt), 3 steps
    assert gaps.tolist() == [1, 1, 1, 2, 1, 2, 1, 1, 1]
    assert applied == [s for s, g in zip(stamps[:-1], gaps) if g == 1]
    assert sim.counters["episodes"] == 3 and sim.counters["resets"] == 1 and sim.counters["episodes_completed"] == 1
    for x in starts:
        assert -2.0 <= x[0] <= 2.0 and x[1] == 0.0
    assert len({float(x[0]) for x in starts}) == len(starts)  # freshly sampled


def test_max_sim_time_ends_the_run() -> None:
    fr = get_system("friction")
    sim = build_stepped_sim(fr, SimConfig(mode="lockstep", max_sim_time=0.5))
    _, t = only(sim.begin(0), STATE)
    n = 0
    while not sim.done:
        _, t = only(sim.on_cmd([0.0], t, 0), STATE)
        n += 1
    assert n == 5 and t - LOCKSTEP_T0_NS == 500_000_000
    assert sim.on_cmd([0.0], t, 0) == [] and sim.poll(10**18) == []


def test_divergence_restarts_the_episode() -> None:
    fr = FrictionDoubleIntegrator()
    sim = SteppedSim(friction_model(fr), SimConfig(mode="lockstep"), step_fn=lambda x, u: x * np.nan)
    _, t = only(sim.begin(0), STATE)
    out = sim.on_cmd([0.0], t, 0)
    assert kinds(out) == [CLOCK, STATE] and only(out, STATE)[1] == t + 2 * DT_NS
    assert sim.counters["diverged"] == 1 and np.all(np.isfinite(only(out, STATE)[0]))


# ------------------------------------------------------------------------------------------- realtime
def test_realtime_uses_the_newest_command_and_times_out_to_the_safe_default() -> None:
    quad = Quadrotor()
    sim = build_stepped_sim(quad, SimConfig(mode="realtime", cmd_timeout=0.3, initial_state=QUAD_START),
                            publish_clock=False)
    assert sim.tick(0) == []  # not started
    t0 = 5 * 10**18 // 10**9  # realtime stamps start at the wall time
    out = sim.begin(0, t0_ns=t0)
    assert kinds(out) == [STATE] and only(out, STATE)[1] == t0
    np.testing.assert_array_equal(only(sim.tick(1), APPLIED)[0], quad.hover_thrust())
    assert sim.counters["cmd_timeouts"] == 1
    u = np.array([5.0, 5.0, 5.0, 5.0])
    assert sim.on_cmd(u, t0 + DT_NS, now_ns=100) == []
    out = sim.tick(200)
    applied, t_applied = only(out, APPLIED)
    assert t_applied == t0 + DT_NS and only(out, STATE)[1] == t0 + 2 * DT_NS
    np.testing.assert_array_equal(applied, u)
    assert sim.on_cmd(quad.hover_thrust(), t0, now_ns=250) == []  # older stamp than the held one
    assert sim.counters["rejected/out_of_order"] == 1
    np.testing.assert_array_equal(only(sim.tick(100 + 300_000_000), APPLIED)[0], u)
    np.testing.assert_array_equal(only(sim.tick(101 + 300_000_000), APPLIED)[0], quad.hover_thrust())
    assert sim.counters["cmd_timeouts"] == 2 and sim.poll(10**18) == []  # no lockstep misses in realtime


# ------------------------------------------------------------------------------------- ground contact
def test_ground_contact_function() -> None:
    x = np.zeros(13)
    x[2], x[5], x[3], x[10:13] = 0.05, -1.0, 0.7, (0.1, 0.2, 0.3)
    y, touched = ground_contact(x, 0.1)
    assert touched and y[2] == 0.1 and y[5] == 0.0 and y[3] == 0.7 and not y[10:13].any()
    assert x[2] == 0.05  # input untouched
    x[2], x[5] = 0.1, 0.5  # at the ground, lifting off
    assert ground_contact(x, 0.1) == (x, False)
    x[5] = -0.1  # at the ground, pushed down
    assert ground_contact(x, 0.1)[1]
    x[2] = 0.3
    assert not ground_contact(x, 0.1)[1]


def test_quadrotor_on_the_ground_never_sinks_and_contact_steps_are_not_learning_data() -> None:
    quad = Quadrotor()
    start = list(QUAD_START)
    start[2] = 0.3
    sim = build_stepped_sim(quad, SimConfig(mode="lockstep", initial_state=tuple(start)), landing_height=0.1)
    x, t = only(sim.begin(0), STATE)
    n_applied = 0
    for _ in range(30):  # motors off: falls, lands, rests
        out = sim.on_cmd(np.zeros(4), t, 0)
        x_next, t = only(out, STATE)
        assert x_next[2] >= 0.1
        if APPLIED in kinds(out):
            n_applied += 1
            np.testing.assert_allclose(x_next, quad.true_step_np(x, np.zeros(4)), atol=1e-12)
        x = x_next
    assert x[2] == 0.1 and x[5] == 0.0
    assert sim.counters["ground_contacts"] == 30 - n_applied and 0 < n_applied < 5


# ---------------------------------------------------------------------------------------- start states
def test_start_samplers_follow_the_paper_tasks_and_are_seeded() -> None:
    rng = np.random.default_rng(0)
    p = np.array([friction_start(rng) for _ in range(500)])
    assert p[:, 0].min() >= -2 and p[:, 0].max() <= 2 and p[:, 0].std() > 1.0 and not p[:, 1].any()
    quad = Quadrotor()
    xs = np.array([quadrotor_start(quad, rng) for _ in range(500)])
    assert np.all(np.abs(xs[:, :2]) <= 2) and xs[:, 2].min() >= 1 and xs[:, 2].max() <= 3
    np.testing.assert_array_equal(xs[:, 6:10], np.tile([1.0, 0, 0, 0], (500, 1)))
    assert not xs[:, 3:6].any() and not xs[:, 10:].any()
    a = build_stepped_sim(quad, SimConfig(seed=3)).begin(0)
    b = build_stepped_sim(quad, SimConfig(seed=3)).begin(0)
    c = build_stepped_sim(quad, SimConfig(seed=4)).begin(0)
    assert np.array_equal(only(a, STATE)[0], only(b, STATE)[0])
    assert not np.array_equal(only(a, STATE)[0], only(c, STATE)[0])


def test_initial_state_is_checked_and_its_quaternion_normalised() -> None:
    quad = Quadrotor()
    with pytest.raises(ValueError, match="initial_state"):
        build_stepped_sim(quad, SimConfig(initial_state=(1.0, 2.0)))
    with pytest.raises(ValueError, match="initial_state"):
        build_stepped_sim(get_system("friction"), SimConfig(initial_state=(math.nan, 0.0)))
    start = list(QUAD_START)
    start[6] = 2.0
    x, _ = only(build_stepped_sim(quad, SimConfig(initial_state=tuple(start))).begin(0), STATE)
    assert x[6] == 1.0
    with pytest.raises(ValueError, match="mode"):
        SimConfig(mode="fast")


# -------------------------------------------------------------------------------------------- helpers
@pytest.mark.parametrize("name", ["friction", "quadrotor"])
def test_fast_step_is_true_step(name: str) -> None:
    system = get_system(name)
    step = FastStep(system)
    assert step.traced
    x, u = system.sample_inputs(50, np.random.default_rng(7))
    expected = system.true_step_np(x, u)
    for xi, ui, yi in zip(x, u, expected):
        np.testing.assert_array_equal(step(xi, ui), yi)


@pytest.mark.parametrize("name", ["friction", "quadrotor"])
def test_the_simulators_numpy_step_is_true_step(name: str) -> None:
    """The simulator nodes step the numpy twin of the true dynamics (no torch in their processes): it equals
    ``true_step`` (torch) to rounding on the training distribution and on a closed episode of the simulator."""
    entry = get_entry(name)
    system = entry.make_system()
    assert entry.stepped_model is not None
    model = entry.stepped_model(system)
    assert model.step is not None
    x, u = system.sample_inputs(500, np.random.default_rng(7))
    expected = system.true_step_np(x, u)
    got = np.stack([model.step(xi, ui) for xi, ui in zip(x, u)])
    np.testing.assert_allclose(got, expected, rtol=1e-12, atol=1e-12)
    sim = SteppedSim(model, SimConfig(mode="lockstep", seed=3))
    assert sim.step_fn is model.step
    torch_sim = SteppedSim(model, SimConfig(mode="lockstep", seed=3), step_fn=FastStep(system))
    (a, t), (b, _) = only(sim.begin(0), STATE), only(torch_sim.begin(0), STATE)
    np.testing.assert_array_equal(a, b)
    rng = np.random.default_rng(1)
    span = 0.3 * (np.asarray(system.control_high) - np.asarray(system.control_low))
    for _ in range(150):  # commands around the safe one (the quadrotor's hover): the episode moves both ways
        u = system.safe_control() + rng.uniform(-span, span)
        a, t_next = only(sim.on_cmd(u, t, 0), STATE)
        b = only(torch_sim.on_cmd(u, t, 0), STATE)[0]
        np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-9)
        t = t_next
    assert sim.counters["steps"] == 150


def test_fast_step_traces_a_built_in_system_once_per_set_of_parameters() -> None:
    """A second plant of an equal system reuses the checked trace; other parameters (more drag) get their own trace,
    equal to their own dynamics, not the first one's."""
    from saml_ros.systems.quadrotor.model import Quadrotor

    first, again, draggy = FastStep(Quadrotor()), FastStep(Quadrotor()), FastStep(Quadrotor(drag=0.3))
    assert first.traced and again.traced and draggy.traced
    assert again._fn is first._fn and draggy._fn is not first._fn
    x, u = draggy.system.sample_inputs(20, np.random.default_rng(3))
    expected = draggy.system.true_step_np(x, u)
    assert not np.array_equal(expected, first.system.true_step_np(x, u))
    for xi, ui, yi in zip(x, u, expected):
        np.testing.assert_array_equal(draggy(xi, ui), yi)


def test_coerce_param_accepts_yaml_spellings_and_names_bad_ones() -> None:
    assert coerce_param("rate_hz", 20, 10.0) == 20.0 and isinstance(coerce_param("r", 20, 1.0), float)
    assert coerce_param("episode_steps", 5.0, 0) == 5
    assert coerce_param("initial_state", None, []) == []
    assert coerce_param("initial_state", [1, 2.5], []) == [1.0, 2.5]
    for value, default in ((True, 1.0), ("x", 1.0), (2.5, 0), (1, True), ([True], []), (math.nan, 1.0)):
        with pytest.raises(ValueError, match="parameter 'p'"):
            coerce_param("p", value, default)


# ---------------------------------------------------------------------------------------- paddle ball
@pytest.fixture(scope="module")
def ball_world() -> Any:
    from saml_ros.systems.paddle_ball.world import PaddleBallWorld

    return PaddleBallWorld(seed=0)


def test_paddle_ball_lockstep_publishes_consistent_impact_triples(ball_world: Any) -> None:
    from saml_ros.core.worlds.sim_core import FLIGHT, TARGET
    from saml_ros.systems.paddle_ball.sim import PaddleBallSim

    sim = PaddleBallSim(ball_world, SimConfig(mode="lockstep", initial_state=(0, 0, 1.0, 0, 0, 0)),
                        flight_rate_hz=30.0)
    out = sim.begin(0)
    x, stamp = only(out, STATE)
    assert abs(x[2]) < 1e-9 and x[5] < -4.0  # the ball predicted at the impact plane, falling
    u = np.array([0.0, 0.0, 1.0, -math.sin(0.2), 0.0, math.cos(0.2)])  # real normal (bias 0.2 rad) vertical
    assert sim.on_cmd(u, stamp - 1, 0) == []  # not the awaited stamp
    assert sim.on_cmd([0, 0, 1.0, 0, 0, 0.1], stamp, 0) == []  # normal far too short: rejected
    assert sim.counters["rejected/bounds"] == 1
    triples = 0
    for _ in range(4):
        out = sim.on_cmd(u, stamp, 0)
        assert FLIGHT in kinds(out)
        if APPLIED in kinds(out):
            applied, t_a = only(out, APPLIED)
            y, t_y = only(out, TARGET)
            assert t_a == t_y == stamp
            np.testing.assert_allclose(applied, np.concatenate((u[:3], u[3:] / np.linalg.norm(u[3:]))))
            assert y[2] > 2.0  # bounced up
            triples += 1
        x_next, t_next = only(out, STATE)
        assert t_next > stamp and abs(x_next[2]) < 1e-9
        stamp = t_next
    assert triples >= 3 and sim.counters["steps"] == triples


def test_paddle_ball_realtime_bounces_on_the_safe_default_and_restarts_lost_balls(ball_world: Any) -> None:
    from saml_ros.core.worlds.sim_core import TARGET
    from saml_ros.systems.paddle_ball.sim import PaddleBallSim

    sim = PaddleBallSim(ball_world, SimConfig(mode="realtime", seed=2, cmd_timeout=0.1), publish_clock=False,
                        flight_rate_hz=0.0, tick_seconds=0.02)
    out = sim.begin(0, t0_ns=10**18)
    states = {t: x for k, x, t in out if k == STATE}
    applied: dict[int, np.ndarray] = {}
    targets: dict[int, np.ndarray] = {}
    for i in range(1, 400):  # 8 s of simulated time
        for kind, vec, t in sim.tick(now_ns=i * 20_000_000):
            sink: dict[str, dict[int, Any]] = {STATE: states, APPLIED: applied, TARGET: targets}
            sink[kind][t] = vec
    assert len(targets) >= 3 and set(applied) == set(targets) and set(targets) <= set(states)
    for t in targets:
        np.testing.assert_array_equal(applied[t], [0.0, 0.0, 0.0, 0.0, 0.0, 1.0])  # level paddle at rest
    stamps = sorted(states)
    assert stamps[0] > 10**18 and all(np.diff(stamps) > 0)
    assert sim.counters["cmd_timeouts"] >= 3 and sim.counters["episodes"] >= 1
