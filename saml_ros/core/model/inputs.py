"""What a model reads and which kinds there are, without torch (the learner node checks its parameters with
these before the training process builds the network of :mod:`saml_ros.core.model.network`, which re-exports them).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from saml_ros.core.dynamics.system import System

MODEL_KINDS = ("residual", "full")
#: the smallest input spread :meth:`DynamicsModel.fit_normalization` uses for a field with declared operating bounds
#: (``System.input_bounds``), as a fraction of half the bounds' width: a field that barely moved in the data (a
#: yaw held at 0 during a take-off) is not blown up into the network's strongest input
NORM_FLOOR_FRACTION = 0.1


def input_names(system: System) -> tuple[str, ...]:
    """The qualified names of a model's candidate inputs, ``x.<state field>`` then ``u.<control field>``."""
    return (*(f"x.{n}" for n in system.state.names), *(f"u.{n}" for n in system.control.names))


def resolve_inputs(system: System, inputs: Sequence[str] | None) -> tuple[int, ...]:
    """Indices into ``[x, u]`` of the named ``inputs`` (``x.<field>`` / ``u.<field>``, or a bare field name that is
    a state or a control field but not both), in ``[x, u]`` order; ``None`` = every field.

    Raises:
        ValueError: an unknown, ambiguous or repeated name, or an empty list; the message names the field.
    """
    names = input_names(system)
    if inputs is None:
        return tuple(range(len(names)))
    if isinstance(inputs, str) or not len(inputs):
        raise ValueError(f"model inputs must be a non-empty list of fields (of {list(names)}), got {inputs!r}")
    out: list[int] = []
    for name in inputs:
        if not isinstance(name, str):
            raise ValueError(f"model input {name!r} is not a field name")
        if name in names:
            i = names.index(name)
        else:
            hits = [i for i, n in enumerate(names) if n[2:] == name]
            if len(hits) != 1:
                why = "is both a state and a control field: write x.{0} or u.{0}" if hits else "is not a field"
                raise ValueError(f"model input {name!r} {why.format(name)} (fields: {list(names)})")
            i = hits[0]
        if i in out:
            raise ValueError(f"model input {name!r} is listed twice")
        out.append(i)
    return tuple(sorted(out))
