"""bringup: configuration, episode bookkeeping, process groups, and whole closed loops in real processes.

The closed-loop tests run the double integrator with friction (its MPC is the cheapest) in a private ROS domain:
the learner's in-region model error falls and the MPC switches checkpoints while the loop runs; SIGINT, SIGTERM,
the end of the simulated time and even SIGKILL of bringup leave no process of the loop behind.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml
from helpers import REPO

from saml_ros.bringup import (
    BringupResult,
    Episode,
    EpisodeTracker,
    apply_sets,
    child_env,
    default_config,
    format_summary,
    load_config,
    ros_params_file,
)

DT_NS = 100_000_000


# ------------------------------------------------------------------------------------------ ROS-free
def test_config_file_matches_the_embedded_defaults() -> None:
    path = REPO / "config" / "bringup_quadrotor.yaml"
    assert load_config(path, None) == default_config("quadrotor")
    assert yaml.safe_load(path.read_text())["system"] == "quadrotor"


def test_config_overrides_and_errors(tmp_path: Path) -> None:
    cfg = apply_sets(load_config(None, "friction"), ["mpc.solver=slsqp", "sim.episode_steps=7", "sim_time=12"])
    assert cfg["mpc"]["solver"] == "slsqp" and cfg["sim"]["episode_steps"] == 7 and cfg["sim_time"] == 12
    assert cfg["mpc"]["horizon"] == default_config("friction")["mpc"]["horizon"]  # the rest is kept
    with pytest.raises(ValueError, match="section.param=value"):
        apply_sets(cfg, ["nonsense"])
    with pytest.raises(ValueError, match="must be sim_time or one of"):
        apply_sets(cfg, ["bogus.x=1"])
    bad = tmp_path / "bad.yaml"
    bad.write_text("system: friction\nsimulator: {mode: lockstep}\n")
    with pytest.raises(ValueError, match="unknown config key 'simulator'"):
        load_config(bad, None)
    with pytest.raises(ValueError, match="contradicts"):
        load_config(bad, "quadrotor")
    text = ros_params_file({"goal.position": (1.0, 2.0, 3.0), "solver": "fast"})
    assert yaml.safe_load(text) == {"/**": {"ros__parameters": {"goal.position": [1.0, 2.0, 3.0], "solver": "fast"}}}


def test_child_env_respects_the_user_and_defaults_to_localhost(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("ROS_AUTOMATIC_DISCOVERY_RANGE", raising=False)
    monkeypatch.setenv("ROS_DOMAIN_ID", "42")
    env = child_env(None)
    assert env["ROS_DOMAIN_ID"] == "42" and env["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "LOCALHOST"
    assert child_env(7)["ROS_DOMAIN_ID"] == "7"
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "SUBNET")
    assert child_env(None)["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "SUBNET"


def test_episode_tracker_splits_at_resets_and_measures_the_final_error() -> None:
    goal = np.zeros(3)
    tr = EpisodeTracker("quadrotor", 0.1, goal)
    x = np.zeros(13)
    k = 0
    for final, version in (((0.3, 0.4, 0.2), 0), ((0.0, 0.1, 0.2), 2)):
        for i in range(10):
            x = x.copy()
            x[0:3] = np.array(final) * (1 + (9 - i))
            assert tr.add(x, 10**9 + k * DT_NS, version) is None or i == 0
            k += 1
        k += 1  # a reset: the next start is stamped 2 dt later
    tr.add(np.zeros(13), 10**9 + (k + 1) * DT_NS, 2)
    assert [e.steps for e in tr.episodes] == [10, 10]
    first, second = tr.episodes
    assert first.error == pytest.approx(np.linalg.norm([0.3, 0.4, 0.2]))
    assert first.xy_error == pytest.approx(0.5)
    assert (first.model_first, second.model_first) == (0, 2)
    assert tr.sim_time == pytest.approx((k + 1) * 0.1)


def test_summary_compares_base_and_learned_episodes() -> None:
    res = BringupResult("quadrotor", Path("/tmp/run"), sim_time=10.0, wall_time=5.0, stop_reason="sim_time")
    z = np.zeros(13)
    res.episodes = [Episode(i, 0, 1, 10, z, z, err, err, v, v) for i, (err, v) in
                    enumerate(((0.5, 0), (0.4, 0), (0.3, 0), (0.2, 1), (0.1, 3)))]
    res.model_error = [(0, float("nan")), (0, 0.1), (0, 0.12), (10, 0.05), (20, 0.01), (30, 0.02)]
    res.constraint, res.model_versions = "near_ground", [0, 1, 3]
    text = format_summary(res, n_last=2)
    assert "base model 0.12 -> 0.02 after 30 learner updates" in text
    assert "base model f_hat:   0.400 +- 0.082 m over 3 episode(s)" in text
    assert "last learned models: 0.150 +- 0.050 m over 2 episode(s)" in text
    assert "MPC models used: 3 (0 -> 3)" in text
