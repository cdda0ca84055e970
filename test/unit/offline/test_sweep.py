"""``sweep``: grids, the Pareto front, bags, and identical tables in-process and on a local Ray instance (2 CPUs)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from helpers.offline import SMALL, sweep_setup

from saml_ros.offline import sweep, sweep_cli
from saml_ros.offline.sweep import SweepError, Task, pareto_front, parse_grid, run_sweep, table


def test_grid_parsing_and_errors() -> None:
    grid = parse_grid(["eps=0.02,0.05", "hidden=4x2,paper", "seed=0,1", "primal_lr=0.001", "train.batch_size=64",
                       "uniform=false,true"])
    assert grid == {"eps": [0.02, 0.05], "hidden": [(4, 2), None], "seed": [0, 1], "primal_lr": [0.001],
                    "train.batch_size": [64], "uniform": [False, True]}
    for bad, match in (("nope=1", "unknown sweep axis"), ("eps", "NAME=V1"), ("seed=a", "bad value"),
                       ("uniform=maybe", "bad value")):
        with pytest.raises(SweepError, match=match):
            parse_grid([bad])
    with pytest.raises(SweepError, match="twice"):
        parse_grid(["seed=0", "seed=1"])
    with pytest.raises(SweepError, match="no constraint 'far'"):
        run_sweep({"eps.far": [0.1]}, sweep_setup())
    with pytest.raises(SweepError, match="no MPC task for paddle_ball"):
        run_sweep({"seed": [0]}, sweep_setup(system="paddle_ball", task=Task(starts=1, steps=1)))


def test_pareto_front_keeps_exactly_the_undominated_points() -> None:
    pts = [(0.1, 0.9), (0.2, 0.5), (0.3, 0.6), (0.5, 0.2), (0.5, 0.2), (0.9, 0.1), (0.4, float("nan"))]
    assert pareto_front(pts) == [0, 1, 3, 4, 5]  # (0.3, 0.6) is beaten by (0.2, 0.5); NaN never counts


def test_eps_moves_the_trade_off_and_the_table_marks_the_front(tmp_path: Path) -> None:
    """A loose and a tight eps on the same data and seed: the tight one buys in-region accuracy with
    out-of-region accuracy (the paper's trade-off), and its constraint value is relative to its own eps."""
    result = run_sweep({"eps": [0.2, 0.01]}, sweep_setup(base={**SMALL, "epochs": 20, "samples": 3000}))
    loose, tight = result.rows
    assert tight["err_in/near_origin"] < loose["err_in/near_origin"]
    assert tight["lambda/near_origin"] > loose["lambda/near_origin"]
    assert loose["met/near_origin"] and loose["g/near_origin"] <= 0
    assert tight["g/near_origin"] == pytest.approx(tight["err_in/near_origin"] - 0.01, abs=1e-9)
    text = table(result)
    assert text.count("\n") == 4 and "| pareto | point | eps |" in text
    paths = sweep.write_outputs(result, tmp_path)
    assert paths["plot"].stat().st_size > 10_000
    assert json.loads(paths["json"].read_text())["rows"][1]["eps"] == 0.01


def test_sweep_on_bags(tmp_path: Path) -> None:
    from helpers.bag_publisher import rollout

    from msg_schemas import DATA_QOS, TypestoreFactory, get_schema
    from saml_ros.bags.io import BagWriter, jazzy_typestore

    schema, factory = get_schema("friction"), TypestoreFactory(jazzy_typestore())
    events = rollout("friction", 300, 50, seed=4, t0_ns=10**9)
    with BagWriter(tmp_path / "bag") as w:
        for topic in ("state", "applied_cmd"):
            w.add_topic(f"/friction/{topic}", "sensor_msgs/msg/JointState", DATA_QOS)
        for ev in events:
            w.write_msg("/friction/state", schema.state_to_msg(ev["x"], ev["stamp"], factory=factory), ev["stamp"])
            if "u" in ev:
                w.write_msg("/friction/applied_cmd", schema.control_to_msg(ev["u"], ev["stamp"], factory=factory),
                            ev["stamp"])
    out = tmp_path / "out"
    assert sweep_cli.main(["--system", "friction", "--bag", str(tmp_path / "bag"), "--grid", "seed=0,1",
                           "--epochs", "2", "--out", str(out), "--quiet"]) == 0
    rows = json.loads((out / "results.json").read_text())["rows"]
    assert len(rows) == 2 and all(np.isfinite(r["err_in/near_origin"]) for r in rows)
    assert (out / "results.csv").read_text().splitlines()[0].startswith("pareto,point,seed,objective")


def test_sweep_cli_refuses_cuda_without_cuda_before_training(tmp_path: Path,
                                                             capsys: pytest.CaptureFixture[str]) -> None:
    import torch

    if torch.cuda.is_available():
        pytest.skip("this machine has CUDA")
    assert sweep_cli.main(["--system", "friction", "--device", "cuda", "--out", str(tmp_path / "o")]) == 2
    assert "sweep: device 'cuda' asked for, but CUDA is not available" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()
