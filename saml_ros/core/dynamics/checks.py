"""Validation of system constructor parameters: every failure is a ``ValueError`` naming the parameter."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any


def real(owner: str, name: str, value: Any, *, lo: float = -math.inf, hi: float = math.inf,
         lo_open: bool = False, hi_open: bool = False) -> float:
    """``value`` as a finite float within ``[lo, hi]`` (ends open if asked), else ``ValueError``."""
    try:
        f = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{owner}: parameter {name!r} must be a number, got {value!r}") from None
    if isinstance(value, bool) or not math.isfinite(f):
        raise ValueError(f"{owner}: parameter {name!r} must be a finite number, got {value!r}")
    bad_lo = f <= lo if lo_open else f < lo
    bad_hi = f >= hi if hi_open else f > hi
    if bad_lo or bad_hi:
        lb = "(" if lo_open else "["
        rb = ")" if hi_open else "]"
        raise ValueError(f"{owner}: parameter {name!r} must be in {lb}{lo}, {hi}{rb}, got {f}")
    return f


def positive(owner: str, name: str, value: Any) -> float:
    """``value`` as a finite float > 0."""
    return real(owner, name, value, lo=0.0, lo_open=True)


def real_vector(owner: str, name: str, value: Any, size: int, *, lo: float = -math.inf,
                lo_open: bool = False) -> tuple[float, ...]:
    """``value`` as a tuple of ``size`` finite floats, each ``>= lo`` (``> lo`` if ``lo_open``)."""
    if isinstance(value, (str, bytes)) or not isinstance(value, Sequence) or len(value) != size:
        raise ValueError(f"{owner}: parameter {name!r} must be a sequence of {size} numbers, got {value!r}")
    return tuple(real(owner, f"{name}[{i}]", v, lo=lo, lo_open=lo_open) for i, v in enumerate(value))
