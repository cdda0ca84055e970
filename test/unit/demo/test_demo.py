"""The demo's task, metrics, paired evaluation and pooling of runs (saml_ros.demo), ROS-free."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from saml_ros.core.systems import get_system
from saml_ros.demo.aggregate import aggregate, format_aggregate, load_runs
from saml_ros.demo.evaluation import Arm, captured, evaluate_arms, paired_diff, summarize
from saml_ros.demo.landing import LandingTask, aggressive_starts, episode_metrics, standard_starts
from saml_ros.systems.quadrotor.model import Quadrotor

_QUAD = get_system("quadrotor")
assert isinstance(_QUAD, Quadrotor)
QUAD: Quadrotor = _QUAD
TASK = LandingTask()


def test_metrics_of_a_known_trajectory() -> None:
    """A descent that settles 5 cm above the pad after crossing 2 cm above it: every metric by hand."""
    steps = 50
    z = np.concatenate((np.linspace(1.2, 0.22, 20), np.full(steps + 1 - 20, 0.25)))
    xs = np.zeros((steps + 1, 13))
    xs[:, 0] = 0.1  # 10 cm off in x throughout
    xs[:, 2] = z
    m = episode_metrics(xs, np.ones(steps, bool), np.full(steps, 0.004), TASK)
    assert math.isclose(m["landing_error"], math.hypot(0.1, 0.05), rel_tol=1e-9)
    assert math.isclose(m["height_error"], 0.05, rel_tol=1e-9)
    assert math.isclose(m["horizontal_error"], 0.1, rel_tol=1e-9)
    assert m["settling_time"] == (steps + 1) * 0.1  # never within 3 cm at the end
    assert math.isclose(m["overshoot"], 0.05, rel_tol=1e-9)  # first within 5 cm at z = 0.22..., then 0.25
    assert math.isclose(m["cost"], float(np.linalg.norm(xs[1:, :3] - TASK.goal, axis=1).sum()), rel_tol=1e-12)
    assert m["failed_solves"] == 0.0 and math.isclose(m["solve_ms"], 4.0)


def test_paired_statistics_and_captured_headroom() -> None:
    rng = np.random.default_rng(0)
    base = 0.07 + 0.01 * rng.standard_normal(40)
    oracle = np.zeros(40)
    learned = 0.1 * base  # captures 90 % of the headroom
    d = paired_diff(base, learned)
    assert d["lo"] > 0 and math.isclose(d["diff"], float(np.mean(base - learned)))
    assert d["frac_b_better"] == 1.0
    c = captured(base, learned, oracle)
    assert math.isclose(c["capture"], 0.9, rel_tol=1e-9) and c["lo"] <= 0.9 <= c["hi"]
    assert math.isnan(captured(base, learned, base)["capture"])  # no headroom: no fraction


def test_the_oracle_lands_on_the_pad_and_the_base_model_above_it() -> None:
    """The headroom the demo rests on, in the real MPC on the simulator's dynamics (2 starts, one process)."""
    starts = standard_starts(QUAD, 2, 4242)
    res = evaluate_arms([Arm("base", "base"), Arm("oracle", "oracle")], TASK, starts, workers=1)
    s = summarize(res)
    base, oracle = res["base"].metrics, res["oracle"].metrics
    assert np.all(oracle["landing_error"] < 0.01), oracle["landing_error"]
    assert np.all(base["height_error"] > oracle["height_error"] + 0.01), (base["height_error"],
                                                                           oracle["height_error"])
    assert s["metrics"]["landing_error"]["headroom"]["diff"] > 0.01
    assert res["base"].xs.shape == (2, TASK.steps + 1, 13)
    agg = aggressive_starts(QUAD, 3, 1)
    assert np.all(agg[:, 5] <= 0) and np.all(np.abs(agg[:, :2]) <= 4)


def _summary(rng: np.random.Generator, n: int, shift: float) -> dict[str, Any]:
    per = {}
    base = 0.07 + 0.01 * rng.random(n)
    for arm, v in (("base", base), ("oracle", np.zeros(n)), ("SA", 0.1 * base + shift), ("UA", 0.2 * base)):
        per[arm] = {k: v.tolist() for k in ("landing_error", "height_error", "horizontal_error", "settling_time",
                                            "overshoot", "cost", "failed_solves", "solve_ms")}
    return {"evaluation": {"arms": ["base", "oracle", "SA", "UA"], "sets": {"standard": {"per_start": per},
                                                                             "aggressive": {"per_start": per}}},
            "bringup": {"episodes": [{"error": 0.01, "model_first": 3, "model_last": 3},
                                     {"error": 0.2, "model_first": 0, "model_last": 0}]},
            "wall_seconds": 170.0}


def test_runs_are_pooled_per_start(tmp_path: Path) -> None:
    rng = np.random.default_rng(1)
    dirs = []
    for i in range(3):
        d = tmp_path / f"run{i}"
        d.mkdir()
        (d / "demo_summary.json").write_text(json.dumps(_summary(rng, 10, 0.0)))
        dirs.append(d)
    agg = aggregate(load_runs(dirs))
    std = agg["sets"]["standard"]
    assert std["n"] == 30 and agg["sets"]["all"]["n"] == 60
    row = std["metrics"]["landing_error"]
    assert math.isclose(row["captured/SA"]["capture"], 0.9, rel_tol=1e-9)
    assert row["sa_vs_ua"]["diff"] > 0 and row["sa_vs_ua"]["lo"] > 0  # UA - SA: SA better here
    assert agg["live"] == {"learned_episodes": 3, "learned_far": 0, "learned_worst": 0.01, "base_episodes": 3,
                           "base_worst": 0.2}
    text = format_aggregate(agg)
    assert "CI excludes 0: yes" in text and "(>= 50%: yes)" in text and "no worse: yes" in text


def test_demo_set_overrides_reach_both_learners_and_the_evaluation(tmp_path: Path) -> None:
    """demo --set: a learner parameter reaches the SA and the UA learner's ROS parameters, an mpc one the MPC's
    (which the evaluation reads too); without --set the demo's configuration is bringup's."""
    from saml_ros.bringup.config import node_params
    from saml_ros.demo.cli import demo_config, live_config

    assert live_config(3, 60.0, []) == demo_config(3, 60.0)
    config = live_config(3, 60.0, ["learner.training_niceness=5", "learner.training_idle=true",
                                   "mpc.horizon=8"])
    params = node_params(config, tmp_path)
    for name in ("learner", "learner_ua"):
        assert params[name]["training_niceness"] == 5 and params[name]["training_idle"] is True
    assert params["learner_ua"]["uniform"] is True
    assert params["mpc"]["horizon"] == 8
    assert config["sim"]["seed"] == 3 and config["sim_time"] == 60.0
    # the live loop's speed limit reaches the simulator, and --set lifts it
    assert params["sim"]["max_speed"] == 5.0
    assert node_params(live_config(3, 60.0, ["sim.max_speed=0"]), tmp_path)["sim"]["max_speed"] == 0


def test_demo_guards_flies_a_runs_checkpoint_with_each_guard_setting(tmp_path: Path,
                                                                   capsys: Any) -> None:
    """``demo --guards RUN_DIR``: the base model and the run's newest checkpoint under every guard setting, from
    the run's evaluation starts; a directory that is no run is refused with exit code 2. ``demo --spread``: the same
    checkpoint and the base model from one start and moved copies of it.

    One aggressive start: what is checked is that every setting flies the run's checkpoint from the run's starts (as
    many as asked for), each with its own guard counters; the guards' effect on landings is test_guard.py's."""
    import shutil

    import yaml
    from helpers.models import hover_only_checkpoint

    from saml_ros.bringup.config import CHECKPOINTS
    from saml_ros.demo.cli import demo_config, main

    run = tmp_path / "run"
    (run / CHECKPOINTS).mkdir(parents=True)
    (run / "bringup.yaml").write_text(yaml.safe_dump(demo_config(0, 60.0)))
    ckpt = hover_only_checkpoint(tmp_path, updates=200, n_models=3)
    shutil.copy(ckpt, run / CHECKPOINTS / ckpt.name)
    out = tmp_path / "guards.json"
    assert main(["--guards", str(run), "--aggressive-starts", "1", "--workers", "1", "--json", str(out)]) == 0
    text = capsys.readouterr().out
    got = json.loads(out.read_text())
    settings = ["base", "unguarded", "disagreement 0.1 only", "bound only", "roll back only",
                "run's guard without roll back", "run's guard + constraint watch", "run's guard without task check",
                "infeasible fallback only", "run's guard without infeasible fallback",
                "run's guard"]
    assert list(got["sets"]) == ["aggressive"] and list(got["sets"]["aggressive"]) == settings
    for name in settings:
        arm = got["sets"]["aggressive"][name]
        assert len(arm["landing_error"]) == 1 and all(math.isfinite(e) for e in arm["landing_error"])
        assert name in text
    # the demo's guard plans with f_hat where the members disagree; unguarded never does
    assert got["sets"]["aggressive"]["unguarded"]["guard"].get("solves_base", 0) == 0
    assert got["sets"]["aggressive"]["run's guard"]["guard"]["solves"] == 1 * 50
    assert main(["--guards", str(tmp_path)]) == 2
    assert "not a demo run directory" in capsys.readouterr().out
    # demo --spread: the base model and the run's guarded checkpoint from one start and moved copies of it
    from saml_ros.demo.guards import spread

    got = spread(run, 0, "aggressive:1", 2, workers=1)
    assert list(got["landing_error"]) == ["base", "SA, run's guard"]
    assert all(len(e) == 2 and all(math.isfinite(v) for v in e) for e in got["landing_error"].values())
    assert main(["--spread", str(run), "--start", "aggressive:10"]) == 2  # 10 aggressive starts: 0..9
    assert "aggressive:I (I < 10)" in capsys.readouterr().out


def test_a_second_effect_is_in_the_simulator_the_oracle_and_the_evaluation(tmp_path: Path) -> None:
    """The demo's wind world (``demo --world wind``: the capacity sweep's second effect, the wind above the pad's
    shelter) is in all three: the simulator node's system (built from the demo configuration's ``sim`` parameters
    as the node builds it), the oracle arm's model (zero one-step error on the evaluation's plant, wind included)
    and the evaluation's plant; a world without it has model error there (so the check can fail). The paper's
    world has no wind."""
    from saml_ros.bringup.config import node_params
    from saml_ros.core.mpc.dynamics_np import NumpyDynamics
    from saml_ros.core.systems.registry import get_entry
    from saml_ros.core.worlds.sim_core import SimConfig, SteppedSim
    from saml_ros.demo.cli import demo_config, live_config
    from saml_ros.demo.evaluation import run_task_and_guard
    from saml_ros.demo.landing import WORLDS, plant
    from saml_ros.experiments.capacity import CapacitySettings
    from sim_nodes.binding import read_sim_params
    from sim_nodes.quadrotor_sim import BINDING

    assert dict(run_task_and_guard(demo_config(0, 60.0, "paper"))[0].world).get("wind", 0.0) == 0.0
    config = live_config(0, 60.0, [], world="wind")  # demo --world wind: the capacity sweep's world
    assert WORLDS["wind"] == CapacitySettings().world
    task, _ = run_task_and_guard(config)
    world = dict(task.world)
    assert world.get("wind", 0.0) > 0.0, "the sweep's world has the wind field"
    # the simulator node: its parameters from the demo configuration, its system built as SimNode builds it
    p = read_sim_params(BINDING, node_params(config, tmp_path)["sim"])
    sim_system = get_entry("quadrotor").make_system(**{k[7:]: v for k, v in p.items() if k.startswith("system.")})
    assert isinstance(sim_system, Quadrotor)
    assert sim_system.params() == task.system().params()
    sim = get_entry("quadrotor").simulator(sim_system, SimConfig(mode="lockstep", seed=0), p)
    assert isinstance(sim, SteppedSim)
    # a state in the wind (3 m up, between the wind's extremes), a state in the ground effect, one in between
    rng = np.random.default_rng(0)
    xs = np.stack([sim_system.hover_state((0.3, -0.2, z)) for z in (3.0, 1.7, 0.6)])
    xs[:, 3:6] = rng.uniform(-1, 1, (3, 3))
    u = sim_system.hover_thrust() + rng.uniform(-1, 1, (3, 4))
    f = plant(task.system(), task.landing_height)
    oracle = NumpyDynamics(task.system(), "oracle")
    windless = NumpyDynamics(get_system("quadrotor"), "oracle")
    for x, ui in zip(xs, u, strict=True):
        sim.x = x.copy()
        sim._step(ui, 0)  # the simulator's own step (lockstep core)
        y_plant = f(x, ui)
        np.testing.assert_allclose(sim.x, y_plant, rtol=0, atol=1e-12)
        np.testing.assert_allclose(oracle.step1(x, ui), y_plant, rtol=0, atol=1e-12)
        if x[2] > world.get("wind_floor", 1.5):
            assert np.abs(windless.step1(x, ui) - y_plant)[3:5].max() > 1e-3  # the wind is model error to f
