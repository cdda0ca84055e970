"""The system registry: the table of :class:`~saml_ros.core.systems.entry.SystemEntry` records by name.

``get_system(name, **overrides)`` builds a system by its registry name with physical parameters overridden,
e.g. ``get_system("quadrotor", alpha=0.3)``; ``get_entry(name)`` is the system's entry (dynamics, numpy twins,
MPC, goals, schema, simulator, bringup defaults, experiment). The systems themselves live above the core, one
folder each (``saml_ros.systems``: the built-in three and robots described by a YAML system file), and register
themselves here when ``saml_ros`` is imported; the contract their classes implement is
:mod:`saml_ros.core.dynamics.system`. See ``docs/systems.md``.

This face imports no torch (an entry imports a system's modules only when it is asked for them).
"""

from __future__ import annotations

from typing import Any

from saml_ros.core.systems import registry as _registry
from saml_ros.core.systems.entry import SystemEntry
from saml_ros.core.systems.registry import (
    default_params,
    find_entry,
    get_entry,
    get_system,
    register_builtin,
    register_system,
    system_class,
    system_names,
    unregister_system,
)


def __getattr__(name: str) -> Any:
    """``SYSTEM_NAMES``, read from the registry when asked (it fills as the built-in systems register)."""
    if name == "SYSTEM_NAMES":
        return _registry.SYSTEM_NAMES
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = [
    "SYSTEM_NAMES",
    "SystemEntry",
    "default_params",
    "find_entry",
    "get_entry",
    "get_system",
    "register_builtin",
    "register_system",
    "system_class",
    "system_names",
    "unregister_system",
]
