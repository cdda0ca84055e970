"""``sweep``: grids, the Pareto front, bags, and identical tables in-process and on a local Ray instance (2 CPUs)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
from helpers.offline import sweep_setup

from saml_ros.offline.sweep import Task, run_sweep, table


def test_same_numbers_in_process_and_on_local_ray(tmp_path: Path) -> None:
    """A 2 x 2 sweep with an MPC task, and the convergence experiment's grid cells (the experiment runners'
    independent units), in this process and on one private 2-CPU Ray instance: every value bit for bit."""
    pytest.importorskip("ray")
    from saml_ros.experiments.convergence import ConvergenceSettings, run
    from saml_ros.offline.parallel import ray_session

    grid: dict[str, list[Any]] = {"eps": [0.02, 0.05], "seed": [0, 1]}
    setup = sweep_setup(task=Task(starts=2, steps=8, horizon=5))
    conv = ConvergenceSettings(nets=((2, 1), (4, 2)), sizes=(100, 200), n_datasets=2, epochs=3, n_pstar=20_000,
                               n_test=1000)
    here = run_sweep(grid, setup)
    conv_here = run(conv, tmp_path / "here", progress=False)
    with ray_session("local", num_cpus=2):  # one instance for both (map_units alone starts and stops one)
        on_ray = run_sweep(grid, setup, ray="local")
        conv_ray = run(conv, tmp_path / "ray", progress=False, ray="local")
    assert on_ray.backend == "local" and here.backend == "in-process"
    assert table(on_ray) == table(here)
    strip = [{k: v for k, v in r.items() if k != "train_seconds"} for r in here.rows]
    assert [{k: v for k, v in r.items() if k != "train_seconds"} for r in on_ray.rows] == strip
    assert {r["seed"] for r in here.rows} == {0, 1} and len({r["objective"] for r in here.rows}) >= 2
    assert conv_here["backend"] == "in-process" and conv_ray["backend"] == "local"
    keys = ("net", "n", "seeds", "lagrangian", "objective", "constraint", "lambda", "test_objective", "test_constraint")
    assert len(conv_here["cells"]) == len(conv_ray["cells"]) == 4
    for a, b in zip(conv_here["cells"], conv_ray["cells"], strict=True):
        for k in keys:
            np.testing.assert_array_equal(np.asarray(a[k]), np.asarray(b[k]), err_msg=k)
