"""The system registry: one :class:`~saml_ros.core.systems.entry.SystemEntry` per system, from which every part
of that system is reached.

A system's dynamics (its :class:`~saml_ros.core.dynamics.system.System` class, which also holds the paper's spec
and the safe command), numpy twin of the base model, MPC controllers, task and goal parameters, topic schema,
simulator core, bringup defaults, paper training budget and experiment are fields of its entry. Code outside
the registry never asks "which system is this?": it looks the entry up by name (:func:`get_entry`) and uses
what the entry holds.

The table is open: :func:`register_system` adds an entry at run time (a robot from a system file:
:mod:`saml_ros.systems.robot_entry`; :func:`register_loader` rebuilds one from a stored definition in a
process that never read its file). The table sits below the layers its entries wire (MPC, worlds, message
schemas) and imports none of them: the built-in systems (:mod:`saml_ros.systems`, above those layers) register
themselves through :func:`register_builtin` when the ``saml_ros`` package is imported, which happens before any of
its modules runs. Importing the registry imports neither torch, MuJoCo nor the MPC.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING, Any

from saml_ros.core.systems.entry import SystemEntry

if TYPE_CHECKING:
    from saml_ros.core.dynamics.system import System

# ---------------------------------------------------------------------------------------------- the table
_ENTRIES: dict[str, SystemEntry] = {}


def register_system(entry: SystemEntry, *, replace: bool = False) -> SystemEntry:
    """Add ``entry`` to the registry and return it; ``ValueError`` if its name is taken (unless ``replace``)
    or is not a valid ROS name token (it becomes the namespace ``/<name>``)."""
    if not isinstance(entry, SystemEntry):
        raise TypeError(f"register_system wants a SystemEntry, got {type(entry).__name__}")
    name = entry.name
    if not (isinstance(name, str) and name and (name[0].isalpha()) and name.replace("_", "").isalnum()
            and name.isascii()):
        raise ValueError(f"system name {name!r} must start with a letter and hold only letters, digits and '_'")
    if entry.goal_position not in {g.name for g in entry.goal_params}:
        raise ValueError(f"system {name!r}: goal_position {entry.goal_position!r} is not one of its goal_params")
    if name in _ENTRIES and not replace:
        raise ValueError(f"system {name!r} is already registered")
    _ENTRIES[name] = entry
    return entry


def unregister_system(name: str) -> SystemEntry | None:
    """Remove the entry registered as ``name`` (a robot loaded from a system file, a test's system) and return
    it; ``None`` if there is none. The built-in systems cannot be removed (``ValueError``)."""
    if name in SYSTEM_NAMES:
        raise ValueError(f"{name!r} is a built-in system; it cannot be unregistered")
    return _ENTRIES.pop(name, None)


def system_names() -> tuple[str, ...]:
    """Names of every registered system, in registration order (the built-in three first)."""
    return tuple(_ENTRIES)


def find_entry(name: str) -> SystemEntry | None:
    """The entry registered as ``name``, or ``None``."""
    return _ENTRIES.get(name) if isinstance(name, str) else None


def get_entry(name: str) -> SystemEntry:
    """The entry registered as ``name``; ``ValueError`` listing the valid names otherwise."""
    entry = find_entry(name)
    if entry is None:
        raise ValueError(f"unknown system {name!r}; valid names are {list(_ENTRIES)}")
    return entry


def system_class(name: str) -> type[System]:
    """The :class:`System` subclass registered as ``name``; ``ValueError`` listing the valid names otherwise."""
    return get_entry(name).system_class()


def default_params(name: str) -> dict[str, Any]:
    """The constructor parameters of system ``name`` with their (paper) defaults."""
    return get_entry(name).default_params()


#: ``loader(name, overrides) -> entry | None``: builds and registers a system this process has not registered from
#: what it is asked with (a robot's stored definition: :mod:`saml_ros.systems.robot_entry`)
Loader = Callable[[str, Mapping[str, Any]], "SystemEntry | None"]
_LOADERS: list[Loader] = []


def register_loader(loader: Loader) -> None:
    """Let :func:`get_system` ask ``loader`` for names that are not registered (see :data:`Loader`)."""
    if loader not in _LOADERS:
        _LOADERS.append(loader)


def get_system(name: str, **overrides: Any) -> System:
    """Build system ``name`` with parameters ``overrides``; a name not registered yet is offered to the
    loaders (:func:`register_loader`), e.g. a robot rebuilt from the definition a checkpoint stored.

    Raises ``ValueError`` for an unknown name, an unknown parameter (listing the valid ones) or an invalid
    parameter value.
    """
    entry = find_entry(name)
    for loader in _LOADERS if entry is None else ():
        entry = loader(name, overrides)
        if entry is not None:
            break
    return (entry or get_entry(name)).make_system(**overrides)


#: the built-in systems, in registration order (:func:`register_builtin`; :func:`system_names` also lists systems
#: registered later). Read it as ``registry.SYSTEM_NAMES`` or from the package face, which both see it filled.
SYSTEM_NAMES: tuple[str, ...] = ()


def register_builtin(*entries: SystemEntry) -> None:
    """Register the built-in systems (``saml_ros.systems`` does, when ``saml_ros`` is imported): like
    :func:`register_system`, and they join :data:`SYSTEM_NAMES` (never unregistered). A second call with the same
    entries changes nothing."""
    global SYSTEM_NAMES
    for entry in entries:
        if entry.name in SYSTEM_NAMES and _ENTRIES.get(entry.name) is entry:
            continue
        register_system(entry)
        SYSTEM_NAMES = (*SYSTEM_NAMES, entry.name)
