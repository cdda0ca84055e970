"""The ``mpc:`` section of a system file: the control task of a user's robot (docs/your_robot.md, "Control it").

    mpc:
      horizon: 20                     # planning steps of the file's dt
      rate: state                     # answer each state ('state'), or a control rate in Hz
      state_timeout: 0.25             # s: a state older than this (or none for this long) gets the safe command
      goal:                           # a setpoint on chosen state fields
        fields: [x, y, yaw, v, w]
        default: [1.5, 0.0, 0.0, 0.0, 0.0]
        bounds: {x: [-2.0, 2.0]}      # optional, tighter than the fields' bounds: a goal outside is refused
        topic: goal_pose              # optional: goals from a topic, by field path (others keep their default)
        type: geometry_msgs/msg/PoseStamped
        paths: {x: pose.position.x, y: pose.position.y, yaw: yaw(pose.orientation)}
      reference:                      # optional: a trajectory to track (nav_msgs/Path), by field path per pose
        topic: plan
        type: nav_msgs/msg/Path
        paths: {x: pose.position.x, y: pose.position.y, yaw: yaw(pose.orientation)}
        timeout: 1.0                  # s: an older reference is dropped (back to the goal)
      cost:
        stage: {x: 10.0, y: 10.0, yaw: 1.0}      # weight of (x_t - goal)^2 per goal field, t = 1..T-1
        terminal: {x: 100.0, y: 100.0, yaw: 10.0}  # at t = T (default: stage)
        effort: {v_cmd: 0.1, w_cmd: 0.1}        # weight of u_t^2 per control field
        rate: {v_cmd: 1.0, w_cmd: 1.0}          # weight of (u_t - u_{t-1})^2 (u_{-1}: the last command sent)
        norm: false                   # true: each step's goal term is the weighted distance, not its square
        norm_eps: 0.001               #   (smoothed: sqrt(d^2 + norm_eps^2); the paper's quadrotor cost)
        disagreement: {x: 1.0e6, y: 1.0e6}  # optional, per state field: weight of the ensemble members' variance
                                      #   of the one-step prediction along the plan (an epistemic penalty; off: {})
      constraints:                    # on the predicted states x_1 .. x_T (soft: exact l1 penalty)
        - {name: speed, box: {v: [-0.4, 0.4]}}
        - {name: slow_turns, norm: {fields: [v, w], max: 1.2}}
        - {name: arrive_slow, norm: {fields: [v], max: 0.05}, at: terminal}   # only on x_T
        - {name: pillar, keep_out: {fields: [x, y], center: [0.5, 0.8], radius: 0.25}}
      penalty: 1000                   # price of one unit of constraint violation in the planner's merit
      solver: sqp                     # sqp (Gauss-Newton SQP, exact derivatives) | ipopt (CasADi NLP)
      solver_options: {max_iter: 10}

or ``mpc_file: task.yaml`` (relative to the system file) holding the same mapping. The control bounds are the
control fields' bounds, the safe command is ``control.safe``; angle fields (``angle: true``) are compared with their
goal the short way round (the goal is unwrapped relative to the current state). Everything is checked when the file
is loaded: :func:`parse_mpc_section` raises :class:`MPCSectionError` naming the key (``mpc.cost.stage.yw``) and the
problem; :func:`mpc_task` turns the normalised section into a :class:`MPCTask`.

This module is ROS-free and imports neither torch nor CasADi: the planner (``saml_ros.core.mpc.generic``) builds on
the :class:`MPCTask` it returns.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from saml_ros.core.errors import SamlError

#: keys of the ``mpc:`` section
MPC_KEYS = frozenset({"horizon", "rate", "state_timeout", "goal", "reference", "cost", "constraints", "penalty",
                      "solver", "solver_options", "description"})
_GOAL_KEYS = frozenset({"fields", "default", "bounds", "topic", "type", "paths"})
_REF_KEYS = frozenset({"topic", "type", "paths", "timeout"})
_COST_KEYS = frozenset({"stage", "terminal", "effort", "rate", "norm", "norm_eps", "disagreement"})
_CONSTRAINT_KINDS = ("box", "norm", "keep_out")
#: the planner paths a section may choose (``saml_ros.core.mpc.generic``) and the options each takes
PLANNERS = ("sqp", "ipopt")
PLANNER_OPTIONS: dict[str, frozenset[str]] = {
    "sqp": frozenset({"max_iter", "tol", "max_time", "rho0", "lm_floor", "feas_tol", "qp_backend", "smoothing",
                      "penalty_max", "undamped_check", "compile", "ensemble"}),
    "ipopt": frozenset({"max_iter", "tol", "max_time", "feas_tol", "linear_solver", "smoothing"}),
}
#: what ``rate`` accepts besides a number of Hz: answer every state
ON_STATE = "state"
#: largest horizon accepted (the condensed QP grows with T^2)
MAX_HORIZON = 200


class MPCSectionError(SamlError, ValueError):
    """A bad ``mpc:`` section; ``key`` is the dotted key (``mpc.goal.default``), ``detail`` what is wrong."""

    def __init__(self, key: str, detail: str) -> None:
        super().__init__(f"{key}: {detail}")
        self.key = key
        self.detail = detail


@dataclass(frozen=True)
class StateConstraint:
    """One constraint on every predicted state ``x_1 .. x_T`` (``terminal``: on ``x_T`` only), as ``g(x) <= 0``
    rows.

    ``kind``: ``box`` (``low <= x[i] <= high`` per field, either side may be open: ``+-inf``), ``norm``
    (``||x[idx]||_2 <= max``) or ``keep_out`` (``||(x[idx] - center) / radius||_2 >= 1``: a disc, ball or, with one
    radius per field, an ellipse to stay out of).
    """

    name: str
    kind: str
    idx: tuple[int, ...]
    low: tuple[float, ...] = ()
    high: tuple[float, ...] = ()
    max: float = math.inf
    center: tuple[float, ...] = ()
    radius: tuple[float, ...] = ()
    terminal: bool = False

    @property
    def rows(self) -> int:
        """``g`` rows per time step: two per box field with both sides finite, one otherwise."""
        if self.kind == "box":
            return sum(math.isfinite(lo) + math.isfinite(hi) for lo, hi in zip(self.low, self.high, strict=True))
        return 1


@dataclass(frozen=True)
class GoalTopic:
    """Goals (or a reference) from a topic: the message type and a field path per state field it sets."""

    topic: str
    type: str
    paths: tuple[tuple[str, str], ...]  #: (state field, field path)
    timeout: float = math.inf  #: s, references only: an older one is dropped


@dataclass(frozen=True)
class MPCTask:
    """The normalised ``mpc:`` section with field names resolved to indices (see the module docstring).

    Arrays are float64; index tuples refer to the state (``goal_idx``, constraints) or control vector.
    """

    horizon: int
    rate: float  #: Hz; 0 = answer every state
    state_timeout: float  #: s
    goal_idx: tuple[int, ...]
    goal_default: np.ndarray  #: (k,)
    goal_low: np.ndarray  #: (k,) the bounds a goal must lie within
    goal_high: np.ndarray  #: (k,)
    goal_angle: tuple[bool, ...]  #: (k,) which goal fields are angles (wrapped)
    w_stage: np.ndarray  #: (k,)
    w_terminal: np.ndarray  #: (k,)
    w_effort: np.ndarray  #: (m,)
    w_rate: np.ndarray  #: (m,)
    u_low: np.ndarray  #: (m,)
    u_high: np.ndarray  #: (m,)
    u_safe: np.ndarray  #: (m,)
    constraints: tuple[StateConstraint, ...] = ()
    penalty: float = 1000.0
    planner: str = "sqp"
    solver_options: Mapping[str, Any] = field(default_factory=dict)
    goal_topic: GoalTopic | None = None
    reference: GoalTopic | None = None
    state_names: tuple[str, ...] = ()
    control_names: tuple[str, ...] = ()
    #: each step's goal term is the weighted distance ``sqrt(||sqrt(W) (x_t - r_t)||^2 + norm_eps^2)`` instead of
    #: its square (the paper's quadrotor cost)
    norm_cost: bool = False
    norm_eps: float = 1e-3
    #: ``(n,)`` per state field: weight of the ensemble members' variance of the one-step prediction along the plan
    #: (``cost.disagreement``; empty: off)
    w_disagreement: np.ndarray = field(default_factory=lambda: np.zeros(0))

    @property
    def goal_fields(self) -> tuple[str, ...]:
        return tuple(self.state_names[i] for i in self.goal_idx)

    def check_goal(self, goal: Any) -> np.ndarray:
        """``goal`` as ``(k,)`` float64 if it is finite and within the goal bounds; ``ValueError`` naming the field
        otherwise (a NaN goal, one outside the bounds)."""
        g = np.asarray(goal, dtype=np.float64).reshape(-1)
        if g.shape != self.goal_default.shape:
            raise ValueError(f"goal must have {self.goal_default.size} value(s) ({list(self.goal_fields)}), "
                             f"got {g.size}")
        for name, v, lo, hi in zip(self.goal_fields, g, self.goal_low, self.goal_high, strict=True):
            if not math.isfinite(v):
                raise ValueError(f"goal field {name!r} is {v}")
            if not lo <= v <= hi:
                raise ValueError(f"goal field {name!r} = {v:g} is outside its bounds [{lo:g}, {hi:g}]")
        return g


# ------------------------------------------------------------------------------------------ parsing
def _keys(d: Any, key: str, allowed: frozenset[str], required: Sequence[str] = ()) -> dict[str, Any]:
    if not isinstance(d, Mapping):
        raise MPCSectionError(key, f"expected a mapping, got {type(d).__name__}")
    unknown = sorted(set(d) - allowed)
    if unknown:
        raise MPCSectionError(key, f"unknown key(s) {unknown}; valid keys: {sorted(allowed)}")
    missing = [k for k in required if k not in d]
    if missing:
        raise MPCSectionError(key, f"missing key(s) {missing}")
    return dict(d)


def _number(v: Any, key: str, *, positive: bool = False, nonneg: bool = False, allow_inf: bool = False) -> float:
    if isinstance(v, bool) or not isinstance(v, int | float) or math.isnan(float(v)) or (
            not allow_inf and math.isinf(float(v))):
        raise MPCSectionError(key, f"expected a {'' if allow_inf else 'finite '}number, got {v!r}")
    f = float(v)
    if positive and not f > 0:
        raise MPCSectionError(key, f"must be > 0, got {f:g}")
    if nonneg and not f >= 0:
        raise MPCSectionError(key, f"must be >= 0, got {f:g}")
    return f


def _field_list(v: Any, key: str, names: Sequence[str], kind: str, *, min_len: int = 1) -> list[str]:
    if not isinstance(v, list) or len(v) < min_len:
        raise MPCSectionError(key, f"expected a list of at least {min_len} {kind} field name(s), got {v!r}")
    out: list[str] = []
    for i, n in enumerate(v):
        _field_name(n, f"{key}[{i}]", names, kind)
        if n in out:
            raise MPCSectionError(f"{key}[{i}]", f"field {n!r} is listed twice")
        out.append(n)
    return out


def _field_name(n: Any, key: str, names: Sequence[str], kind: str) -> str:
    if n not in names:
        import difflib

        close = difflib.get_close_matches(str(n), list(names), n=1)
        hint = f" (did you mean {close[0]!r}?)" if close else ""
        raise MPCSectionError(key, f"{n!r} is not a {kind} field{hint}; {kind} fields are {list(names)}")
    return str(n)


def _weights(raw: Any, key: str, names: Sequence[str], kind: str) -> dict[str, float]:
    if not isinstance(raw, Mapping):
        raise MPCSectionError(key, f"expected a mapping of {kind} field -> weight, got {type(raw).__name__}")
    out: dict[str, float] = {}
    for n, v in raw.items():
        _field_name(n, f"{key}.{n}", names, kind)
        out[str(n)] = _number(v, f"{key}.{n}", nonneg=True)
    return out


def _topic(raw: Any, key: str, fields: Sequence[str], field_units: Mapping[str, str], allowed: frozenset[str],
           *, element: str | None = None) -> dict[str, Any]:
    """A goal / reference topic: ``topic``, ``type`` and ``paths`` (field -> field path) checked against the message
    type (for a reference: against the type of the array ``element`` it carries, e.g. ``poses[]``)."""
    from msg_schemas.field_path import (
        _ARRAY,
        _NAME_T,
        _SEQUENCE,
        FieldPathError,
        check_message_type,
        message_fields,
        resolve,
    )

    d = _keys(raw, key, allowed, ("topic", "type", "paths"))
    topic = d["topic"]
    import re

    if not isinstance(topic, str) or not re.fullmatch(r"/?[A-Za-z_][A-Za-z0-9_/]*", topic) or topic.endswith("/") \
            or "//" in topic:
        raise MPCSectionError(f"{key}.topic", f"{topic!r} is not a valid ROS topic name")
    try:
        msg_type = check_message_type(d["type"])
    except FieldPathError as exc:
        raise MPCSectionError(f"{key}.type", str(exc)) from None
    path_type = msg_type
    if element is not None:
        fields_of = dict(message_fields(msg_type))
        spec = fields_of.get(element)
        if spec is None or spec[0] not in (_ARRAY, _SEQUENCE):
            raise MPCSectionError(f"{key}.type", f"a reference needs a message with an array '{element}' of "
                                                 f"poses (nav_msgs/msg/Path), {msg_type} has none")
        (sub_node, sub_spec), _ = spec[1]
        if sub_node != _NAME_T:
            raise MPCSectionError(f"{key}.type", f"{msg_type}.{element} is not an array of messages")
        path_type = sub_spec
    paths = d["paths"]
    if not isinstance(paths, Mapping) or not paths:
        raise MPCSectionError(f"{key}.paths", "expected a mapping of state field -> field path")
    out: list[list[str]] = []
    for name, path in paths.items():
        pk = f"{key}.paths.{name}"
        _field_name(name, pk, fields, "goal")
        try:
            units = resolve(str(path), path_type).units
        except FieldPathError as exc:
            raise MPCSectionError(pk, str(exc)) from None
        unit = field_units[name]
        if units and unit not in units:
            raise MPCSectionError(pk, f"field {name!r} is in {unit!r}, but {path} of {path_type} is in "
                                      f"{' or '.join(repr(u) for u in units)} (REP 103)")
        out.append([str(name), str(path)])
    result: dict[str, Any] = {"topic": topic, "type": msg_type, "paths": dict(out)}
    if "timeout" in d:
        result["timeout"] = _number(d["timeout"], f"{key}.timeout", positive=True)
    return result


def parse_mpc_section(raw: Any, definition: Mapping[str, Any], key: str = "mpc") -> dict[str, Any]:
    """Check the ``mpc:`` section ``raw`` against the (already checked) state and control sections of
    ``definition``; returns the normalised section (plain data, re-parseable: a checkpoint stores it).

    Raises:
        MPCSectionError: naming the key and the problem.
    """
    sf, cf = definition["state"]["fields"], definition["control"]["fields"]
    names = [f["name"] for f in sf]
    units = {f["name"]: f["unit"] for f in sf}
    bounds = {f["name"]: (float(f["bounds"][0]), float(f["bounds"][1])) for f in sf}
    angles = {f["name"] for f in sf if f.get("angle")}
    cnames = [f["name"] for f in cf]
    d = _keys(raw, key, MPC_KEYS, ("goal",))
    out: dict[str, Any] = {}
    h = d.get("horizon", 20)
    if isinstance(h, bool) or not isinstance(h, int) or not 1 <= h <= MAX_HORIZON:
        raise MPCSectionError(f"{key}.horizon", f"expected an integer in [1, {MAX_HORIZON}], got {h!r}")
    out["horizon"] = h
    rate = d.get("rate", ON_STATE)
    if rate != ON_STATE:
        rate = _number(rate, f"{key}.rate", positive=True)
    out["rate"] = rate
    dt = float(definition["dt"])
    default_timeout = max(0.1, 5.0 * (dt if rate == ON_STATE else max(dt, 1.0 / float(rate))))
    out["state_timeout"] = _number(d.get("state_timeout", default_timeout), f"{key}.state_timeout", positive=True)
    if "description" in d:
        out["description"] = str(d["description"])

    # goal
    g = _keys(d["goal"], f"{key}.goal", _GOAL_KEYS, ("fields", "default"))
    fields = _field_list(g["fields"], f"{key}.goal.fields", names, "state")
    default = g["default"]
    if not isinstance(default, list) or len(default) != len(fields):
        raise MPCSectionError(f"{key}.goal.default", f"expected {len(fields)} value(s), one per goal field "
                                                     f"{fields}, got {default!r}")
    default = [_number(v, f"{key}.goal.default[{i}]") for i, v in enumerate(default)]
    gb = {n: bounds[n] for n in fields}
    if "bounds" in g:
        raw_b = g["bounds"]
        if not isinstance(raw_b, Mapping):
            raise MPCSectionError(f"{key}.goal.bounds", "expected a mapping of goal field -> [low, high]")
        for n, b in raw_b.items():
            bk = f"{key}.goal.bounds.{n}"
            _field_name(n, bk, fields, "goal")
            if not isinstance(b, list | tuple) or len(b) != 2:
                raise MPCSectionError(bk, f"expected [low, high], got {b!r}")
            lo, hi = (_number(v, bk) for v in b)
            if not lo < hi:
                raise MPCSectionError(bk, f"low ({lo:g}) must be below high ({hi:g})")
            flo, fhi = bounds[n]
            if lo < flo or hi > fhi:
                raise MPCSectionError(bk, f"[{lo:g}, {hi:g}] goes beyond the bounds [{flo:g}, {fhi:g}] of state "
                                          f"field {n!r}")
            gb[n] = (lo, hi)
    for i, (n, v) in enumerate(zip(fields, default, strict=True)):
        lo, hi = gb[n]
        if not lo <= v <= hi:
            raise MPCSectionError(f"{key}.goal.default[{i}]", f"{n} = {v:g} is outside its bounds [{lo:g}, {hi:g}]")
    goal: dict[str, Any] = {"fields": fields, "default": default, "bounds": {n: list(gb[n]) for n in fields}}
    if any(k in g for k in ("topic", "type", "paths")):
        goal.update(_topic({k: g[k] for k in ("topic", "type", "paths") if k in g}, f"{key}.goal", fields, units,
                           frozenset({"topic", "type", "paths"})))
    out["goal"] = goal
    if "reference" in d:
        ref = _topic(d["reference"], f"{key}.reference", fields, units, _REF_KEYS, element="poses")
        ref.setdefault("timeout", 1.0)
        out["reference"] = ref

    # cost
    c = _keys(d.get("cost") or {}, f"{key}.cost", _COST_KEYS)
    stage = _weights(c.get("stage", {n: 1.0 for n in fields}), f"{key}.cost.stage", fields, "goal")
    terminal = _weights(c.get("terminal", stage), f"{key}.cost.terminal", fields, "goal")
    effort = _weights(c.get("effort", {}), f"{key}.cost.effort", cnames, "control")
    rate_w = _weights(c.get("rate", {}), f"{key}.cost.rate", cnames, "control")
    if not any(stage.values()) and not any(terminal.values()):
        raise MPCSectionError(f"{key}.cost", "every stage and terminal weight is 0: the plan would ignore the goal")
    out["cost"] = {"stage": stage, "terminal": terminal, "effort": effort, "rate": rate_w}
    if "norm" in c:
        if not isinstance(c["norm"], bool):
            raise MPCSectionError(f"{key}.cost.norm", f"expected true or false, got {c['norm']!r}")
        out["cost"]["norm"] = c["norm"]
    if "norm_eps" in c:
        out["cost"]["norm_eps"] = _number(c["norm_eps"], f"{key}.cost.norm_eps", positive=True)
    if "disagreement" in c:
        out["cost"]["disagreement"] = _weights(c["disagreement"], f"{key}.cost.disagreement", names, "state")

    # constraints
    cons = d.get("constraints") or []
    if not isinstance(cons, list):
        raise MPCSectionError(f"{key}.constraints", "expected a list of constraints")
    out["constraints"] = [_constraint(ci, f"{key}.constraints[{i}]", names, bounds, angles, i)
                          for i, ci in enumerate(cons)]
    seen: set[str] = set()
    for i, ci in enumerate(out["constraints"]):
        if ci["name"] in seen:
            raise MPCSectionError(f"{key}.constraints[{i}].name", f"duplicate constraint name {ci['name']!r}")
        seen.add(ci["name"])
    out["penalty"] = _number(d.get("penalty", 1000.0), f"{key}.penalty", positive=True)
    planner = d.get("solver", "sqp")
    if planner not in PLANNERS:
        raise MPCSectionError(f"{key}.solver", f"expected one of {list(PLANNERS)}, got {planner!r}")
    out["solver"] = planner
    so = d.get("solver_options") or {}
    if not isinstance(so, Mapping) or not all(isinstance(k, str) and isinstance(v, int | float | str | bool)
                                              for k, v in so.items()):
        raise MPCSectionError(f"{key}.solver_options", f"expected a mapping of option names to scalars, got {so!r}")
    unknown = sorted(set(so) - PLANNER_OPTIONS[planner])
    if unknown:
        raise MPCSectionError(f"{key}.solver_options", f"unknown option(s) {unknown} for solver {planner!r}; valid: "
                                                       f"{sorted(PLANNER_OPTIONS[planner])}")
    out["solver_options"] = dict(so)
    return out


def _constraint(raw: Any, key: str, names: Sequence[str], bounds: Mapping[str, tuple[float, float]],
                angles: set[str], i: int) -> dict[str, Any]:
    if not isinstance(raw, Mapping):
        raise MPCSectionError(key, "expected a mapping such as {name: speed, box: {v: [-0.4, 0.4]}}")
    unknown = sorted(set(raw) - {"name", "at", *_CONSTRAINT_KINDS})
    if unknown:
        raise MPCSectionError(key, f"unknown key(s) {unknown}; valid keys: ['name', 'at', "
                                   f"{', '.join(map(repr, _CONSTRAINT_KINDS))}]")
    at = raw.get("at", "all")
    if at not in ("all", "terminal"):
        raise MPCSectionError(f"{key}.at", f"expected 'all' (every predicted state) or 'terminal' (x_T), got {at!r}")
    out = _constraint_body(raw, key, names, bounds, angles, i)
    if at == "terminal":
        out["at"] = "terminal"
    return out


def _constraint_body(raw: Mapping[str, Any], key: str, names: Sequence[str], bounds: Mapping[str, tuple[float, float]],
                     angles: set[str], i: int) -> dict[str, Any]:
    kinds = [k for k in _CONSTRAINT_KINDS if k in raw]
    if len(kinds) != 1:
        raise MPCSectionError(key, f"give exactly one of {list(_CONSTRAINT_KINDS)}, got {kinds or 'none'}")
    kind = kinds[0]
    name = raw.get("name", f"{kind}{i}")
    if not isinstance(name, str) or not name:
        raise MPCSectionError(f"{key}.name", f"expected a non-empty string, got {name!r}")
    body = raw[kind]
    k = f"{key}.{kind}"
    if kind == "box":
        if not isinstance(body, Mapping) or not body:
            raise MPCSectionError(k, "expected a mapping of state field -> [low, high] (null = open)")
        box: dict[str, list[float]] = {}
        for n, b in body.items():
            fk = f"{k}.{n}"
            _field_name(n, fk, names, "state")
            if not isinstance(b, list | tuple) or len(b) != 2:
                raise MPCSectionError(fk, f"expected [low, high] (null = open), got {b!r}")
            lo = -math.inf if b[0] is None else _number(b[0], fk, allow_inf=True)
            hi = math.inf if b[1] is None else _number(b[1], fk, allow_inf=True)
            if not lo < hi:
                raise MPCSectionError(fk, f"low ({lo:g}) must be below high ({hi:g})")
            if not (math.isfinite(lo) or math.isfinite(hi)):
                raise MPCSectionError(fk, "both sides are open: the box constrains nothing")
            flo, fhi = bounds[n]
            if hi < flo or lo > fhi:
                raise MPCSectionError(fk, f"[{lo:g}, {hi:g}] lies outside the bounds [{flo:g}, {fhi:g}] of field "
                                          f"{n!r}: no state could satisfy it")
            if n in angles:
                raise MPCSectionError(fk, f"{n!r} is an angle field (wrapped): a box on it is not supported")
            box[str(n)] = [lo, hi]
        return {"name": name, "box": box}
    if kind == "norm":
        nd = _keys(body, k, frozenset({"fields", "max"}), ("fields", "max"))
        fields = _field_list(nd["fields"], f"{k}.fields", names, "state")
        if set(fields) & angles:
            raise MPCSectionError(f"{k}.fields", f"angle field(s) {sorted(set(fields) & angles)} cannot be in a norm")
        return {"name": name, "norm": {"fields": fields, "max": _number(nd["max"], f"{k}.max", positive=True)}}
    kd = _keys(body, k, frozenset({"fields", "center", "radius"}), ("fields", "center", "radius"))
    fields = _field_list(kd["fields"], f"{k}.fields", names, "state")
    if set(fields) & angles:
        raise MPCSectionError(f"{k}.fields", f"angle field(s) {sorted(set(fields) & angles)} cannot bound a region")
    center = kd["center"]
    if not isinstance(center, list) or len(center) != len(fields):
        raise MPCSectionError(f"{k}.center", f"expected {len(fields)} value(s), one per field, got {center!r}")
    center = [_number(v, f"{k}.center[{j}]") for j, v in enumerate(center)]
    radius = kd["radius"]
    radii = [radius] * len(fields) if not isinstance(radius, list) else radius
    if len(radii) != len(fields):
        raise MPCSectionError(f"{k}.radius", f"expected one radius or {len(fields)} (one per field), got {radius!r}")
    radii = [_number(v, f"{k}.radius", positive=True) for v in radii]
    return {"name": name, "keep_out": {"fields": fields, "center": center, "radius": radii}}


# ------------------------------------------------------------------------------------------ the task
def mpc_task(definition: Mapping[str, Any]) -> MPCTask | None:
    """The :class:`MPCTask` of a parsed system file definition (``None`` when it has no ``mpc:`` section)."""
    sec = definition.get("mpc")
    if not sec:
        return None
    sf, cf = definition["state"]["fields"], definition["control"]["fields"]
    names = tuple(f["name"] for f in sf)
    cnames = tuple(f["name"] for f in cf)
    angles = {f["name"] for f in sf if f.get("angle")}
    g = sec["goal"]
    fields = list(g["fields"])
    cost = sec["cost"]
    cons: list[StateConstraint] = []
    for c in sec["constraints"]:
        terminal = c.get("at") == "terminal"
        if "box" in c:
            items = list(c["box"].items())
            cons.append(StateConstraint(c["name"], "box", tuple(names.index(n) for n, _ in items),
                                        low=tuple(float(b[0]) for _, b in items),
                                        high=tuple(float(b[1]) for _, b in items), terminal=terminal))
        elif "norm" in c:
            cons.append(StateConstraint(c["name"], "norm", tuple(names.index(n) for n in c["norm"]["fields"]),
                                        max=float(c["norm"]["max"]), terminal=terminal))
        else:
            k = c["keep_out"]
            cons.append(StateConstraint(c["name"], "keep_out", tuple(names.index(n) for n in k["fields"]),
                                        center=tuple(float(v) for v in k["center"]),
                                        radius=tuple(float(v) for v in k["radius"]), terminal=terminal))

    def topic(t: Mapping[str, Any] | None) -> GoalTopic | None:
        if not t or "topic" not in t:
            return None
        return GoalTopic(t["topic"], t["type"], tuple((str(a), str(b)) for a, b in t["paths"].items()),
                         float(t.get("timeout", math.inf)))

    safe = np.asarray(definition["control"].get("safe") or np.zeros(len(cnames)), dtype=np.float64)
    rate = sec["rate"]
    return MPCTask(
        horizon=int(sec["horizon"]),
        rate=0.0 if rate == ON_STATE else float(rate),
        state_timeout=float(sec["state_timeout"]),
        goal_idx=tuple(names.index(n) for n in fields),
        goal_default=np.asarray(g["default"], dtype=np.float64),
        goal_low=np.array([g["bounds"][n][0] for n in fields], dtype=np.float64),
        goal_high=np.array([g["bounds"][n][1] for n in fields], dtype=np.float64),
        goal_angle=tuple(n in angles for n in fields),
        w_stage=np.array([cost["stage"].get(n, 0.0) for n in fields], dtype=np.float64),
        w_terminal=np.array([cost["terminal"].get(n, 0.0) for n in fields], dtype=np.float64),
        w_effort=np.array([cost["effort"].get(n, 0.0) for n in cnames], dtype=np.float64),
        w_rate=np.array([cost["rate"].get(n, 0.0) for n in cnames], dtype=np.float64),
        u_low=np.array([f["bounds"][0] for f in cf], dtype=np.float64),
        u_high=np.array([f["bounds"][1] for f in cf], dtype=np.float64),
        u_safe=safe,
        constraints=tuple(cons),
        penalty=float(sec["penalty"]),
        planner=str(sec["solver"]),
        solver_options=dict(sec["solver_options"]),
        goal_topic=topic(g),
        reference=topic(sec.get("reference")),
        state_names=names,
        control_names=cnames,
        norm_cost=bool(cost.get("norm", False)),
        norm_eps=float(cost.get("norm_eps", 1e-3)),
        w_disagreement=np.array([cost.get("disagreement", {}).get(n, 0.0) for n in names], dtype=np.float64)
        if any(cost.get("disagreement", {}).values()) else np.zeros(0),
    )
