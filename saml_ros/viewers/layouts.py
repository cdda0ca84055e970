"""Viewer layouts for one system's closed loop, built from msg_schemas (ROS-free; no viewer needed).

The same panels for every viewer (:func:`panels`): the state, the applied command, the learner's live one-step
model error inside and outside each constraint region, the constraint estimates and multipliers (lambda), and the
MPC's solve time. :func:`plotjuggler_layout` writes them as a PlotJuggler layout (XML, ROS 2 topic subscriber) and
:func:`foxglove_layout` as a Foxglove layout (JSON, version 1 of the format of ``foxglove.layouts``; with a 3D panel
showing the ``nav_msgs/Odometry`` of the quadrotor or the ball). Every series is a field that msg_schemas
documents (``FieldDoc.path`` / ``FieldDoc.plotjuggler``), so a schema change shows up in test/test_layouts.py.

``layouts write [--out DIR] [--namespace NS]`` writes the files (layouts/ holds the ones for the default namespaces);
``layouts render BAG -o PNG`` draws the same panels from a recorded bag with matplotlib.
"""

from __future__ import annotations

import json
import xml.etree.ElementTree as ET
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from msg_schemas import get_schema
from msg_schemas.base import FieldDoc, full_topic
from msg_schemas.telemetry import MODEL_ERROR_TOPIC, MPC_STATUS_NAMES, MPC_STATUS_TOPIC, model_error_names
from saml_ros.core.systems.registry import SYSTEM_NAMES

#: the constraint names of each system's paper spec (config/specs/<system>.yaml); model_error names depend on them
PAPER_CONSTRAINTS: dict[str, tuple[str, ...]] = {
    "friction": ("near_origin",),
    "quadrotor": ("near_ground",),
    "paddle_ball": ("slow_balls",),
}
#: state fields plotted per system (the quadrotor's quaternion and body rates stay in the 3D view)
STATE_FIELDS: dict[str, tuple[str, ...]] = {
    "friction": ("p", "v"),
    "quadrotor": ("px", "py", "pz", "vx", "vy", "vz"),
    "paddle_ball": ("px", "py", "pz", "vx", "vy", "vz"),
}
#: Odometry topics shown in the Foxglove 3D panel
THREE_D_TOPICS: dict[str, tuple[str, ...]] = {"friction": (), "quadrotor": ("state",), "paddle_ball": ("flight", "state")}
COLORS = ("#1f77b4", "#d62728", "#2ca02c", "#ff7f0e", "#9467bd", "#8c564b", "#e377c2", "#17becf")


@dataclass(frozen=True)
class Series:
    """One plotted value: ``topic`` (absolute), message field ``path`` (ROS style, e.g. ``position[7]``) and the
    PlotJuggler series name; ``name`` is the vector field or metric name, ``unit`` its unit."""

    topic: str
    name: str
    unit: str
    path: str
    plotjuggler: str

    @property
    def foxglove(self) -> str:
        """The Foxglove message path, ``/ns/topic.field.sub[i]``."""
        return f"{self.topic}.{self.path}"


@dataclass(frozen=True)
class PanelSpec:
    title: str
    series: tuple[Series, ...]


def _vector_series(namespace: str, system: str, topic_name: str, fields: Sequence[str] | None = None) -> list[Series]:
    spec = get_schema(system).topic(topic_name)
    docs = {d.name: d for d in spec.field_docs()}
    names = list(fields) if fields is not None else list(docs)
    topic = full_topic(namespace, topic_name)
    return [Series(topic, n, docs[n].unit, docs[n].path, topic + docs[n].plotjuggler) for n in names]


def _named_series(namespace: str, topic_name: str, names: Sequence[str], wanted: Sequence[str],
                  docs: Sequence[FieldDoc]) -> list[Series]:
    """Series of a JointState "named vector" topic: ``position[i]`` with i the name's index in ``names``."""
    topic = full_topic(namespace, topic_name)
    units = {d.name: d.unit for d in docs}
    out = []
    for n in wanted:
        template = n.split("/", 1)[0] + "/<k>" if "/" in n else n
        out.append(Series(topic, n, units.get(n, units.get(template, "")), f"position[{names.index(n)}]",
                          f"{topic}/{n}/position"))
    return out


def _constraint_names(system: str) -> tuple[str, ...]:
    """The constraints whose live error a layout plots: the paper's spec of a built-in system, the spec of a robot's
    system file (loaded, so registered by its name)."""
    if system in PAPER_CONSTRAINTS:
        return PAPER_CONSTRAINTS[system]
    from saml_ros.core.systems import get_system

    definition: dict[str, Any] = getattr(get_system(system), "definition", {})
    return tuple(c["name"] for c in definition.get("spec", {}).get("constraints", []))


def _three_d_topics(system: str) -> tuple[str, ...]:
    """Topics drawn in the 3D panel: a built-in's, or a robot's state topic when it is an Odometry with a frame."""
    if system in THREE_D_TOPICS:
        return THREE_D_TOPICS[system]
    spec = get_schema(system).topic(get_schema(system).state_topic)
    frame = getattr(spec.codec, "frame_id", "")
    return (spec.name,) if spec.msg_type == "nav_msgs/msg/Odometry" and frame else ()


def panels(system: str, namespace: str | None = None) -> list[PanelSpec]:
    """The panels of ``system``'s layout in ``namespace`` (default ``/<system>``); ``system`` a built-in one or a
    robot whose system file is loaded."""
    from msg_schemas.telemetry import TELEMETRY_TOPICS

    ns = namespace or f"/{system}"
    constraints = _constraint_names(system)
    error_names = model_error_names(constraints)
    docs = {t.name: t.fields for t in TELEMETRY_TOPICS}
    out = [
        PanelSpec("state", tuple(_vector_series(ns, system, get_schema(system).state_topic, STATE_FIELDS.get(system)))),
        PanelSpec("applied command", tuple(_vector_series(ns, system, get_schema(system).applied_cmd_topic))),
    ]
    for k in constraints:
        out.append(PanelSpec(f"live model error in / out of {k}", tuple(_named_series(
            ns, MODEL_ERROR_TOPIC, error_names, [f"error_in/{k}", f"error_out/{k}"], docs[MODEL_ERROR_TOPIC]))))
    out.append(PanelSpec("multipliers and constraint estimates", tuple(_named_series(
        ns, MODEL_ERROR_TOPIC, error_names, [f"{p}/{k}" for k in constraints for p in ("lambda", "constraint")],
        docs[MODEL_ERROR_TOPIC]))))
    out.append(PanelSpec("MPC solve time (ms)", tuple(_named_series(
        ns, MPC_STATUS_TOPIC, list(MPC_STATUS_NAMES), ["solve_time_ms"], docs[MPC_STATUS_TOPIC]))))
    return out


def subscribed_topics(system: str, namespace: str | None = None) -> list[str]:
    """Every topic the layout of ``system`` reads, in a stable order."""
    topics = [s.topic for p in panels(system, namespace) for s in p.series]
    ns = namespace or f"/{system}"
    topics += [full_topic(ns, t) for t in _three_d_topics(system)]
    return list(dict.fromkeys(topics))


# ------------------------------------------------------------------------------------------- PlotJuggler
def plotjuggler_layout(system: str, namespace: str | None = None) -> str:
    """A PlotJuggler layout (XML text): one plot per panel, stacked, and the ROS 2 topic subscriber set to the
    layout's topics (``ros2 run plotjuggler plotjuggler -l <file>``, then Start the ROS2 Topic Subscriber)."""
    specs = panels(system, namespace)
    root = ET.Element("root")
    tabs = ET.SubElement(root, "tabbed_widget", {"name": "Main Window", "parent": "main_window"})
    tab = ET.SubElement(tabs, "Tab", tab_name=f"saml_ros {system}", containers="1")
    container = ET.SubElement(tab, "Container")
    split = ET.SubElement(container, "DockSplitter", orientation="-", count=str(len(specs)),
                          sizes=";".join([f"{1 / len(specs):.6f}"] * len(specs)))
    for spec in specs:
        area = ET.SubElement(split, "DockArea", name=spec.title)
        plot = ET.SubElement(area, "plot", mode="TimeSeries", style="Lines", flip_x="false", flip_y="false")
        ET.SubElement(plot, "range", left="0", right="1", bottom="0", top="1")
        ET.SubElement(plot, "limitY")
        for i, s in enumerate(spec.series):
            ET.SubElement(plot, "curve", name=s.plotjuggler, color=COLORS[i % len(COLORS)])
    ET.SubElement(tabs, "currentTabIndex", index="0")
    ET.SubElement(root, "use_relative_time_offset", enabled="1")
    plugins = ET.SubElement(root, "Plugins")
    sub = ET.SubElement(plugins, "plugin", ID="ROS2 Topic Subscriber")
    for tag, value in (("use_header_stamp", "true"), ("discard_large_arrays", "true"), ("max_array_size", "100"),
                       ("boolean_strings_to_number", "true"), ("remove_suffix_from_strings", "true")):
        ET.SubElement(sub, tag, value=value)
    ET.SubElement(sub, "selected_topics", value=";".join(subscribed_topics(system, namespace)))
    ET.SubElement(root, "previouslyLoaded_Datafiles")
    ET.SubElement(root, "previouslyLoaded_Streamer", name="ROS2 Topic Subscriber")
    ET.indent(root, space=" ")
    return "<?xml version='1.0' encoding='UTF-8'?>\n" + ET.tostring(root, encoding="unicode") + "\n"


# ---------------------------------------------------------------------------------------------- Foxglove
def foxglove_layout(system: str, namespace: str | None = None) -> dict[str, Any]:
    """A Foxglove layout (``foxglove.layouts.Layout`` JSON, version 1): the 3D panel (quadrotor, paddle ball) on
    the left, the plots stacked on the right; series are timed by their header stamps (simulated time)."""
    from msg_schemas.field_path import has_header

    ns = namespace or f"/{system}"
    # a message without a header (a robot's unstamped cmd_vel) is timed by its arrival
    unstamped = {full_topic(ns, t.name) for t in get_schema(system).topics if not has_header(t.msg_type)}
    plots: list[dict[str, Any]] = []
    for spec in panels(system, namespace):
        paths = [{"value": s.foxglove, "enabled": True, "color": COLORS[i % len(COLORS)],
                  "label": f"{s.name} ({s.unit})" if s.unit not in ("", "1", "count") else s.name,
                  "timestampMethod": "receiveTime" if s.topic in unstamped else "headerStamp"}
                 for i, s in enumerate(spec.series)]
        config = {"paths": paths, "showLegend": True, "legendDisplay": "floating", "showXAxisLabels": True,
                  "showYAxisLabels": True, "isSynced": True, "xAxisVal": "timestamp"}
        plots.append({"proportion": 1, "content": {"type": "panel", "panelType": "Plot", "config": config,
                                                   "title": spec.title, "version": 1}})
    column: dict[str, Any] = {"type": "split", "direction": "column", "items": plots}
    odometry = _three_d_topics(system)
    if not odometry:
        content = column
    else:
        frame = get_schema(system).topic(odometry[0]).codec.frame_id  # type: ignore[union-attr]
        three_d = {"type": "panel", "panelType": "ThreeDee", "title": f"{system}: " + ", ".join(odometry),
                   "version": 1, "config": {
                       "followTf": frame,
                       "topics": {full_topic(ns, t): {"visible": True} for t in odometry},
                       "layers": {"grid": {"visible": True, "layerId": "foxglove.Grid", "frameId": frame,
                                           "size": 6, "divisions": 12}},
                       "cameraState": {"distance": 8.0, "perspective": True, "phi": 60.0, "thetaOffset": 45.0,
                                       "target": [0.0, 0.0, 0.5]}}}
        content = {"type": "split", "direction": "row",
                   "items": [{"proportion": 1, "content": three_d}, {"proportion": 1, "content": column}]}
    return {"version": 1, "content": content}


def layout_files(namespace: str | None = None, systems: Sequence[str] = SYSTEM_NAMES) -> dict[str, str]:
    """``{file name: text}`` of the layouts (``<system>.plotjuggler.xml``, ``<system>.foxglove.json``) of
    ``systems`` (default: every built-in one)."""
    out: dict[str, str] = {}
    for system in systems:
        out[f"{system}.plotjuggler.xml"] = plotjuggler_layout(system, namespace)
        out[f"{system}.foxglove.json"] = json.dumps(foxglove_layout(system, namespace), indent=1) + "\n"
    return out


def write_layouts(out: Path, namespace: str | None = None, systems: Sequence[str] = SYSTEM_NAMES) -> list[Path]:
    """Write :func:`layout_files` into directory ``out``; returns the paths."""
    out.mkdir(parents=True, exist_ok=True)
    written = []
    for name, text in layout_files(namespace, systems).items():
        (out / name).write_text(text)
        written.append(out / name)
    return written
