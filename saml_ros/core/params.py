"""Node parameters described without ROS: name, default (its type is the parameter's type), description.

The nodes declare these through rclpy (with a ``ParameterDescriptor`` carrying the description); everything
here is plain Python, so parameter validation is unit-tested without rclpy.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True)
class Param:
    """One node parameter: name, default (its type is the parameter's type) and description."""

    name: str
    default: Any
    description: str



def coerce_param(name: str, value: Any, default: Any) -> Any:
    """A parameter value converted to the type of ``default`` (ints are accepted for floats, integral floats
    for ints, any numeric list for a float list; an empty YAML list arrives as ``None``); ``ValueError``
    naming the parameter otherwise."""
    def bad() -> ValueError:
        return ValueError(f"parameter {name!r}: expected {type(default).__name__}, got {value!r}")

    if isinstance(default, bool):
        if not isinstance(value, bool):
            raise bad()
        return value
    if isinstance(default, int):
        if isinstance(value, bool) or not isinstance(value, int | float) or value != int(value):
            raise bad()
        return int(value)
    if isinstance(default, float):
        if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
            raise bad()
        return float(value)
    if isinstance(default, str):
        if not isinstance(value, str):
            raise bad()
        return value
    if isinstance(default, list):
        if value is None or (isinstance(value, bytes | bytearray) and len(value) == 0):
            return []
        if isinstance(value, str) or not hasattr(value, "__iter__"):
            raise bad()
        items = list(value)
        if any(isinstance(v, bool) or not isinstance(v, int | float) for v in items):
            raise bad()
        return [float(v) for v in items]
    raise TypeError(f"unsupported parameter type for {name!r}: {type(default).__name__}")
