"""Bag I/O on ``rosbags`` (no rclpy): write what Jazzy's ``ros2 bag record`` writes, read it back with clear errors.

A bag is a rosbag2 directory: ``metadata.yaml`` (format version 9, each topic's ``offered_qos_profiles``)
plus one MCAP file (``<dir>/<dir name>.mcap``, profile ``ros2``, CDR messages, ``ros2msg`` schemas), the
format and storage Jazzy's rosbag2 uses by default. ``ros2 bag info/play``, Foxglove, PlotJuggler and the
``mcap`` readers open it.

* :class:`BagWriter` writes raw CDR bytes (what a raw subscription receives; never re-serialised, see
  docs/bags.md) or rosbags messages. It closes the pending MCAP chunk and flushes the file at least every
  ``flush_period`` seconds, so a killed writer loses at most that much data; such a bag has no footer and
  no metadata.yaml and is recovered with :func:`repair_bag` (``bag_info --repair``).
* :class:`Bag` opens a bag read-only and turns every problem (missing path, not a bag, unfinished or
  truncated recording, unreadable metadata, undecodable message, wrong message type) into a
  :class:`BagError` whose message names the bag and the problem.

Times are int nanoseconds. ``log_time`` is when the recorder received a message (its node clock); vector
stamps (``header.stamp``) are separate and are what the learner pairs on.
"""

from __future__ import annotations

import functools
import time
from collections.abc import Iterable, Iterator, Mapping, Sequence
from contextlib import suppress
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import Any, Literal

from msg_schemas import QosSpec, TopicSpec, get_schema
from msg_schemas.names import join_topic, normalize_namespace
from msg_schemas.telemetry import GLOBAL_TOPICS, TELEMETRY_TOPICS
from saml_ros.core.errors import SamlError

#: rosbag2 metadata format version Jazzy writes
BAG_VERSION: Literal[9] = 9
#: storage plugin Jazzy uses by default
STORAGE_ID = "mcap"
#: custom_data keys saml_ros writes into metadata.yaml
CUSTOM_SYSTEM = "saml_ros.system"
CUSTOM_NAMESPACES = "saml_ros.namespaces"
CUSTOM_SCHEMA_HASH = "saml_ros.schema_hash"
#: default: close the MCAP chunk and flush the file at least this often (s)
DEFAULT_FLUSH_PERIOD = 0.5

_MCAP_MAGIC = b"\x89MCAP0\r\n"
_UNFINISHED_HINT = (
    "the recording did not finish cleanly (recorder killed or disk full?); "
    "recover the data written so far with `bag_info --repair {path}`"
)


class BagError(SamlError, ValueError):
    """A bag cannot be used; the message names the bag and the problem."""


@functools.cache
def jazzy_typestore() -> Any:
    """The rosbags typestore of ROS 2 Jazzy's message definitions (cached)."""
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_JAZZY)


# ------------------------------------------------------------------------------------------ topics
def saml_topics(system: str, namespace: str | None = None) -> dict[str, TopicSpec]:
    """Every topic a closed loop of ``system`` uses in ``namespace`` (default ``/<system>``), by absolute name.

    Data topics (msg_schemas), telemetry (model error, checkpoint, MPC status), ``/diagnostics`` and ``/clock``.
    """
    ns = normalize_namespace(namespace if namespace is not None else system)
    out = {join_topic(ns, t.name): t for t in get_schema(system).topics}
    out.update({join_topic(ns, t.name): t for t in TELEMETRY_TOPICS})
    out.update({t.name: t for t in GLOBAL_TOPICS})
    return out


# ------------------------------------------------------------------------------------------ writer
@dataclass
class _Topic:
    connection: Any
    count: int = 0


class BagWriter:
    """Write a rosbag2 bag (version 9, MCAP) the way Jazzy's rosbag2 does.

    Args:
        path: bag directory to create; must not exist (nothing is ever overwritten).
        custom_data: string key/values for metadata.yaml's ``custom_data`` (e.g. :data:`CUSTOM_SYSTEM`).
        flush_period: close the pending chunk and flush the file when this many seconds (wall clock)
            have passed since the last flush; checked on every write and by :meth:`maybe_flush`.
            ``0`` flushes after every message (slow; tests).

    Use as a context manager, or call :meth:`close`. On an exception inside the ``with`` block the bag is
    still finished (footer + metadata.yaml) so the data written so far stays readable.
    """

    def __init__(
        self,
        path: str | Path,
        *,
        custom_data: Mapping[str, str] | None = None,
        flush_period: float = DEFAULT_FLUSH_PERIOD,
    ) -> None:
        from rosbags.rosbag2 import StoragePlugin, Writer, WriterError

        self.path = Path(path)
        if self.path.exists():
            raise BagError(f"bag {self.path}: already exists; not overwriting it")
        self.flush_period = float(flush_period)
        self._writer = Writer(self.path, version=BAG_VERSION, storage_plugin=StoragePlugin.MCAP)
        for key, value in (custom_data or {}).items():
            self._writer.set_custom_data(str(key), str(value))
        try:
            self._writer.open()
        except (WriterError, OSError) as exc:
            raise BagError(f"bag {self.path}: cannot create it: {exc}") from None
        self._storage: Any = self._writer.storage
        # rosbags' MCAP storage keeps the current chunk in memory until it reaches 1 MiB; we close it early.
        if not (hasattr(self._storage, "close_chunk") and hasattr(self._storage, "chunk")):
            raise BagError("this rosbags version has no MCAP chunk control (need rosbags 0.11.x)")
        self._topics: dict[tuple[str, str], _Topic] = {}
        self._last_flush = time.monotonic()
        self.closed = False

    # -- topics
    def add_topic(
        self,
        topic: str,
        msg_type: str,
        qos: Sequence[QosSpec | Any] | QosSpec = (),
        *,
        type_hash: str | None = None,
    ) -> None:
        """Declare ``topic`` with ``msg_type`` (a Jazzy type) and its offered QoS profiles.

        ``qos``: a :class:`~msg_schemas.QosSpec`, or a list of them and/or rosbags ``Qos`` (the profiles the
        publishers offered; Jazzy's recorder writes one per publisher). ``type_hash`` (``RIHS01_...``) is
        checked against the definition in the typestore. Declaring the same topic and type twice is a no-op.
        """
        if (topic, msg_type) in self._topics:
            return
        store = jazzy_typestore()
        if msg_type not in store.types:
            raise BagError(f"bag {self.path}: topic {topic}: unknown message type {msg_type!r}")
        rihs01 = store.hash_rihs01(msg_type)
        if type_hash and type_hash != rihs01:
            raise BagError(
                f"bag {self.path}: topic {topic}: publisher's {msg_type} has type hash {type_hash}, "
                f"but the Jazzy definition has {rihs01}"
            )
        profiles = [qos] if isinstance(qos, QosSpec) else list(qos)
        offered = [p.to_rosbags() if isinstance(p, QosSpec) else p for p in profiles]
        conn = self._writer.add_connection(topic, msg_type, typestore=store, offered_qos_profiles=offered)
        self._topics[(topic, msg_type)] = _Topic(conn)

    def has_topic(self, topic: str, msg_type: str) -> bool:
        return (topic, msg_type) in self._topics

    # -- messages
    def write(self, topic: str, msg_type: str, data: bytes | memoryview, log_time_ns: int) -> None:
        """Append one serialized (CDR) message received at ``log_time_ns`` on a declared topic."""
        entry = self._topics.get((topic, msg_type))
        if entry is None:
            raise BagError(f"bag {self.path}: topic {topic} ({msg_type}) was not declared with add_topic")
        self._writer.write(entry.connection, int(log_time_ns), data)
        entry.count += 1
        self.maybe_flush()

    def write_msg(self, topic: str, msg: Any, log_time_ns: int) -> None:
        """Serialize a rosbags message (``TypestoreFactory`` output) and append it."""
        msg_type = msg.__msgtype__
        self.write(topic, msg_type, jazzy_typestore().serialize_cdr(msg, msg_type), log_time_ns)

    @property
    def counts(self) -> dict[str, int]:
        """Messages written per topic so far."""
        out: dict[str, int] = {}
        for (topic, _), entry in self._topics.items():
            out[topic] = out.get(topic, 0) + entry.count
        return out

    # -- durability
    def maybe_flush(self) -> None:
        """:meth:`flush` if ``flush_period`` seconds have passed since the last flush."""
        if time.monotonic() - self._last_flush >= self.flush_period:
            self.flush()

    def flush(self) -> None:
        """Write the pending chunk (if it holds messages) and push the file to the OS.

        After this returns, every message written so far survives the process being killed.
        """
        if self.closed:
            return
        if self._storage.chunk.msgs:
            self._storage.close_chunk()
        self._storage.bio.flush()
        self._last_flush = time.monotonic()

    def close(self) -> None:
        """Finish the bag: last chunk, MCAP summary and footer, then metadata.yaml (atomically)."""
        if self.closed:
            return
        self.closed = True
        self._writer.close()

    def __enter__(self) -> BagWriter:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None) -> None:
        self.close()


# ------------------------------------------------------------------------------------------ reader
@dataclass(frozen=True)
class TopicInfo:
    """One topic of a bag.

    Attributes:
        name: absolute topic name.
        msg_type: message type (``"a, b"`` when connections with different types share the topic).
        message_count: messages on the topic.
        qos: offered QoS profiles (rosbags ``Qos``) recorded in the metadata.
        type_hash: ``RIHS01_...`` recorded in the metadata (empty for old bags).
    """

    name: str
    msg_type: str
    message_count: int
    qos: tuple[Any, ...] = ()
    type_hash: str = ""


@dataclass(frozen=True)
class BagMessage:
    """One raw message: topic, type, receive time (ns) and CDR bytes."""

    topic: str
    msg_type: str
    log_time_ns: int
    data: bytes


class Bag:
    """A rosbag2 bag opened read-only. ``Bag(path)`` validates it; every failure is a :class:`BagError`.

    Attributes:
        path: the bag directory.
        version / storage / ros_distro: from metadata.yaml.
        start_ns / end_ns: first and last message receive times (0, 0 for an empty bag).
        message_count: messages in the bag.
        topics: :class:`TopicInfo` by topic name (sorted by name).
        custom_data: metadata.yaml ``custom_data`` (empty dict when absent).
    """

    def __init__(self, path: str | Path) -> None:
        self.path = resolve_bag_path(path)
        info = _read_metadata(self.path)
        self.version = int(info.get("version", 0))
        self.storage = str(info.get("storage_identifier", ""))
        self._reader: Any = _open_reader(self.path)
        try:
            r = self._reader
            self.ros_distro = str(r.ros_distro or "")
            self.message_count = int(r.message_count)
            self.start_ns = int(r.start_time) if self.message_count else 0
            self.end_ns = int(r.end_time) - 1 if self.message_count else 0
            self.custom_data = {str(k): str(v) for k, v in (r.storage.metadata.custom or {}).items()}
            topics: dict[str, TopicInfo] = {}
            for name, tinfo in sorted(r.topics.items()):
                conns = tinfo.connections
                types = sorted({c.msgtype for c in conns})
                qos: list[Any] = []
                for c in conns:
                    qos += list(getattr(c.ext, "offered_qos_profiles", []) or [])
                topics[name] = TopicInfo(name, ", ".join(types), int(tinfo.msgcount), tuple(qos), conns[0].digest or "")
            self.topics = topics
        except BaseException:
            self.close()
            raise

    @property
    def duration_ns(self) -> int:
        """``end_ns - start_ns`` (0 for fewer than two messages)."""
        return max(0, self.end_ns - self.start_ns)

    def require_topics(self, needed: Mapping[str, str], purpose: str) -> None:
        """Check that every ``topic -> msg_type`` in ``needed`` is in the bag with that type.

        Raises :class:`BagError` listing the missing topics (and the ones the bag has) or naming the topic
        whose type (or definition hash) does not match.
        """
        missing = [t for t in needed if t not in self.topics]
        if missing:
            have = ", ".join(f"{t} ({i.msg_type})" for t, i in self.topics.items()) or "none"
            raise BagError(f"bag {self.path}: missing topic(s) {', '.join(missing)} needed for {purpose}; "
                           f"the bag has: {have}")
        store = jazzy_typestore()
        for topic, expected in needed.items():
            info = self.topics[topic]
            if info.msg_type != expected:
                raise BagError(f"bag {self.path}: topic {topic} has message type {info.msg_type}, "
                               f"but {purpose} needs {expected}")
            want = store.hash_rihs01(expected)
            if info.type_hash and info.type_hash != want:
                raise BagError(f"bag {self.path}: topic {topic}: the bag's {expected} definition (hash "
                               f"{info.type_hash}) is not Jazzy's ({want}); recorded with another ROS distro?")

    def messages(self, topics: Iterable[str] | None = None) -> Iterator[BagMessage]:
        """Raw messages in receive-time order, optionally only on ``topics``.

        A read failure (damaged chunk, ...) raises :class:`BagError` naming the bag.
        """
        wanted = None if topics is None else set(topics)
        conns = [c for c in self._reader.connections if wanted is None or c.topic in wanted]
        if not conns:
            return
        it = self._reader.messages(connections=conns)
        while True:
            try:
                conn, stamp, data = next(it)
            except StopIteration:
                return
            except Exception as exc:  # rosbags raises ReaderError, struct.error, ... on damaged data
                raise BagError(f"bag {self.path}: cannot read messages: {exc}; {_hint(self.path)}") from None
            yield BagMessage(conn.topic, conn.msgtype, int(stamp), bytes(data))

    def decode(self, message: BagMessage) -> Any:
        """Deserialize a :class:`BagMessage` with the Jazzy typestore; :class:`BagError` if the bytes are bad."""
        try:
            return jazzy_typestore().deserialize_cdr(message.data, message.msg_type)
        except Exception as exc:
            raise BagError(
                f"bag {self.path}: topic {message.topic}: message at {message.log_time_ns} ns does not "
                f"decode as {message.msg_type}: {exc}"
            ) from None

    def close(self) -> None:
        if self._reader is not None:
            with suppress(Exception):
                self._reader.close()
            self._reader = None

    def __enter__(self) -> Bag:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None) -> None:
        self.close()


def resolve_bag_path(path: str | Path) -> Path:
    """The bag directory for ``path`` (a bag directory, or the ``.mcap`` file inside one).

    Raises :class:`BagError` when the path does not exist, is not a bag, or the recording is unfinished.
    """
    p = Path(path)
    if not p.exists():
        raise BagError(f"bag {p}: path does not exist")
    if p.is_file():
        if p.suffix == ".mcap" and (p.parent / "metadata.yaml").exists():
            return p.parent
        if p.suffix == ".mcap":
            raise BagError(f"bag {p}: an MCAP file without a rosbag2 metadata.yaml next to it; "
                           + _UNFINISHED_HINT.format(path=p))
        raise BagError(f"bag {p}: not a rosbag2 bag (expected a directory with metadata.yaml)")
    if not (p / "metadata.yaml").exists():
        if any(p.glob("*.mcap")):
            raise BagError(f"bag {p}: has no metadata.yaml; " + _UNFINISHED_HINT.format(path=p))
        raise BagError(f"bag {p}: not a rosbag2 bag (no metadata.yaml in the directory)")
    return p


def _open_reader(path: Path) -> Any:
    from rosbags.rosbag2 import Reader

    try:
        reader = Reader(path)
        reader.open()
    except Exception as exc:  # ReaderError, FileNotFoundError, struct.error, ...
        raise BagError(_describe_open_error(path, exc)) from None
    return reader


def _describe_open_error(path: Path, exc: Exception) -> str:
    text = str(exc)
    for mcap in sorted(path.glob("*.mcap")):
        size = mcap.stat().st_size
        if size == 0:
            return f"bag {path}: MCAP file {mcap.name} is empty (0 bytes); " + _UNFINISHED_HINT.format(path=path)
        if not _has_mcap_footer(mcap):
            return (f"bag {path}: MCAP file {mcap.name} is truncated or damaged ({size} bytes, no valid MCAP "
                    "footer); " + _UNFINISHED_HINT.format(path=path))
    return f"bag {path}: cannot open it ({text}); {_hint(path)}"


def _hint(path: Path) -> str:
    return "the file may be damaged; try `bag_info --repair " + str(path) + "`"


#: bytes of the smallest valid MCAP file: magic, a Header record (opcode, length, two empty strings), a Footer
#: record (opcode, length, summary start, summary offset start, summary CRC), magic
_MCAP_MIN_SIZE = 8 + (1 + 8 + 4 + 4) + (1 + 8 + 8 + 8 + 4) + 8
_MCAP_FOOTER_OPCODE = b"\x02"


def _has_mcap_footer(mcap: Path) -> bool:
    """Whether ``mcap`` starts with the MCAP magic and ends with a Footer record and the magic."""
    try:
        if mcap.stat().st_size < _MCAP_MIN_SIZE:
            return False
        with mcap.open("rb") as f:
            if f.read(8) != _MCAP_MAGIC:
                return False
            f.seek(-(8 + 29), 2)
            footer = f.read(1)
            f.seek(-8, 2)
            return footer == _MCAP_FOOTER_OPCODE and f.read(8) == _MCAP_MAGIC
    except OSError:
        return False


def _read_metadata(path: Path) -> dict[str, Any]:
    """``rosbag2_bagfile_information`` of ``path/metadata.yaml``; :class:`BagError` if unreadable."""
    import yaml

    try:
        # libyaml's safe loader where PyYAML has it (the same documents, ~10x faster than the pure-Python one: every
        # bag opened reads this file, and rosbags' reader parses it once more)
        data = yaml.load((path / "metadata.yaml").read_text(), Loader=getattr(yaml, "CSafeLoader", yaml.SafeLoader))
        info = data["rosbag2_bagfile_information"]
        if not isinstance(info, dict):
            raise TypeError("rosbag2_bagfile_information is not a mapping")
        return info
    except Exception as exc:
        raise BagError(f"bag {path}: metadata.yaml is not valid rosbag2 metadata: {exc}") from None


# ------------------------------------------------------------------------------------------ repair
@dataclass(frozen=True)
class RepairResult:
    """What :func:`repair_bag` recovered.

    Attributes:
        path: the repaired bag directory.
        messages: messages recovered.
        topics: messages recovered per topic.
        complete: ``True`` when the source file ended with a valid footer (nothing was lost).
        problem: why reading stopped early (empty when complete).
    """

    path: Path
    messages: int
    topics: dict[str, int]
    complete: bool
    problem: str = ""


def repair_bag(src: str | Path, dst: str | Path | None = None) -> RepairResult:
    """Recover the readable messages of a bag whose recording did not finish (no footer / no metadata.yaml).

    Reads the MCAP files of ``src`` (a bag directory or one ``.mcap`` file) record by record with the
    ``mcap`` library until the data ends or stops making sense (a partly written last chunk is dropped)
    and writes every complete message to a new bag ``dst`` (default ``<src>_repaired``) with the recorded
    topics, types and offered QoS. ``src`` is never modified. Raises :class:`BagError` if nothing useful
    can be read or ``dst`` exists.
    """
    from mcap.records import Channel, Message, Schema
    from mcap.stream_reader import StreamReader
    from rosbags.rosbag2.metadata import parse_qos

    src_p = Path(src)
    if not src_p.exists():
        raise BagError(f"bag {src_p}: path does not exist")
    files = [src_p] if src_p.is_file() else sorted(src_p.glob("*.mcap"))
    if not files:
        raise BagError(f"bag {src_p}: no MCAP file to repair")
    dst_p = Path(dst) if dst is not None else src_p.with_name(src_p.stem + "_repaired")
    if dst_p.exists():
        raise BagError(f"bag {dst_p}: already exists; not overwriting it (choose another output)")
    schemas: dict[int, Any] = {}
    channels: dict[int, Any] = {}
    recovered: list[tuple[Any, Any]] = []  # (channel, message)
    complete = True
    problems = []
    for mcap in files:
        got_footer = False
        good_end = 0  # the byte offset after the last complete record
        try:
            with mcap.open("rb") as f:
                for rec in StreamReader(f, record_size_limit=2**31).records:
                    good_end = f.tell()
                    if isinstance(rec, Schema):
                        schemas[rec.id] = rec
                    elif isinstance(rec, Channel):
                        channels[rec.id] = rec
                    elif isinstance(rec, Message):
                        ch = channels.get(rec.channel_id)
                        if ch is not None:
                            recovered.append((ch, rec))
                got_footer = True
        except Exception as exc:  # EndOfFile, bad record, ...: keep everything read before it
            problems.append(_stopped_early(mcap, exc, good_end))
        complete = complete and got_footer
    if not recovered:
        raise BagError(f"bag {src_p}: no complete message could be recovered"
                       + (f" ({'; '.join(problems)})" if problems else ""))
    store = jazzy_typestore()
    recovered.sort(key=lambda cm: cm[1].log_time)
    counts: dict[str, int] = {}
    with BagWriter(dst_p, flush_period=3600.0) as writer:
        for ch, msg in recovered:
            schema = schemas.get(ch.schema_id)
            msg_type = schema.name if schema is not None else ""
            if msg_type not in store.types:
                continue
            if not writer.has_topic(ch.topic, msg_type):
                qos_text = ch.metadata.get("offered_qos_profiles", "")
                try:
                    qos = parse_qos(qos_text) if qos_text else []
                except Exception:
                    qos = []
                writer.add_topic(ch.topic, msg_type, qos)
            writer.write(ch.topic, msg_type, msg.data, msg.log_time)
            counts[ch.topic] = counts.get(ch.topic, 0) + 1
    return RepairResult(dst_p, sum(counts.values()), counts, complete, "; ".join(problems))


def _stopped_early(mcap: Path, exc: Exception, good_end: int) -> str:
    """Why reading ``mcap`` stopped before its footer, in words (not the MCAP reader's internal text, e.g. "unpack
    requires a buffer of 8 bytes"); ``good_end``: the offset after the last complete record."""
    import struct

    from mcap.exceptions import EndOfFile

    try:
        size = f" of {mcap.stat().st_size}"
    except OSError:
        size = ""
    if isinstance(exc, EndOfFile | struct.error):
        return (f"{mcap.name}: the file ends inside a record after byte {good_end}{size} (the recording was cut off: "
                "a killed recorder or a full disk); the records before it are recovered")
    return (f"{mcap.name}: the data after byte {good_end}{size} is damaged ({type(exc).__name__}: {exc}); the records "
            "before it are recovered")


# ------------------------------------------------------------------------- rclpy conversions (lazy)
def message_class(msg_type: str) -> Any:
    """The rclpy message class of ``"pkg/msg/Name"`` (imports rclpy's generated module); ``None`` if missing."""
    import importlib

    try:
        package, kind, name = msg_type.split("/")
        return getattr(importlib.import_module(f"{package}.{kind}"), name)
    except (ValueError, ImportError, AttributeError):
        return None


def qos_from_rclpy(profile: Any) -> Any:
    """An rclpy ``QoSProfile`` (e.g. a publisher's offered profile from graph discovery) -> rosbags ``Qos``.

    Discovery reports ``history: unknown, depth: 0`` (DDS does not share them); Jazzy's recorder writes
    exactly that, and so do we.
    """
    from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime

    def t(duration: Any) -> Any:
        sec, nsec = divmod(int(duration.nanoseconds), 1_000_000_000)
        return QosTime(sec, nsec)

    def enum(cls: Any, value: Any) -> Any:
        try:
            return cls(int(value))
        except ValueError:
            return cls.UNKNOWN

    return Qos(
        history=enum(QosHistory, profile.history),
        depth=int(profile.depth),
        reliability=enum(QosReliability, profile.reliability),
        durability=enum(QosDurability, profile.durability),
        deadline=t(profile.deadline),
        lifespan=t(profile.lifespan),
        liveliness=enum(QosLiveliness, profile.liveliness),
        liveliness_lease_duration=t(profile.liveliness_lease_duration),
        avoid_ros_namespace_conventions=bool(profile.avoid_ros_namespace_conventions),
    )


def rclpy_qos_for_playback(offered: Sequence[Any], min_depth: int = 100) -> Any:
    """The rclpy ``QoSProfile`` a player offers for a topic recorded with ``offered`` (rosbags ``Qos``) profiles.

    Reliable unless every recorded publisher was best effort; transient local if every recorded publisher
    was; keep last ``max(recorded depth, min_depth)`` (discovery records depth 0). No profile: reliable,
    volatile (the saml_ros default).
    """
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
    from rosbags.interfaces import QosDurability, QosReliability

    best_effort = bool(offered) and all(q.reliability == QosReliability.BEST_EFFORT for q in offered)
    transient = bool(offered) and all(q.durability == QosDurability.TRANSIENT_LOCAL for q in offered)
    depth = max([min_depth] + [int(q.depth) for q in offered])
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=depth,
        reliability=ReliabilityPolicy.BEST_EFFORT if best_effort else ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.TRANSIENT_LOCAL if transient else DurabilityPolicy.VOLATILE,
    )
