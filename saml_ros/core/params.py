"""Node parameters described without ROS: name, default (its type is the parameter's type), description.

The nodes declare these through rclpy (with a ``ParameterDescriptor`` carrying the description); everything
here is plain Python, so parameter validation is unit-tested without rclpy. A node's configuration class
(e.g. :class:`saml_ros.core.mpc.config.MPCConfig`) lists its :class:`Param` table and builds itself from the
declared values with :func:`read_params` plus its own range checks, every error naming the parameter.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True)
class Param:
    """One node parameter: name, default (its type is the parameter's type) and description.

    ``item_type`` is the element type of a list parameter (``float``, ``int`` or ``str``); it matters when the
    default is an empty list, which does not show it. ``finite=False`` lets a float parameter be infinite
    (never NaN).
    """

    name: str
    default: Any
    description: str
    item_type: type = float
    finite: bool = True


def coerce_param(name: str, value: Any, default: Any, item_type: type = float, finite: bool = True) -> Any:
    """A parameter value converted to the type of ``default`` (ints are accepted for floats, integral floats
    for ints; floats must be finite unless ``finite`` is False, never NaN; a list parameter takes any sequence
    of ``item_type`` values, numbers for ``float``; an empty YAML list arrives as ``None``); ``ValueError``
    naming the parameter otherwise."""
    def bad() -> ValueError:
        what = f"a list of {item_type.__name__}" if isinstance(default, list) else type(default).__name__
        return ValueError(f"parameter {name!r}: expected {what}, got {value!r}")

    if isinstance(default, bool):
        if not isinstance(value, bool):
            raise bad()
        return value
    if isinstance(default, int):
        if isinstance(value, bool) or not isinstance(value, int | float) or value != int(value):
            raise bad()
        return int(value)
    if isinstance(default, float):
        if isinstance(value, bool) or not isinstance(value, int | float) or math.isnan(value):
            raise bad()
        if finite and not math.isfinite(value):
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
        try:
            return [coerce_param(name, v, item_type(), item_type) for v in value]
        except ValueError:
            raise bad() from None
    raise TypeError(f"unsupported parameter type for {name!r}: {type(default).__name__}")


def read_params(params: Iterable[Param], values: Mapping[str, Any]) -> dict[str, Any]:
    """``{name: value}`` for every parameter of ``params``: ``values[name]`` coerced to the parameter's type
    (:func:`coerce_param`), its default where ``values`` has none. ``ValueError`` naming the first bad one."""
    out: dict[str, Any] = {}
    for p in params:
        out[p.name] = (coerce_param(p.name, values[p.name], p.default, p.item_type, p.finite) if p.name in values
                       else p.default)
    return out


def check(ok: bool, name: str, requirement: str, value: Any) -> None:
    """``ValueError("parameter 'name' must be <requirement>, got <value>")`` unless ``ok``."""
    if not ok:
        raise ValueError(f"parameter {name!r} must be {requirement}, got {value!r}")
