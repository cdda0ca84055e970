"""Bring your own robot, end to end with real processes (docs/your_robot.md).

The example differential-drive robot (examples/diff_drive/robot.py: its own rclpy node, nav_msgs/Odometry at
50 Hz, unstamped geometry_msgs/Twist on cmd_vel) is driven by examples/diff_drive/wander.py at 10 Hz, recorded by
``record``, and learned online by the unmodified ``learner`` from ``system_file:=examples/diff_drive/system.yaml``
(no saml_ros code knows this robot). The model error in the dock approach must fall, a checkpoint is written and
exported (ONNX, TorchScript, numpy) with predictions equal to the model's, and the recorded bag pairs into the
same kind of transitions, on which the learned model beats the base model in the dock approach.
"""

from __future__ import annotations

import signal
from pathlib import Path

import numpy as np
import pytest
from helpers.ros_helpers import RosDomain, TestNode, wait_for
from helpers.your_robot import EXAMPLE, NS, SYSTEM_FILE, launch_script

from msg_schemas import telemetry as tele

pytestmark = pytest.mark.usefixtures("restore_registry")  # robots these tests load are registered by name


def test_example_robot_learned_online_recorded_exported(ros_env: RosDomain, ros_node: TestNode,
                                                        tmp_path: Path) -> None:
    from sensor_msgs.msg import JointState

    run, bag = tmp_path / "run", tmp_path / "bag"
    learner = ros_env.launch(
        "learner", "-p", f"system_file:={SYSTEM_FILE}", "-p", f"run_dir:={run}", "-p", "min_transitions:=200",
        "-p", "checkpoint_period:=2.0", "-p", "telemetry_rate:=4.0", "-p", "train.primal_lr:=0.003",
        "-p", "train.batch_size:=256", namespace=NS)
    rec = ros_env.launch("record", args=["-o", str(bag), "--topics", f"{NS}/odom", f"{NS}/cmd_vel"])
    from diagnostic_msgs.msg import DiagnosticArray

    diagnostics = ros_node.subscribe(DiagnosticArray, "/diagnostics")
    telemetry: list[dict[str, float]] = []
    ros_node.subscribe(JointState, f"{NS}/learner/model_error",
                       callback=lambda m: telemetry.append(tele.model_error_from_msg(m)[0]))
    # the robot starts once the learner listens, so the learner sees its first drive into the dock approach
    try:
        wait_for(lambda: telemetry or not learner.alive(), timeout=60, what="the learner to start")
    except TimeoutError:
        raise AssertionError(f"no learner telemetry within 60 s; learner output:\n{learner.output()}") from None
    assert learner.alive(), learner.output()
    wait_for(lambda: "record: recording" in rec.output() or "record: writing" in rec.output() or not rec.alive(),
             what="the recorder")
    robot = launch_script(ros_env, EXAMPLE / "robot.py", "-p", "x0:=0.4")  # starts 0.3 m before the dock approach
    wander = launch_script(ros_env, EXAMPLE / "wander.py", "-p", "seed:=3")

    key = "error_in/dock_approach"

    def first_in_region() -> float | None:
        """The live in-region error of the model before (or within the first 50 updates of) training: f_hat's."""
        vals = [t[key] for t in telemetry if t["updates"] <= 50 and t["n_in/dock_approach"] >= 20]
        return vals[-1] if vals else None

    try:
        wait_for(lambda: first_in_region() is not None or not learner.alive(), timeout=45,
                 what="the first in-region model error: " + str([(t["updates"], t["n_in/dock_approach"])
                                                                 for t in telemetry[-5:]]))
        assert learner.alive(), learner.output()
        base_err = first_in_region()
        assert base_err is not None

        def paired_now() -> int:
            entries = [e for m in list(diagnostics) for e in tele.diagnostics_from_msg(m)[0]
                       if e.name.endswith("learner")]
            return int(entries[-1].values.get("paired", 0)) if entries else 0

        def learned() -> bool:
            t = telemetry[-1]
            # the kernel-fast learner can halve the error within ~200 transitions: the run also lasts until 400
            # intervals paired, so the recording checked below is long enough to judge
            return t["training"] == 1 and t["updates"] >= 1000 and t[key] < 0.5 * base_err and paired_now() >= 400

        wait_for(lambda: learned() or not learner.alive(), timeout=120, what="the in-region error to halve")
        assert learner.alive(), learner.output()
        last = telemetry[-1]
    finally:
        for p in (wander, robot):
            p.stop()
    learner.signal(signal.SIGINT)  # both stop at once: the learner writes its final checkpoint, the recorder its bag
    rec.signal(signal.SIGINT)
    assert learner.stop(timeout=30) == 0, learner.output()
    assert rec.stop(timeout=20) == 0, rec.output()
    out = learner.output()
    assert "configuration error" not in out and "system file" in out, out
    # /diagnostics carries the resampling counters of the robot's own topics
    entries = [e for m in diagnostics for e in tele.diagnostics_from_msg(m)[0] if e.name.endswith("learner")]
    assert entries, "no learner diagnostics"
    values = entries[-1].values
    assert int(values["unstamped/applied_cmd"]) > 0 and int(values["paired"]) > 200, values
    assert int(values["intervals"]) == sum(int(values[k]) for k in ("paired", "gap", "no_cmd", "stale_cmd",
                                                                  "ambiguous_cmd")), values
    assert last[key] < 0.5 * base_err and last["rejected/duplicate"] == 0, last

    # the checkpoint, through the Python API; its export equals it
    from saml_ros.api import load_model
    from saml_ros.bags.transitions import extract_transitions

    model = load_model(run)
    assert model.system.name == "diff_drive" and model.loaded.meta["updates"] >= 1000
    res = model.export(tmp_path / "export")
    assert set(res.files) == {"onnx", "torchscript", "numpy", "casadi"} and res.base_exported
    assert max(res.max_abs_error.values()) < 1e-5, res.max_abs_error

    # the recording: the same pairing rule yields the robot's transitions; the learned model beats f_hat there
    data = extract_transitions([bag], model.system)
    c = data.counts
    # the run's length depends on how fast the learner learns; most intervals of the recording must pair
    assert len(data) > 100 and len(data) >= 0.6 * c["received/state"], c
    # cmd_vel at 10 Hz beside odom at 50 Hz, every one unstamped
    assert c["unstamped/applied_cmd"] == c["received/applied_cmd"] >= 0.1 * c["received/state"], c
    inside = (data.x[:, 0] >= 0.7) & (data.x[:, 0] <= 1.9) & (np.abs(data.x[:, 1]) <= 0.5)
    assert inside.sum() >= 20
    xi, ui, yi = data.x[inside], data.u[inside], data.y[inside]
    err_model = float(np.linalg.norm(model.predict(xi, ui) - yi, axis=1).mean())
    err_base = float(np.linalg.norm(model.base(xi, ui) - yi, axis=1).mean())
    assert err_model < 0.75 * err_base, (err_model, err_base)
    import onnxruntime

    sess = onnxruntime.InferenceSession(str(res.files["onnx"]))
    dt = np.float32 if model.loaded.model.in_mean.dtype.is_floating_point and \
        str(model.loaded.model.in_mean.dtype) == "torch.float32" else np.float64
    (y_onnx,) = sess.run(["y"], {"x": xi.astype(dt), "u": ui.astype(dt)})
    np.testing.assert_allclose(y_onnx, model.predict(xi, ui), atol=1e-5)

    # (``train --system-file ... --bag`` on such a bag: test_your_robot_offline.py)


@pytest.mark.parametrize("problem, message", [
    ("path", "state.fields[0].path"),
    ("missing", "no such file"),
])
def test_learner_refuses_a_bad_system_file(ros_env: RosDomain, tmp_path: Path, problem: str, message: str) -> None:
    path = tmp_path / "robot.yaml"
    if problem == "path":
        path.write_text(SYSTEM_FILE.read_text().replace("pose.pose.position.x", "pose.pose.positon.x"))
    learner = ros_env.launch("learner", "-p", f"system_file:={path}", "-p", f"run_dir:={tmp_path / 'run'}",
                             namespace=NS)
    assert learner.wait(60) == 2, learner.output()
    out = learner.output()
    assert "configuration error" in out and message in out, out
