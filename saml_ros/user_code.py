"""The one place saml_ros imports a user's code named in configuration: a system file's base model f_hat.

``base_model: {function: "my_pkg.dynamics:f_hat"}`` names a module and a function; ``base_model: {entry_point:
NAME}`` an entry point in the group ``saml_ros.systems`` of an installed package (docs/your_robot.md). The
ROS-free core never imports by name (test/test_layers.py); the learner node, ``train``, ``bag_info`` and
:mod:`saml_ros.api` load system files through :func:`load_system_file` here, which resolves the function and
hands it to the core. Every failure raises :class:`~saml_ros.core.systems.base_models.BaseModelError` naming the
target and why (wrapped in a ``SystemFileError`` naming the file).
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from pathlib import Path
from typing import Any

from saml_ros.core.systems.base_models import ENTRY_POINT_GROUP, BaseModelError, BaseModelSpec
from saml_ros.core.systems.robot_entry import register_robot
from saml_ros.core.systems.system_file import FileSystem, SystemFileError, read_system_file


def import_function(target: str) -> Callable[..., Any]:
    """``"module.path:function"`` -> the function; :class:`BaseModelError` if it cannot be imported or called."""
    module, sep, attr = str(target).partition(":")
    if not sep or not module or not attr:
        raise BaseModelError(f"base model function {target!r}: expected 'module.path:function'")
    try:
        mod = importlib.import_module(module)
    except Exception as exc:  # noqa: BLE001 - any import failure is a configuration error
        raise BaseModelError(f"base model function {target!r}: cannot import module {module!r}: "
                             f"{type(exc).__name__}: {exc}") from None
    obj: Any = mod
    for part in attr.split("."):
        if not hasattr(obj, part):
            raise BaseModelError(f"base model function {target!r}: module {module!r} has no {attr!r}")
        obj = getattr(obj, part)
    if not callable(obj):
        raise BaseModelError(f"base model function {target!r}: {attr!r} is not callable")
    return obj


def load_entry_point(name: str) -> Callable[..., Any]:
    """The function an installed package publishes as entry point ``name`` in the group ``saml_ros.systems``."""
    from importlib.metadata import entry_points

    eps = {ep.name: ep for ep in entry_points(group=ENTRY_POINT_GROUP)}
    if name not in eps:
        raise BaseModelError(f"base model entry point {name!r}: no entry point of that name in group "
                             f"{ENTRY_POINT_GROUP!r} (installed: {sorted(eps) or 'none'})")
    ep = eps[name]
    try:
        obj = ep.load()
    except Exception as exc:  # noqa: BLE001
        raise BaseModelError(f"base model entry point {name!r} ({ep.value}): failed to import: "
                             f"{type(exc).__name__}: {exc}") from None
    if not callable(obj):
        raise BaseModelError(f"base model entry point {name!r} ({ep.value}) is not callable")
    return obj


def resolve_base_model(spec: BaseModelSpec) -> Callable[..., Any] | None:
    """The user's function a ``base_model`` section names (``None`` for a built-in)."""
    if spec.function is not None:
        return import_function(spec.function)
    if spec.entry_point is not None:
        return load_entry_point(spec.entry_point)
    return None


def load_system_file(path: str | Path) -> FileSystem:
    """Read, validate and build the robot of system file ``path``, importing its base model if it is user code
    (see :func:`saml_ros.core.systems.system_file.read_system_file`), and register it under its name
    (:func:`saml_ros.core.systems.robot_entry.register_robot`); ``SystemFileError`` on any problem."""
    system = read_system_file(path, resolve=resolve_base_model)
    try:
        register_robot(system)
    except ValueError as exc:
        raise SystemFileError(str(path), "name", str(exc)) from None
    return system


def system_from_definition(definition: dict[str, Any], where: str = "") -> FileSystem:
    """A robot from a parsed (e.g. checkpoint-stored) definition, importing its base model if it is user code."""
    from saml_ros.core.systems.system_file import parse_definition

    label = where or f"stored definition of {definition.get('name')!r}"
    return FileSystem(parse_definition(definition, label), label, resolve=resolve_base_model)


def load_robot_param(path: str, param: str = "system_file") -> FileSystem:
    """:func:`load_system_file` for a node's parameter ``param``: ``ValueError`` naming it and the problem."""
    try:
        return load_system_file(path)
    except SystemFileError as exc:
        raise ValueError(f"parameter '{param}': {exc}") from None
