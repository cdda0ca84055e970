"""System files (saml_ros.systems.system_file): a robot described in YAML, every bad configuration fails at
load time with a message naming what is wrong; field paths read rclpy and rosbags messages; base models."""

from __future__ import annotations

import copy
import math
import sys
import textwrap
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
import yaml
from helpers import REPO

from msg_schemas import RCLPY, SchemaError, TypestoreFactory
from msg_schemas.field_path import FieldPathError, resolve
from saml_ros.core.dynamics.base_models import BaseModelError
from saml_ros.systems.system_file import (
    FileSystem,
    SystemFileError,
    parse_definition,
    system_from_params,
)
from saml_ros.user_code import load_system_file, resolve_base_model

EXAMPLE = REPO / "examples" / "diff_drive" / "system.yaml"


pytestmark = pytest.mark.usefixtures("restore_registry")  # robots these tests load are registered by name


def example() -> dict[str, Any]:
    return yaml.safe_load(EXAMPLE.read_text())


def build(raw: dict[str, Any], tmp: Path | None = None) -> FileSystem:
    system = FileSystem(parse_definition(raw, "test.yaml", tmp), "test.yaml", resolve=resolve_base_model)
    system.schema()
    return system


def test_example_loads_and_reads_its_messages() -> None:
    s = load_system_file(EXAMPLE)
    assert s.state.names == ("x", "y", "yaw", "v", "w") and s.control.names == ("v_cmd", "w_cmd")
    assert s.angle_indices == (2,) and s.dt == 0.02
    sc = s.schema()
    assert sc.state.stamped and not sc.control.stamped
    x = np.array([0.5, -1.0, 2.5, 0.3, -0.7])
    for factory in (RCLPY, TypestoreFactory()):
        msg = sc.state_to_msg(x, 1_234_000_000, factory=factory)
        got, stamp = sc.state_from_msg(msg)
        np.testing.assert_allclose(got, x, atol=1e-12)
        assert stamp == 1_234_000_000
        cmd = sc.control_to_msg(np.array([0.2, -1.0]), 0, factory=factory)
        u, t = sc.control.from_msg(cmd, receipt_ns=99)
        np.testing.assert_allclose(u, [0.2, -1.0])
        assert t == 99
    with pytest.raises(SchemaError, match="needs the time it was received"):
        sc.control.from_msg(RCLPY.cls("geometry_msgs/msg/Twist")())
    p = s.pairing()
    assert p.stamped_state and not p.stamped_cmd and p.angle_indices == (2,) and p.dt_ns == 20_000_000


def test_definition_survives_a_checkpoint_round_trip() -> None:
    s = load_system_file(EXAMPLE)
    again = system_from_params(s.params())
    assert again.schema_hash() == s.schema_hash()
    x, u = s.sample_inputs(20, np.random.default_rng(0))
    np.testing.assert_array_equal(again.base_step_np(x, u), s.base_step_np(x, u))


def test_joint_state_by_name_and_malformed_messages() -> None:
    raw = example()
    del raw["mpc"]  # its task names the example's fields
    raw["state"] = {"topic": "joint_states", "type": "sensor_msgs/JointState", "fields": [
        {"name": "q", "unit": "rad", "bounds": [-3, 3], "path": "position[elbow]"},
        {"name": "qd", "unit": "rad/s", "bounds": [-5, 5], "path": "velocity[elbow]"}]}
    raw["control"] = {"topic": "cmd", "type": "std_msgs/msg/Float64MultiArray", "fields": [
        {"name": "tau", "unit": "N*m", "bounds": [-1, 1], "path": "data[0]"}]}
    raw["base_model"] = "hold"
    raw["spec"] = {"objective": {"loss": "l2"}}
    s = build(raw)
    codec = s.schema().state
    js = RCLPY.cls("sensor_msgs/msg/JointState")(name=["shoulder", "elbow"], position=[0.1, 0.2], velocity=[1.0, 2.0])
    js.header.stamp.sec = 3
    x, stamp = codec.from_msg(js)
    np.testing.assert_allclose(x, [0.2, 2.0])
    assert stamp == 3_000_000_000
    js.name = ["shoulder", "wrist"]
    with pytest.raises(SchemaError, match="no entry named 'elbow'") as e:
        codec.from_msg(js)
    assert e.value.reason == "names"
    js.name = ["shoulder", "elbow"]
    js.velocity = [1.0]
    with pytest.raises(SchemaError) as e:
        codec.from_msg(js)
    assert e.value.reason == "shape"
    js.velocity = [1.0, math.nan]
    with pytest.raises(SchemaError) as e:
        codec.from_msg(js)
    assert e.value.reason == "nan"


def test_quaternion_to_yaw_and_bad_quaternions() -> None:
    rp = resolve("yaw(pose.pose.orientation)", "nav_msgs/Odometry")
    odom = RCLPY.cls("nav_msgs/msg/Odometry")()
    for yaw in (-3.0, -0.5, 0.0, 1.0, 3.1):
        rp.write(odom, yaw)
        assert rp.read(odom) == pytest.approx(yaw, abs=1e-12)
    odom.pose.pose.orientation.w = 2.0
    with pytest.raises(SchemaError) as e:
        rp.read(odom)
    assert e.value.reason == "quaternion"


def mutate(path: str, value: Any) -> dict[str, Any]:
    raw = copy.deepcopy(example())
    *keys, last = path.split(".")
    node: Any = raw
    for k in keys:
        node = node[int(k)] if k.isdigit() else node[k]
    if value is KeyError:
        del node[int(last) if last.isdigit() else last]
    elif last.isdigit():
        node[int(last)] = value
    else:
        node[last] = value
    return raw


BAD: list[tuple[str, Any, str]] = [
    ("state.fields.0.path", "pose.pose.postion.x", r"state.fields\[0\].path: .*no field 'postion' \(did you mean 'position'"),
    ("state.fields.2.path", "pose.pose.orientation", r"state.fields\[2\].path: .*not a number \(use yaw"),
    ("state.fields.3.path", "twist.twist.linear", r"state.fields\[3\].path: .*ends on a geometry_msgs/msg/Vector3"),
    ("state.type", "nav_msgs/msg/Odom", r"state.type: .*unknown message type.*nav_msgs/msg/Odometry"),
    ("control.type", "geometry_msgs/msg/Twist3", r"control.type: .*unknown message type"),
    ("control.fields.0.path", "linear", r"control.fields\[0\].path"),
    ("state.fields.3.unit", "rad/s", r"state.fields\[3\].unit: field 'v' is declared in 'rad/s', but "
                                     r"twist.twist.linear.x of nav_msgs/msg/Odometry is in 'm/s'"),
    ("state.fields.0.unit", "meters", r"state.fields\[0\].unit: unit 'meters': 'meters' is not an SI symbol"),
    ("state.fields.2.unit", "deg", r"state.fields\[2\].unit: unit 'deg': 'deg' is not an SI symbol"),
    ("state.fields.4.bounds", [2.0, -2.0], r"state.fields\[4\].bounds: low \(2.0\) must be below high"),
    ("state.fields.2.bounds", [-4, 4], r"angle field 'yaw' is wrapped into \[-pi, pi\]"),
    ("control.fields.0.bounds", [0.0], r"control.fields\[0\].bounds: expected \[low, high\]"),
    ("control.safe", [0.0, 3.0], r"control.safe: the safe command is outside the bounds of \['w_cmd'\]"),
    ("dt", 0.0, r"dt: must be > 0"),
    ("spec.constraints.0.region", {"box": {"x.x": [5.0, 6.0]}}, r"spec.constraints\[0\].region: box x.x \[5.0, 6.0\] "
                                                                 r"lies outside the bounds \[-2.5, 2.5\]"),
    ("spec.constraints.0.region", {"box": {"x.speed": [0, 1]}}, r"spec: .*speed"),
    ("base_model.params.v", "v", r"base_model: .*'v' is not a control field"),
    ("base_model.params.yaw", "v", r"base_model: .*field 'v' has unit 'm/s', but this base model needs 'rad'"),
    ("base_model.builtin", "bicycle", r"base_model: .*unknown built-in 'bicycle'"),
    ("pairing.command_guard", 0.015, r"pairing: cmd_guard_ns .* must be less than half of dt_ns"),
    ("pairing.state", "cubic", r"pairing.state: expected one of"),
    ("pairing.command", "latest", r"pairing.command: expected one of \['hold', 'answer_next_step', 'answer'\]"),
    ("colour", "red", r"unknown key\(s\) \['colour'\]"),
    ("control.topic", "odom", r"control.topic: the state and the control come on the same topic"),
    ("state.topic", "odom//x", r"state.topic: 'odom//x' is not a valid ROS topic name"),
    ("name", "Diff-Drive", r"name: 'Diff-Drive' is not a valid system name"),
]


@pytest.mark.parametrize("path, value, message", BAD, ids=[b[0] + "=" + str(b[1])[:20] for b in BAD])
def test_bad_configuration_names_the_problem(path: str, value: Any, message: str) -> None:
    with pytest.raises(SystemFileError, match=message):
        build(mutate(path, value))


def test_pairing_command_rule() -> None:
    """``pairing.command`` picks the rule for which command each interval gets (docs/your_robot.md)."""
    assert build(example()).pairing().cmd_rule == "hold"  # the default: zero-order hold
    raw = mutate("pairing.command", "answer")
    s = build(raw)
    assert s.pairing().cmd_rule == "answer" and s.definition["pairing"]["command"] == "answer"
    assert system_from_params(s.params()).pairing().cmd_rule == "answer"  # a checkpoint keeps it
    raw["dt"] = 0.01  # the odometry comes at 50 Hz: "answer" needs one state message per interval
    with pytest.raises(SystemFileError, match=r"pairing: cmd_rule 'answer' pairs each state message with its "
                                              r"answer: the state period \(0.02 s\) must equal dt \(0.01 s\)"):
        build(raw)


def test_missing_file_and_bad_yaml(tmp_path: Path) -> None:
    with pytest.raises(SystemFileError, match="no such file"):
        load_system_file(tmp_path / "nope.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("name: [unclosed\n")
    with pytest.raises(SystemFileError, match="cannot read it as YAML"):
        load_system_file(bad)


@pytest.fixture
def user_module(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[str]:
    (tmp_path / "my_robot_models.py").write_text(textwrap.dedent("""
        import torch

        def good(x, u, *, dt, gain=1.0):
            out = x.clone()
            out[:, 0] = x[:, 0] + gain * u[:, 0] * dt
            return out

        def wrong_shape(x, u, *, dt):
            return x[:, :2]

        def not_a_tensor(x, u, *, dt):
            return x.numpy()

        def not_batched(x, u, *, dt):
            return x + x.mean(0)

        def crashes(x, u, *, dt):
            raise RuntimeError("boom")
        """))
    (tmp_path / "broken_models.py").write_text("import this_module_does_not_exist\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    yield "my_robot_models"
    for name in ("my_robot_models", "broken_models"):
        sys.modules.pop(name, None)


@pytest.mark.parametrize("function, message", [
    ("wrong_shape", r"returned shape \(5, 2\) for 5 states, expected \(5, 5\)"),
    ("not_a_tensor", r"returned ndarray, expected a torch.Tensor"),
    ("not_batched", r"row 0 of a batch differs from the same state alone"),
    ("crashes", r"failed on a probe batch .*RuntimeError: boom"),
    ("missing", r"module 'my_robot_models' has no 'missing'"),
])
def test_user_base_model_failures(user_module: str, function: str, message: str) -> None:
    with pytest.raises(SystemFileError, match=message):
        build(mutate("base_model", {"function": f"{user_module}:{function}"}))


def test_user_base_model_import_failure(user_module: str) -> None:
    with pytest.raises(SystemFileError, match=r"cannot import module 'broken_models': ModuleNotFoundError"):
        build(mutate("base_model", {"function": "broken_models:f"}))
    with pytest.raises(SystemFileError, match=r"no entry point of that name in group 'saml_ros.systems'"):
        build(mutate("base_model", {"entry_point": "no_such_robot_model"}))


def test_user_base_model_is_used(user_module: str) -> None:
    s = build(mutate("base_model", {"function": f"{user_module}:good", "params": {"gain": 2.0}}))
    x, u = s.sample_inputs(4, np.random.default_rng(1))
    y = s.base_step_np(x, u)
    np.testing.assert_allclose(y[:, 0], x[:, 0] + 2.0 * u[:, 0] * 0.02)
    np.testing.assert_allclose(y[:, 1:], x[:, 1:])
    assert s.base_step(torch.zeros(2, 5, dtype=torch.float32), torch.zeros(2, 2, dtype=torch.float32)).dtype == \
        torch.float32


def axes_system(model: dict[str, Any]) -> FileSystem:
    raw = example()
    del raw["mpc"]  # its task names the example's fields
    raw["state"]["fields"] = [
        {"name": "p", "unit": "m", "bounds": [-1, 1], "path": "pose.pose.position.x"},
        {"name": "v", "unit": "m/s", "bounds": [-1, 1], "path": "twist.twist.linear.x"}]
    raw["control"] = {"topic": "accel", "type": "geometry_msgs/msg/AccelStamped", "fields": [
        {"name": "a", "unit": "m/s^2", "bounds": [-2, 2], "path": "accel.linear.x"}]}
    raw["base_model"] = model
    raw["spec"] = {"objective": {"loss": "l2"}}
    return build(raw)


def test_builtin_base_models() -> None:
    dt = 0.02
    x = np.array([[0.1, 0.5], [-0.3, -0.2]])
    u = np.array([[1.0], [-2.0]])
    di = axes_system({"builtin": "double_integrator", "params": {"axes": [{"position": "p", "velocity": "v",
                                                                            "acceleration": "a"}]}})
    np.testing.assert_allclose(di.base_step_np(x, u), np.c_[x[:, 0] + x[:, 1] * dt + 0.5 * u[:, 0] * dt**2,
                                                            x[:, 1] + u[:, 0] * dt])
    cv = axes_system({"builtin": "constant_velocity", "params": {"axes": [{"position": "p", "velocity": "v"}]}})
    np.testing.assert_allclose(cv.base_step_np(x, u), np.c_[x[:, 0] + x[:, 1] * dt, x[:, 1]])
    assert np.all(axes_system({"builtin": "zero"}).base_step_np(x, u) == 0)
    np.testing.assert_array_equal(axes_system("hold").base_step_np(x, u), x)  # type: ignore[arg-type]
    with pytest.raises(SystemFileError, match=r"field 'a' has unit 'm/s\^2'|needs 'm/s'"):
        axes_system({"builtin": "constant_velocity", "params": {"axes": [{"position": "p", "velocity": "p"}]}})
    # linear: fitted on data, then stored with the definition and rebuilt exactly
    lin = axes_system({"builtin": "linear"})
    rng = np.random.default_rng(0)
    xs, us = rng.uniform(-1, 1, (200, 2)), rng.uniform(-2, 2, (200, 1))
    ys = di.base_step_np(xs, us)
    np.testing.assert_array_equal(lin.base_step_np(xs, us), xs)  # holds x before it is fitted
    lin.fit_base(xs, us, ys)
    np.testing.assert_allclose(lin.base_step_np(xs, us), ys, atol=1e-6)
    again = system_from_params(lin.params())
    np.testing.assert_array_equal(again.base_step_np(xs, us), lin.base_step_np(xs, us))
    with pytest.raises(BaseModelError, match="A must have shape"):
        from saml_ros.core.dynamics.base_models import BaseModelSpec, FieldInfo, Layouts, build_base_model

        lay = Layouts((FieldInfo("p", "m", -1, 1),), (FieldInfo("a", "m/s^2", -1, 1),), 0.1)
        build_base_model(BaseModelSpec(builtin="linear", params={"A": [[1, 2]], "B": [[0]], "c": [0]}), lay)


def test_field_path_errors_name_path_and_type() -> None:
    with pytest.raises(FieldPathError, match=r"'position\[elbow\]' of geometry_msgs/msg/Twist: .*no field"):
        resolve("position[elbow]", "geometry_msgs/msg/Twist")
    with pytest.raises(FieldPathError, match=r"looks an element up by name, but .*has no parallel 'name' array"):
        resolve("data[elbow]", "std_msgs/msg/Float64MultiArray")
    with pytest.raises(FieldPathError, match=r"index 36 is outside .*covariance \(fixed size 36\)"):
        resolve("pose.covariance[36]", "nav_msgs/msg/Odometry")
    with pytest.raises(FieldPathError, match=r"unknown conversion 'heading'"):
        resolve("heading(pose.pose.orientation)", "nav_msgs/msg/Odometry")


def test_user_base_model_reaches_a_training_process_and_a_checkpoint(user_module: str, tmp_path: Path) -> None:
    """The core imports no code by name: the learner hands its training process the user's function pickled by
    reference, and saml_ros.api imports it for a checkpoint that names it."""
    import pickle

    from saml_ros.api import load_model
    from saml_ros.core.model.checkpoint import CheckpointStore
    from saml_ros.core.model.network import DynamicsModel
    from saml_ros.core.spec import ProblemSpec
    from saml_ros.core.systems import get_system
    from saml_ros.core.training import PrimalDualTrainer, TrainConfig, save_checkpoint

    s = build(mutate("base_model", {"function": f"{user_module}:good", "params": {"gain": 2.0}}))
    params = pickle.loads(pickle.dumps({**s.params(), "base_function": s.user_function}))
    again = get_system(s.name, **params)
    x, u = s.sample_inputs(6, np.random.default_rng(2))
    np.testing.assert_array_equal(again.base_step_np(x, u), s.base_step_np(x, u))
    from saml_ros.core.systems import unregister_system

    unregister_system(s.name)  # a fresh process: the registry has not seen the robot
    with pytest.raises(SystemFileError, match="user code is imported only when the system file is loaded"):
        get_system(s.name, **s.params())  # the definition alone: the core does not import my_robot_models
    model = DynamicsModel(s, [4])
    model.fit_normalization(x, u, s.base_step_np(x, u) + 0.01)
    trainer = PrimalDualTrainer(model, ProblemSpec.for_system(s.paper_spec(), s), TrainConfig())
    save_checkpoint(CheckpointStore(tmp_path), trainer)
    loaded = load_model(tmp_path)
    np.testing.assert_allclose(loaded.predict(x, u), model.predict_np(x, u), atol=1e-6)


def test_a_loaded_robot_is_a_registry_entry(tmp_path: Path) -> None:
    """load_system_file registers the robot: the schema and the system are found by name, a process that only has
    the stored definition rebuilds it; the MPC plans for it with the generic planner (its mpc: section), and refuses
    a robot without one with a clear message."""
    from msg_schemas import get_schema
    from saml_ros.core.mpc.factory import make_controller
    from saml_ros.core.systems import get_entry, get_system, unregister_system

    s = load_system_file(EXAMPLE)
    assert get_schema("diff_drive").state_topic == "odom"
    assert get_entry("diff_drive").make_system().schema_hash() == s.schema_hash()
    from saml_ros.core.mpc.generic import GenericSQP

    assert isinstance(make_controller(s), GenericSQP)
    no_task = example()
    del no_task["mpc"]
    (tmp_path / "no_task.yaml").write_text(yaml.safe_dump(no_task))
    with pytest.raises(ValueError, match="without an 'mpc:' section: add one"):
        make_controller(load_system_file(tmp_path / "no_task.yaml"))
    unregister_system("diff_drive")
    rebuilt = get_system("diff_drive", **s.params())  # the registry loader: from the stored definition alone
    assert rebuilt.schema_hash() == s.schema_hash() and get_entry("diff_drive") is not None
    raw = example()
    raw["name"] = "friction"
    path = tmp_path / "robot.yaml"
    path.write_text(yaml.safe_dump(raw))
    with pytest.raises(SystemFileError, match="is the built-in system of that name"):
        load_system_file(path)
