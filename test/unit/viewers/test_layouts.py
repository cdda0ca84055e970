"""The viewer layouts in layouts/: every topic and field they reference exists in msg_schemas.

The valid names are built here from msg_schemas alone (topics, message types, FieldDoc paths, the model_error
names of each system's paper spec), independently of saml_ros.viewers.layouts, so renaming a field, a topic or a
metric breaks this test rather than a user's dashboard. The shipped files are also what the generator writes.
"""

from __future__ import annotations

import json
import re
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from helpers import REPO

from msg_schemas import get_schema
from msg_schemas.telemetry import MODEL_ERROR_TOPIC, MPC_STATUS_NAMES, TELEMETRY_TOPICS, model_error_names
from saml_ros.core.systems.registry import SYSTEM_NAMES
from saml_ros.viewers import layouts

LAYOUTS = REPO / "layouts"
ODOMETRY = "nav_msgs/msg/Odometry"


def _paper_constraints(system: str) -> list[str]:
    from saml_ros.core.spec import ProblemSpec
    from saml_ros.core.systems import get_system

    sys_ = get_system(system)
    return list(ProblemSpec.for_system(sys_.paper_spec(), sys_).constraint_names)


def valid_fields(system: str) -> dict[str, dict[str, str]]:
    """``{absolute topic: {PlotJuggler series name: Foxglove message path}}`` of ``system`` in ``/<system>``."""
    ns = f"/{system}"
    out: dict[str, dict[str, str]] = {}
    for t in get_schema(system).topics:
        topic = f"{ns}/{t.name}"
        out[topic] = {topic + d.plotjuggler: f"{topic}.{d.path}" for d in t.field_docs()}
    constraints = _paper_constraints(system)
    for t in TELEMETRY_TOPICS:
        topic = f"{ns}/{t.name}"
        if t.name == MODEL_ERROR_TOPIC:
            names = model_error_names(constraints)
        elif t.msg_type.endswith("JointState"):
            names = list(MPC_STATUS_NAMES)
        else:
            continue
        fields = out.setdefault(topic, {})
        templates = [re.compile("^" + re.escape(d.name).replace("<k>", "[^/]+").replace("<reason>", "[^/]+") + "$")
                     for d in t.field_docs()]
        for i, name in enumerate(names):
            if any(tp.match(name) for tp in templates):
                fields[f"{topic}/{name}/position"] = f"{topic}.position[{i}]"
    return out


def test_every_system_has_both_layouts_and_nothing_else() -> None:
    expected = {f"{s}.plotjuggler.xml" for s in SYSTEM_NAMES} | {f"{s}.foxglove.json" for s in SYSTEM_NAMES}
    assert {p.name for p in LAYOUTS.iterdir()} == expected


@pytest.mark.parametrize("system", SYSTEM_NAMES)
def test_plotjuggler_layout_references_only_schema_fields(system: str) -> None:
    root = ET.parse(LAYOUTS / f"{system}.plotjuggler.xml").getroot()
    fields = valid_fields(system)
    series = {name for topic in fields.values() for name in topic}
    curves = [c.attrib["name"] for c in root.iter("curve")]
    assert curves, system
    assert not [c for c in curves if c not in series], f"unknown series in {system}.plotjuggler.xml"
    plugin = root.find("Plugins/plugin[@ID='ROS2 Topic Subscriber']")
    assert plugin is not None
    selected = plugin.find("selected_topics").attrib["value"].split(";")  # type: ignore[union-attr]
    assert set(selected) <= set(fields), set(selected) - set(fields)
    assert {c for c in curves} <= {s for t in selected for s in fields[t]}  # every curve's topic is subscribed
    titles = [a.attrib["name"] for a in root.iter("DockArea")]
    k = _paper_constraints(system)[0]
    for title, wanted in (("state", "/state/"), ("applied command", "/applied_cmd/"),
                          (f"live model error in / out of {k}", f"/error_in/{k}/"),
                          ("multipliers and constraint estimates", f"/lambda/{k}/"),
                          ("MPC solve time (ms)", "/solve_time_ms/")):
        area = next(a for a in root.iter("DockArea") if a.attrib["name"] == title)
        assert any(wanted in c.attrib["name"] for c in area.iter("curve")), (title, titles)


def _walk(content: dict[str, Any]) -> list[dict[str, Any]]:
    if content["type"] == "panel":
        return [content]
    return [p for item in content["items"] for p in _walk(item["content"])]


@pytest.mark.parametrize("system", SYSTEM_NAMES)
def test_foxglove_layout_references_only_schema_fields(system: str) -> None:
    data = json.loads((LAYOUTS / f"{system}.foxglove.json").read_text())
    assert data["version"] == 1
    fields = valid_fields(system)
    paths = {p for topic in fields.values() for p in topic.values()}
    found = _walk(data["content"])
    plots = [p for p in found if p["panelType"] == "Plot"]
    values = [s["value"] for p in plots for s in p["config"]["paths"]]
    assert len(plots) == 5 and values
    assert not [v for v in values if v not in paths], f"unknown paths in {system}.foxglove.json"
    three_d = [p for p in found if p["panelType"] == "ThreeDee"]
    odometry = {f"/{system}/{t.name}" for t in get_schema(system).topics if t.msg_type == ODOMETRY}
    if odometry:
        (panel,) = three_d
        assert set(panel["config"]["topics"]) and set(panel["config"]["topics"]) <= odometry
        assert panel["config"]["followTf"] == get_schema(system).state.frame_id
    else:
        assert not three_d


@pytest.mark.parametrize("system", SYSTEM_NAMES)
def test_model_error_indices_point_at_the_named_metric(system: str) -> None:
    """Foxglove addresses JointState values by index: position[i] must be the metric the label names, in the
    order the learner publishes (assemble_telemetry)."""
    from saml_ros.core.online import assemble_telemetry

    names = list(assemble_telemetry(_paper_constraints(system), {}, {}))
    for spec in layouts.panels(system):
        for s in spec.series:
            if s.topic.endswith(MODEL_ERROR_TOPIC):
                assert names[int(s.path[len("position["):-1])] == s.name


def test_generator_constraints_are_the_paper_specs() -> None:
    assert {s: list(c) for s, c in layouts.PAPER_CONSTRAINTS.items()} == {s: _paper_constraints(s) for s in SYSTEM_NAMES}


def test_shipped_layouts_are_what_the_generator_writes(tmp_path: Path) -> None:
    for path in layouts.write_layouts(tmp_path):
        assert path.read_text() == (LAYOUTS / path.name).read_text(), f"regenerate: ./dev layouts write ({path.name})"


def test_a_namespace_moves_every_topic(tmp_path: Path) -> None:
    layouts.write_layouts(tmp_path, "/robot1")
    text = (tmp_path / "quadrotor.plotjuggler.xml").read_text() + (tmp_path / "quadrotor.foxglove.json").read_text()
    assert "/robot1/state" in text and "/quadrotor/" not in text


def test_render_draws_every_panel_from_a_bag(tmp_path: Path) -> None:
    """The README picture's code path: series decoded from a real bag written like record writes one."""
    from helpers.bag_publisher import rollout

    from msg_schemas import DATA_QOS, TELEMETRY_QOS, TypestoreFactory
    from msg_schemas.telemetry import model_error_to_msg, mpc_status_to_msg
    from saml_ros.bags.io import Bag, BagWriter, jazzy_typestore
    from saml_ros.viewers.render import render_layout, series_from_bag

    ns, factory, schema = "/friction", TypestoreFactory(jazzy_typestore()), get_schema("friction")
    events = rollout("friction", 30, 0, seed=5, t0_ns=10**9)
    names = model_error_names(["near_origin"])
    with BagWriter(tmp_path / "bag") as w:
        for topic, qos in (("state", DATA_QOS), ("applied_cmd", DATA_QOS), ("learner/model_error", TELEMETRY_QOS),
                           ("mpc/status", TELEMETRY_QOS)):
            w.add_topic(f"{ns}/{topic}", "sensor_msgs/msg/JointState", qos)
        for k, ev in enumerate(events):
            t = ev["stamp"]
            w.write_msg(f"{ns}/state", schema.state_to_msg(ev["x"], t, factory=factory), t)
            if "u" in ev:
                w.write_msg(f"{ns}/applied_cmd", schema.control_to_msg(ev["u"], t, factory=factory), t)
            w.write_msg(f"{ns}/learner/model_error", model_error_to_msg(
                {n: float(k) for n in names}, t, factory=factory), t)
            w.write_msg(f"{ns}/mpc/status", mpc_status_to_msg(
                {n: 2.0 * k for n in MPC_STATUS_NAMES}, t, factory=factory), t)
    with Bag(tmp_path / "bag") as bag:
        data = series_from_bag(bag, "friction")
    assert {name for _, name in data} == {"p", "v", "u", "error_in/near_origin", "error_out/near_origin",
                                          "lambda/near_origin", "constraint/near_origin", "solve_time_ms"}
    np.testing.assert_allclose(data[(f"{ns}/mpc/status", "solve_time_ms")][:, 1], 2.0 * np.arange(30))
    np.testing.assert_allclose(data[(f"{ns}/state", "p")][:, 1], [ev["x"][0] for ev in events])
    out = render_layout(tmp_path / "bag", "friction", tmp_path / "panels.png")
    assert out.stat().st_size > 10_000


@pytest.mark.usefixtures("restore_registry")
def test_a_robots_layouts_from_its_system_file(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``layouts write --system-file``: the robot's own topics and fields, the live error of its file's constraints,
    its unstamped command timed by arrival; a file that cannot be loaded exits 2 naming it."""
    from saml_ros.viewers.cli import main

    system_file = REPO / "examples" / "diff_drive" / "system.yaml"
    assert main(["write", "--out", str(tmp_path), "--system-file", str(system_file), "--namespace", "/dd"]) == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["diff_drive.foxglove.json", "diff_drive.plotjuggler.xml"]
    schema = get_schema("diff_drive")
    valid = {f"/dd/{t.name}.{d.path}" for t in schema.topics for d in t.field_docs()}
    series = {p["value"]: p["timestampMethod"] for p in _plot_paths(json.loads(
        (tmp_path / "diff_drive.foxglove.json").read_text()))}
    robot = {v: m for v, m in series.items() if not v.startswith(("/dd/learner", "/dd/mpc"))}
    assert robot and set(robot) <= valid, set(robot) - valid
    assert {m for v, m in robot.items() if v.startswith("/dd/cmd_vel")} == {"receiveTime"}
    assert {m for v, m in robot.items() if v.startswith("/dd/odom")} == {"headerStamp"}
    names = model_error_names(["dock_approach"])
    assert f"/dd/learner/model_error.position[{names.index('error_in/dock_approach')}]" in series
    xml = (tmp_path / "diff_drive.plotjuggler.xml").read_text()
    assert "/dd/odom;/dd/cmd_vel;/dd/learner/model_error" in xml
    assert main(["write", "--out", str(tmp_path), "--system-file", str(tmp_path / "missing.yaml")]) == 2
    assert "missing.yaml" in capsys.readouterr().err


def _plot_paths(node: Any) -> list[dict[str, Any]]:
    """Every Plot panel's series in a Foxglove layout."""
    if isinstance(node, dict):
        if node.get("panelType") == "Plot":
            return list(node["config"]["paths"])
        return [p for v in node.values() for p in _plot_paths(v)]
    if isinstance(node, list):
        return [p for v in node for p in _plot_paths(v)]
    return []
