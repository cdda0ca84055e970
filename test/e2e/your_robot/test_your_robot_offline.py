"""The example robot offline: a recorded bag of its own topics (odom at 50 Hz, unstamped cmd_vel at 10 Hz with
jittered receipt times) -> the resampled transitions (checked against the simulator's truth) -> ``train
--system-file`` -> ``load_model(...).predict`` -> ``export`` (ONNX, TorchScript, numpy) equal to the model."""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from helpers import REPO

from msg_schemas import TypestoreFactory
from saml_ros.api import load_model
from saml_ros.bags.io import BagWriter
from saml_ros.bags.transitions import extract_transitions
from saml_ros.export import ExportError, export_model, numpy_residual
from saml_ros.offline import cli, export_cli
from saml_ros.systems.system_file import read_system_file
from saml_ros.user_code import load_system_file

SYSTEM_FILE = REPO / "examples" / "diff_drive" / "system.yaml"
sys.path.insert(0, str(REPO / "examples" / "diff_drive"))
import dynamics  # type: ignore[import-not-found]  # noqa: E402

DT_NS = 20_000_000
T0 = 1_800_000_000 * 1_000_000_000
DOCK = ((0.7, 1.9), (-0.5, 0.5))


pytestmark = pytest.mark.usefixtures("restore_registry")  # robots these tests load are registered by name


def simulate(seconds: float, seed: int) -> tuple[list, list, dict[int, tuple[np.ndarray, np.ndarray]]]:
    """The robot at 50 Hz and a waypoint driver at 10 Hz. Returns odom ``(stamp, x)``, commands ``(receipt,
    u)`` and the truth ``{t_k: (x_k, u applied over [t_k, t_k+1))}``."""
    rng = np.random.default_rng(seed)
    base = dynamics.DiffDrive()
    odom, cmds, truth = [], [], {}
    goal = (1.2, 0.0)
    speed = 0.3
    t_cmd = T0 + 3_000_000
    held = np.zeros(2)
    pending: list[tuple[int, np.ndarray]] = []
    for k in range(int(seconds * 50)):
        t = T0 + k * DT_NS
        x = base.state()
        while t_cmd <= t + DT_NS:  # the driver publishes at 10 Hz with jitter; receipt times are not on the grid
            px, py, yaw = x[:3]
            if math.hypot(goal[0] - px, goal[1] - py) < 0.15:
                goal = ((rng.uniform(*DOCK[0]), rng.uniform(*DOCK[1])) if rng.random() < 0.5
                        else (rng.uniform(-2, 2), rng.uniform(-2, 2)))
                speed = rng.uniform(0.1, 0.5)
            err = (math.atan2(goal[1] - py, goal[0] - px) - yaw + math.pi) % (2 * math.pi) - math.pi
            u = np.clip([speed * max(0.0, math.cos(err)) + rng.normal(0, 0.05), 2 * err + rng.normal(0, 0.2)],
                        [-0.5, -1.5], [0.5, 1.5])
            cmds.append((t_cmd, u))
            pending.append((t_cmd, u))
            t_cmd += 100_000_000 + int(rng.uniform(-8, 8) * 1e6)
        while pending and pending[0][0] <= t:  # the robot applies the last command received at or before t_k
            held = pending.pop(0)[1]
        odom.append((t, x))
        truth[t] = (x, held.copy())
        base.step(held, DT_NS / 1e9)
    return odom, cmds, truth


def write_bag(path: Path, odom: list, cmds: list) -> None:
    system = read_system_file(SYSTEM_FILE)  # not registered: the fixture outlives the per-test clean-up
    sc = system.schema()
    fac = TypestoreFactory()
    events = [(t + 700_000, "/dd/odom", sc.state_to_msg(x, t, factory=fac)) for t, x in odom]
    events += [(t, "/dd/cmd_vel", sc.control_to_msg(u, 0, factory=fac)) for t, u in cmds]
    events.sort(key=lambda e: e[0])
    with BagWriter(path) as w:
        w.add_topic("/dd/odom", sc.state.msg_type)
        w.add_topic("/dd/cmd_vel", sc.control.msg_type)
        for log_time, topic, msg in events:
            w.write_msg(topic, msg, log_time)


@pytest.fixture(scope="module")
def recording(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict]:
    tmp = tmp_path_factory.mktemp("dd_bag")
    odom, cmds, truth = simulate(90.0, seed=0)
    write_bag(tmp / "bag", odom, cmds)
    return tmp / "bag", truth


def test_bag_transitions_are_the_robots_true_steps(recording: tuple[Path, dict]) -> None:
    bag, truth = recording
    system = load_system_file(SYSTEM_FILE)
    out = extract_transitions([bag], system)
    c = out.counts
    assert len(out) > 3500, c
    assert c["unstamped/applied_cmd"] == c["received/applied_cmd"] > 800
    assert c["intervals"] == c["paired"] + c["gap"] + c["no_cmd"] + c["stale_cmd"] + c["ambiguous_cmd"]
    assert c["ambiguous_cmd"] > 0 and c["gap"] == 0
    for x, u, y, t in zip(out.x, out.u, out.y, out.stamps, strict=True):
        want_x, want_u = truth[int(t)]
        np.testing.assert_allclose(x, want_x, atol=1e-12)
        np.testing.assert_array_equal(u, want_u)  # never mis-paired
        nxt = truth[int(t) + DT_NS][0].copy()
        nxt[2] = x[2] + (nxt[2] - x[2] + math.pi) % (2 * math.pi) - math.pi
        np.testing.assert_allclose(y, nxt, atol=1e-12)
    inside = (out.x[:, 0] >= 0.7) & (out.x[:, 0] <= 1.9) & (np.abs(out.x[:, 1]) <= 0.5)
    assert inside.mean() > 0.1


def test_train_from_bag_predict_and_export(recording: tuple[Path, dict], tmp_path: Path,
                                           capsys: pytest.CaptureFixture[str]) -> None:
    torch.set_num_threads(1)
    bag, _ = recording
    run = tmp_path / "run"
    rc = cli.main(["--system-file", str(SYSTEM_FILE), "--bag", str(bag), "--epochs", "40", "--out", str(run),
                   "--no-progress", "--batch-size", "256", "--primal-lr", "3e-3"])
    assert rc == 0, capsys.readouterr().err
    metrics = json.loads((run / "metrics.json").read_text())
    region = metrics["test"]["regions"]["dock_approach"]
    model = load_model(run)
    assert model.state_fields == ("x", "y", "yaw", "v", "w") and model.units["w"] == "rad/s"
    # the learned model beats the unicycle base model in the dock approach, on held-out transitions
    system = model.system
    out = extract_transitions([bag], system)
    inside = (out.x[:, 0] >= 0.7) & (out.x[:, 0] <= 1.9) & (np.abs(out.x[:, 1]) <= 0.5)
    xi, ui, yi = out.x[inside], out.u[inside], out.y[inside]
    err_base = np.linalg.norm(model.base(xi, ui) - yi, axis=1).mean()
    err_model = np.linalg.norm(model.predict(xi, ui) - yi, axis=1).mean()
    assert err_model < 0.5 * err_base, (err_model, err_base)
    assert region["inside"][0] < err_base
    # named, single and batched predictions agree
    one = model.predict(xi[0], ui[0])
    named = model.predict(dict(zip(model.state_fields, xi[:3].T, strict=True)),
                          dict(zip(model.control_fields, ui[:3].T, strict=True)))
    # float32 weights: a single row and a batch may round differently in the last bit
    np.testing.assert_allclose(one, model.predict(xi[:3], ui[:3])[0], rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(named["v"], model.predict(xi[:3], ui[:3])[:, 3], rtol=1e-6, atol=1e-7)
    # export: every format reproduces the model on random inputs (the check inside export) and on real data
    res = model.export(tmp_path / "export")
    assert set(res.files) == {"onnx", "torchscript", "numpy", "casadi"} and res.base_exported
    assert max(res.max_abs_error.values()) < 1e-5
    import onnxruntime

    sess = onnxruntime.InferenceSession(str(res.files["onnx"]))
    dtype = np.float32 if json.loads((tmp_path / "export" / "model.json").read_text())["dtype"] == "float32" \
        else np.float64
    y_onnx, phi_onnx = sess.run(["y", "residual"], {"x": xi.astype(dtype), "u": ui.astype(dtype)})
    np.testing.assert_allclose(y_onnx, model.predict(xi, ui), atol=1e-5)
    ts = torch.jit.load(str(res.files["torchscript"]))
    tdt = torch.float32 if dtype == np.float32 else torch.float64
    with torch.no_grad():
        y_ts, _ = ts(torch.as_tensor(xi, dtype=tdt), torch.as_tensor(ui, dtype=tdt))
    np.testing.assert_allclose(y_ts.double().numpy(), model.predict(xi, ui), atol=1e-5)
    with np.load(res.files["numpy"]) as f:
        phi_np = numpy_residual({k: f[k] for k in f.files}, xi, ui)
    np.testing.assert_allclose(phi_np, model.residual(xi, ui), atol=1e-5)
    # the command-line exporter does the same
    assert export_cli.main([str(run), "-o", str(tmp_path / "cli"), "--format", "numpy"]) == 0
    assert (tmp_path / "cli" / "weights.npz").exists()


def test_export_refuses_unknown_formats(tmp_path: Path) -> None:
    from saml_ros.core.model.network import DynamicsModel

    m = DynamicsModel(load_system_file(SYSTEM_FILE), [4])
    with pytest.raises(ExportError, match="unknown export format"):
        export_model(m, tmp_path, ["tflite"])


def test_train_system_file_without_bag_is_refused(capsys: pytest.CaptureFixture[str]) -> None:
    assert cli.main(["--system-file", str(SYSTEM_FILE)]) == 2
    assert "has no simulator in saml_ros: give its recordings with --bag" in capsys.readouterr().err


def test_bag_info_with_a_system_file(recording: tuple[Path, dict], capsys: pytest.CaptureFixture[str]) -> None:
    from saml_ros.bags import info

    bag, _ = recording
    assert info.main([str(bag), "--system-file", str(SYSTEM_FILE)]) == 0
    out = capsys.readouterr().out
    n = len(extract_transitions([bag], load_system_file(SYSTEM_FILE)))
    assert "system:      diff_drive" in out and f"transitions: {n} (/dd: {n})" in out
    assert "unstamped/applied_cmd" in out and "dock_approach:" in out
