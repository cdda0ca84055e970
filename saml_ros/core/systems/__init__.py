"""The paper's three systems and their registry.

``get_system(name, **overrides)`` builds a system by its registry name with physical parameters overridden,
e.g. ``get_system("quadrotor", alpha=0.3)``. See ``docs/systems.md`` for the models and their parameters.
"""

from __future__ import annotations

import inspect
from typing import Any

from saml_ros.core.systems.base import System
from saml_ros.core.systems.friction import FrictionDoubleIntegrator
from saml_ros.core.systems.paddle_ball import PaddleBall
from saml_ros.core.systems.quadrotor import Quadrotor

_REGISTRY: dict[str, type[System]] = {
    FrictionDoubleIntegrator.name: FrictionDoubleIntegrator,
    Quadrotor.name: Quadrotor,
    PaddleBall.name: PaddleBall,
}

#: valid registry names, in a stable order
SYSTEM_NAMES: tuple[str, ...] = tuple(_REGISTRY)


def system_class(name: str) -> type[System]:
    """The class registered as ``name``; ``ValueError`` listing the valid names otherwise."""
    try:
        return _REGISTRY[name]
    except (KeyError, TypeError):
        raise ValueError(f"unknown system {name!r}; valid names are {list(SYSTEM_NAMES)}") from None


def default_params(name: str) -> dict[str, Any]:
    """The constructor parameters of system ``name`` with their (paper) defaults."""
    sig = inspect.signature(system_class(name).__init__)
    return {k: p.default for k, p in sig.parameters.items() if p.kind is inspect.Parameter.KEYWORD_ONLY}


def get_system(name: str, **overrides: Any) -> System:
    """Build system ``name`` (one of :data:`SYSTEM_NAMES`) with parameters ``overrides``.

    ``get_system(name, definition=...[, base_function=f])`` rebuilds a robot described by a system file from its
    stored definition (:meth:`~saml_ros.core.systems.system_file.FileSystem.params`; ``base_function``: its
    user base model function, already imported).

    Raises ``ValueError`` for an unknown name, an unknown parameter (listing the valid ones) or an invalid
    parameter value.
    """
    if "definition" in overrides and set(overrides) <= {"definition", "base_function"} and name not in _REGISTRY:
        # a robot described by a system file: checkpoints and training processes carry its whole definition
        from saml_ros.core.systems.system_file import system_from_params

        return system_from_params(overrides)
    cls = system_class(name)
    valid = default_params(name)
    unknown = sorted(set(overrides) - set(valid))
    if unknown:
        raise ValueError(f"system {name!r} has no parameter(s) {unknown}; valid parameters are {sorted(valid)}")
    return cls(**overrides)


__all__ = [
    "SYSTEM_NAMES",
    "FrictionDoubleIntegrator",
    "PaddleBall",
    "Quadrotor",
    "System",
    "default_params",
    "get_system",
    "system_class",
]
