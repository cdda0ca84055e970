"""What the built-in systems' entries share: a system checked against its class, the shooting MPC's controllers."""

from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING, TypeVar

from saml_ros.core.systems.entry import ControllerFactory

if TYPE_CHECKING:
    from saml_ros.core.dynamics.system import System


T = TypeVar("T")


def _as(system: System, cls: type[T]) -> T:
    """``system`` typed as ``cls``; ``ValueError`` if it is another system."""
    if not isinstance(system, cls):
        raise ValueError(f"expected a {cls.__name__} system, got {type(system).__name__} ({system.name!r})")
    return system


def _shooting_controllers() -> Mapping[str, ControllerFactory]:
    from saml_ros.core.mpc.shooting import SLSQPShootingMPC, SQPShootingMPC

    return {"fast": SQPShootingMPC, "slsqp": SLSQPShootingMPC}
