"""Plausibility bounds: the range of values a system's states, commands and targets can physically take.

A finite value far outside any physical range (a broken sensor, a driver bug, a hostile sender) is as useless
as NaN and much more dangerous: it passes every finiteness check and poisons whatever learns from it or plans
with it. Every receiver therefore checks vectors against :class:`Plausibility` and rejects, counting
``rejected/bounds``, what falls outside: the learner's pairing (:mod:`saml_ros.core.data.pairing`), the MPC
(:mod:`saml_ros.core.mpc.service`, which answers such a state with the safe command), bag extraction
(:mod:`saml_ros.bags.transitions`) and the checkpoint acceptance of the MPC (predictions of a model outside the
plausible range, :mod:`saml_ros.core.mpc.acceptance`). The simulators reject implausible commands with the same
reason (:class:`~saml_ros.core.worlds.sim_core.CommandValidator`).

The defaults live in the system's one home, its :class:`~saml_ros.core.dynamics.system.System` class
(:meth:`~saml_ros.core.dynamics.system.System.plausible_state`, ``plausible_control``, ``plausible_target``). Nodes
take overrides as the parameter ``plausible_bounds``: a YAML mapping from a field, named as in a problem spec
(``x.<state field>``, ``u.<control field>``, ``next.<target field>``), to ``[low, high]`` in the field's unit
(``.inf`` / ``-.inf`` or ``null`` for an open end), e.g. ``"{x.pz: [-1.0, 2000.0], u.f1: [0.0, 40.0]}"``. For a
time-stepped system ``next`` is the state, so ``next.<field>`` and ``x.<field>`` name the same range.

No torch here: the learner node builds its pairing configuration before its training process has imported it.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
import yaml

if TYPE_CHECKING:
    from saml_ros.core.dynamics.system import System

#: vector kinds and the prefix naming their fields in ``plausible_bounds`` (as in a problem spec)
PREFIXES: dict[str, str] = {"state": "x", "control": "u", "target": "next"}
#: pairing event kinds -> vector kinds (``applied_cmd`` is a control)
EVENT_KINDS: dict[str, str] = {"state": "state", "applied_cmd": "control", "target": "target"}


@dataclass(frozen=True)
class Range:
    """Bounds of one vector kind: ``low`` / ``high`` per field (``-inf`` / ``inf`` = open), field ``names``."""

    names: tuple[str, ...]
    low: tuple[float, ...]
    high: tuple[float, ...]

    def __post_init__(self) -> None:
        object.__setattr__(self, "_lo", np.array(self.low, dtype=np.float64))
        object.__setattr__(self, "_hi", np.array(self.high, dtype=np.float64))

    def outside(self, vec: np.ndarray) -> str | None:
        """``None`` if ``vec`` ``(n,)`` is within the bounds, else which fields are outside (for a log line)."""
        v = np.asarray(vec, dtype=np.float64)
        lo, hi = self._lo, self._hi  # type: ignore[attr-defined]
        inside = (v >= lo) & (v <= hi)
        if inside.all():
            return None
        bad = np.flatnonzero(~inside)
        return ", ".join(f"{self.names[i]} = {v[i]:.6g} not in [{lo[i]:g}, {hi[i]:g}]" for i in bad[:4]) + (
            f" (+{bad.size - 4} more)" if bad.size > 4 else "")

    def inside(self, rows: np.ndarray) -> np.ndarray:
        """Boolean ``(B,)``: which rows of ``rows`` ``(B, n)`` are within the bounds (NaN is outside)."""
        r = np.asarray(rows, dtype=np.float64)
        return np.all((r >= self._lo) & (r <= self._hi), axis=-1)  # type: ignore[attr-defined]


@dataclass(frozen=True)
class Plausibility:
    """The plausible ranges of one system's state, control and target vectors (picklable, immutable)."""

    state: Range
    control: Range
    target: Range

    @classmethod
    def for_system(cls, system: System, overrides: Mapping[str, Any] | str | None = None) -> Plausibility:
        """The system's default ranges with ``overrides`` applied (a mapping or the YAML text of the
        ``plausible_bounds`` parameter, see the module docstring); ``ValueError`` naming a bad entry."""
        table = {
            "state": _defaults(system.state.names, system.plausible_state()),
            "control": _defaults(system.control.names, system.plausible_control()),
            "target": _defaults(system.target.names, system.plausible_target()),
        }
        same = system.target is system.state
        for key, (lo, hi) in parse_overrides(overrides).items():
            prefix, _, name = key.partition(".")
            kind = next((k for k, p in PREFIXES.items() if p == prefix), None)
            if kind is None or name not in table[kind]:
                valid = [f"{PREFIXES[k]}.{f}" for k in PREFIXES for f in table[k]]
                raise ValueError(f"plausible_bounds: unknown field {key!r}; fields are {valid}")
            for k in (("state", "target") if same and kind in ("state", "target") else (kind,)):
                table[k][name] = (lo, hi)
        ranges = {k: Range(tuple(v), tuple(a for a, _ in v.values()), tuple(b for _, b in v.values()))
                  for k, v in table.items()}
        return cls(ranges["state"], ranges["control"], ranges["target"])

    def range(self, kind: str) -> Range:
        """The :class:`Range` of ``kind``: ``state``, ``control`` / ``applied_cmd`` or ``target``."""
        return getattr(self, EVENT_KINDS.get(kind, kind))

    def outside(self, kind: str, vec: np.ndarray) -> str | None:
        """``None`` if ``vec`` of ``kind`` is plausible, else which fields are outside."""
        return self.range(kind).outside(vec)

    def describe(self) -> dict[str, list[float]]:
        """``{"x.<field>": [low, high], ...}`` (JSON-safe: open ends as +-1e308)."""
        out: dict[str, list[float]] = {}
        for kind, prefix in PREFIXES.items():
            r = self.range(kind)
            for n, lo, hi in zip(r.names, r.low, r.high):
                out[f"{prefix}.{n}"] = [max(lo, -1e308), min(hi, 1e308)]
        return out


def _defaults(names: Sequence[str], given: Mapping[str, tuple[float, float]]) -> dict[str, tuple[float, float]]:
    unknown = sorted(set(given) - set(names))
    if unknown:
        raise ValueError(f"plausible ranges name unknown field(s) {unknown}; fields are {list(names)}")
    return {n: (float(given[n][0]), float(given[n][1])) if n in given else (-math.inf, math.inf) for n in names}


def parse_overrides(overrides: Mapping[str, Any] | str | None) -> dict[str, tuple[float, float]]:
    """``plausible_bounds`` (YAML text or a mapping) -> ``{field: (low, high)}``; ``ValueError`` if malformed."""
    if overrides is None or (isinstance(overrides, str) and not overrides.strip()):
        return {}
    try:
        data = yaml.safe_load(overrides) if isinstance(overrides, str) else overrides
    except yaml.YAMLError as exc:
        raise ValueError(f"plausible_bounds is not YAML: {exc}") from None
    if not isinstance(data, Mapping):
        raise ValueError(f"plausible_bounds must be a mapping of fields to [low, high], got {overrides!r}")
    out: dict[str, tuple[float, float]] = {}
    for key, value in data.items():
        if not isinstance(key, str) or not isinstance(value, Sequence) or isinstance(value, str) or len(value) != 2:
            raise ValueError(f"plausible_bounds: {key!r} must map to [low, high], got {value!r}")
        lo = -math.inf if value[0] is None else value[0]
        hi = math.inf if value[1] is None else value[1]
        if any(isinstance(b, bool) or not isinstance(b, int | float) or math.isnan(b) for b in (lo, hi)) or lo > hi:
            raise ValueError(f"plausible_bounds: {key!r} must map to [low, high] numbers with low <= high, "
                             f"got {value!r}")
        out[key] = (float(lo), float(hi))
    return out
