"""Draw a layout's panels (:func:`saml_ros.viewers.layouts.panels`) from a recorded bag with matplotlib.

What PlotJuggler or Foxglove would show for the same topics, as a static PNG: one row per panel, the series over
their header stamps (s, relative to the first stamp in the bag).
"""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path

import numpy as np

from msg_schemas import SchemaError, get_schema
from msg_schemas.telemetry import named_vector_from_msg
from saml_ros.bags.io import Bag
from saml_ros.viewers.layouts import panels


def series_from_bag(bag: Bag, system: str, namespace: str | None = None) -> dict[tuple[str, str], np.ndarray]:
    """``{(topic, name): array (n, 2) of [stamp s, value]}`` for every series of the layout found in ``bag``."""
    schema = get_schema(system)
    wanted = {(s.topic, s.name) for p in panels(system, namespace) for s in p.series}
    topics = sorted({t for t, _ in wanted if t in bag.topics})
    data: dict[tuple[str, str], list[tuple[float, float]]] = defaultdict(list)
    for m in bag.messages(topics):
        msg = bag.decode(m)
        try:
            if m.topic.endswith("/" + schema.state_topic):
                vec, stamp = schema.state_from_msg(msg, m.topic)
                values = dict(zip(schema.state.field_names, vec.tolist(), strict=True))
            elif m.topic.endswith("/" + schema.applied_cmd_topic):
                vec, stamp = schema.control_from_msg(msg, m.topic)
                values = dict(zip(schema.control.field_names, vec.tolist(), strict=True))
            else:
                values, stamp = named_vector_from_msg(msg, m.topic)
        except SchemaError:
            continue
        for name, value in values.items():
            if (m.topic, name) in wanted:
                data[(m.topic, name)].append((stamp * 1e-9, value))
    return {k: np.asarray(v, dtype=np.float64) for k, v in data.items()}


def render_layout(bag_path: Path, system: str, out: Path, namespace: str | None = None, title: str | None = None) -> Path:
    """Write ``out`` (PNG): the layout's panels for ``system`` drawn from the bag at ``bag_path``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    specs = panels(system, namespace)
    with Bag(bag_path) as bag:
        data = series_from_bag(bag, system, namespace)
    stamps = [v[:, 0].min() for v in data.values() if len(v)]
    t0 = min(stamps) if stamps else 0.0
    fig, axes = plt.subplots(len(specs), 1, figsize=(9, 2.0 * len(specs)), sharex=True)
    for ax, spec in zip(np.atleast_1d(axes), specs, strict=True):
        for s in spec.series:
            v = data.get((s.topic, s.name))
            if v is None or not len(v):
                continue
            label = f"{s.name} ({s.unit})" if s.unit not in ("", "1", "count") else s.name
            ax.plot(v[:, 0] - t0, v[:, 1], lw=1.0, label=label)
        ax.set_title(spec.title, fontsize=9, loc="left")
        ax.legend(fontsize=7, loc="upper right", ncol=3)
        ax.grid(alpha=0.3)
    np.atleast_1d(axes)[-1].set_xlabel("header stamp (s, simulated time)")
    fig.suptitle(title or f"{system} layout panels, drawn from the bag {Path(bag_path).name}", fontsize=10)
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=90)
    plt.close(fig)
    return out
