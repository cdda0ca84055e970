"""Transitions from recorded bags: exactly the ones the online learner pairs (no rclpy).

For every bag and every system namespace in it, the ``state``, ``applied_cmd`` (and, for the paddle ball,
``post_impact``) messages are decoded with ``msg_schemas`` and fed, in the order the recorder received
them, to the learner's own pairing code (:class:`saml_ros.core.data.pairing.StampPairer`, one per bag and
namespace; for a robot described by a system file, its :class:`saml_ros.core.data.resampling.ResamplingPairer`, an
unstamped message taking its log time as receipt time): one implementation pairs online and offline. Malformed
messages are dropped and counted exactly as the learner counts them (``SchemaError.reason``). A transition
never spans two bags.

    x, u, y = transitions_from_bags([Path("runs/flight1")], get_system("quadrotor"))

Every problem (missing path, unfinished or truncated recording, empty bag, missing topic, wrong message
type, undecodable message, no transition at all) raises :class:`~saml_ros.bags.io.BagError` naming the bag.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from msg_schemas import SchemaError, SystemSchema, get_schema
from msg_schemas.names import join_topic, normalize_namespace
from msg_schemas.path_codec import FieldPathCodec
from saml_ros.bags.io import CUSTOM_NAMESPACES, CUSTOM_SYSTEM, Bag, BagError
from saml_ros.core.data.pairing import PairingConfig, StampPairer, total_counts
from saml_ros.core.data.plausibility import Plausibility
from saml_ros.core.data.resampling import ResamplingPairer
from saml_ros.core.systems import get_system, system_names


@dataclass
class SourceStats:
    """Pairing result of one (bag, namespace) source.

    Attributes:
        bag: bag directory.
        namespace: system namespace (``"/friction"``).
        transitions: transitions paired.
        counts: the pairer's counters (``received/<kind>``, ``paired``, rejection reasons, ``unpaired``, ...).
    """

    bag: Path
    namespace: str
    transitions: int
    counts: dict[str, int]


@dataclass
class BagTransitions:
    """Transitions extracted from bags.

    Attributes:
        x: ``(N, n_x)`` float64 states x_t.
        u: ``(N, n_u)`` float64 applied controls.
        y: ``(N, n_y)`` float64 targets.
        stamps: ``(N,)`` int64 stamp of x_t (ns).
        source: ``(N,)`` int64 index into ``sources``.
        sources: one :class:`SourceStats` per (bag, namespace), in extraction order.
    """

    x: np.ndarray
    u: np.ndarray
    y: np.ndarray
    stamps: np.ndarray
    source: np.ndarray
    sources: list[SourceStats] = field(default_factory=list)

    def __len__(self) -> int:
        return int(self.x.shape[0])

    @property
    def counts(self) -> dict[str, int]:
        """All sources' pairing counters summed."""
        return total_counts(s.counts for s in self.sources)


def _system_of(system: Any) -> Any:
    return get_system(system) if isinstance(system, str) else system


def schema_of(system: Any) -> SystemSchema:
    """The topic schema of a system: its own (a robot from a system file) or the built-in one of its name."""
    own = getattr(system, "schema", None)
    return own() if callable(own) else get_schema(system.name)


def make_pairer(system: Any, schema: SystemSchema, source: int, name: str,
                config: PairingConfig | None = None) -> StampPairer | ResamplingPairer:
    """The learner's pairer for ``system``: resampling for a robot from a system file, else exact stamps."""
    own = getattr(system, "pairing", None)
    if callable(own) and config is None:  # with the system's plausible ranges, as the learner checks them
        return ResamplingPairer(dataclasses.replace(own(), bounds=Plausibility.for_system(system)), source=source,
                                name=name)
    return StampPairer(config or PairingConfig.for_system(system, schema.target_pairing), source=source, name=name)


def pairing_topics(schema: SystemSchema, namespace: str) -> dict[str, str]:
    """``{absolute topic: message type}`` the learner pairs in ``namespace``."""
    names = [schema.state_topic, schema.applied_cmd_topic]
    if schema.target_pairing == "same":
        names.append(schema.target_topic)
    return {join_topic(namespace, n): schema.topic(n).msg_type for n in names}


def find_namespaces(bag: Bag, system: str | SystemSchema) -> list[str]:
    """Namespaces of ``bag`` holding ``system``'s pairing topics (state, applied_cmd, [post_impact]).

    Uses metadata.yaml's ``saml_ros.namespaces`` when the recorder stored them, else every ``<ns>`` with
    ``<ns>/state`` and the other pairing topics in the bag (types not checked here).
    """
    schema = get_schema(system) if isinstance(system, str) else system
    stored = bag.custom_data.get(CUSTOM_NAMESPACES, "")
    if stored and bag.custom_data.get(CUSTOM_SYSTEM) == schema.system:
        return [normalize_namespace(n) for n in stored.split(",") if n]
    if schema.state_topic.startswith("/"):  # absolute topics: no namespace
        return ["/"] if all(t in bag.topics for t in pairing_topics(schema, "/")) else []
    suffix = "/" + schema.state_topic
    out = []
    for topic in bag.topics:
        if topic.endswith(suffix):
            ns = normalize_namespace(topic[: -len(suffix)])
            if all(t in bag.topics for t in pairing_topics(schema, ns)):
                out.append(ns)
    return out


def infer_system(bag: Bag) -> str:
    """The system a bag recorded: metadata.yaml's ``saml_ros.system``, else the one whose pairing topics
    (names and message types) are in the bag, preferring the default namespace ``/<system>`` and then
    the one whose first state and applied_cmd messages decode. :class:`BagError` if none fits.
    """
    names = system_names()
    stored = bag.custom_data.get(CUSTOM_SYSTEM)
    if stored in names:
        return stored
    candidates: list[tuple[int, str]] = []
    for name in names:
        schema = get_schema(name)
        for ns in find_namespaces(bag, name):
            topics = pairing_topics(schema, ns)
            if all(bag.topics[t].msg_type == m for t, m in topics.items()) and _first_messages_decode(bag, schema, ns):
                candidates.append((0 if ns == f"/{name}" else 1, name))
    if not candidates:
        raise BagError(f"bag {bag.path}: no system's topics found (for each of {list(names)} expected "
                       f"<ns>/state and <ns>/applied_cmd with the schema's message types); the bag has: "
                       + (", ".join(f"{t} ({i.msg_type})" for t, i in bag.topics.items()) or "no topics"))
    return sorted(candidates)[0][1]


def _first_messages_decode(bag: Bag, schema: SystemSchema, ns: str) -> bool:
    """True unless the first ``state`` or ``applied_cmd`` message of ``ns`` is rejected by ``schema``."""
    for name, decode in ((schema.state_topic, schema.state_from_msg), (schema.applied_cmd_topic,
                                                                         schema.control_from_msg)):
        topic = join_topic(ns, name)
        for m in bag.messages([topic]):
            try:
                decode(bag.decode(m), topic)
            except (SchemaError, BagError):
                return False
            break
    return True


def extract_transitions(
    paths: Sequence[str | Path],
    system: Any,
    namespaces: Sequence[str] | None = None,
    *,
    config: PairingConfig | None = None,
) -> BagTransitions:
    """Pair every bag's messages into transitions (see the module docstring).

    Args:
        paths: bag directories (or the ``.mcap`` files inside them).
        system: a :class:`~saml_ros.core.dynamics.system.System` or its name.
        namespaces: system namespaces to use (default: every namespace of the system found in each bag).
        config: exact-stamp pairing rule and limits (default: the learner's rule for the system: resampling
            (:mod:`saml_ros.core.data.resampling`) for a robot from a system file, where an unstamped message's
            receipt time is its log time, else exact stamps).

    One function on purpose (longer than 80 lines): one streaming pass over the bags' messages in log order
    feeds the per-namespace pairers; splitting it would pass that state around.
    """
    sysobj = _system_of(system)
    schema = schema_of(sysobj)
    if not paths:
        raise BagError("no bag given")
    xs: list[np.ndarray] = []
    us: list[np.ndarray] = []
    ys: list[np.ndarray] = []
    stamps: list[int] = []
    src: list[int] = []
    sources: list[SourceStats] = []
    for path in paths:
        with Bag(path) as bag:
            if bag.message_count == 0:
                raise BagError(f"bag {bag.path}: is empty (0 messages)")
            nss = [normalize_namespace(n) for n in namespaces] if namespaces else find_namespaces(bag, schema)
            if not nss:
                nss = [f"/{sysobj.name}"]  # so the error below names the expected topics
            needed: dict[str, str] = {}
            for ns in nss:
                needed.update(pairing_topics(schema, ns))
            bag.require_topics(needed, f"{sysobj.name} transitions")
            first = len(sources)
            pairers = {}
            kinds: dict[str, tuple[StampPairer | ResamplingPairer, str]] = {}
            for ns in nss:
                pairer = make_pairer(sysobj, schema, len(sources), f"{bag.path}:{ns}", config)
                pairers[ns] = pairer
                sources.append(SourceStats(bag.path, ns, 0, {}))
                kinds[join_topic(ns, schema.state_topic)] = (pairer, "state")
                kinds[join_topic(ns, schema.applied_cmd_topic)] = (pairer, "applied_cmd")
                if schema.target_pairing == "same":
                    kinds[join_topic(ns, schema.target_topic)] = (pairer, "target")
            for msg in bag.messages(kinds):
                pairer, kind = kinds[msg.topic]
                decoded = bag.decode(msg)  # undecodable CDR: a damaged bag, BagError
                try:
                    vec, stamp = _from_msg(schema, kind, decoded, msg.topic, msg.log_time_ns)
                except SchemaError as exc:  # counted exactly as the learner node counts it
                    pairer.reject(exc.reason)
                    continue
                except Exception:
                    pairer.reject("format")
                    continue
                for t in pairer.add(kind, stamp, vec).transitions:
                    xs.append(t.x)
                    us.append(t.u)
                    ys.append(t.y)
                    stamps.append(t.stamp_ns)
                    src.append(t.source)
            for pairer in pairers.values():
                pairer.flush()
                stats = sources[pairer.source]
                stats.counts = dict(pairer.counts)
                stats.transitions = pairer.counts["paired"]
            if sum(s.transitions for s in sources[first:]) == 0:
                detail = "; ".join(f"{s.namespace}: {_describe_counts(s.counts)}" for s in sources[first:])
                raise BagError(f"bag {bag.path}: contains no complete {sysobj.name} transition ({detail})")
    n_x, n_u, n_y = sysobj.state.size, sysobj.control.size, sysobj.target.size
    return BagTransitions(
        x=np.array(xs, dtype=np.float64).reshape(-1, n_x),
        u=np.array(us, dtype=np.float64).reshape(-1, n_u),
        y=np.array(ys, dtype=np.float64).reshape(-1, n_y),
        stamps=np.array(stamps, dtype=np.int64),
        source=np.array(src, dtype=np.int64),
        sources=sources,
    )


def _from_msg(schema: SystemSchema, kind: str, msg: Any, topic: str, log_time_ns: int) -> tuple[np.ndarray, int]:
    codec = schema.state if kind == "state" else schema.control if kind == "applied_cmd" else schema.target
    if isinstance(codec, FieldPathCodec):  # a robot's own messages: unstamped ones were stamped when recorded
        return codec.from_msg(msg, topic, receipt_ns=log_time_ns)
    if kind == "state":
        return schema.state_from_msg(msg, topic)
    if kind == "applied_cmd":
        return schema.control_from_msg(msg, topic)
    return schema.target_from_msg(msg, topic)


def _describe_counts(counts: dict[str, int]) -> str:
    received = ", ".join(f"{counts.get('received/' + k, 0)} {k}" for k in ("state", "applied_cmd", "target")
                         if counts.get("received/" + k, 0))
    rejected = {k: v for k, v in counts.items() if v and not k.startswith("received/") and k != "paired"}
    return f"received {received or 'nothing'}" + (f", dropped {rejected}" if rejected else "")


def transitions_from_bags(
    paths: Sequence[Path], system: Any, namespaces: Sequence[str] | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(x, u, y)`` float64 arrays ``(N, n_x), (N, n_u), (N, n_y)`` of every transition in ``paths``.

    See :func:`extract_transitions`; raises :class:`~saml_ros.bags.io.BagError` (a ``ValueError``) on any problem.
    """
    out = extract_transitions(paths, system, namespaces)
    return out.x, out.u, out.y
