"""Named vector layouts: which scalar sits at which index of a state, control or target vector.

Every vector that crosses a module boundary (simulator, learner, MPC, bag tools, messages) is a flat
float vector whose meaning is given by a :class:`VectorLayout`. Units follow REP 103 (SI, radians).
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Iterable, Sequence
from dataclasses import dataclass


@dataclass(frozen=True)
class Field:
    """One scalar of a vector.

    Attributes:
        name: identifier, unique within its layout (``"p"``, ``"vz"``, ``"qw"``).
        unit: SI unit string (``"m"``, ``"m/s"``, ``"rad/s"``, ``"N"``, ``"1"`` for dimensionless).
        description: one line for docs and ``--help``.
    """

    name: str
    unit: str
    description: str = ""


@dataclass(frozen=True)
class VectorLayout:
    """An ordered set of named fields, e.g. the 13-dimensional quadrotor state."""

    name: str
    fields: tuple[Field, ...]

    def __post_init__(self) -> None:
        names = [f.name for f in self.fields]
        dup = {n for n in names if names.count(n) > 1}
        if dup:
            raise ValueError(f"layout {self.name!r}: duplicate field names {sorted(dup)}")

    @property
    def size(self) -> int:
        return len(self.fields)

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(f.name for f in self.fields)

    def index(self, name: str) -> int:
        """Index of field ``name``; raises ``KeyError`` naming the field and the valid ones."""
        for i, f in enumerate(self.fields):
            if f.name == name:
                return i
        raise KeyError(f"{self.name} has no field {name!r}; fields are {list(self.names)}")

    def indices(self, names: Iterable[str]) -> list[int]:
        return [self.index(n) for n in names]

    def as_dict(self) -> dict[str, object]:
        return {"name": self.name, "fields": [[f.name, f.unit] for f in self.fields]}

    def schema_hash(self) -> str:
        """Stable hash of names, order and units (not descriptions)."""
        blob = json.dumps(self.as_dict(), sort_keys=True).encode()
        return hashlib.sha256(blob).hexdigest()[:16]


def make_layout(name: str, spec: Sequence[tuple[str, str] | tuple[str, str, str]]) -> VectorLayout:
    """Build a layout from ``(name, unit[, description])`` tuples."""
    return VectorLayout(name, tuple(Field(*s) for s in spec))


def schema_hash(*layouts: VectorLayout) -> str:
    """Combined hash of several layouts (state, control, target) for checkpoint compatibility."""
    h = hashlib.sha256()
    for lay in layouts:
        h.update(json.dumps(lay.as_dict(), sort_keys=True).encode())
    return h.hexdigest()[:16]
