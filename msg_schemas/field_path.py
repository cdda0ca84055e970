"""Read (and write) one number of any stock ROS 2 message by its field path.

A *field path* names one scalar of a message, ROS style::

    pose.pose.position.x            nested fields
    twist.twist.angular.z
    position[2]                     an element of an array / sequence field
    position[left_wheel]            the element whose name in the message's parallel ``name`` array is
                                    ``left_wheel`` (sensor_msgs/JointState); looked up in every message
    yaw(pose.pose.orientation)      a conversion of a geometry_msgs/Quaternion: ``yaw``, ``pitch``, ``roll``
                                    (Z-Y-X Euler angles, rad, REP 103)

:func:`resolve` checks a path against a message type *before* any message arrives (with the Jazzy type
definitions of ``rosbags``, so no rclpy is needed) and raises :class:`FieldPathError` naming the path, the
type and what is wrong (unknown field and the valid ones, an index out of a fixed array, a named index on a
message without a ``name`` array, a conversion applied to something that is not a quaternion, a path that
ends on a non-numeric field). The :class:`ResolvedPath` it returns reads rclpy messages and rosbags
dataclasses alike (both have attribute access) and raises :class:`~msg_schemas.base.SchemaError` (reason
``shape``, ``names``, ``nan`` or ``quaternion``) for a malformed message.

:func:`field_unit` gives the REP 103 unit of the common stock fields (``m`` for a Point, ``m/s`` for
``Twist.linear``, ...), so a system file's declared units can be checked against what the message carries.
"""

from __future__ import annotations

import difflib
import functools
import math
import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from msg_schemas.base import SchemaError
from saml_ros.core.errors import SamlError

#: conversions of a geometry_msgs/Quaternion to one Euler angle (rad)
CONVERSIONS: tuple[str, ...] = ("yaw", "pitch", "roll")
QUATERNION = "geometry_msgs/msg/Quaternion"
#: a read quaternion must have a norm within 1 +- this tolerance
QUAT_NORM_TOL = 1e-3
NUMERIC_TYPES = frozenset({"float64", "float32", "int8", "uint8", "int16", "uint16", "int32", "uint32",
                           "int64", "uint64", "byte", "octet", "char", "bool"})

_NAME = r"[A-Za-z_][A-Za-z0-9_]*"
_STEP = re.compile(rf"^({_NAME})(?:\[([^\[\]]+)\])?$")
_CONVERSION = re.compile(rf"^({_NAME})\((.*)\)$")

# rosbags node types (rosbags.interfaces.Nodetype values)
_BASE, _NAME_T, _ARRAY, _SEQUENCE = 1, 2, 3, 4


class FieldPathError(SamlError, ValueError):
    """A field path that does not fit its message type; the message names both and what is wrong."""

    def __init__(self, path: str, msg_type: str, detail: str) -> None:
        where = f"field path {path!r} of {msg_type or 'a message'}" if path else f"message type {msg_type!r}"
        super().__init__(f"{where}: {detail}")
        self.path = path
        self.msg_type = msg_type
        self.detail = detail


@dataclass(frozen=True)
class Step:
    """One step of a path: a field ``name`` and an optional index (``int``) or joint name (``str``)."""

    name: str
    index: int | str | None = None

    def __str__(self) -> str:
        return self.name if self.index is None else f"{self.name}[{self.index}]"


@dataclass(frozen=True)
class FieldPath:
    """A parsed field path (see the module docstring)."""

    steps: tuple[Step, ...]
    conversion: str | None = None

    def __str__(self) -> str:
        inner = ".".join(str(s) for s in self.steps)
        return f"{self.conversion}({inner})" if self.conversion else inner


def parse_field_path(text: str, msg_type: str = "") -> FieldPath:
    """Parse ``text``; :class:`FieldPathError` on a syntax error (``msg_type`` only labels the error)."""
    if not isinstance(text, str) or not text.strip():
        raise FieldPathError(str(text), msg_type, "must be a non-empty string such as 'pose.pose.position.x'")
    raw = text.strip()
    conversion = None
    m = _CONVERSION.match(raw)
    if m:
        conversion, raw = m.group(1), m.group(2).strip()
        if conversion not in CONVERSIONS:
            raise FieldPathError(text, msg_type, f"unknown conversion {conversion!r}; valid: {list(CONVERSIONS)}")
    steps = []
    for part in raw.split("."):
        sm = _STEP.match(part.strip())
        if not sm:
            raise FieldPathError(text, msg_type, f"cannot parse {part!r} (expected 'field', 'field[3]' or "
                                                 "'field[joint_name]')")
        name, index = sm.group(1), sm.group(2)
        idx: int | str | None = None
        if index is not None:
            index = index.strip()
            idx = int(index) if re.fullmatch(r"-?\d+", index) else index
            if isinstance(idx, int) and idx < 0:
                raise FieldPathError(text, msg_type, f"negative index in {part!r}")
        steps.append(Step(name, idx))
    return FieldPath(tuple(steps), conversion)


# ------------------------------------------------------------------------------------------ types
@functools.cache
def _typestore() -> Any:
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_JAZZY)


def normalize_type(msg_type: str) -> str:
    """``"nav_msgs/Odometry"`` -> ``"nav_msgs/msg/Odometry"``; full names pass unchanged."""
    parts = str(msg_type).strip().split("/")
    if len(parts) == 2:
        return f"{parts[0]}/msg/{parts[1]}"
    return "/".join(parts)


def check_message_type(msg_type: str) -> str:
    """The normalised type name if it is a stock ROS 2 Jazzy message; :class:`FieldPathError` otherwise,
    with the closest known names."""
    name = normalize_type(msg_type)
    known = _typestore().fielddefs
    if name not in known:
        close = difflib.get_close_matches(name, list(known), n=3, cutoff=0.6)
        hint = f"; did you mean {close}?" if close else ""
        raise FieldPathError("", str(msg_type), f"unknown message type (not a ROS 2 Jazzy message){hint}")
    return name


def message_fields(msg_type: str) -> list[tuple[str, tuple[int, Any]]]:
    """``[(field name, (node type, spec)), ...]`` of ``msg_type`` (rosbags field definitions)."""
    return list(_typestore().fielddefs[check_message_type(msg_type)][1])


def has_header(msg_type: str) -> bool:
    """True when ``msg_type`` has a top-level ``std_msgs/Header header`` (its messages carry a stamp)."""
    return any(n == "header" and t == (_NAME_T, "std_msgs/msg/Header") for n, t in message_fields(msg_type))


# ------------------------------------------------------------------------------------------ units
#: REP 103 unit of a field, keyed by (containing message type, field name); a scalar inherits the unit of the
#: nearest entry on its path. A tuple lists several valid units (JointState joints may be linear or angular).
_UNITS: dict[tuple[str, str], tuple[str, ...]] = {
    ("geometry_msgs/msg/Point", "*"): ("m",),
    ("geometry_msgs/msg/Point32", "*"): ("m",),
    ("geometry_msgs/msg/Transform", "translation"): ("m",),
    ("geometry_msgs/msg/Twist", "linear"): ("m/s",),
    ("geometry_msgs/msg/Twist", "angular"): ("rad/s",),
    ("geometry_msgs/msg/Accel", "linear"): ("m/s^2",),
    ("geometry_msgs/msg/Accel", "angular"): ("rad/s^2",),
    ("geometry_msgs/msg/Wrench", "force"): ("N",),
    ("geometry_msgs/msg/Wrench", "torque"): ("N*m",),
    ("geometry_msgs/msg/Quaternion", "*"): ("1",),
    ("sensor_msgs/msg/Imu", "angular_velocity"): ("rad/s",),
    ("sensor_msgs/msg/Imu", "linear_acceleration"): ("m/s^2",),
    ("sensor_msgs/msg/JointState", "position"): ("m", "rad"),
    ("sensor_msgs/msg/JointState", "velocity"): ("m/s", "rad/s"),
    ("sensor_msgs/msg/JointState", "effort"): ("N", "N*m"),
    ("sensor_msgs/msg/Range", "range"): ("m",),
    ("sensor_msgs/msg/NavSatFix", "altitude"): ("m",),
    ("sensor_msgs/msg/Temperature", "temperature"): ("degC",),
    ("sensor_msgs/msg/FluidPressure", "fluid_pressure"): ("Pa",),
    ("sensor_msgs/msg/BatteryState", "voltage"): ("V",),
    ("sensor_msgs/msg/BatteryState", "current"): ("A",),
}


# ------------------------------------------------------------------------------------------ resolve
@dataclass(frozen=True)
class _Hop:
    """How to take one step at run time."""

    name: str
    index: int | str | None  # int: element; str: element named so in the owner's ``name`` array
    fixed_len: int | None  # length of a fixed-size array (None for sequences)


@dataclass(frozen=True)
class ResolvedPath:
    """A field path checked against a message type: reads (and writes) that scalar.

    Attributes:
        path: the parsed path.
        msg_type: the full message type it was resolved against.
        leaf_type: the scalar's ROS type (``float64``, ...); ``geometry_msgs/msg/Quaternion`` for conversions.
        units: the REP 103 unit(s) the field carries, ``()`` when not known (e.g. ``std_msgs/Float64.data``).
    """

    path: FieldPath
    msg_type: str
    leaf_type: str
    units: tuple[str, ...]
    hops: tuple[_Hop, ...]

    def __str__(self) -> str:
        return str(self.path)

    # -------------------------------------------------------------------------------------- read
    def read(self, msg: Any, topic: str = "") -> float:
        """The scalar of ``msg`` (rclpy message or rosbags dataclass) as a float; :class:`SchemaError` when
        an array is too short (``shape``), a named joint is missing (``names``), a quaternion is not unit
        (``quaternion``) or the value is NaN / Inf (``nan``)."""
        label = topic or self.msg_type
        obj = msg
        for hop in self.hops:
            owner = obj
            obj = getattr(owner, hop.name)
            if hop.index is None:
                continue
            if isinstance(hop.index, str):
                names = list(owner.name)
                try:
                    i = names.index(hop.index)
                except ValueError:
                    raise SchemaError(label, str(self.path), "names",
                                      f"no entry named {hop.index!r} in name {names}") from None
            else:
                i = hop.index
            if i >= len(obj):
                raise SchemaError(label, str(self.path), "shape", f"{hop.name} has {len(obj)} element(s), "
                                                                  f"needs index {i}")
            obj = obj[i]
        if self.path.conversion is not None:
            value = _euler(label, str(self.path), obj, self.path.conversion)
        else:
            value = float(obj)
        if not math.isfinite(value):
            raise SchemaError(label, str(self.path), "nan", f"value is {value}")
        return value

    # -------------------------------------------------------------------------------------- write
    def write(self, msg: Any, value: float) -> None:
        """Set the scalar in ``msg`` (built by :func:`default_message`): array elements are appended as
        needed, a named element adds its name to ``name``; a conversion writes the quaternion of that one
        angle (the other two zero)."""
        obj = msg
        hops = self.hops
        for k, hop in enumerate(hops):
            last = k == len(hops) - 1
            owner = obj
            if hop.index is None:
                if last and self.path.conversion is None:
                    setattr(owner, hop.name, _cast(self.leaf_type, value))
                    return
                obj = getattr(owner, hop.name)
                continue
            if isinstance(hop.index, str):
                names = list(owner.name)
                if hop.index not in names:
                    names.append(hop.index)
                    owner.name = names
                i = names.index(hop.index)
            else:
                i = hop.index
            arr = getattr(owner, hop.name)
            if last and self.path.conversion is None:
                vals = [float(v) for v in arr]
                vals += [0.0] * (i + 1 - len(vals))
                vals[i] = float(value)
                setattr(owner, hop.name, _as_array_like(arr, vals))
                return
            obj = arr[i]
        if self.path.conversion is not None:
            half = 0.5 * float(value)
            c, s = math.cos(half), math.sin(half)
            q = {"yaw": (c, 0.0, 0.0, s), "pitch": (c, 0.0, s, 0.0), "roll": (c, s, 0.0, 0.0)}[self.path.conversion]
            for attr, v in zip("wxyz", q, strict=True):
                setattr(obj, attr, v)


def _cast(ros_type: str, value: float) -> Any:
    if ros_type in ("float64", "float32"):
        return float(value)
    if ros_type == "bool":
        return bool(value)
    return int(round(value))


def _as_array_like(template: Any, values: list[float]) -> Any:
    return np.asarray(values, dtype=np.float64) if isinstance(template, np.ndarray) else values


def _euler(topic: str, path: str, q: Any, which: str) -> float:
    w, x, y, z = (float(getattr(q, a)) for a in "wxyz")
    norm = math.sqrt(w * w + x * x + y * y + z * z)
    if not math.isfinite(norm):
        raise SchemaError(topic, path, "nan", f"quaternion has a non-finite component ({w}, {x}, {y}, {z})")
    if abs(norm - 1.0) > QUAT_NORM_TOL:
        raise SchemaError(topic, path, "quaternion", f"quaternion norm {norm:.6g} is not 1")
    w, x, y, z = w / norm, x / norm, y / norm, z / norm
    if which == "yaw":
        return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))
    if which == "pitch":
        return math.asin(max(-1.0, min(1.0, 2.0 * (w * y - z * x))))
    return math.atan2(2.0 * (w * x + y * z), 1.0 - 2.0 * (x * x + y * y))


def resolve(path: str | FieldPath, msg_type: str) -> ResolvedPath:
    """Check ``path`` against ``msg_type`` (see the module docstring); :class:`FieldPathError` if it does not fit."""
    full = check_message_type(msg_type)
    fp = path if isinstance(path, FieldPath) else parse_field_path(path, full)
    text = str(path)
    current = full
    hops: list[_Hop] = []
    units: tuple[str, ...] = ()
    leaf = ""
    for k, step in enumerate(fp.steps):
        last = k == len(fp.steps) - 1
        if current in ("", None) or current in NUMERIC_TYPES or current == "string":
            raise FieldPathError(text, full, f"{'.'.join(str(s) for s in fp.steps[:k])} is a {current or 'scalar'}"
                                             f", it has no field {step.name!r}")
        fields = dict(message_fields(current))
        if step.name not in fields:
            close = difflib.get_close_matches(step.name, list(fields), n=1)
            hint = f" (did you mean {close[0]!r}?)" if close else ""
            raise FieldPathError(text, full, f"{current} has no field {step.name!r}{hint}; its fields are "
                                             f"{list(fields)}")
        node, spec = fields[step.name]
        units = _UNITS.get((current, step.name), _UNITS.get((current, "*"), units))
        fixed_len = None
        if step.index is not None:
            if node not in (_ARRAY, _SEQUENCE):
                raise FieldPathError(text, full, f"{current}.{step.name} is not an array, it cannot be indexed")
            (sub_node, sub_spec), length = spec
            if node == _ARRAY:
                fixed_len = int(length)
                if isinstance(step.index, int) and step.index >= fixed_len:
                    raise FieldPathError(text, full, f"index {step.index} is outside {current}.{step.name} "
                                                     f"(fixed size {fixed_len})")
            if isinstance(step.index, str):
                names = fields.get("name")
                if names is None or names[0] != _SEQUENCE or names[1][0] != (_BASE, ("string", 0)):
                    raise FieldPathError(text, full, f"[{step.index}] looks an element up by name, but {current} "
                                                     "has no parallel 'name' array (use an integer index)")
            node, spec = sub_node, sub_spec
        elif node in (_ARRAY, _SEQUENCE):
            raise FieldPathError(text, full, f"{current}.{step.name} is an array: add an index, e.g. "
                                             f"'{step.name}[0]' or '{step.name}[joint_name]'")
        hops.append(_Hop(step.name, step.index, fixed_len))
        if node == _NAME_T:
            current = spec
            leaf = spec
        else:
            current = spec[0]
            leaf = spec[0]
        if last:
            break
    if fp.conversion is not None:
        if leaf != QUATERNION:
            raise FieldPathError(text, full, f"{fp.conversion}() needs a {QUATERNION}, but {fp.steps and fp.steps[-1]}"
                                             f" is a {leaf}")
        units = ("rad",)
    elif leaf not in NUMERIC_TYPES:
        what = "a string" if leaf == "string" else f"a {leaf} message"
        hint = " (use yaw(...), pitch(...) or roll(...) for an angle)" if leaf == QUATERNION else ""
        raise FieldPathError(text, full, f"ends on {what}, not a number{hint}")
    return ResolvedPath(fp, full, leaf, tuple(units), tuple(hops))


def field_unit(path: str | FieldPath, msg_type: str) -> tuple[str, ...]:
    """The REP 103 unit(s) of ``path`` in ``msg_type`` (``()`` when unknown); see :func:`resolve`."""
    return resolve(path, msg_type).units


# ------------------------------------------------------------------------------------------ building
def default_message(factory: Any, msg_type: str) -> Any:
    """A message of ``msg_type`` with every field zero / empty, built by a :class:`~msg_schemas.base.MessageFactory`
    (rosbags dataclasses have no defaults, so they are built field by field from the type definition)."""
    name = check_message_type(msg_type)
    from msg_schemas.base import RclpyFactory

    if isinstance(factory, RclpyFactory):
        return factory.cls(name)()
    return factory.make(name, **{n: _default_value(factory, t) for n, t in message_fields(name)})


def _default_value(factory: Any, node_spec: tuple[int, Any]) -> Any:
    node, spec = node_spec
    if node == _BASE:
        typ = spec[0]
        return "" if typ == "string" else False if typ == "bool" else 0.0 if typ.startswith("float") else 0
    if node == _NAME_T:
        return default_message(factory, spec)
    (sub_node, sub_spec), length = spec
    if sub_node == _BASE and sub_spec[0] != "string":
        dtype = np.float64 if sub_spec[0].startswith("float") else np.int64
        return np.zeros(int(length) if node == _ARRAY else 0, dtype=dtype)
    n = int(length) if node == _ARRAY else 0
    return [_default_value(factory, (sub_node, sub_spec)) for _ in range(n)]


def pad_named_arrays(msg: Any, paths: Sequence[ResolvedPath]) -> None:
    """Make every array that ``paths`` index by name as long as its message's ``name`` array (zeros appended),
    so a written JointState is valid whatever order its values were set in."""
    for rp in paths:
        obj = msg
        for hop in rp.hops:
            owner, obj = obj, getattr(obj, hop.name)
            if isinstance(hop.index, str):
                n = len(list(owner.name))
                if len(obj) < n:
                    setattr(owner, hop.name, _as_array_like(obj, [float(v) for v in obj] + [0.0] * (n - len(obj))))
                break
            if hop.index is not None:
                if hop.index >= len(obj):
                    break
                obj = obj[hop.index]


def reader(paths: Sequence[ResolvedPath]) -> Callable[[Any, str], np.ndarray]:
    """A function reading all ``paths`` of one message into a float64 vector ``(len(paths),)``."""

    def read(msg: Any, topic: str = "") -> np.ndarray:
        return np.array([p.read(msg, topic) for p in paths], dtype=np.float64)

    return read
