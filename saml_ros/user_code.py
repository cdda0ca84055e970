"""The one place saml_ros imports a user's code named in configuration: a system file's base model f_hat.

``base_model: {function: "dynamics:f_hat"}`` names a module and a function; the module is looked for first in the
system file's folder (or the directories ``base_model.path`` names, relative to the file), then on the Python
path. ``base_model: {entry_point: NAME}`` names an entry point in the group ``saml_ros.systems`` of an installed
package (docs/your_robot.md). The ROS-free core never imports by name (test/test_layers.py); the learner node,
``train``, ``bag_info`` and :mod:`saml_ros.api` load system files through :func:`load_system_file` here, which
resolves the function and hands it to the core. Every failure raises
:class:`~saml_ros.core.dynamics.base_models.BaseModelError` naming the target, the file or module that is missing
and where it was looked for (wrapped in a ``SystemFileError`` naming the file).

A system file's definition stores those directories absolute, and a checkpoint stores the definition: a process
that loads the checkpoint (``load_model``, ``export``, the MPC) imports the same module from the same folder, from
any working directory, with no ``PYTHONPATH``. Nothing stored in the checkpoint is executed: only the module the
user's own system file named is imported. The imported function is a :class:`UserFunction`, which pickles as
its name and directories, so the learner's training process imports it the same way.
"""

from __future__ import annotations

import importlib
import importlib.machinery
import importlib.util
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from saml_ros.core.dynamics.base_models import ENTRY_POINT_GROUP, BaseModelError, BaseModelSpec
from saml_ros.systems.robot_entry import register_robot
from saml_ros.systems.system_file import FileSystem, SystemFileError, read_system_file


class UserFunction:
    """A user's base model function; pickles as ``(target, search)`` and is imported again on unpickling
    (:func:`import_function`), so it reaches another process whatever that process's ``sys.path``."""

    def __init__(self, target: str, search: Sequence[str], fn: Callable[..., Any]) -> None:
        self.target = target
        self.search = tuple(search)
        self.fn = fn
        self.__doc__ = getattr(fn, "__doc__", None)
        self.__wrapped__ = fn  # inspect.signature sees the function's (an array-namespace form takes ``xp``)

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        return self.fn(*args, **kwargs)

    def __reduce__(self) -> tuple[Any, ...]:
        return import_function, (self.target, self.search)

    def __repr__(self) -> str:
        return f"UserFunction({self.target!r} from {list(self.search) or 'the Python path'})"


def _module_dirs(mod: Any) -> list[Path]:
    """The folders a loaded module or package comes from."""
    if getattr(mod, "__file__", None):
        f = Path(mod.__file__).resolve()
        return [f.parent.parent if f.name == "__init__.py" else f.parent]
    return [Path(p).resolve().parent for p in getattr(mod, "__path__", [])]


def _locate(module: str, target: str, search: Sequence[str]) -> None:
    """Put the directory of ``search`` that holds ``module``'s top-level name first on ``sys.path``; a clear
    :class:`BaseModelError` when the module is in none of them and not importable otherwise."""
    top = module.split(".")[0]
    for d in search:
        folder = Path(d)
        if not folder.is_dir() or importlib.machinery.PathFinder.find_spec(top, [str(folder)]) is None:
            continue
        loaded = sys.modules.get(top)
        if loaded is not None and folder.resolve() not in _module_dirs(loaded):
            where = ", ".join(str(x) for x in _module_dirs(loaded)) or "a built-in"
            raise BaseModelError(f"base model function {target!r}: a module {top!r} is already imported in this "
                                 f"process from {where}, not from {folder}: two robots' modules share a name; give "
                                 "this one a name of its own")
        if str(folder) not in sys.path:
            sys.path.insert(0, str(folder))
            importlib.invalidate_caches()
        return
    if not search:
        return
    try:
        found = importlib.util.find_spec(top) is not None
    except (ImportError, ValueError):
        found = False
    if not found:
        looked = "; ".join(f"{d}{'' if Path(d).is_dir() else ' (no such folder)'}" for d in search)
        raise BaseModelError(f"base model function {target!r}: no module {top!r} ({top}.py or a package {top}/) in "
                             f"{looked} (the system file's folder, or base_model.path), nor on the Python path")


def import_function(target: str, search: Sequence[str] = ()) -> UserFunction:
    """``"module.path:function"`` -> the function, its module looked for first in the directories ``search``
    (:func:`_locate`), then on the Python path; :class:`BaseModelError` if it cannot be imported or called."""
    module, sep, attr = str(target).partition(":")
    if not sep or not module or not attr:
        raise BaseModelError(f"base model function {target!r}: expected 'module.path:function'")
    _locate(module, target, search)
    try:
        mod = importlib.import_module(module)
    except Exception as exc:  # noqa: BLE001 - any import failure is a configuration error
        where = f" (looked in {', '.join(search)} first)" if search else ""
        raise BaseModelError(f"base model function {target!r}: cannot import module {module!r}{where}: "
                             f"{type(exc).__name__}: {exc}") from None
    obj: Any = mod
    for part in attr.split("."):
        if not hasattr(obj, part):
            raise BaseModelError(f"base model function {target!r}: module {module!r} has no {attr!r} "
                                 f"({getattr(mod, '__file__', None) or 'no file'})")
        obj = getattr(obj, part)
    if not callable(obj):
        raise BaseModelError(f"base model function {target!r}: {attr!r} is not callable")
    return UserFunction(str(target), search, obj)


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
        return import_function(spec.function, spec.path)
    if spec.entry_point is not None:
        return load_entry_point(spec.entry_point)
    return None


def load_system_file(path: str | Path) -> FileSystem:
    """Read, validate and build the robot of system file ``path``, importing its base model if it is user code
    (see :func:`saml_ros.systems.system_file.read_system_file`), and register it under its name
    (:func:`saml_ros.systems.robot_entry.register_robot`); ``SystemFileError`` on any problem."""
    system = read_system_file(path, resolve=resolve_base_model)
    try:
        register_robot(system)
    except ValueError as exc:
        raise SystemFileError(str(path), "name", str(exc)) from None
    return system


def system_from_definition(definition: dict[str, Any], where: str = "") -> FileSystem:
    """A robot from a parsed (e.g. checkpoint-stored) definition, importing its base model if it is user code."""
    from saml_ros.systems.system_file import parse_definition

    label = where or f"stored definition of {definition.get('name')!r}"
    return FileSystem(parse_definition(definition, label), label, resolve=resolve_base_model)


def load_robot_param(path: str, param: str = "system_file") -> FileSystem:
    """:func:`load_system_file` for a node's parameter ``param``: :class:`~saml_ros.core.params.ParamErrors` (a
    ``ValueError``) naming it and the problem."""
    from saml_ros.core.params import ParamErrors

    try:
        return load_system_file(path)
    except SystemFileError as exc:
        raise ParamErrors([f"parameter '{param}': {exc}"]) from None
