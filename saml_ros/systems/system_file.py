"""Systems defined outside saml_ros: a YAML *system file* describing a user's robot (see docs/your_robot.md).

    system = read_system_file("examples/diff_drive/system.yaml")     # SystemFileError if anything is wrong
    system.schema()        # topics and field paths (msg_schemas.SystemSchema)
    system.pairing()       # the resampling rule (saml_ros.core.data.resampling.ResampleConfig)

The file names the state and control fields (SI units, bounds), the sampling period, which topic and message
field carries each value, the base model f_hat and the Sufficiently Accurate spec. Everything is checked when it
is loaded, before any node starts, and every problem raises :class:`SystemFileError` naming the file, the key
(``state.fields[2].path``) and what is wrong: unknown keys, unknown message types, field paths that do not fit
the message type, units that are not SI symbols or do not match the message field (a ``twist.linear`` value
declared in ``rad/s``), angle fields not in ``rad``, empty or reversed bounds, a safe command outside the control
bounds, a spec region that lies outside the bounds, a base model that fails to import or returns the wrong shape.

:class:`FileSystem` implements the :class:`~saml_ros.core.dynamics.system.System` contract. A robot has no simulator
inside saml_ros, so ``true_step`` is not available (its data comes from its topics); ``sample_inputs`` draws
uniformly inside the declared bounds (used to check exports and to seed searches, not as training data).
:meth:`FileSystem.params` returns the whole definition, so a checkpoint carries it and rebuilds the system
(:func:`system_from_params`) without the file.
"""

from __future__ import annotations

import copy
import math
import re
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import yaml

from saml_ros.core.data.resampling import COMMAND_RULES, MIXED_POLICIES, STATE_RULES, ResampleConfig
from saml_ros.core.dynamics.base_models import (
    BaseModel,
    BaseModelError,
    BaseModelSpec,
    FieldInfo,
    Layouts,
    build_base_model,
)
from saml_ros.core.dynamics.system import System
from saml_ros.core.errors import SamlError
from saml_ros.core.layout import Field, VectorLayout

if TYPE_CHECKING:
    import torch

#: format version of system files (``version:`` key, optional)
FORMAT_VERSION = 1
_NAME = re.compile(r"^[a-z][a-z0-9_]*$")
_FIELD_NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")
#: SI unit symbols a unit may be composed of (``m/s^2``, ``N*m``, ``rad/s``); ``1`` = dimensionless
UNIT_SYMBOLS = frozenset({"m", "s", "rad", "kg", "N", "A", "V", "W", "Pa", "K", "degC", "Hz", "J", "T", "1"})
_UNIT = re.compile(r"^[A-Za-z0-9]+(\^-?\d+)?([*/][A-Za-z0-9]+(\^-?\d+)?)*$")
_TOP_KEYS = {"version", "name", "description", "dt", "state", "control", "pairing", "base_model", "model", "spec",
             "spec_file", "mpc", "mpc_file"}
_SECTION_KEYS = {"topic", "type", "fields", "rate", "qos", "frame_id", "child_frame_id", "safe"}
_FIELD_KEYS = {"name", "unit", "bounds", "path", "angle", "description"}
_PAIRING_KEYS = {"state", "command", "state_tolerance", "command_guard", "command_timeout", "command_delay",
                 "mixed_command", "latency", "jitter_tolerance"}
_MODEL_KEYS = {"kind", "hidden", "inputs"}
_QOS_KEYS = {"reliable", "depth"}


class SystemFileError(SamlError, ValueError):
    """A system file that cannot be used; the message names the file, the key and the problem."""

    def __init__(self, where: str, key: str, detail: str) -> None:
        super().__init__(f"system file {where}: {key}: {detail}" if key else f"system file {where}: {detail}")
        self.where = where
        self.key = key
        self.detail = detail


# ------------------------------------------------------------------------------------------ parsing
def _fail(where: str, key: str, detail: str) -> SystemFileError:
    return SystemFileError(where, key, detail)


def _keys(d: Any, where: str, key: str, allowed: set[str], required: set[str] = frozenset()) -> dict[str, Any]:  # type: ignore[assignment]
    if not isinstance(d, Mapping):
        raise _fail(where, key, f"expected a mapping, got {type(d).__name__}")
    unknown = sorted(set(d) - allowed)
    if unknown:
        raise _fail(where, key, f"unknown key(s) {unknown}; valid keys: {sorted(allowed)}")
    missing = sorted(set(required) - set(d))
    if missing:
        raise _fail(where, key, f"missing key(s) {missing}")
    return dict(d)


def _number(v: Any, where: str, key: str, *, positive: bool = False, nonneg: bool = False) -> float:
    if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(float(v)):
        raise _fail(where, key, f"expected a finite number, got {v!r}")
    f = float(v)
    if positive and f <= 0:
        raise _fail(where, key, f"must be > 0, got {f}")
    if nonneg and f < 0:
        raise _fail(where, key, f"must be >= 0, got {f}")
    return f


def check_unit(unit: Any, where: str, key: str) -> str:
    """``unit`` if it is composed of :data:`UNIT_SYMBOLS` (``m/s^2``, ``N*m``); :class:`SystemFileError` otherwise."""
    if not isinstance(unit, str) or not _UNIT.match(unit):
        raise _fail(where, key, f"unit {unit!r} is not an SI unit expression such as 'm', 'm/s', 'rad/s', 'm/s^2', "
                                "'N*m' or '1'")
    symbols = re.split(r"[*/]", unit)
    for s in symbols:
        base = s.split("^")[0]
        if base not in UNIT_SYMBOLS:
            raise _fail(where, key, f"unit {unit!r}: {base!r} is not an SI symbol (valid: {sorted(UNIT_SYMBOLS)}); "
                                    "REP 103 wants SI units (m, rad, s, ...)")
    return unit


def _section(raw: Any, where: str, key: str) -> dict[str, Any]:
    from msg_schemas.field_path import FieldPathError, check_message_type

    sec = _keys(raw, where, key, _SECTION_KEYS, {"topic", "type", "fields"})
    topic = sec["topic"]
    if not isinstance(topic, str) or not re.fullmatch(r"/?[A-Za-z_][A-Za-z0-9_/]*", topic) or topic.endswith("/") \
            or "//" in topic:
        raise _fail(where, f"{key}.topic", f"{topic!r} is not a valid ROS topic name")
    try:
        sec["type"] = check_message_type(sec["type"])
    except FieldPathError as exc:
        raise _fail(where, f"{key}.type", str(exc)) from None
    fields = sec["fields"]
    if not isinstance(fields, list) or not fields:
        raise _fail(where, f"{key}.fields", "expected a non-empty list of fields")
    out = []
    seen: set[str] = set()
    for i, f in enumerate(fields):
        fk = f"{key}.fields[{i}]"
        fd = _keys(f, where, fk, _FIELD_KEYS, {"name", "unit", "bounds", "path"})
        name = fd["name"]
        if not isinstance(name, str) or not _FIELD_NAME.match(name):
            raise _fail(where, f"{fk}.name", f"{name!r} is not a valid field name (letters, digits, _)")
        if name in seen:
            raise _fail(where, f"{fk}.name", f"duplicate field name {name!r}")
        seen.add(name)
        fd["unit"] = check_unit(fd["unit"], where, f"{fk}.unit")
        b = fd["bounds"]
        if not isinstance(b, list | tuple) or len(b) != 2:
            raise _fail(where, f"{fk}.bounds", f"expected [low, high], got {b!r}")
        lo, hi = (_number(v, where, f"{fk}.bounds") for v in b)
        if not lo < hi:
            raise _fail(where, f"{fk}.bounds", f"low ({lo}) must be below high ({hi})")
        fd["bounds"] = [lo, hi]
        angle = fd.get("angle", False)
        if not isinstance(angle, bool):
            raise _fail(where, f"{fk}.angle", f"expected true or false, got {angle!r}")
        fd["angle"] = angle
        if angle:
            if fd["unit"] != "rad":
                raise _fail(where, f"{fk}.unit", f"angle field {name!r} must be in 'rad', got {fd['unit']!r}")
            if lo < -math.pi - 1e-6 or hi > math.pi + 1e-6:
                raise _fail(where, f"{fk}.bounds", f"angle field {name!r} is wrapped into [-pi, pi]; bounds "
                                                   f"[{lo}, {hi}] go beyond it")
        fd.setdefault("description", "")
        try:
            from msg_schemas.field_path import resolve

            units = resolve(fd["path"], sec["type"]).units
        except FieldPathError as exc:
            raise _fail(where, f"{fk}.path", str(exc)) from None
        if units and fd["unit"] not in units:
            raise _fail(where, f"{fk}.unit", f"field {name!r} is declared in {fd['unit']!r}, but {fd['path']} of "
                                             f"{sec['type']} is in {' or '.join(repr(u) for u in units)} (REP 103)")
        out.append(fd)
    sec["fields"] = out
    if "rate" in sec:
        sec["rate"] = _number(sec["rate"], where, f"{key}.rate", positive=True)
    if "qos" in sec:
        q = _keys(sec["qos"], where, f"{key}.qos", _QOS_KEYS)
        if "reliable" in q and not isinstance(q["reliable"], bool):
            raise _fail(where, f"{key}.qos.reliable", "expected true or false")
        if "depth" in q and (isinstance(q["depth"], bool) or not isinstance(q["depth"], int) or q["depth"] < 1):
            raise _fail(where, f"{key}.qos.depth", "expected an integer >= 1")
        sec["qos"] = q
    for k in ("frame_id", "child_frame_id"):
        if k in sec and not isinstance(sec[k], str):
            raise _fail(where, f"{key}.{k}", "expected a string")
    return sec


def parse_definition(raw: Any, where: str = "<dict>", base_dir: Path | None = None) -> dict[str, Any]:
    """Validate a system file's contents; returns the normalised definition (a plain dict, the spec inlined).

    ``where`` labels errors (the file name); ``base_dir`` (the file's folder) resolves a relative ``spec_file`` and
    a user base model's ``path`` (default: ``base_dir`` itself), stored absolute. Does not import the base model
    (see :class:`FileSystem`).
    """
    d = _keys(raw, where, "", _TOP_KEYS, {"name", "dt", "state", "control"})
    d = copy.deepcopy(d)
    version = d.pop("version", FORMAT_VERSION)
    if version != FORMAT_VERSION:
        raise _fail(where, "version", f"this saml_ros reads system file version {FORMAT_VERSION}, got {version!r}")
    name = d["name"]
    if not isinstance(name, str) or not _NAME.match(name):
        raise _fail(where, "name", f"{name!r} is not a valid system name (lower case letters, digits, _; "
                                   "starting with a letter)")
    d["description"] = str(d.get("description", ""))
    d["dt"] = _number(d["dt"], where, "dt", positive=True)
    d["state"] = _section(d["state"], where, "state")
    d["control"] = _section(d["control"], where, "control")
    if d["state"]["topic"] == d["control"]["topic"]:
        raise _fail(where, "control.topic", f"the state and the control come on the same topic "
                                            f"{d['state']['topic']!r}: give the command topic")
    if "safe" in d["state"]:
        raise _fail(where, "state.safe", "'safe' (the safe command) belongs in the control section")
    n_u = len(d["control"]["fields"])
    lo = np.array([f["bounds"][0] for f in d["control"]["fields"]])
    hi = np.array([f["bounds"][1] for f in d["control"]["fields"]])
    safe = d["control"].get("safe")
    if safe is None:
        safe = np.clip(np.zeros(n_u), lo, hi).tolist()
    if not isinstance(safe, list | tuple) or len(safe) != n_u:
        raise _fail(where, "control.safe", f"expected a list of {n_u} values (one per control field), got {safe!r}")
    safe = [_number(v, where, "control.safe") for v in safe]
    bad = [f["name"] for f, v in zip(d["control"]["fields"], safe, strict=True)
           if not f["bounds"][0] <= v <= f["bounds"][1]]
    if bad:
        raise _fail(where, "control.safe", f"the safe command is outside the bounds of {bad}")
    d["control"]["safe"] = safe
    d["pairing"] = _pairing(d.get("pairing") or {}, where, d)
    try:
        base = BaseModelSpec.parse(d.get("base_model"))
    except BaseModelError as exc:
        raise _fail(where, "base_model", str(exc)) from None
    if base.function is not None and base_dir is not None:  # user code next to the file: record where, absolute
        base.path = [str((base_dir / d).resolve()) for d in base.path or ["."]]
    d["base_model"] = base.to_dict()
    m = _keys(d.get("model") or {}, where, "model", _MODEL_KEYS)
    kind = m.get("kind", "residual")
    if kind not in ("residual", "full"):
        raise _fail(where, "model.kind", f"expected 'residual' or 'full', got {kind!r}")
    hidden = m.get("hidden", [32, 32])
    if not isinstance(hidden, list) or not hidden or any(isinstance(h, bool) or not isinstance(h, int) or h < 1
                                                         for h in hidden):
        raise _fail(where, "model.hidden", f"expected a list of layer sizes >= 1, got {hidden!r}")
    d["model"] = {"kind": kind, "hidden": list(hidden)}
    if m.get("inputs") is not None:
        d["model"]["inputs"] = _model_inputs(m["inputs"], where, d)
    if "spec" in d and "spec_file" in d:
        raise _fail(where, "spec_file", "give either 'spec' or 'spec_file', not both")
    if "spec_file" in d:
        path = Path(str(d.pop("spec_file")))
        if not path.is_absolute() and base_dir is not None:
            path = base_dir / path
        try:
            d["spec"] = yaml.safe_load(path.read_text())
        except (OSError, yaml.YAMLError) as exc:
            raise _fail(where, "spec_file", f"cannot read {path}: {exc}") from None
    d.setdefault("spec", {"name": "uniform", "objective": {"loss": "l2"}})
    if "mpc" in d or "mpc_file" in d:
        d["mpc"] = _mpc_section(d, where, base_dir)
    return d


def _mpc_section(d: dict[str, Any], where: str, base_dir: Path | None) -> dict[str, Any]:
    """The checked ``mpc:`` section (inline, or the file ``mpc_file`` names); see :mod:`saml_ros.core.mpc.generic.section`."""
    from saml_ros.core.mpc.generic.section import MPCSectionError, parse_mpc_section

    if "mpc" in d and "mpc_file" in d:
        raise _fail(where, "mpc_file", "give either 'mpc' or 'mpc_file', not both")
    key, raw = "mpc", d.get("mpc")
    if "mpc_file" in d:
        path = Path(str(d.pop("mpc_file")))
        if not path.is_absolute() and base_dir is not None:
            path = base_dir / path
        try:
            raw = yaml.safe_load(path.read_text())
        except (OSError, yaml.YAMLError) as exc:
            raise _fail(where, "mpc_file", f"cannot read {path}: {exc}") from None
        key = f"mpc (from {path.name})"
    try:
        return parse_mpc_section(raw, d, key)
    except MPCSectionError as exc:
        raise SystemFileError(where, exc.key, exc.detail) from None


def _model_inputs(raw: Any, where: str, d: dict[str, Any]) -> list[str]:
    """``model.inputs``: the state and control fields the learned residual sees, as qualified names ``x.<field>`` /
    ``u.<field>`` (a bare name must be a state or a control field, not both)."""
    state = [f["name"] for f in d["state"]["fields"]]
    control = [f["name"] for f in d["control"]["fields"]]
    qualified = [f"x.{n}" for n in state] + [f"u.{n}" for n in control]
    if not isinstance(raw, list) or not raw:
        raise _fail(where, "model.inputs", f"expected a non-empty list of state / control fields (of {qualified}), "
                                           f"got {raw!r}")
    out: list[str] = []
    for i, name in enumerate(raw):
        key = f"model.inputs[{i}]"
        if not isinstance(name, str):
            raise _fail(where, key, f"expected a field name, got {name!r}")
        hits = [q for q in qualified if name in (q, q[2:])]
        if not hits:
            raise _fail(where, key, f"{name!r} is not a state or control field (fields: {qualified})")
        if len(hits) > 1:
            raise _fail(where, key, f"{name!r} is both a state and a control field: write x.{name} or u.{name}")
        if hits[0] in out:
            raise _fail(where, key, f"{name!r} is listed twice")
        out.append(hits[0])
    return [q for q in qualified if q in out]  # in [x, u] order


def _pairing(raw: Any, where: str, d: dict[str, Any]) -> dict[str, Any]:
    p = _keys(raw, where, "pairing", _PAIRING_KEYS)
    rule = p.get("state", "interpolate")
    if rule not in STATE_RULES:
        raise _fail(where, "pairing.state", f"expected one of {list(STATE_RULES)}, got {rule!r}")
    mixed = p.get("mixed_command", "hold")
    if mixed not in MIXED_POLICIES:
        raise _fail(where, "pairing.mixed_command", f"expected one of {list(MIXED_POLICIES)}, got {mixed!r}")
    command = p.get("command", "hold")
    if command not in COMMAND_RULES:
        raise _fail(where, "pairing.command", f"expected one of {list(COMMAND_RULES)}, got {command!r}")
    out: dict[str, Any] = {"state": rule, "command": command, "mixed_command": mixed}
    for k, default in (("state_tolerance", None), ("command_guard", 0.002), ("command_timeout", 0.5),
                       ("command_delay", 0.0), ("latency", None), ("jitter_tolerance", 0.25)):
        v = p.get(k, default)
        out[k] = None if v is None else _number(v, where, f"pairing.{k}", nonneg=True)
    return out


# ------------------------------------------------------------------------------------------ the system
class FileSystem(System):
    """A :class:`~saml_ros.core.dynamics.system.System` built from a system file's definition.

    Args:
        definition: the dict :func:`parse_definition` returns (or a checkpoint stored).
        where: label for error messages (the file name).
        resolve: imports a user's base model function from its ``base_model`` section
            (:func:`saml_ros.user_code.resolve_base_model`; the core imports nothing by name).
        function: the user's base model function, already imported (e.g. unpickled in a training process).

    Raises:
        SystemFileError: the base model cannot be built, or the spec / pairing does not fit.
    """

    #: :func:`parse_definition`, reachable from the class (the registry entry rebuilds robots with it)
    parse = staticmethod(parse_definition)

    def __init__(self, definition: Mapping[str, Any], where: str = "<definition>", *,
                 resolve: Callable[[BaseModelSpec], Callable[..., Any] | None] | None = None,
                 function: Callable[..., Any] | None = None) -> None:
        d = copy.deepcopy(dict(definition))
        self.definition = d
        self.where = where
        self.name = d["name"]
        self.description = d.get("description", "")
        self.dt = float(d["dt"])
        sf, cf = d["state"]["fields"], d["control"]["fields"]
        self.state = VectorLayout("state", tuple(Field(f["name"], f["unit"], f.get("description", "")) for f in sf))
        self.control = VectorLayout("control", tuple(Field(f["name"], f["unit"], f.get("description", "")) for f in cf))
        self.target = self.state
        self.paper_hidden = tuple(d["model"]["hidden"])
        self.model_kind: str = d["model"]["kind"]
        #: the fields the learned residual sees (``model.inputs``; None = all), read by ``DynamicsModel``
        self.model_inputs: tuple[str, ...] | None = (tuple(d["model"]["inputs"]) if d["model"].get("inputs")
                                                     else None)
        self._x_low = np.array([f["bounds"][0] for f in sf])
        self._x_high = np.array([f["bounds"][1] for f in sf])
        self._u_low = np.array([f["bounds"][0] for f in cf])
        self._u_high = np.array([f["bounds"][1] for f in cf])
        self.angle_indices = tuple(i for i, f in enumerate(sf) if f.get("angle"))
        self.safe_command = np.array(d["control"]["safe"], dtype=np.float64)
        lay = Layouts(tuple(FieldInfo(f["name"], f["unit"], *f["bounds"]) for f in sf),
                      tuple(FieldInfo(f["name"], f["unit"], *f["bounds"]) for f in cf), self.dt)
        try:
            spec = BaseModelSpec.parse(d["base_model"])
            if function is None and resolve is not None:
                function = resolve(spec)
            #: the user's base model function (None for a built-in); picklable by reference
            self.user_function = function
            self.base_model: BaseModel = build_base_model(spec, lay, function=function)
        except BaseModelError as exc:
            raise SystemFileError(where, "base_model", str(exc)) from None
        self._check_spec()
        self.pairing()  # the pairing times must fit dt

    def __repr__(self) -> str:
        return f"FileSystem({self.name!r}, where={self.where!r})"

    def __str__(self) -> str:
        """What the file defines, one part per line (what ``print(load_system_file(...))`` shows a user)."""
        d = self.definition

        def fields(section: str) -> str:
            return ", ".join(f"{f['name']} [{f['unit']}] {f['bounds'][0]:g}..{f['bounds'][1]:g}"
                             + (" (angle)" if f.get("angle") else "") for f in d[section]["fields"])

        base = d["base_model"]
        base_text = (f"built-in {base['builtin']}" if "builtin" in base else f"function {base.get('function')}")
        lines = [f"robot {self.name!r} from {self.where}: dt {self.dt:g} s",
                 f"  state   {d['state']['topic']} ({d['state']['type']}): {fields('state')}",
                 f"  control {d['control']['topic']} ({d['control']['type']}): {fields('control')}; "
                 f"safe {self.safe_command.tolist()}",
                 f"  base model: {base_text}; learned: {self.model_kind} {list(self.paper_hidden)}"
                 + (f" on {list(self.model_inputs)}" if self.model_inputs else "")]
        for c in d["spec"].get("constraints", []):
            lines.append(f"  constraint {c['name']}: {c['loss']} error <= {c['eps']:g} in {c.get('region', 'all')}")
        if d.get("mpc"):
            m = d["mpc"]
            lines.append(f"  mpc: horizon {m['horizon']}, rate {m['rate']}, goal on {m['goal']['fields']}")
        return "\n".join(lines)

    # ------------------------------------------------------------------------------------------ contract
    @property
    def control_low(self) -> np.ndarray:
        return self._u_low.copy()

    @property
    def control_high(self) -> np.ndarray:
        return self._u_high.copy()

    @property
    def state_low(self) -> np.ndarray:
        return self._x_low.copy()

    @property
    def state_high(self) -> np.ndarray:
        return self._x_high.copy()

    def input_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """The declared bounds over ``[x, u]``, ``(low, high)`` each ``(n_x + n_u,)``: the model's input
        normalisation takes a tenth of their half-width as the smallest spread of a field
        (:meth:`~saml_ros.core.model.network.DynamicsModel.input_floor`)."""
        return np.concatenate([self._x_low, self._u_low]), np.concatenate([self._x_high, self._u_high])

    def safe_control(self) -> np.ndarray:
        """The file's ``control.safe`` command (default: zeros clipped into the bounds)."""
        return self.safe_command.copy()

    def true_step(self, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        raise NotImplementedError(f"{self.name} is a robot described by a system file: saml_ros has no simulator "
                                  "of it, its transitions come from its topics")

    def base_step(self, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        return self.base_model(x, u)

    def sample_inputs(self, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """Uniform inside the declared state and control bounds (not a training distribution)."""
        x = rng.uniform(self._x_low, self._x_high, (n, self.state.size))
        u = rng.uniform(self._u_low, self._u_high, (n, self.control.size))
        return x, u

    def paper_spec(self) -> dict[str, Any]:
        """The file's spec (there is no paper for a user's robot)."""
        return copy.deepcopy(self.definition["spec"])

    def params(self) -> dict[str, Any]:
        """``{"definition": ...}`` with the base model's current parameters (fitted coefficients included)."""
        d = copy.deepcopy(self.definition)
        d["base_model"]["params"] = self.base_model.params()
        return {"definition": d}

    def fit_base(self, x: np.ndarray, u: np.ndarray, y: np.ndarray) -> None:
        """Fit the base model to transitions (the ``linear`` built-in without coefficients; others ignore it)."""
        self.base_model.fit(np.asarray(x, np.float64), np.asarray(u, np.float64), np.asarray(y, np.float64))

    # ------------------------------------------------------------------------------------------ topics
    def schema(self) -> Any:
        """The robot's :class:`msg_schemas.SystemSchema` (field paths validated)."""
        from msg_schemas.path_codec import robot_schema_from_definition

        return robot_schema_from_definition(self.definition)

    def pairing(self) -> ResampleConfig:
        """The resampling rule for this robot's topics (``pairing`` section; see saml_ros.core.data.resampling)."""
        from msg_schemas.field_path import has_header

        p, st, ct = self.definition["pairing"], self.definition["state"], self.definition["control"]
        try:
            return ResampleConfig.from_seconds(
                self.state.size, self.control.size, self.dt, state_rule=p["state"],
                state_tolerance=p["state_tolerance"], cmd_guard=p["command_guard"],
                cmd_timeout=p["command_timeout"], cmd_delay=p["command_delay"], latency=p["latency"],
                mixed=p["mixed_command"], cmd_rule=p.get("command", "hold"), angle_indices=self.angle_indices, jitter_tolerance=p["jitter_tolerance"],
                state_period=1.0 / st["rate"] if st.get("rate") else 0.0,
                cmd_period=1.0 / ct["rate"] if ct.get("rate") else 0.0,
                stamped_state=has_header(st["type"]), stamped_cmd=has_header(ct["type"]),
            )
        except ValueError as exc:
            raise SystemFileError(self.where, "pairing", str(exc)) from None

    # ------------------------------------------------------------------------------------------ checks
    def _check_spec(self) -> None:
        from saml_ros.core.spec import ProblemSpec, SpecError

        try:
            ProblemSpec.for_system(self.definition["spec"], self)
        except SpecError as exc:
            raise SystemFileError(self.where, "spec", str(exc)) from None
        bounds = {f"x.{n}": (lo, hi) for n, lo, hi in zip(self.state.names, self._x_low, self._x_high, strict=True)}
        bounds.update({f"next.{n}": b for n, b in [(k[2:], v) for k, v in bounds.items()]})
        bounds.update({f"u.{n}": (lo, hi) for n, lo, hi in zip(self.control.names, self._u_low, self._u_high,
                                                               strict=True)})
        for i, c in enumerate(self.definition["spec"].get("constraints") or []):
            for ref, (lo, hi) in _boxes(c.get("region")):
                blo, bhi = bounds.get(ref, (-math.inf, math.inf))
                lo = -math.inf if lo is None else float(lo)
                hi = math.inf if hi is None else float(hi)
                if hi < blo or lo > bhi:
                    raise SystemFileError(self.where, f"spec.constraints[{i}].region",
                                          f"box {ref} [{lo}, {hi}] lies outside the bounds [{blo}, {bhi}] of that "
                                          f"field: constraint {c.get('name')!r} could never hold a transition")


def _boxes(region: Any) -> list[tuple[str, tuple[Any, Any]]]:
    """``(field, (lo, hi))`` of every box in ``region`` that must hold (top level and ``all_of``)."""
    if not isinstance(region, Mapping):
        return []
    out: list[tuple[str, tuple[Any, Any]]] = []
    if isinstance(region.get("box"), Mapping):
        out += [(k, (v[0], v[1])) for k, v in region["box"].items() if isinstance(v, list | tuple) and len(v) == 2]
    for part in region.get("all_of") or []:
        out += _boxes(part)
    return out


def read_system_file(path: str | Path, *,
                     resolve: Callable[[BaseModelSpec], Callable[..., Any] | None] | None = None) -> FileSystem:
    """Read, validate and build the system of ``path`` (see the module docstring); :class:`SystemFileError`.

    ``resolve`` imports a user's base model (:func:`saml_ros.user_code.load_system_file` passes it); without it
    only built-in base models load.
    """
    p = Path(path)
    try:
        raw = yaml.safe_load(p.read_text())
    except FileNotFoundError:
        raise SystemFileError(str(p), "", "no such file") from None
    except (OSError, yaml.YAMLError) as exc:
        raise SystemFileError(str(p), "", f"cannot read it as YAML: {exc}") from None
    definition = parse_definition(raw, str(p), p.parent)
    system = FileSystem(definition, str(p), resolve=resolve)
    try:
        system.schema()
    except ValueError as exc:
        raise SystemFileError(str(p), "", str(exc)) from None
    return system


def system_from_params(params: Mapping[str, Any]) -> FileSystem:
    """Rebuild a :class:`FileSystem` from :meth:`FileSystem.params` (what checkpoints store), plus optionally
    ``base_function``: the user's base model function, already imported (what the learner hands its training
    process, pickled by reference)."""
    definition = params["definition"]
    where = f"stored definition of {definition.get('name')!r}"
    return FileSystem(parse_definition(definition, where), where, function=params.get("base_function"))
