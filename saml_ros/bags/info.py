"""``ros2 run saml_ros bag_info BAG``: what a bag holds, the transitions in it, and a model-error plot.

    bag_info runs/flight1                      # topics, types, counts, QoS, duration, transitions, regions
    bag_info runs/flight1 --plot error.png     # learner/model_error channels over time
    bag_info runs/flight1 --json               # the same as JSON
    bag_info runs/killed --repair              # recover a bag whose recorder was killed -> runs/killed_repaired

The system is read from metadata.yaml (``custom_data`` written by ``record --system``) or inferred from
the topics; transitions are extracted with :mod:`saml_ros.bags.transitions` (the learner's pairing), and the
fraction of them inside each constraint region of the system's paper spec is reported. Exit status 1 when
the bag cannot be read (the message says why), 0 otherwise.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from msg_schemas.names import join_topic
from saml_ros.bags.io import Bag, BagError, repair_bag


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="bag_info", description="Describe a saml_ros bag (rosbag2, MCAP).")
    p.add_argument("bag", type=Path)
    p.add_argument("--system", help="system (default: from metadata.yaml or inferred from the topics)")
    p.add_argument("--system-file", type=Path, help="a robot described by a system file (docs/your_robot.md)")
    p.add_argument("--namespace", nargs="+", metavar="NS", help="system namespace(s) (default: all found)")
    p.add_argument("--plot", type=Path, metavar="PNG", help="plot learner/model_error channels over time")
    p.add_argument("--json", action="store_true", help="print the summary as JSON")
    p.add_argument("--repair", action="store_true",
                   help="recover an unfinished/truncated bag into a new bag (see --out), then describe it")
    p.add_argument("--out", type=Path, help="--repair output directory (default: <bag>_repaired)")
    return p


def describe_qos(profiles: Sequence[Any]) -> str:
    """``"reliable, volatile"`` for the recorded profiles (``"?"`` if none)."""
    if not profiles:
        return "?"
    parts = []
    for q in profiles:
        parts.append(f"{q.reliability.name.lower().replace('_', ' ')}, {q.durability.name.lower().replace('_', ' ')}")
    return " | ".join(dict.fromkeys(parts))


def summarize(bag: Bag, system: Any = None, namespaces: Sequence[str] | None = None) -> dict[str, Any]:
    """Everything ``bag_info`` prints, as a JSON-able dict (``system``: a name, a System or None = inferred)."""
    info: dict[str, Any] = {
        "path": str(bag.path),
        "version": bag.version,
        "storage": bag.storage,
        "ros_distro": bag.ros_distro,
        "start_s": bag.start_ns / 1e9,
        "duration_s": bag.duration_ns / 1e9,
        "messages": bag.message_count,
        "custom_data": bag.custom_data,
        "topics": {
            t.name: {"type": t.msg_type, "count": t.message_count, "qos": describe_qos(t.qos)}
            for t in bag.topics.values()
        },
    }
    try:
        info.update(_transitions_summary(bag, system, namespaces))
    except BagError as exc:
        info["transitions_error"] = str(exc)
    return info


def _transitions_summary(bag: Bag, system: Any, namespaces: Sequence[str] | None) -> dict[str, Any]:
    import torch

    from msg_schemas.telemetry import REJECT_REASONS
    from saml_ros.bags.transitions import extract_transitions, infer_system
    from saml_ros.core.spec import ProblemSpec
    from saml_ros.core.systems import get_system

    sysobj = system if system is not None and not isinstance(system, str) else get_system(system or infer_system(bag))
    name = sysobj.name
    tr = extract_transitions([bag.path], sysobj, namespaces)
    spec = ProblemSpec.for_system(sysobj.paper_spec(), sysobj)
    regions: dict[str, float] = {}
    if len(tr):
        x, u, y = (torch.as_tensor(a) for a in (tr.x, tr.u, tr.y))
        for term, mask in zip(spec.constraints, spec.masks(x, u, y)[1:], strict=True):
            regions[term.name] = 1.0 if mask is None else float(mask.double().mean())
    return {
        "system": name,
        "transitions": len(tr),
        "sources": {s.namespace: {"transitions": s.transitions,
                                  "dropped": {k: s.counts[k] for k in REJECT_REASONS if s.counts.get(k)}}
                    for s in tr.sources},
        "spec": spec.raw.get("name", ""),
        "regions": regions,
        # a robot's own topics (resampled): every counter of its pairing rule that is not zero
        "pairing": {s.namespace: {k: v for k, v in s.counts.items() if v} for s in tr.sources}
        if callable(getattr(sysobj, "pairing", None)) else {},
    }


def print_summary(info: dict[str, Any]) -> None:
    print(f"bag:         {info['path']}")
    print(f"format:      rosbag2 version {info['version']}, storage {info['storage']}, "
          f"written by {info['ros_distro'] or '?'}")
    print(f"duration:    {info['duration_s']:.3f} s (first message at {info['start_s']:.3f} s)")
    print(f"messages:    {info['messages']}")
    if info["custom_data"]:
        print("custom data: " + ", ".join(f"{k}={v}" for k, v in info["custom_data"].items()))
    print("topics:")
    width = max([len(t) for t in info["topics"]] + [5])
    twidth = max([len(t["type"]) for t in info["topics"].values()] + [4])
    for name, t in info["topics"].items():
        print(f"  {name:<{width}}  {t['type']:<{twidth}}  {t['count']:>8} msgs  {t['qos']}")
    if "transitions_error" in info:
        print(f"transitions: none: {info['transitions_error']}")
        return
    print(f"system:      {info['system']}")
    per_ns = "; ".join(f"{ns}: {s['transitions']}" + (f" (dropped {s['dropped']})" if s["dropped"] else "")
                       for ns, s in info["sources"].items())
    print(f"transitions: {info['transitions']} ({per_ns})")
    for ns, counts in info.get("pairing", {}).items():
        print(f"pairing {ns}: " + ", ".join(f"{k} {v}" for k, v in counts.items()))
    if info["regions"]:
        print(f"constraint regions of the paper spec '{info['spec']}':")
        for k, frac in info["regions"].items():
            print(f"  {k}: {100 * frac:.2f}% of transitions inside")


# ------------------------------------------------------------------------------------------------ plot
_GROUPS = (
    ("loss", ("objective", "lagrangian", "error_in/", "error_out/")),
    ("constraint g_k", ("constraint/",)),
    ("lambda", ("lambda/",)),
    ("count", ("buffer_size", "updates", "model_version")),
    ("rejected (count)", ("rejected/",)),
)


def plot_model_error(bag: Bag, out: Path, namespaces: Sequence[str] | None = None) -> Path:
    """Draw every ``<ns>/learner/model_error`` channel over its stamps (s) into ``out`` (PNG).

    Channels are grouped into panels (losses, constraints, lambdas, counts, rejections); NaN values
    (no sample yet) leave gaps. Raises :class:`BagError` if the bag has no such topic or message.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from msg_schemas.telemetry import MODEL_ERROR_TOPIC, model_error_from_msg

    topics = ([join_topic(ns, MODEL_ERROR_TOPIC) for ns in namespaces] if namespaces else
              [t for t in bag.topics if t.endswith("/" + MODEL_ERROR_TOPIC)])
    topics = [t for t in topics if t in bag.topics]
    if not topics:
        raise BagError(f"bag {bag.path}: no {MODEL_ERROR_TOPIC} topic to plot (is a learner running while recording?)")
    series: dict[str, dict[str, list[tuple[float, float]]]] = {t: {} for t in topics}
    bad = 0
    for m in bag.messages(topics):
        try:
            values, stamp = model_error_from_msg(bag.decode(m), m.topic)
        except ValueError:
            bad += 1
            continue
        for k, v in values.items():
            series[m.topic].setdefault(k, []).append((stamp / 1e9, v))
    if not any(series.values()):
        raise BagError(f"bag {bag.path}: {', '.join(topics)} has no valid message to plot ({bad} malformed)")
    panels = []
    for title, prefixes in _GROUPS:
        names = sorted({k for s in series.values() for k in s if k.startswith(prefixes)})
        if names:
            panels.append((title, names))
    other = sorted({k for s in series.values() for k in s} - {n for _, ns in panels for n in ns})
    if other:
        panels.append(("other", other))
    fig, axes = plt.subplots(len(panels), 1, figsize=(10, 2.6 * len(panels)), sharex=True, squeeze=False)
    for ax, (title, names) in zip(axes[:, 0], panels, strict=True):
        for topic, chans in series.items():
            for name in names:
                if name in chans:
                    t, v = np.array(chans[name]).T
                    label = name if len(series) == 1 else f"{topic}: {name}"
                    ax.plot(t, v, label=label, lw=1.2)
        ax.set_ylabel(title)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, ncol=2, loc="best")
    axes[-1, 0].set_xlabel("stamp (s)")
    fig.suptitle(f"{', '.join(topics)} in {bag.path.name}")
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(sys.argv[1:] if argv is None else argv)
    path = args.bag
    system: Any = args.system
    if args.system_file is not None:
        from saml_ros.systems.system_file import SystemFileError
        from saml_ros.user_code import load_system_file

        try:
            system = load_system_file(args.system_file)
        except SystemFileError as exc:
            print(f"bag_info: {exc}", file=sys.stderr)
            return 2
    if args.repair:
        try:
            res = repair_bag(path, args.out)
        except BagError as exc:
            print(f"bag_info: {exc}", file=sys.stderr)
            return 1
        state = "complete (nothing was lost)" if res.complete else f"stopped early: {res.problem}"
        print(f"bag_info: recovered {res.messages} messages into {res.path}; source {state}")
        path = res.path
    try:
        with Bag(path) as bag:
            info = summarize(bag, system, args.namespace)
            if args.plot:
                info["plot"] = str(plot_model_error(bag, args.plot, args.namespace))
    except BagError as exc:
        print(f"bag_info: {exc}", file=sys.stderr)
        return 1
    if args.json:
        print(json.dumps(info, indent=2))
    else:
        print_summary(info)
        if args.plot:
            print(f"plot:        {info['plot']}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
