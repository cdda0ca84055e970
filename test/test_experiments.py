"""End-to-end runs of tiny versions of every experiment runner (saml_ros.experiments): the output files are
well formed, the numbers are consistent with each other, and every plan the MPC returned respected its
constraints (control bounds; quadrotor height bound; paddle roll/pitch bounds)."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from saml_ros.experiments import EXPERIMENT_NAMES, cli
from saml_ros.experiments.common import paired, paired_rate

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def check_outputs(out: Path, data: dict[str, Any]) -> dict[str, Any]:
    """results.md / results.json exist and agree with the returned dict; every listed figure is a PNG."""
    md = (out / "results.md").read_text()
    assert md.startswith("# ") and "|---|" in md
    saved = json.loads((out / "results.json").read_text())
    assert set(saved) == set(data)
    for name in data.get("figures", []):
        assert (out / name).read_bytes()[:8] == PNG_MAGIC
        assert f"]({name})" in md
    assert saved["timing"]["total"] > 0
    return saved


# ------------------------------------------------------------------------------------------------ statistics
def test_paired_statistics_match_known_cases() -> None:
    rng = np.random.default_rng(0)
    a = rng.normal(5.0, 1.0, 40)
    b = a - 0.5 + rng.normal(0.0, 0.05, 40)  # b clearly lower
    p = paired(a, b)
    assert p.n == 40 and p.diff == pytest.approx(float(np.mean(b - a)))
    assert p.ci_low < p.diff < p.ci_high < 0
    assert p.p_ttest < 1e-6 and p.p_wilcoxon < 1e-6 and p.frac_b_better == 1.0
    same = paired(a, a)
    assert same.diff == 0 and same.ci_low == same.ci_high == 0 and same.p_ttest == 1.0
    assert math.isnan(same.p_wilcoxon)
    nan_pair = paired([1.0, np.nan, 3.0], [1.5, 2.0, 2.0])
    assert nan_pair.n == 2
    r = paired_rate([True, True, False, False, True], [False, True, False, False, False])
    assert (r.only_a, r.only_b, r.rate_a, r.rate_b) == (2, 0, 0.6, 0.2)
    assert r.p_mcnemar == pytest.approx(0.5)


def test_cli_parses_every_experiment_and_applies_seeds() -> None:
    parser = cli.build_parser()
    for name in (*EXPERIMENT_NAMES, "all"):
        assert parser.parse_args([name, "--quick"]).name == name
    with pytest.raises(SystemExit):
        parser.parse_args(["nonsense"])
    assert cli.settings_for("friction", True, [3, 4]).seeds == (3, 4)
    assert cli.settings_for("convergence", False, [7]).seed == 7
    assert cli.settings_for("paddle_ball", True, None).n_trials < cli.settings_for("paddle_ball", False, None).n_trials
    assert cli.main(["friction", "--seeds", "1", "1"]) == 2


# ------------------------------------------------------------------------------------------------ convergence
def test_convergence_grid_tiny(tmp_path: Path) -> None:
    from saml_ros.experiments.convergence import ConvergenceSettings, run

    s = ConvergenceSettings(nets=((2, 1), (4, 2)), sizes=(100, 300), n_datasets=3, epochs=4, n_pstar=200_000,
                            n_test=2000)
    data = run(s, tmp_path, progress=False)
    saved = check_outputs(tmp_path, data)
    assert len(saved["cells"]) == 4
    for c in saved["cells"]:
        assert len(c["lagrangian"]) == 3 and all(np.isfinite(c["lagrangian"]))
        # the Lagrangian is the objective plus lambda * g
        lag = np.asarray(c["objective"]) + np.asarray(c["lambda"]) * np.asarray(c["constraint"])
        np.testing.assert_allclose(c["lagrangian"], lag, rtol=1e-6, atol=1e-9)
        assert len(set(c["seeds"])) == 3
    ps = saved["pstar_check"]
    # P* = sigma^2 for the squared spec; the true model satisfies the unconditional constraint ...
    assert abs(ps["objective_squared"] - 0.04) < 4 * ps["objective_squared_se"] + 1e-4
    assert ps["constraint_squared_unconditional"] < s.eps
    # ... while the l2 readings would not give 0.04 and a conditional l2 constraint would be infeasible
    assert ps["objective_l2"] == pytest.approx(0.2 * math.sqrt(2 / math.pi), rel=0.02)
    assert ps["constraint_l2_conditional"] > s.eps
    assert (tmp_path / "convergence_boxplot.png").exists()


# ------------------------------------------------------------------------------------------------ friction
def test_friction_experiment_tiny(tmp_path: Path) -> None:
    from saml_ros.experiments.friction import FrictionSettings, run, starts

    s = FrictionSettings(seeds=(0, 1), n_train=1500, epochs=4, n_test=2000, n_starts=4, steps=8,
                         slsqp_starts=2, traj_starts=(1.0,))
    data = run(s, tmp_path, progress=False)
    saved = check_outputs(tmp_path, data)
    p0 = starts(s.n_starts, s.start_seed)[:, 0]
    np.testing.assert_allclose(saved["starts"], p0)
    for solver, n_seeds, n_starts in (("slsqp", 1, 2), ("fast", 2, 4)):
        res = data["control"][solver]
        for label in ("uniform", "sufficient"):
            c = res[label]
            assert c["raw"].shape == c["norm"].shape == (n_seeds, n_starts)
            # the cost sums |p_t| from the start on, and the normalised cost divides by |p0|
            assert np.all(c["raw"] >= np.abs(p0[:n_starts]) - 1e-12)
            np.testing.assert_allclose(c["norm"], c["raw"] / np.abs(p0[:n_starts]))
            np.testing.assert_array_equal(c["stuck"], np.abs(c["final"][..., 0]) > 0.05)
            ch = c["checks"]
            assert ch.solves == n_seeds * n_starts * s.steps
            assert ch.max_u_violation == 0.0  # |u| <= 10 on every returned plan
        assert data["paired"][solver]["raw_by_start"].n == n_seeds * n_starts
    from saml_ros.core.model_io import load_model

    loaded = load_model(tmp_path / saved["models"]["sufficient"])
    assert loaded.model.n_models == 2 and loaded.meta["seeds"] == [0, 1]
    errs = saved["model_errors"]["near_origin"]
    assert len(errs["uniform"]["inside"]) == 2 and 0 < errs["frac_inside"] < 0.2
    assert "| Sufficiently Accurate |" in (tmp_path / "results.md").read_text()


def test_closed_loop_runs_the_true_system() -> None:
    from saml_ros.core.mpc import closed_loop, make_controller
    from saml_ros.core.systems import get_system

    system = get_system("friction")
    ro = closed_loop(system, make_controller(system, None, "fast", horizon=10), np.array([1.2, 0.0]), 6,
                     true_step=system.true_step_np)
    for k in range(6):
        np.testing.assert_allclose(ro.xs[k + 1], system.true_step_np(ro.xs[k], ro.us[k]))
    assert np.all(np.abs(ro.us) <= 10.0)
    assert abs(ro.xs[-1, 0]) < 1.2  # it moved towards the origin


# ------------------------------------------------------------------------------------------------ quadrotor
def test_quadrotor_experiment_tiny(tmp_path: Path) -> None:
    from saml_ros.experiments.quadrotor import QuadrotorSettings, run

    s = QuadrotorSettings(seeds=(0,), n_train=1000, epochs=3, n_test=2000, n_starts=2, steps=6, base=False)
    data = run(s, tmp_path, progress=False)
    saved = check_outputs(tmp_path, data)
    for label in ("uniform", "sufficient"):
        c = data["control"][label]
        assert c["cost"].shape == (1, 2) and np.all(np.isfinite(c["cost"]))
        ch = c["checks"]
        assert ch.solves == 2 * s.steps
        assert ch.max_u_violation == 0.0  # 0 <= u <= 10 on every returned plan
        assert ch.max_state_violation_success <= 1e-4  # pz >= 0.2 m on every plan reported successful
        e = saved["errors"][label]
        assert e["loss"][0] > 0 and e["loss_times_indicator"][0] <= e["loss"][0]
    assert 0.2 < saved["errors"]["frac_inside"] < 0.4  # pz ~ U[0.1, 5]: P(pz <= 1.5) = 0.286


# ------------------------------------------------------------------------------------------------ paddle ball
@pytest.fixture(scope="module")
def paddle_run(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict[str, Any], Any]:
    from saml_ros.experiments.paddle_ball import PaddleSettings, run

    out = tmp_path_factory.mktemp("paddle")
    s = PaddleSettings(seeds=(0, 1), mpc_seeds=2, n_impacts=150, n_val=60, epochs=8, n_trials=6)
    return out, run(s, out, progress=False), s


def test_paddle_experiment_tiny(paddle_run: tuple[Path, dict[str, Any], Any]) -> None:
    out, data, s = paddle_run
    saved = check_outputs(out, data)
    assert set(data["control"]) == {"base", "full/uniform", "full/sufficient", "residual/uniform",
                                    "residual/sufficient"}
    for name, c in data["control"].items():
        n = s.n_trials * (1 if name == "base" else 2)  # learned models: both seeds' members, trial by trial
        assert c["failed"].shape == (n,) and c["failed"].dtype == bool
        assert not np.any(c["lost"] & ~c["failed"])
        assert np.all(np.isfinite(c["error"][~c["failed"]])) and np.all(np.isnan(c["error"][c["failed"]]))
        assert c["max_box_violation"] == 0.0  # control bounds on every returned command
        assert c["max_angle_violation"] <= 1e-6  # roll / pitch bounds
        assert c["max_speed_violation_success"] <= 1e-3  # |v_rel| bounds when the solver reports success
    assert saved["data"]["n_train"] == s.n_impacts
    assert set(data["paired"]) == {"full", "residual"}
    assert data["paired"]["full"]["failure"].n == 2 * s.n_trials


def test_paddle_trial_measures_landing_against_target() -> None:
    from saml_ros.core.mpc import make_controller
    from saml_ros.core.systems.paddle_ball import PaddleBall
    from saml_ros.core.worlds.paddle_world import PaddleBallWorld
    from saml_ros.experiments.paddle_ball import PaddleSettings, make_trials, run_trial

    s = PaddleSettings()
    world = PaddleBallWorld(seed=0)
    ctrl = make_controller(world.system, None, s.solver)
    trials = make_trials(3, 11)
    for t in trials:
        assert -1 <= t.target_xy.min() and t.target_xy.max() <= 1 and 1 <= t.v_max - t.v_min <= 2
        r = run_trial(world, ctrl, t, s, record=True)
        if not r["failed"]:
            assert r["error"] == pytest.approx(float(np.linalg.norm(r["landing"] - t.target_xy)))
            # landing = where the ball came back down to the impact height (or met the paddle there)
            assert abs(r["landing_z"] - r["x_pre"][2]) <= 0.05
            assert len(r["track"]) > 0.2 / world.timestep  # it flew
    assert isinstance(world.system, PaddleBall)



def test_single_threaded_runner_decorator_pins_one_thread_and_restores() -> None:
    import torch

    from saml_ros.experiments.common import single_threaded

    seen: list[int] = []

    @single_threaded
    def job(x: int) -> int:
        seen.append(torch.get_num_threads())
        return 2 * x

    old = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        assert job(3) == 6 and seen == [1]
        assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(old)
