"""Node parameters described without ROS: name, default (its type is the parameter's type), description, and
when a change takes effect; their validation, and the review of a change on a running node.

The nodes declare these through rclpy (with a ``ParameterDescriptor`` carrying the description and
:func:`change_note`); everything here is plain Python, so parameter validation is unit-tested without rclpy. A
node's configuration class (e.g. :class:`saml_ros.core.mpc.config.MPCConfig`) lists its :class:`Param` table and
builds itself from the declared values with :func:`read_params` plus its own range checks, every error naming the
parameter and every bad parameter reported at once (:class:`Problems`, :class:`ParamErrors`).

A change on a running node (``ros2 param set``) is judged by :func:`review_change` with the same validation as
start-up / configure, on the current values with the change applied; whether it may be made depends on the
parameter's :attr:`Param.when`: :data:`LIVE` (applied at once), :data:`CONFIGURE` (a managed node reads it at
``configure``: refused while the node is configured) or :data:`START` (read when the process starts: refused
once it runs). docs/nodes.md, "Parameter changes".
"""

from __future__ import annotations

import contextlib
import difflib
import math
import os
from collections.abc import Callable, Collection, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from saml_ros.core.errors import SamlError

#: a change applies at once on the running node
LIVE = "live"
#: a managed node reads it at ``configure``: change it while the node is unconfigured (a node that is not managed
#: reads it at start-up)
CONFIGURE = "configure"
#: read when the process starts: restart the node to change it
START = "start"
WHEN = (LIVE, CONFIGURE, START)


@dataclass(frozen=True)
class Param:
    """One node parameter: name, default (its type is the parameter's type) and description.

    ``item_type`` is the element type of a list parameter (``float``, ``int`` or ``str``); it matters when the
    default is an empty list, which does not show it. ``finite=False`` lets a float parameter be infinite
    (never NaN). ``when`` says when a change takes effect (:data:`LIVE`, :data:`CONFIGURE`, :data:`START`).
    """

    name: str
    default: Any
    description: str
    item_type: type = float
    finite: bool = True
    when: str = CONFIGURE


def change_note(param: Param, managed: bool) -> str:
    """How a change of ``param`` is handled, as the sentence its declared description ends with."""
    when = effective_when(param, managed)
    if when == LIVE:
        return "Changes apply at once."
    if when == CONFIGURE:
        return "Read at configure: change it while the node is unconfigured."
    return "Read at start-up: restart the node to change it."


def effective_when(param: Param, managed: bool) -> str:
    """``param.when`` for a node that is (``managed``) or is not a lifecycle node (which has no configure: its
    :data:`CONFIGURE` parameters are read at start-up)."""
    return param.when if managed or param.when != CONFIGURE else START


# ------------------------------------------------------------------------------------------------ problems
class ParamErrors(SamlError, ValueError):
    """One or more bad parameters: ``problems`` holds one message per problem (each naming its parameter); the
    text is all of them, joined by ``"; "``."""

    def __init__(self, problems: Sequence[str]) -> None:
        self.problems = list(problems)
        super().__init__("; ".join(self.problems))


def problems_of(exc: BaseException) -> list[str]:
    """The messages of ``exc``: its ``problems`` for a :class:`ParamErrors`, else its text."""
    return list(exc.problems) if isinstance(exc, ParamErrors) else [str(exc)]


class Problems:
    """Collects every problem of a set of parameter values, so that all of them are reported at once.

    ``check`` / ``add`` record a problem (and the parameter it names); ``capture`` records what a block raises
    (``ValueError`` / ``TypeError``); :meth:`raise_if_any` raises :class:`ParamErrors` with all of them.
    """

    def __init__(self) -> None:
        self.messages: list[str] = []
        self.names: set[str] = set()

    def __bool__(self) -> bool:
        return bool(self.messages)

    def add(self, message: str, *names: str) -> None:
        """Record ``message`` (about the parameters ``names``); a repeated message is kept once."""
        if message not in self.messages:
            self.messages.append(message)
        self.names.update(names)

    def check(self, ok: bool, name: str, requirement: str, value: Any) -> None:
        """Record ``"parameter 'name' must be <requirement>, got <value>"`` unless ``ok``."""
        if not ok:
            self.add(f"parameter {name!r} must be {requirement}, got {value!r}", name)

    def has(self, *names: str) -> bool:
        """True when a problem was recorded about one of ``names``."""
        return any(n in self.names for n in names)

    @contextlib.contextmanager
    def capture(self, *names: str, prefix: str = "") -> Iterator[None]:
        """Record the ``ValueError`` / ``TypeError`` the block raises (every message of a :class:`ParamErrors`),
        prefixed with ``prefix`` (e.g. ``"parameter 'x': "``), as a problem about ``names``."""
        try:
            yield
        except (ValueError, TypeError) as exc:
            for message in problems_of(exc):
                self.add(f"{prefix}{message}", *names)

    def raise_if_any(self) -> None:
        """Raise :class:`ParamErrors` with every recorded problem (nothing when there is none)."""
        if self.messages:
            raise ParamErrors(self.messages)


def check(ok: bool, name: str, requirement: str, value: Any) -> None:
    """``ValueError("parameter 'name' must be <requirement>, got <value>")`` unless ``ok``."""
    if not ok:
        raise ValueError(f"parameter {name!r} must be {requirement}, got {value!r}")


# ------------------------------------------------------------------------------------------------ values
def coerce_param(name: str, value: Any, default: Any, item_type: type = float, finite: bool = True) -> Any:
    """A parameter value converted to the type of ``default`` (ints are accepted for floats, integral floats
    for ints; floats must be finite unless ``finite`` is False, never NaN; a list parameter takes any sequence
    of ``item_type`` values, numbers for ``float``; an empty YAML list arrives as ``None``); ``ValueError``
    naming the parameter otherwise."""
    def bad() -> ValueError:
        what = f"a list of {item_type.__name__}" if isinstance(default, list) else type(default).__name__
        return ValueError(f"parameter {name!r}: expected {what}, got {value!r}")

    if isinstance(default, bool):
        if not isinstance(value, bool):
            raise bad()
        return value
    if isinstance(default, int):
        if isinstance(value, bool) or not isinstance(value, int | float) or value != int(value):
            raise bad()
        return int(value)
    if isinstance(default, float):
        if isinstance(value, bool) or not isinstance(value, int | float) or math.isnan(value):
            raise bad()
        if finite and not math.isfinite(value):
            raise bad()
        return float(value)
    if isinstance(default, str):
        if not isinstance(value, str):
            raise bad()
        return value
    if isinstance(default, list):
        if value is None or (isinstance(value, bytes | bytearray) and len(value) == 0):
            return []
        if isinstance(value, str) or not hasattr(value, "__iter__"):
            raise bad()
        try:
            return [coerce_param(name, v, item_type(), item_type) for v in value]
        except ValueError:
            raise bad() from None
    raise TypeError(f"unsupported parameter type for {name!r}: {type(default).__name__}")


def read_params(params: Iterable[Param], values: Mapping[str, Any], problems: Problems | None = None
                ) -> dict[str, Any]:
    """``{name: value}`` for every parameter of ``params``: ``values[name]`` coerced to the parameter's type
    (:func:`coerce_param`), its default where ``values`` has none.

    A value of the wrong type is recorded in ``problems`` (and its default used in its place, so that further
    checks can go on); without ``problems``, :class:`ParamErrors` names every bad one.
    """
    own = Problems() if problems is None else problems
    out: dict[str, Any] = {}
    for p in params:
        out[p.name] = p.default
        if p.name in values:
            with own.capture(p.name):
                out[p.name] = coerce_param(p.name, values[p.name], p.default, p.item_type, p.finite)
    if problems is None:
        own.raise_if_any()
    return out


def unknown_problems(given: Iterable[str], declared: Collection[str], node: str) -> list[str]:
    """One message per name of ``given`` that is not in ``declared`` (the closest declared names suggested)."""
    out = []
    for name in sorted(set(given) - set(declared)):
        close = difflib.get_close_matches(name, list(declared), n=2)
        hint = f" (did you mean {' or '.join(repr(c) for c in close)}?)" if close else ""
        out.append(f"parameter {name!r} is not a parameter of {node}{hint}")
    return out


def exclusive_problems(values: Mapping[str, Any], given: Collection[str],
                       exclusive: Iterable[tuple[str, str]]) -> list[str]:
    """One message per pair of ``exclusive`` whose parameters were both given (``given``) with a non-empty value
    (e.g. ``system`` and ``system_file``)."""
    out = []
    for a, b in exclusive:
        if a in given and b in given and values.get(a) not in ("", None) and values.get(b) not in ("", None):
            out.append(f"parameters {a!r} and {b!r} were both given ({a}={values[a]!r}, {b}={values[b]!r}): give "
                       f"one of them")
    return out


# ------------------------------------------------------------------------------------------------ memory
def available_memory() -> int | None:
    """Bytes of memory this process could still allocate: the smallest of the system's ``MemAvailable``
    (``/proc/meminfo``), the cgroup's limit minus its use (cgroup v2) and, where neither is readable, the
    physical memory; None if nothing is known."""
    found: list[int] = []
    with contextlib.suppress(OSError, ValueError):
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    found.append(int(line.split()[1]) * 1024)
    with contextlib.suppress(OSError, ValueError):
        with open("/sys/fs/cgroup/memory.max") as f:
            limit = f.read().strip()
        if limit != "max":
            with open("/sys/fs/cgroup/memory.current") as f:
                found.append(max(0, int(limit) - int(f.read().strip())))
    if not found:
        with contextlib.suppress(OSError, ValueError, AttributeError):
            found.append(os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"))
    return min(found) if found else None


def format_bytes(n: float) -> str:
    """``n`` bytes as ``"7.28 TiB"`` (binary units)."""
    for unit in ("B", "KiB", "MiB", "GiB", "TiB", "PiB"):
        if abs(n) < 1024 or unit == "PiB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.2f} {unit}"
        n /= 1024
    raise AssertionError("unreachable")


def memory_problems(needs: Sequence[tuple[str, str, int]], available: int | None = None) -> list[str]:
    """Messages for the sizes that cannot be allocated: ``needs`` are ``(parameter, what, bytes)``; each one
    larger than ``available`` (default :func:`available_memory`) is named with its size, and when each fits
    alone but not all together, all of them are named."""
    avail = available_memory() if available is None else available
    if avail is None:
        return []
    out = [f"parameter {name!r}: {what} would take {format_bytes(n)}, more than the {format_bytes(avail)} of "
           f"memory available" for name, what, n in needs if n > avail]
    total = sum(n for _, _, n in needs)
    if not out and total > avail:
        names = ", ".join(repr(name) for name, _, _ in needs)
        out.append(f"parameters {names}: together they would take {format_bytes(total)}, more than the "
                   f"{format_bytes(avail)} of memory available")
    return out


# ------------------------------------------------------------------------------------------------ changes
@dataclass(frozen=True)
class ChangeReview:
    """What :func:`review_change` decided about a change of parameters on a running node.

    Attributes:
        accepted: the change may be made (rclpy stores it).
        reason: why not (every problem, ``"; "``-joined): what ``ros2 param set`` prints.
        live: the changed values (converted) the node applies at once.
        stored: the changed values (converted) the node reads at its next configure (it is unconfigured).
    """

    accepted: bool
    reason: str = ""
    live: dict[str, Any] = field(default_factory=dict)
    stored: dict[str, Any] = field(default_factory=dict)


def review_change(table: Sequence[Param], current: Mapping[str, Any], changes: Mapping[str, Any],
                  validate: Callable[[dict[str, Any]], object] | None = None, *, configured: bool,
                  managed: bool, node: str = "the node", given: Collection[str] = (),
                  exclusive: Iterable[tuple[str, str]] = ()) -> ChangeReview:
    """Judge ``changes`` (``{name: new value}``, names of ``table``) to the parameters ``current`` (``{name:
    value}`` of every parameter of ``table``) of a running node.

    Refused, with every reason at once: a value of the wrong type; a change that makes ``validate`` (the node's
    start-up / configure validation, called with the current values and the change) report a problem it does not
    report for the current values alone (a problem that was already there, e.g. in an unconfigured node's values,
    does not block fixing another); a parameter of an ``exclusive`` pair given (at start-up: ``given``, or in this
    change) with the other; a change of a :data:`START` parameter, or of a :data:`CONFIGURE` one while the node is
    ``configured`` (``managed`` nodes; see :func:`effective_when`). A value equal to the current one is never
    refused for when it applies.
    """
    by_name = {p.name: p for p in table}
    problems = Problems()
    new: dict[str, Any] = {}
    for name, value in changes.items():
        p = by_name[name]
        with problems.capture(name):
            new[name] = coerce_param(name, value, p.default, p.item_type, p.finite)
    candidate = {**current, **changes}
    for message in exclusive_problems(candidate, {*given, *changes}, exclusive):
        problems.add(message)
    if validate is not None and not problems:
        before = _validation_problems(validate, dict(current))
        for message in _validation_problems(validate, candidate):
            if message not in before:
                problems.add(message)
    changed = {}
    for name, value in new.items():
        p = by_name[name]
        try:
            old = coerce_param(name, current.get(name, p.default), p.default, p.item_type, p.finite)
        except ValueError:
            old = None  # an unconfigured node may hold a bad value: any valid one is a change
        if value != old or type(value) is not type(old):
            changed[name] = value
    for name in changed:
        when = effective_when(by_name[name], managed)
        if when == START:
            problems.add(f"parameter {name!r} is read only at start-up: restart {node} to change it", name)
        elif when == CONFIGURE and configured:
            problems.add(f"parameter {name!r} is read at configure and {node} is configured: deactivate it and "
                         f"clean it up (lifecycle transitions deactivate, cleanup), set {name!r}, then configure "
                         f"(and activate) again", name)
    if problems:
        return ChangeReview(False, "; ".join(problems.messages))
    live = {n: v for n, v in changed.items() if effective_when(by_name[n], managed) == LIVE}
    return ChangeReview(True, "", live, {n: v for n, v in changed.items() if n not in live})


def _validation_problems(validate: Callable[[dict[str, Any]], object], values: dict[str, Any]) -> list[str]:
    try:
        validate(values)
    except (ValueError, TypeError) as exc:
        return problems_of(exc)
    return []
