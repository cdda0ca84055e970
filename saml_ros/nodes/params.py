"""Declaring a node's :class:`~saml_ros.core.params.Param` table through rclpy, and reading ``system`` first.

Every parameter gets a ``ParameterDescriptor`` with its description, so ``ros2 param describe`` and
``--params-file`` work as usual. Float parameters are dynamically typed, so a YAML ``10`` is accepted for
``10.0``; an empty list default is declared with its ``item_type``'s array type. The values come back raw:
the node's configuration class (``from_params``) converts and validates them, naming a bad parameter.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

from rcl_interfaces.msg import ParameterDescriptor
from rclpy.exceptions import ParameterUninitializedException
from rclpy.node import Node
from rclpy.parameter import Parameter

from saml_ros.core.params import Param

#: rclpy type of an empty list parameter, by element type
_ARRAY_TYPES = {float: Parameter.Type.DOUBLE_ARRAY, int: Parameter.Type.INTEGER_ARRAY,
                str: Parameter.Type.STRING_ARRAY, bool: Parameter.Type.BOOL_ARRAY}


def declare_params(node: Node, params: Iterable[Param]) -> dict[str, Any]:
    """Declare ``params`` on ``node``; ``{name: value}`` (the default where rclpy has none).

    Raises:
        ValueError: rclpy refused a value (e.g. an override of the wrong type); the message names the parameter.
    """
    out: dict[str, Any] = {}
    for p in params:
        descriptor = ParameterDescriptor(description=p.description, dynamic_typing=isinstance(p.default, float))
        value = _ARRAY_TYPES[p.item_type] if isinstance(p.default, list) and not p.default else p.default
        try:
            got = node.declare_parameter(p.name, value, descriptor).value
        except Exception as exc:  # noqa: BLE001 - rclpy raises several types for bad overrides
            raise ValueError(f"parameter {p.name!r}: {exc}") from None
        out[p.name] = p.default if got is None else got
    return out


def current_values(node: Node, params: Iterable[Param]) -> dict[str, Any]:
    """The current values of the declared ``params`` of ``node`` by name (the default where rclpy has none, as
    for an empty list); a managed node reads them at ``configure``, so values set meanwhile apply."""
    out: dict[str, Any] = {}
    for p in params:
        try:
            got = node.get_parameter(p.name).value
        except ParameterUninitializedException:  # an empty list declared by its type holds no value
            got = None
        out[p.name] = p.default if got is None else got
    return out


def probe_system(node_name: str, default: str = "friction", file_param: str | None = None) -> tuple[str, bool]:
    """``(system, remapped)``: the ``system`` parameter a node called ``node_name`` gets (from the command line or
    a parameter file) and whether ``__ns`` is remapped, read by a short-lived probe node: a node's namespace
    (``/<system>`` unless remapped) must be known when it is created. With ``file_param`` (e.g. ``system_file``)
    set to a system file, the system is the ``name`` in that file (the node reports a bad file when it loads it).
    ``ValueError`` naming ``system`` if rclpy refuses the value."""
    probe = Node(node_name)
    try:
        system = probe.declare_parameter("system", default).value
        path = probe.declare_parameter(file_param, "").value if file_param else ""
    except Exception as exc:  # noqa: BLE001 - rclpy raises several types for bad overrides
        raise ValueError(f"parameter 'system': {exc}") from None
    finally:
        remapped = probe.get_namespace() != "/"
        probe.destroy_node()
    if path:
        system = _file_system_name(str(path)) or system
    return system, remapped


def _file_system_name(path: str) -> str | None:
    """The ``name`` of a system file, or None when it cannot be read."""
    import yaml

    try:
        with open(path) as f:
            name = yaml.safe_load(f).get("name")
    except Exception:  # noqa: BLE001 - reported properly when the node loads the file
        return None
    return name if isinstance(name, str) and name.isidentifier() else None
