"""MuJoCo paddle-ball world: restitution, controller, normal bias, failure detection, data collection."""

from __future__ import annotations

import math

import mujoco
import numpy as np
import pytest

from saml_ros.systems.paddle_ball.bounces import CollectStats, collect_impacts, impacts_to_arrays, random_commands
from saml_ros.systems.paddle_ball.model import PaddleBall
from saml_ros.systems.paddle_ball.world import Impact, PaddleBallWorld

BIAS = PaddleBall().normal_bias_y


def real_normal_command(n_real: np.ndarray, bias: float = BIAS) -> np.ndarray:
    """The commanded normal whose realised normal R_y(bias) n_cmd is ``n_real``."""
    c, s = math.cos(-bias), math.sin(-bias)
    return np.array([c * n_real[0] + s * n_real[2], n_real[1], -s * n_real[0] + c * n_real[2]])


LEVEL = real_normal_command(np.array([0.0, 0.0, 1.0]))


@pytest.fixture(scope="module")
def world() -> PaddleBallWorld:
    return PaddleBallWorld(seed=0)


def drop(world: PaddleBallWorld, u: np.ndarray, height: float = 1.0) -> Impact:
    world.reset(np.array([0.0, 0.0, height]), np.zeros(3))
    world.set_command(u)
    impact = world.run_until_impact(max_time=2.0)
    assert impact is not None and impact.on_plan
    return impact


@pytest.mark.parametrize("restitution", [0.8, 0.6])
def test_level_still_paddle_rebounds_vertically_with_the_system_restitution(restitution: float) -> None:
    world = PaddleBallWorld(PaddleBall(restitution_true=restitution))
    imp = drop(world, np.r_[0.0, 0.0, 0.0, LEVEL])
    assert imp.pre[5] == pytest.approx(-math.sqrt(2 * 9.81 * 1.0), rel=0.02)
    assert -imp.post_velocity[2] / imp.pre[5] == pytest.approx(restitution, abs=0.05)
    assert np.abs(imp.post_velocity[:2]).max() < 1e-6
    assert np.abs(imp.paddle_velocity).max() < 1e-9
    assert 0.0 <= imp.pre[2] < 0.02  # met at the impact plane z = 0


def test_upward_paddle_velocity_gives_a_faster_rebound(world: PaddleBallWorld) -> None:
    still = drop(world, np.r_[0.0, 0.0, 0.0, LEVEL])
    swung = drop(world, np.r_[0.0, 0.0, 1.5, LEVEL])
    np.testing.assert_allclose(swung.paddle_velocity, [0.0, 0.0, 1.5], atol=1e-9)
    assert swung.post_velocity[2] > still.post_velocity[2] + 2.0  # analytic: + (1 + 0.8) * 1.5 = 2.7 m/s
    assert swung.post_velocity[2] == pytest.approx(0.8 * -swung.pre[5] + 1.8 * 1.5, rel=0.05)


@pytest.mark.parametrize(("n_real", "axis"), [((math.sin(0.3), 0.0, math.cos(0.3)), 0),
                                               ((-math.sin(0.3), 0.0, math.cos(0.3)), 0),
                                               ((0.0, math.sin(0.3), math.cos(0.3)), 1),
                                               ((0.0, -math.sin(0.3), math.cos(0.3)), 1)])
def test_tilted_normal_deflects_the_ball_towards_the_tilt(world: PaddleBallWorld, n_real: tuple, axis: int) -> None:
    n = np.array(n_real)
    imp = drop(world, np.r_[0.0, 0.0, 0.0, real_normal_command(n)])
    other = 1 - axis
    assert np.sign(imp.post_velocity[axis]) == np.sign(n[axis])
    assert abs(imp.post_velocity[axis]) > 1.0
    assert abs(imp.post_velocity[other]) < 0.05
    np.testing.assert_allclose(imp.n_real, n, atol=1e-9)


def test_realised_normal_includes_the_y_bias(world: PaddleBallWorld) -> None:
    world.reset()
    world.set_command(np.r_[0.0, 0.0, 0.5, 0.0, 0.0, 1.0])
    world.step(10)
    mujoco.mj_forward(world.model, world.data)
    geom = mujoco.mj_name2id(world.model, mujoco.mjtObj.mjOBJ_GEOM, "paddle")
    z_axis = world.data.geom_xmat[geom].reshape(3, 3)[:, 2]
    expected = np.array([math.sin(BIAS), 0.0, math.cos(BIAS)])
    np.testing.assert_allclose(z_axis, expected, atol=1e-9)
    np.testing.assert_allclose(world.paddle_normal, expected, atol=1e-9)
    _, quat = world.paddle_pose
    body = mujoco.mj_name2id(world.model, mujoco.mjtObj.mjOBJ_BODY, "paddle")
    np.testing.assert_allclose(quat, world.data.xquat[body], atol=1e-9)
    imp = world.run_until_impact()
    assert imp is not None
    np.testing.assert_allclose(imp.u_cmd[3:], [0.0, 0.0, 1.0])  # the learner sees the commanded normal
    np.testing.assert_allclose(imp.n_real, expected, atol=1e-12)
    assert imp.post_velocity[0] > 0.5  # the real paddle is pitched towards +x


def test_fixed_command_keeps_the_ball_bouncing(world: PaddleBallWorld) -> None:
    world.reset()
    world.set_command(np.r_[0.0, 0.0, 0.5, LEVEL])
    impacts = [world.run_until_impact(max_time=2.0) for _ in range(15)]
    assert all(i is not None and i.on_plan for i in impacts)
    assert not world.failed()
    pre = np.stack([i.pre for i in impacts if i is not None])
    assert np.abs(pre[:, :2]).max() < 0.05 and np.abs(pre[:, 2]).max() < 0.02
    # the steady bounce of the analytic model: |v| = 0.8 |v| + 1.8 * 0.5  ->  4.5 m/s
    assert -pre[-1, 5] == pytest.approx(4.5, rel=0.1)


def test_controller_meets_moving_balls(world: PaddleBallWorld) -> None:
    """A ball thrown sideways is met at its predicted impact point with the commanded velocity."""
    for vel in ([1.0, 0.0, 0.0], [0.0, -0.8, 2.0], [-0.6, 0.5, 1.0]):
        world.reset(np.array([0.0, 0.0, 0.8]), np.array(vel))
        world.set_command(np.r_[0.3, -0.2, 1.0, 0.1, 0.0, 1.0])
        t_left, predicted = world.next_impact()
        imp = world.run_until_impact()
        assert imp is not None and imp.on_plan
        assert imp.time == pytest.approx(t_left, abs=2 * world.timestep)
        np.testing.assert_allclose(imp.pre, predicted, atol=0.05)
        np.testing.assert_allclose(imp.paddle_velocity, [0.3, -0.2, 1.0], atol=1e-9)


def test_knocking_the_ball_away_is_a_failure(world: PaddleBallWorld) -> None:
    world.reset()
    world.set_command(np.r_[1.0, 0.0, 2.0, math.sin(0.35), 0.0, math.cos(0.35)])
    assert world.run_until_impact() is not None
    assert not world.failed()
    assert world.run_until_impact(max_time=4.0) is None
    assert world.failed() and world.failure_reason == "out_of_reach"
    world.reset(np.array([0.0, 0.0, 1.0]))
    assert not world.failed()


def test_command_validation(world: PaddleBallWorld) -> None:
    world.reset()
    for bad in ([0.0] * 5, [np.nan, 0, 0, 0, 0, 1], [0, 0, 0, 0, 0, 0.1], [0, 0, 0, 0, 0, -1]):
        with pytest.raises(ValueError):
            world.set_command(np.array(bad, dtype=float))
    before = world.n_clipped
    world.set_command(np.array([5.0, 0.0, 0.0, 0.0, 0.0, 1.02]))
    np.testing.assert_allclose(world.command, [1.0, 0.0, 0.0, 0.0, 0.0, 1.0])
    world.set_command(np.array([0.0, 0.0, 0.0, 1.0, 0.0, 0.1]))  # tilted beyond max_tilt
    tilt = math.acos(world.command[5])
    assert tilt == pytest.approx(world.options.max_tilt) and world.command[3] > 0
    assert world.n_clipped == before + 2
    with pytest.raises(ValueError):
        PaddleBallWorld(no_such_option=1.0)


def test_collect_impacts_gives_finite_data_close_to_the_analytic_true_model() -> None:
    world = PaddleBallWorld(seed=0)
    stats = CollectStats()
    impacts = collect_impacts(world, 40, np.random.default_rng(1), stats=stats)
    x, u, y = impacts_to_arrays(impacts)
    assert x.shape == (40, 6) and u.shape == (40, 6) and y.shape == (40, 3)
    assert all(np.all(np.isfinite(a)) for a in (x, u, y))
    assert all(i.on_plan for i in impacts) and stats.kept == 40 and stats.resets >= 1
    np.testing.assert_allclose(np.linalg.norm(u[:, 3:], axis=1), 1.0)
    speed = np.linalg.norm(y, axis=1)
    true_err = np.linalg.norm(world.system.true_step_np(x, u) - y, axis=1) / speed
    base_err = np.linalg.norm(world.system.base_step_np(x, u) - y, axis=1) / speed
    assert true_err.mean() < 0.08  # measured about 0.03
    assert base_err.mean() > 3 * true_err.mean()


def test_fixed_seed_is_deterministic() -> None:
    runs = []
    for _ in range(2):
        world = PaddleBallWorld(seed=3)
        world.reset_random()
        rng = np.random.default_rng(7)
        runs.append(impacts_to_arrays(collect_impacts(world, 10, rng, random_commands)))
    for a, b in zip(runs[0], runs[1], strict=True):
        np.testing.assert_array_equal(a, b)


def test_a_ball_pushed_through_the_paddle_is_flagged_and_lost() -> None:
    world = PaddleBallWorld()
    fine = drop(world, np.r_[0.0, 0.0, 2.0, LEVEL], height=8.0**2 / (2 * 9.81))  # 10 m/s relative
    assert fine.post_velocity[2] > 9.0
    world.reset(np.array([0.0, 0.0, 12.0**2 / (2 * 9.81)]))
    world.set_command(np.r_[0.0, 0.0, 4.0, LEVEL])  # 16 m/s relative: beyond what the soft contact holds
    imp = world.run_until_impact()
    assert imp is not None and not imp.on_plan and imp.post_velocity[2] < 0
    assert world.run_until_impact() is None and world.failure_reason == "fell"


# ------------------------------------------------------------------------------------------------ tracking error
def test_tracking_error_perturbs_the_realised_paddle_but_not_the_learned_command() -> None:
    u = np.r_[0.3, -0.2, 1.0, 0.1, 0.0, 1.0]
    u_cmd = PaddleBallWorld(seed=0).validate_command(u)[0]
    exact = PaddleBallWorld(seed=3)
    noisy = PaddleBallWorld(seed=3, velocity_noise=0.1, normal_noise=0.03)
    dv: list[float] = []
    dn: list[float] = []
    for w, out in ((exact, None), (noisy, (dv, dn))):
        for k in range(40):
            w.reset(np.array([0.0, 0.0, 0.8]), np.array([0.2 * math.sin(k), 0.2 * math.cos(k), 0.0]))
            w.set_command(u)
            imp = w.run_until_impact()
            assert imp is not None
            np.testing.assert_allclose(imp.u_cmd, u_cmd, atol=1e-12)  # the learner sees the command ...
            n_cmd_real = np.array([math.sin(BIAS) * u_cmd[5] + math.cos(BIAS) * u_cmd[3], u_cmd[4],
                                   math.cos(BIAS) * u_cmd[5] - math.sin(BIAS) * u_cmd[3]])
            if out is None:  # exact tracking: realised = commanded
                np.testing.assert_allclose(imp.paddle_velocity, u_cmd[:3], atol=1e-9)
                np.testing.assert_allclose(imp.n_real, n_cmd_real, atol=1e-12)
            else:  # ... while the paddle realises something else
                out[0].append(imp.paddle_velocity - u_cmd[:3])
                out[1].append(math.acos(min(1.0, float(imp.n_real @ n_cmd_real))))
    dv_a, dn_a = np.array(dv), np.array(dn)
    assert 0.06 < float(dv_a.std()) < 0.14 and abs(float(dv_a.mean())) < 0.05  # sigma_v = 0.1 m/s
    assert 0.02 < float(np.median(dn_a)) < 0.06  # two 0.03 rad rotations: about 0.035 rad off
    with pytest.raises(ValueError, match="noise"):
        PaddleBallWorld(velocity_noise=-0.1)


def test_tracking_error_is_reproducible_from_the_seed() -> None:
    runs = []
    for _ in range(2):
        w = PaddleBallWorld(seed=5, velocity_noise=0.2, normal_noise=0.05)
        w.reset()
        w.set_command(np.r_[0.0, 0.0, 0.5, LEVEL])
        runs.append([w.run_until_impact().post_velocity for _ in range(4)])  # type: ignore[union-attr]
    np.testing.assert_array_equal(np.array(runs[0]), np.array(runs[1]))


# ------------------------------------------------------------------------------------------------ multi-bounce
def test_bounce_sequence_completes_with_a_keeping_command_and_counts_bounces() -> None:
    from saml_ros.systems.paddle_ball.bounces import bounce_sequence

    w = PaddleBallWorld(seed=0)
    w.reset()
    seen: list[int] = []

    def level(k: int, x_pre: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        seen.append(k)
        assert x_pre.shape == (6,) and abs(x_pre[2]) < 0.02  # a predicted pre-impact state at the plane
        return np.r_[0.0, 0.0, 0.5, LEVEL], np.zeros(2)

    rec = bounce_sequence(w, level, 12)
    assert rec.completed and rec.failure is None and rec.bounces == 12 and seen == list(range(12))
    assert len(rec.errors) == len(rec.landings) == len(rec.impacts) == 12
    for landing, err in zip(rec.landings, rec.errors):
        assert err == pytest.approx(float(np.linalg.norm(landing)))
    assert max(rec.errors) < 0.05  # a level paddle sends the ball straight back up


def test_bounce_sequence_fails_when_the_ball_is_not_kept_bouncing() -> None:
    from saml_ros.systems.paddle_ball.bounces import LANDS_OUT, bounce_sequence

    w = PaddleBallWorld(seed=0)
    w.reset()
    n_away = np.array([math.sin(0.5), 0.0, math.cos(0.5)])  # tilted: the ball flies off sideways

    def away_at_third(k: int, x_pre: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return (np.r_[0.0, 0.0, 1.5, n_away] if k == 2 else np.r_[0.0, 0.0, 0.5, LEVEL]), np.zeros(2)

    rec = bounce_sequence(w, away_at_third, 10)
    assert not rec.completed and rec.bounces == 2 and rec.failure == LANDS_OUT
    assert len(rec.impacts) == 3 and len(rec.errors) == 2
    # a command the world refuses ends the sequence as well, before any bounce
    w.reset()
    rec = bounce_sequence(w, lambda k, x: (np.r_[0.0, 0.0, 0.5, 0.0, 0.0, 0.1], np.zeros(2)), 5)
    assert rec.bounces == 0 and rec.failure is not None and rec.failure.startswith("invalid command")
