"""Bag I/O, offline pairing and bag errors (saml_ros.bags.io, saml_ros.bags.transitions, bag_info, train --bag); no ROS graph.

Bags are written with :class:`saml_ros.bags.io.BagWriter` from roll-outs of the systems' true dynamics
(``bag_publisher.rollout``, the same events the publisher process sends), and checked with the independent
``mcap`` + ``mcap-ros2-support`` readers as well as with our reader.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from helpers.bag_publisher import rollout
from helpers.bag_test_helpers import FACTORY, T0, expected, write_rollout

from msg_schemas import CHECKPOINT_QOS, DATA_QOS, TELEMETRY_QOS, get_schema
from saml_ros.bags import info as bag_info
from saml_ros.bags.io import Bag, BagError, BagWriter, jazzy_typestore, repair_bag
from saml_ros.bags.transitions import extract_transitions, infer_system, transitions_from_bags
from saml_ros.core.spec import ProblemSpec
from saml_ros.core.systems import get_system


# ------------------------------------------------------------------------------------------ format
def test_written_bag_is_jazzy_format_with_offered_qos(friction_bag: tuple[Path, list[dict]]) -> None:
    path, events = friction_bag
    meta = yaml.safe_load((path / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert meta["version"] == 9
    assert meta["storage_identifier"] == "mcap"
    assert meta["relative_file_paths"] == [f"{path.name}.mcap"]
    topics = {t["topic_metadata"]["name"]: t for t in meta["topics_with_message_count"]}
    assert topics["/friction/state"]["message_count"] == len(events)
    for name, qos in [("/friction/state", DATA_QOS), ("/friction/learner/model_error", TELEMETRY_QOS),
                      ("/friction/learner/checkpoint", CHECKPOINT_QOS)]:
        md = topics[name]["topic_metadata"]
        (profile,) = md["offered_qos_profiles"]  # version 9: a list of mappings, not a YAML string
        assert profile["reliability"] == "reliable"
        assert profile["durability"] == ("transient_local" if qos.transient_local else "volatile")
        assert profile["history"] == "keep_last" and profile["depth"] == qos.depth
        assert md["serialization_format"] == "cdr"
        assert md["type_description_hash"] == jazzy_typestore().hash_rihs01(md["type"])


def test_independent_mcap_reader_decodes_every_message(friction_bag: tuple[Path, list[dict]]) -> None:
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    path, events = friction_bag
    schema = get_schema("friction")
    states = []
    with open(path / f"{path.name}.mcap", "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        assert reader.get_header().profile == "ros2"
        summary = reader.get_summary()
        assert summary is not None and summary.statistics is not None
        n_all = summary.statistics.message_count
        for _schema, channel, _message, decoded in reader.iter_decoded_messages():
            if channel.topic == "/friction/state":
                states.append(schema.state_from_msg(decoded, channel.topic))
            if channel.topic == "/friction/learner/checkpoint":
                assert json.loads(decoded.data)["version"] == 1
            assert "offered_qos_profiles" in channel.metadata
    assert n_all == Bag(path).message_count
    assert len(states) == len(events)
    for (x, stamp), ev in zip(states, events, strict=True):
        assert stamp == ev["stamp"]
        np.testing.assert_array_equal(x, ev["x"])


def test_reader_reports_topics_counts_and_duration(friction_bag: tuple[Path, list[dict]]) -> None:
    path, events = friction_bag
    with Bag(path) as bag:
        assert bag.version == 9 and bag.storage == "mcap"
        assert bag.topics["/friction/state"].msg_type == "sensor_msgs/msg/JointState"
        assert bag.topics["/friction/applied_cmd"].message_count == sum("u" in e for e in events)
        assert bag.topics["/friction/state"].qos[0].depth == DATA_QOS.depth
        assert bag.start_ns == T0  # the checkpoint announcement
        assert bag.end_ns == events[-1]["stamp"] + 1_000_000
        assert bag.duration_ns == bag.end_ns - bag.start_ns


# ------------------------------------------------------------------------------------------ pairing
@pytest.mark.parametrize("system", ["friction", "quadrotor", "paddle_ball"])
def test_transitions_are_exactly_the_rollouts(tmp_path: Path, system: str) -> None:
    events = rollout(system, 60, 25, seed=1, t0_ns=T0)
    write_rollout(tmp_path / "b", system, events)
    x, u, y = transitions_from_bags([tmp_path / "b"], get_system(system))
    ex, eu, ey = expected(events)
    assert len(x) == len(ex) > 0
    # exact, except the quadrotor's velocities, which go through R(q)^T (message) and R(q) (back)
    tol = 1e-12 if system == "quadrotor" else 0.0
    np.testing.assert_allclose(x, ex, rtol=0, atol=tol)
    np.testing.assert_array_equal(u, eu)
    np.testing.assert_allclose(y, ey, rtol=0, atol=tol)
    with Bag(tmp_path / "b") as bag:
        assert infer_system(bag) == system


def test_several_namespaces_and_bags_pair_separately(tmp_path: Path) -> None:
    ev_a = rollout("friction", 50, 0, seed=1, t0_ns=T0)
    ev_b = rollout("friction", 30, 0, seed=2, t0_ns=T0)  # same stamps as robot a: must not mix
    with BagWriter(tmp_path / "two") as w:
        write_rollout(tmp_path, "friction", ev_a, namespace="/r1", writer=w)
        write_rollout(tmp_path, "friction", ev_b, namespace="/r2", writer=w)
    ev_c = rollout("friction", 20, 0, seed=4, t0_ns=T0 + 10**10)
    write_rollout(tmp_path / "one", "friction", ev_c, namespace="/r1")
    out = extract_transitions([tmp_path / "two", tmp_path / "one"], "friction")
    assert [(s.namespace, s.transitions) for s in out.sources] == [("/r1", 49), ("/r2", 29), ("/r1", 19)]
    for i, ev in enumerate((ev_a, ev_b, ev_c)):
        ex, eu, ey = expected(ev)
        sel = out.source == i
        np.testing.assert_array_equal(out.x[sel], ex)
        np.testing.assert_array_equal(out.y[sel], ey)
    only = extract_transitions([tmp_path / "two"], "friction", namespaces=["r2"])
    assert len(only) == 29


def test_malformed_messages_are_dropped_and_counted_like_the_learner(tmp_path: Path) -> None:
    events = rollout("friction", 30, 0, seed=5, t0_ns=T0)
    events[10]["x"] = np.array([np.nan, 0.0])  # breaks transitions 9 (as target) and 10 (as start)
    schema = get_schema("friction")
    with BagWriter(tmp_path / "b") as w:
        write_rollout(tmp_path, "friction", events, writer=w)
        # a state with foreign joint names at a fresh stamp: rejected as "names", pairs nothing
        js = FACTORY.make("sensor_msgs/msg/JointState", header=schema.state_to_msg(events[0]["x"], 1, factory=FACTORY).header,
                          name=["wheel"], position=np.zeros(1), velocity=np.zeros(1), effort=np.zeros(0))
        w.write_msg("/friction/state", js, events[-1]["stamp"] + 10**9)
    out = extract_transitions([tmp_path / "b"], "friction")
    assert len(out) == 29 - 2
    assert out.counts["nan"] == 1 and out.counts["names"] == 1
    ex, eu, ey = expected(events)
    keep = [k for k in range(29) if k not in (9, 10)]
    np.testing.assert_array_equal(out.x, ex[keep])
    np.testing.assert_array_equal(out.y, ey[keep])


@pytest.mark.parametrize("kind", ["truncated", "unfinished", "notopics", "wrongtype", "empty", "missing", "nopairs"])
def test_bad_bag_raises_bag_error_naming_bag_and_problem(bad_bags: dict, kind: str) -> None:
    path, fragment = bad_bags[kind]
    with pytest.raises(BagError) as err:
        transitions_from_bags([path], get_system("friction"))
    assert isinstance(err.value, ValueError)
    assert str(path) in str(err.value) and fragment in str(err.value)


def test_every_truncation_of_a_bag_gives_an_actionable_bag_error(tmp_path: Path,
                                                                  friction_bag: tuple[Path, list[dict]]) -> None:
    """A bag cut at any offset (from a few bytes to one byte short) fails with a BagError that names the bag, says
    it is truncated (or empty) and how to recover it: never another exception, never a reader's internal text."""
    good = friction_bag[0]
    bag = tmp_path / "cut"
    shutil.copytree(good, bag)
    mcap = next(bag.glob("*.mcap"))
    data = mcap.read_bytes()
    # every offset through the magic, the header and the first records, then 40 spread over the file, then the footer
    offsets = sorted({*range(0, 100), *range(100, len(data), len(data) // 40), *range(len(data) - 40, len(data))})
    for off in offsets:
        mcap.write_bytes(data[:off])
        with pytest.raises(BagError) as err:
            transitions_from_bags([bag], get_system("friction"))
        text = str(err.value)
        assert str(bag) in text and ("truncated" in text or "empty" in text), (off, text)
        assert "--repair" in text, (off, text)


def test_writer_refuses_existing_path_and_unknown_type(tmp_path: Path) -> None:
    (tmp_path / "x").mkdir()
    with pytest.raises(BagError, match="already exists"):
        BagWriter(tmp_path / "x")
    with BagWriter(tmp_path / "y") as w, pytest.raises(BagError, match="unknown message type"):
        w.add_topic("/a", "my_msgs/msg/Nope", DATA_QOS)
    with BagWriter(tmp_path / "z") as w, pytest.raises(BagError, match="type hash"):
        w.add_topic("/a", "sensor_msgs/msg/JointState", DATA_QOS, type_hash="RIHS01_" + "0" * 64)


# ------------------------------------------------------------------------------------------ repair
def test_repair_recovers_every_flushed_chunk_of_an_unfinished_bag(tmp_path: Path) -> None:
    """A writer "killed" after flushes: copy its file before close(), then cut it inside the last chunk."""
    events = rollout("friction", 300, 0, seed=2, t0_ns=T0)
    schema = get_schema("friction")
    w = BagWriter(tmp_path / "live", flush_period=3600)
    w.add_topic("/friction/state", "sensor_msgs/msg/JointState", DATA_QOS)
    w.add_topic("/friction/applied_cmd", "sensor_msgs/msg/JointState", DATA_QOS)
    for k, ev in enumerate(events):
        w.write_msg("/friction/state", schema.state_to_msg(ev["x"], ev["stamp"], factory=FACTORY), ev["stamp"])
        if "u" in ev:
            w.write_msg("/friction/applied_cmd", schema.control_to_msg(ev["u"], ev["stamp"], factory=FACTORY),
                        ev["stamp"])
        if k == 199:
            w.flush()
            flushed = (tmp_path / "live" / "live.mcap").read_bytes()
    w.flush()
    full = (tmp_path / "live" / "live.mcap").read_bytes()
    w.close()
    dead = tmp_path / "dead"
    dead.mkdir()
    # the process died while writing the second chunk: half of it reached the disk
    (dead / "dead.mcap").write_bytes(full[: len(flushed) + (len(full) - len(flushed)) // 2])
    with pytest.raises(BagError, match="no metadata.yaml"):
        Bag(dead)
    res = repair_bag(dead)
    assert res.path == tmp_path / "dead_repaired" and not res.complete and res.problem
    assert res.topics == {"/friction/state": 200, "/friction/applied_cmd": 200}
    out = extract_transitions([res.path], "friction")
    ex, eu, ey = expected(events)
    assert len(out) == 199  # the 200th state's successor was in the lost chunk
    np.testing.assert_array_equal(out.x, ex[:199])
    np.testing.assert_array_equal(out.y, ey[:199])
    with pytest.raises(BagError, match="already exists"):
        repair_bag(dead)
    # a complete bag repairs to an identical copy
    again = repair_bag(tmp_path / "live", tmp_path / "copy")
    assert again.complete and again.messages == Bag(tmp_path / "live").message_count


# ------------------------------------------------------------------------------------------ bag_info
def test_bag_info_reports_transitions_and_paper_spec_regions(friction_bag: tuple[Path, list[dict]],
                                                             tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    path, events = friction_bag
    assert bag_info.main([str(path), "--json", "--plot", str(tmp_path / "err.png")]) == 0
    info = json.loads(capsys.readouterr().out)
    ex, eu, ey = expected(events)
    assert info["system"] == "friction" and info["transitions"] == len(ex)
    assert info["topics"]["/friction/state"] == {"type": "sensor_msgs/msg/JointState", "count": len(events),
                                                 "qos": "reliable, volatile"}
    system = get_system("friction")
    spec = ProblemSpec.for_system(system.paper_spec(), system)
    masks = spec.masks(torch.as_tensor(ex), torch.as_tensor(eu), torch.as_tensor(ey))[1:]
    for term, mask in zip(spec.constraints, masks, strict=True):
        assert mask is not None
        assert info["regions"][term.name] == pytest.approx(float(mask.double().mean()))
    png = (tmp_path / "err.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 10_000
    assert bag_info.main([str(path)]) == 0
    text = capsys.readouterr().out
    assert "transitions: " + str(len(ex)) in text and "near_origin" in text


def test_bag_info_fails_clearly(bad_bags: dict, capsys: pytest.CaptureFixture) -> None:
    path, fragment = bad_bags["truncated"]
    assert bag_info.main([str(path)]) == 1
    assert fragment in capsys.readouterr().err
    empty, _ = bad_bags["notopics"]
    assert bag_info.main([str(empty), "--plot", "/nonexistent/x.png"]) == 1
    assert "no learner/model_error topic" in capsys.readouterr().err


@pytest.mark.parametrize("system", ["quadrotor", "paddle_ball"])
def test_system_is_inferred_from_topics_in_any_namespace(tmp_path: Path, system: str) -> None:
    """Both record Odometry states: the commands' joint names (and post_impact) tell them apart."""
    events = rollout(system, 10, 0, seed=1, t0_ns=T0)
    write_rollout(tmp_path / "b", system, events, namespace="/robot7")
    with Bag(tmp_path / "b") as bag:
        assert bag.custom_data == {}
        assert infer_system(bag) == system
