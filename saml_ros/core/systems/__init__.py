"""The systems and their registry.

``get_system(name, **overrides)`` builds a system by its registry name with physical parameters overridden,
e.g. ``get_system("quadrotor", alpha=0.3)``; ``get_entry(name)`` is the system's
:class:`~saml_ros.core.systems.entry.SystemEntry` (dynamics, numpy twin, MPC, goals, schema, simulator, bringup
defaults, experiment). The dynamics live in :mod:`.friction`, :mod:`.quadrotor` and :mod:`.paddle_ball`
(import the classes from there); the contract they implement is :mod:`.base`. See ``docs/systems.md``.

Robots described by a YAML system file (:mod:`.system_file`) are registered by :mod:`.robot_entry`.

This face imports no torch (the registry imports a system's module only when it is asked for it).
"""

from __future__ import annotations

from saml_ros.core.systems.entry import SystemEntry
from saml_ros.core.systems.registry import (
    SYSTEM_NAMES,
    default_params,
    find_entry,
    get_entry,
    get_system,
    register_system,
    system_class,
    system_names,
    unregister_system,
)
from saml_ros.systems import robot_entry  # noqa: F401 - installs the loader of robots' stored definitions

__all__ = [
    "SYSTEM_NAMES",
    "SystemEntry",
    "default_params",
    "find_entry",
    "get_entry",
    "get_system",
    "register_system",
    "system_class",
    "system_names",
    "unregister_system",
]
