"""msg_schemas: vector <-> stock message round trips (rclpy and rosbags), wire bytes, validation, docs."""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from helpers import REPO
from helpers.messages import BAGS, TS, one_message_per_type, random_vector
from rclpy.serialization import deserialize_message, serialize_message

from msg_schemas import RCLPY, SchemaError, get_schema
from msg_schemas import telemetry as tm
from msg_schemas.base import CHECKPOINT_QOS, DATA_QOS
from msg_schemas.codecs import JointStateCodec, rotation_matrix
from msg_schemas.docs import render
from saml_ros.core.dynamics.quaternion import quat_rotate
from saml_ros.core.systems import get_system, system_names

FACTORIES = {"rclpy": RCLPY, "rosbags": BAGS}
SYSTEMS = ("friction", "quadrotor", "paddle_ball")
MAX_STAMP = (2**31 - 1) * 10**9 + 999_999_999


@pytest.fixture(autouse=True)
def _built_in_systems_only(restore_registry: None) -> None:
    """The registry as a fresh process has it: a robot that a test of another file on this worker registered (a
    system file loaded in-process) is out of it during each test here, and back after (``restore_registry``)."""
    from saml_ros.core.systems import unregister_system

    for name in set(system_names()) - set(SYSTEMS):
        unregister_system(name)


def _assert_built_by(msg: Any, factory_name: str) -> None:
    if factory_name == "rclpy":
        assert not hasattr(msg, "__msgtype__") and type(msg).__module__.split(".")[1] == "msg"
    else:
        assert hasattr(msg, "__msgtype__")


# ------------------------------------------------------------------------------------------- layouts
@pytest.mark.parametrize("system", SYSTEMS)
def test_schema_layouts_match_core_systems(system: str) -> None:
    schema, sys_ = get_schema(system), get_system(system)
    for role in ("state", "control", "target"):
        layout = getattr(sys_, role)
        codec = getattr(schema, role)
        assert codec.field_names == layout.names, role
        assert codec.units == tuple(f.unit for f in layout.fields), role
    assert (schema.target_pairing == "same") == (sys_.dt == 0.0)


def test_get_schema_rejects_unknown_names() -> None:
    with pytest.raises(ValueError, match="friction"):
        get_schema("pendulum")
    assert system_names() == SYSTEMS


# --------------------------------------------------------------------------------------- round trips
@pytest.mark.parametrize("factory_name", FACTORIES)
@pytest.mark.parametrize("system", SYSTEMS)
def test_every_data_topic_round_trips(system: str, factory_name: str) -> None:
    schema, factory = get_schema(system), FACTORIES[factory_name]
    rng = np.random.default_rng(abs(hash((system, factory_name))) % 2**32)
    for spec in schema.topics:
        assert spec.codec is not None and spec.codec.msg_type == spec.msg_type
        role = next(r for r in ("state", "control", "target") if getattr(schema, r) is spec.codec)
        for stamp in (0, 1_700_000_000_123_456_789, MAX_STAMP, int(rng.integers(0, 10**15))):
            x = random_vector(system, role, rng)
            msg = spec.codec.to_msg(x, stamp, factory=factory)
            _assert_built_by(msg, factory_name)
            back, back_stamp = spec.codec.from_msg(msg, spec.name)
            assert back_stamp == stamp
            assert back.dtype == np.float64 and back.shape == x.shape
            if system == "quadrotor" and role == "state":
                np.testing.assert_allclose(back, x, rtol=0, atol=1e-12)
            else:
                assert np.array_equal(back, x), spec.name


@pytest.mark.parametrize("factory_name", FACTORIES)
def test_system_schema_helpers_round_trip(factory_name: str) -> None:
    factory = FACTORIES[factory_name]
    rng = np.random.default_rng(3)
    for system in SYSTEMS:
        schema = get_schema(system)
        for role in ("state", "control", "target"):
            x = random_vector(system, role, rng)
            msg = getattr(schema, f"{role}_to_msg")(x, 42, factory=factory)
            assert msg.header.stamp.sec == 0 and msg.header.stamp.nanosec == 42
            back, stamp = getattr(schema, f"{role}_from_msg")(msg)
            np.testing.assert_allclose(back, x, rtol=0, atol=1e-12)
            assert stamp == 42


def test_quadrotor_twist_is_body_frame_velocity() -> None:
    schema = get_schema("quadrotor")
    yaw90 = [math.cos(math.pi / 4), 0.0, 0.0, math.sin(math.pi / 4)]
    x = np.array([0, 0, 1, 1.0, 0, 0, *yaw90, 0.1, 0.2, 0.3])
    msg = schema.state_to_msg(x, 0)
    assert (msg.header.frame_id, msg.child_frame_id) == ("world", "base_link")
    # body x points along world y, so a world-x velocity is a body -y velocity
    lin = msg.twist.twist.linear
    np.testing.assert_allclose([lin.x, lin.y, lin.z], [0, -1, 0], atol=1e-15)
    assert [msg.twist.twist.angular.x, msg.twist.twist.angular.y, msg.twist.twist.angular.z] == [0.1, 0.2, 0.3]
    o = msg.pose.pose.orientation
    assert [o.w, o.x, o.y, o.z] == yaw90
    # the same convention as core.systems.quaternion: v_world = q (x) twist.linear (x) q*
    rng = np.random.default_rng(0)
    for _ in range(20):
        x = random_vector("quadrotor", "state", rng)
        m = schema.state_to_msg(x, 0)
        v_body = torch.tensor(
            [m.twist.twist.linear.x, m.twist.twist.linear.y, m.twist.twist.linear.z], dtype=torch.float64
        )
        v_world = quat_rotate(torch.from_numpy(x[6:10]), v_body).numpy()
        np.testing.assert_allclose(v_world, x[3:6], atol=1e-12)


def test_paddle_ball_state_reads_any_correctly_framed_odometry() -> None:
    schema = get_schema("paddle_ball")
    x = np.array([0.1, 0.2, 0.3, 1.0, 2.0, -3.0])
    msg = schema.state_to_msg(x, 5)
    o = msg.pose.pose.orientation
    assert (o.w, o.x, o.y, o.z) == (1.0, 0.0, 0.0, 0.0) and msg.child_frame_id == "ball"
    assert (msg.twist.twist.linear.x, msg.twist.twist.linear.y, msg.twist.twist.linear.z) == (1.0, 2.0, -3.0)
    # a tracker publishing a yawed child frame: twist in that frame is rotated back into the world
    o.w, o.z = math.cos(math.pi / 4), math.sin(math.pi / 4)
    msg.twist.twist.linear.x, msg.twist.twist.linear.y, msg.twist.twist.linear.z = 2.0, -1.0, -3.0
    back, _ = schema.state_from_msg(msg)
    np.testing.assert_allclose(back, x, atol=1e-12)


def test_frames_can_be_overridden_per_robot() -> None:
    schema = get_schema("quadrotor")
    msg = schema.state_to_msg(random_vector("quadrotor", "state", np.random.default_rng(1)), 0,
                              frame_id="map", child_frame_id="uav1/base_link")  # fmt: skip
    assert (msg.header.frame_id, msg.child_frame_id) == ("map", "uav1/base_link")


def test_rotation_matrix_is_orthonormal_and_nan_for_zero_quaternion() -> None:
    r = rotation_matrix(np.array([0.3, -0.2, 0.9, 0.1]))
    np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-15)
    assert np.isnan(rotation_matrix(np.zeros(4))).all()


@pytest.mark.parametrize("case", range(8))
def test_rclpy_and_rosbags_serialize_the_same_message(case: int) -> None:
    type_name, build = one_message_per_type()[case]
    rclpy_msg, bag_msg = build(RCLPY), build(BAGS)
    assert bag_msg.__msgtype__ == type_name
    bag_bytes = bytes(TS.serialize_cdr(bag_msg, type_name))
    # rclpy reads rosbags' bytes back into an equal message
    assert deserialize_message(bag_bytes, type(rclpy_msg)) == rclpy_msg
    # rclpy.serialization.serialize_message leaves CDR padding bytes uninitialised and, for JointState with
    # an empty float64[] array, reports a buffer a few bytes longer than the CDR data (trailing junk; the
    # bytes on the wire are exact, see the next test). Compare the decoded values byte for byte instead.
    rclpy_bytes = serialize_message(rclpy_msg)
    assert len(bag_bytes) <= len(rclpy_bytes) <= len(bag_bytes) + 12
    decoded = TS.deserialize_cdr(rclpy_bytes[: len(bag_bytes)], type_name)
    assert bytes(TS.serialize_cdr(decoded, type_name)) == bag_bytes


# ------------------------------------------------------------------------------- CDR fast path
def _cdr_cases() -> list[tuple[str, str, Any]]:
    """(system, role, codec) of every Odometry / JointState codec of every system."""
    from msg_schemas.codecs import OdometryCodec

    out = []
    for system in SYSTEMS:
        schema = get_schema(system)
        for role in ("state", "control", "target"):
            codec = getattr(schema, role)
            if isinstance(codec, OdometryCodec | JointStateCodec):
                out.append((system, role, codec))
    return out


@pytest.mark.parametrize("case", range(len(_cdr_cases())))
def test_cdr_fast_path_writes_and_reads_what_the_object_path_does(case: int) -> None:
    """CdrCodec.encode gives the exact bytes of the message to_msg builds (rosbags' CDR, equal to the bytes on
    the wire, test above); decode reads them back to what from_msg reads from the deserialized message."""
    from msg_schemas.cdr import CdrCodec

    system, role, codec = _cdr_cases()[case]
    fast = CdrCodec(codec)
    rng = np.random.default_rng(case)
    for stamp in (0, 1_700_000_000_123_456_789, MAX_STAMP, int(rng.integers(0, 10**15))):
        x = random_vector(system, role, rng)
        data = fast.encode(x, stamp)
        assert data == bytes(TS.serialize_cdr(codec.to_msg(x, stamp, factory=BAGS), codec.msg_type))
        want, want_stamp = codec.from_msg(deserialize_message(data, RCLPY.cls(codec.msg_type)))
        got, got_stamp = fast.decode(data)
        assert got_stamp == want_stamp == stamp
        assert got.dtype == np.float64 and np.array_equal(got, want)
        # the fast path itself did the work: the same values come back without the object path
        fast._deserialize = None  # type: ignore[method-assign, assignment]
        assert np.array_equal(fast.decode(data)[0], want)
        del fast._deserialize


def test_named_vector_cdr_writes_the_status_message_bytes() -> None:
    """NamedVectorCdr gives the exact bytes of named_vector_to_msg's JointState (mpc/status as the MPC node
    publishes it), also when the names change between messages, and refuses empty names as it does."""
    from msg_schemas.cdr import NamedVectorCdr

    enc = NamedVectorCdr()
    rng = np.random.default_rng(0)
    base = {n: float(v) for n, v in zip(tm.MPC_STATUS_NAMES, rng.normal(size=len(tm.MPC_STATUS_NAMES)), strict=True)}
    for values in (base, base | {"guard_fallbacks": 3.0, "x": math.nan}, {"a": 1.0}, {"abc": -2.5, "de": math.inf},
                   {}, base):
        for stamp in (0, 1_000_000_007, MAX_STAMP):
            want = bytes(TS.serialize_cdr(tm.named_vector_to_msg(values, stamp, factory=BAGS), "sensor_msgs/msg/JointState"))
            assert enc.encode(values, stamp) == want, values
    status = tm.mpc_status_values(base | {"extra": 1.0})
    assert enc.encode(status, 5) == bytes(TS.serialize_cdr(tm.mpc_status_to_msg(base | {"extra": 1.0}, 5, factory=BAGS),
                                                          "sensor_msgs/msg/JointState"))
    with pytest.raises(SchemaError):
        enc.encode({"": 1.0}, 0)


def test_cdr_object_path_writes_the_same_messages_and_names_the_topic(monkeypatch: pytest.MonkeyPatch) -> None:
    """With SAML_CDR=0 (and for codecs without a fast path) encode builds and serializes the message: the same
    message as the fast path's bytes; a bad vector's error names the topic given on either path."""
    from msg_schemas.cdr import CdrCodec, NamedVectorCdr

    rng = np.random.default_rng(7)
    for system, role, codec in _cdr_cases():
        fast = CdrCodec(codec)
        monkeypatch.setenv("SAML_CDR", "0")
        slow = CdrCodec(codec)
        monkeypatch.delenv("SAML_CDR")
        assert fast.fast and not slow.fast
        x = random_vector(system, role, rng)
        cls = RCLPY.cls(codec.msg_type)
        got = codec.from_msg(deserialize_message(slow.encode(x, 123), cls))
        want = codec.from_msg(deserialize_message(fast.encode(x, 123), cls))
        assert got[1] == want[1] == 123 and np.array_equal(got[0], want[0])
        for enc in (fast, slow):
            with pytest.raises(SchemaError, match="/ns/state"):
                enc.encode(np.zeros(codec.size + 1), 0, "/ns/state")
    monkeypatch.setenv("SAML_CDR", "0")
    slow_status = NamedVectorCdr()
    monkeypatch.delenv("SAML_CDR")
    values = {"a": 1.5, "b": -2.0}
    msg = deserialize_message(slow_status.encode(values, 9), RCLPY.cls("sensor_msgs/msg/JointState"))
    assert not slow_status.fast and tm.named_vector_from_msg(msg)[0] == values


def test_cdr_decode_rejects_bytes_that_are_no_message() -> None:
    """A raw subscription may receive bytes rclpy cannot deserialize (a faulty raw publisher): decode raises the
    SchemaError a node counts (``rejected/format``), not rclpy's RMWError, which would end the node's spin."""
    from msg_schemas.cdr import CdrCodec

    for _, _, codec in _cdr_cases():
        for data in (b"", b"\x00\x01\x00\x00garbage", b"\x00\x00\x00\x00" + b"\x01" * 40):
            with pytest.raises(SchemaError) as info:
                CdrCodec(codec).decode(data, "/ns/topic")
            assert info.value.reason == "format" and "/ns/topic" in str(info.value)


def test_cdr_fast_path_leaves_bad_messages_to_from_msg() -> None:
    """Every message from_msg rejects is rejected by CdrCodec.decode with the same SchemaError (the object path
    reads it); other frame ids and a big-endian sender's bytes are read as from_msg reads them."""
    from msg_schemas.cdr import CdrCodec

    quad = get_schema("quadrotor")
    state, control = CdrCodec(quad.state), CdrCodec(quad.control)
    x = random_vector("quadrotor", "state", np.random.default_rng(3))

    def both(codec: Any, msg: Any) -> None:
        data = bytes(TS.serialize_cdr(msg, codec.codec.msg_type))
        rmsg = deserialize_message(data, RCLPY.cls(codec.codec.msg_type))
        try:
            want: Any = codec.codec.from_msg(rmsg, "t")
        except SchemaError as exc:
            with pytest.raises(SchemaError) as info:
                codec.decode(data, "t")
            assert (info.value.reason, info.value.field, str(info.value)) == (exc.reason, exc.field, str(exc))
            return
        got = codec.decode(data, "t")
        assert got[1] == want[1] and np.array_equal(got[0], want[0])

    for path, value in (("twist.twist.linear.y", math.nan), ("twist.twist.angular.z", math.inf),
                        ("pose.pose.position.x", math.nan), ("pose.pose.orientation.w", 0.2),
                        ("header.frame_id", "map"), ("child_frame_id", "a_much_longer_child_frame")):
        m = quad.state_to_msg(x, 5, factory=BAGS)
        *parents, leaf = path.split(".")
        setattr(functools.reduce(getattr, parents, m), leaf, value)
        both(state, m)
    bad_fields: tuple[tuple[str, Any], ...] = (("effort", np.array([1.0, 2.0, math.nan, 4.0])), ("effort", np.array([1.0, 2.0])),
                        ("name", ["rotor1", "rotor2", "rotor4", "rotor3"]), ("name", ["rotor1"]),
                        ("position", np.ones(4)), ("velocity", np.ones(3)))
    for name, value in bad_fields:
        u = quad.control_to_msg([1.0, 2.0, 3.0, 4.0], 7, factory=BAGS)
        setattr(u, name, value)
        both(control, u)
    # a big-endian sender (XCDR1 BE): rclpy reads it, so the fast path hands it over
    be = bytes(TS.serialize_cdr(quad.state_to_msg(x, 9, factory=BAGS), quad.state.msg_type, little_endian=False))
    assert be[:4] != state.encode(x, 9)[:4]
    got, stamp = state.decode(be)
    assert stamp == 9 and np.array_equal(got, quad.state.from_msg(deserialize_message(be, RCLPY.cls(quad.state.msg_type)))[0])
    for bad in (b"", b"\x00\x01\x00\x00" + b"\x01" * 7, state.encode(x, 9)[:-8]):
        with pytest.raises(Exception):  # noqa: B017, PT011 - whatever rclpy raises for a truncated message
            state.decode(bad)


# --------------------------------------------------------------------------------------- rejections
def _raises(fn: Callable[[], Any], reason: str, field: str, *words: str) -> SchemaError:
    with pytest.raises(SchemaError) as info:
        fn()
    err = info.value
    assert isinstance(err, ValueError)
    assert err.reason == reason and err.field == field, (err.reason, err.field, str(err))
    for w in (field, *words):
        assert w in str(err), (w, str(err))
    return err


@pytest.mark.parametrize("factory_name", FACTORIES)
def test_malformed_joint_states_are_rejected_naming_the_field(factory_name: str) -> None:
    factory = FACTORIES[factory_name]
    schema = get_schema("friction")

    def fresh() -> Any:
        return schema.state_to_msg([1.0, 2.0], 10, factory=factory)

    m = fresh()
    m.name = ["pole"]
    _raises(lambda: schema.state_from_msg(m), "names", "name", "friction/state", "cart", "pole")
    m = fresh()
    m.position = np.array([1.0, 2.0])
    _raises(lambda: schema.state_from_msg(m), "shape", "position", "got 2")
    m = fresh()
    m.effort = np.array([1.0, 2.0, 3.0])
    _raises(lambda: schema.state_from_msg(m), "shape", "effort")
    m = fresh()
    m.position = np.array([math.nan])
    _raises(lambda: schema.state_from_msg(m), "nan", "position[0]", "'p'", "nan")
    m = fresh()
    m.velocity = np.array([-math.inf])
    _raises(lambda: schema.state_from_msg(m, topic="/robot7/friction/state"), "nan", "velocity[0]", "'v'",
            "/robot7/friction/state")  # fmt: skip
    m = fresh()
    m.header.stamp.nanosec = 2_000_000_000
    _raises(lambda: schema.state_from_msg(m), "stamp", "header.stamp")
    u = get_schema("quadrotor").control_to_msg([1.0, 2.0, 3.0, 4.0], 0, factory=factory)
    u.effort = np.array([1.0, 2.0, math.nan, 4.0])
    _raises(lambda: get_schema("quadrotor").control_from_msg(u), "nan", "effort[2]", "'f3'", "quadrotor/applied_cmd")
    u.name = ["rotor1", "rotor2", "rotor4", "rotor3"]
    _raises(lambda: get_schema("quadrotor").control_from_msg(u), "names", "name")
    c = get_schema("paddle_ball").control_to_msg(np.arange(6.0), 0, factory=factory)
    c.position = np.arange(5.0)
    _raises(lambda: get_schema("paddle_ball").control_from_msg(c), "shape", "position", "got 5")


@pytest.mark.parametrize("factory_name", FACTORIES)
def test_malformed_odometry_and_twists_are_rejected_naming_the_field(factory_name: str) -> None:
    factory = FACTORIES[factory_name]
    quad = get_schema("quadrotor")
    x = random_vector("quadrotor", "state", np.random.default_rng(5))

    for path, value, field in (("twist.twist.linear.y", math.nan, "'vy'"), ("twist.twist.angular.z", math.inf, "'wz'"),
                               ("pose.pose.position.x", math.nan, "'px'"), ("pose.pose.orientation.w", math.nan, "'qw'")):
        m = quad.state_to_msg(x, 0, factory=factory)
        *parents, leaf = path.split(".")
        setattr(functools.reduce(getattr, parents, m), leaf, value)
        _raises(functools.partial(quad.state_from_msg, m), "nan", path, field)
    m = quad.state_to_msg(x, 0, factory=factory)
    o = m.pose.pose.orientation
    o.w, o.x, o.y, o.z = 0.5 * o.w, 0.5 * o.x, 0.5 * o.y, 0.5 * o.z
    _raises(lambda: quad.state_from_msg(m), "quaternion", "pose.pose.orientation", "norm 0.5")
    ball = get_schema("paddle_ball")
    b = ball.state_to_msg(np.ones(6), 0, factory=factory)
    b.pose.pose.orientation.w = 0.0
    _raises(lambda: ball.state_from_msg(b), "quaternion", "pose.pose.orientation")
    t = ball.target_to_msg(np.ones(3), 0, factory=factory)
    t.twist.linear.z = -math.inf
    _raises(lambda: ball.target_from_msg(t), "nan", "twist.linear.z", "'vz'", "paddle_ball/post_impact")


def test_to_msg_rejects_wrong_shapes_and_stamps_but_publishes_nan() -> None:
    schema = get_schema("quadrotor")
    _raises(lambda: schema.state_to_msg(np.zeros(12), 0), "shape", "vector", "(13,)")
    _raises(lambda: schema.control_to_msg(np.zeros((1, 4)), 0), "shape", "vector")
    _raises(lambda: schema.control_to_msg(np.zeros(4), -1), "stamp", "header.stamp")
    _raises(lambda: schema.control_to_msg(np.zeros(4), 1.5), "stamp", "header.stamp")  # type: ignore[arg-type]
    _raises(lambda: schema.control_to_msg(np.zeros(4), MAX_STAMP + 1), "stamp", "header.stamp")
    # a diverged simulator still publishes; every receiver then counts and drops the message
    msg = schema.control_to_msg([1.0, math.nan, 1.0, 1.0], 0)
    _raises(lambda: schema.control_from_msg(msg), "nan", "effort[1]")


# ----------------------------------------------------------------------------------------- telemetry
@pytest.mark.parametrize("factory_name", FACTORIES)
def test_telemetry_round_trips(factory_name: str) -> None:
    factory = FACTORIES[factory_name]
    names = tm.model_error_names(["near_origin", "far"])
    assert names[:2] == ["objective", "lagrangian"] and "lambda/far" in names and "rejected/nan" in names
    metrics = {n: float(i) for i, n in enumerate(names)} | {"error_in/far": math.nan}
    msg = tm.model_error_to_msg(metrics, 99, factory=factory)
    assert list(msg.name) == names and len(msg.velocity) == 0 and len(msg.effort) == 0
    back, stamp = tm.model_error_from_msg(msg)
    assert stamp == 99 and list(back) == names
    np.testing.assert_array_equal(list(back.values()), list(metrics.values()))  # NaN kept: "no data"

    status = {"iterations": 12, "cost": 0.25, "solve_time_ms": 3.5, "model_version": 2, "deadline_misses": 0,
              "sqp_residual": 1e-6}  # fmt: skip
    msg = tm.mpc_status_to_msg(status, 7, factory=factory)
    assert list(msg.name)[:5] == list(tm.MPC_STATUS_NAMES) and list(msg.name)[5] == "sqp_residual"
    assert tm.mpc_status_from_msg(msg) == (status, 7)

    info = tm.CheckpointInfo("/runs/a/ckpt-000002.saml", 2, "00ff00ff00ff00ff", 3.25)
    assert tm.checkpoint_from_msg(tm.checkpoint_to_msg(info, factory=factory)) == info

    entries = [tm.DiagnosticEntry("/friction/learner", tm.WARN, "drops", {"rejected/nan": 4, "rate": 0.5}),
               tm.DiagnosticEntry("/friction/mpc")]  # fmt: skip
    back_entries, stamp = tm.diagnostics_from_msg(tm.diagnostics_to_msg(entries, 11, factory=factory))
    assert stamp == 11
    assert back_entries[0] == tm.DiagnosticEntry(
        "/friction/learner", tm.WARN, "drops", {"rejected/nan": "4", "rate": "0.5"}
    )
    assert back_entries[1] == entries[1]
    assert tm.clock_from_msg(tm.clock_to_msg(MAX_STAMP, factory=factory)) == MAX_STAMP


def test_malformed_telemetry_is_rejected() -> None:
    msg = tm.model_error_to_msg({"objective": 1.0, "updates": 2.0}, 0)
    msg.position = np.array([1.0])
    _raises(lambda: tm.model_error_from_msg(msg), "shape", "position", "learner/model_error")
    msg = tm.model_error_to_msg({"objective": 1.0, "updates": 2.0}, 0)
    msg.name = ["objective", "objective"]
    _raises(lambda: tm.model_error_from_msg(msg), "names", "name")
    _raises(lambda: tm.model_error_to_msg({"": 1.0}, 0), "names", "name")
    _raises(lambda: tm.mpc_status_to_msg({"cost": 1.0}, 0), "names", "name", "solve_time_ms")
    partial = tm.model_error_to_msg({"cost": 1.0}, 0)
    _raises(lambda: tm.mpc_status_from_msg(partial), "names", "name", "deadline_misses")
    string = RCLPY.cls("std_msgs/msg/String")
    _raises(lambda: tm.checkpoint_from_msg(string(data="{not json")), "format", "data", "learner/checkpoint")
    _raises(lambda: tm.checkpoint_from_msg(string(data="[1, 2]")), "format", "data")
    _raises(lambda: tm.checkpoint_from_msg(string(data='{"path": "/a", "schema_hash": "x", "time": 1}')),
            "format", "data.version")  # fmt: skip
    bad = '{"path": "/a", "version": true, "schema_hash": "x", "time": 1}'
    _raises(lambda: tm.checkpoint_from_msg(string(data=bad)), "format", "data.version")
    bad = '{"path": "/a", "version": 0, "schema_hash": "x", "time": 1}'
    _raises(lambda: tm.checkpoint_from_msg(string(data=bad)), "format", "data")


# -------------------------------------------------------------------------------------- QoS and hashes
def test_qos_specs_convert_to_rclpy_and_to_bag_metadata(tmp_path: Path) -> None:
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, ReliabilityPolicy
    from rosbags.interfaces import ConnectionExtRosbag2
    from rosbags.rosbag2 import Reader, StoragePlugin, Writer

    profile = CHECKPOINT_QOS.to_rclpy()
    assert profile.reliability == ReliabilityPolicy.RELIABLE
    assert profile.durability == DurabilityPolicy.TRANSIENT_LOCAL
    assert profile.history == HistoryPolicy.KEEP_LAST and profile.depth == 1
    assert DATA_QOS.to_rclpy().durability == DurabilityPolicy.VOLATILE

    bag = tmp_path / "bag"
    info = tm.CheckpointInfo("/runs/a/ckpt-000001.saml", 1, "00ff00ff00ff00ff", 1.0)
    with Writer(bag, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        conn = writer.add_connection("/friction/learner/checkpoint", tm.STRING, typestore=TS,
                                     offered_qos_profiles=[CHECKPOINT_QOS.to_rosbags()])  # fmt: skip
        writer.write(conn, 1, TS.serialize_cdr(tm.checkpoint_to_msg(info, factory=BAGS), tm.STRING))
    metadata = (bag / "metadata.yaml").read_text()
    assert "durability: transient_local" in metadata and "depth: 1" in metadata
    with Reader(bag) as reader:
        (conn,) = reader.connections
        assert isinstance(conn.ext, ConnectionExtRosbag2)
        assert conn.ext.offered_qos_profiles == [CHECKPOINT_QOS.to_rosbags()]
        ((_, _, raw),) = list(reader.messages())
        assert tm.checkpoint_from_msg(TS.deserialize_cdr(raw, tm.STRING)) == info


def test_schema_hashes_identify_the_mapping() -> None:
    hashes = {get_schema(s).schema_hash() for s in SYSTEMS}
    assert len(hashes) == 3 and all(len(h) == 16 and int(h, 16) >= 0 for h in hashes)
    assert get_schema("friction").schema_hash() == get_schema("friction").schema_hash()
    base = JointStateCodec([("u", "m/s^2", "cart", "effort")], "c")
    assert base.schema_hash() == JointStateCodec([("u", "m/s^2", "cart", "effort")], "c").schema_hash()
    for variant in (
        JointStateCodec([("u", "N", "cart", "effort")], "c"),
        JointStateCodec([("u", "m/s^2", "cart", "position")], "c"),
        JointStateCodec([("u", "m/s^2", "slider", "effort")], "c"),
        JointStateCodec([("a", "m/s^2", "cart", "effort")], "c"),
    ):
        assert variant.schema_hash() != base.schema_hash()
    assert get_schema("friction").control.schema_hash() == get_schema("friction").topic("cmd").codec.schema_hash()  # type: ignore[union-attr]


# ---------------------------------------------------------------------------------------------- docs
def test_topics_md_is_generated_from_the_schemas() -> None:
    text = render()
    committed = (REPO / "docs" / "topics.md").read_text()
    assert committed == text, "docs/topics.md is stale: ./dev python -m msg_schemas.docs > docs/topics.md"
    for system in SYSTEMS:
        schema = get_schema(system)
        assert schema.schema_hash() in text
        for spec in schema.topics:
            assert f"`/{system}/{spec.name}` — `{spec.msg_type}`" in text
    for spec in tm.TELEMETRY_TOPICS + tm.GLOBAL_TOPICS:
        assert f"`{spec.msg_type}`" in text and spec.qos.describe() in text
