"""Base models f_hat for systems defined in a system file: built-in ones and the user's own Python function.

A base model maps a batch of states and commands to the predicted next state, batched torch:
``f_hat(x (B, n_x), u (B, n_u)) -> (B, n_x)``, keeping the dtype. The learner learns the residual on top of it.

Built-ins (``base_model: {builtin: NAME, params: {...}}``; field names refer to the file's state / control):

* ``zero``: f_hat = 0 (the network learns the whole next state; as ``model.kind: full``).
* ``hold``: f_hat(x, u) = x (nothing moves unless the network learns it).
* ``constant_velocity``: per axis ``{position: p, velocity: v}``: p' = p + v dt, v' = v; other fields held.
* ``double_integrator``: per axis ``{position: p, velocity: v, acceleration: a}`` with ``a`` a *control* field:
  p' = p + v dt + a dt^2 / 2, v' = v + a dt; other fields held.
* ``unicycle``: ``{x, y, yaw}`` state fields and ``{v, w}`` control fields (forward speed, yaw rate commands);
  optional state fields ``v_state``, ``w_state`` (the measured speeds) and ``tau`` (s, their first-order lag;
  0 = they equal the commands after one step). Midpoint integration: yaw' = yaw + w dt (not wrapped: targets of
  angle fields are unwrapped relative to x), x' = x + v cos(yaw + w dt / 2) dt, y' likewise with sin.
* ``linear``: f_hat(x, u) = x + A x + B u + c with ``A (n_x, n_x)``, ``B (n_x, n_u)``, ``c (n_x,)`` given in
  ``params`` or, when omitted, **fitted** by least squares on the first transitions the learner (or offline
  training) sees, at the moment the normalisation is fitted, and stored with the model. Before that it holds x.

Every built-in checks the units of the fields it is bound to (a position in ``m`` needs a velocity in ``m/s``,
a yaw in ``rad``, ...) and raises :class:`BaseModelError` naming the field.

A user's own base model (``base_model: {function: "my_pkg.dynamics:f_hat", params: {...}}`` or
``{entry_point: NAME}`` for an entry point ``NAME`` in the group ``saml_ros.systems`` of an installed package)
is a function ``f_hat(x, u, *, dt, **params) -> torch.Tensor (B, n_x)``; one that also takes the keyword ``xp`` is an
*array-namespace form* (:mod:`.base_forms`), called here with torch and differentiated symbolically by the MPC. It is
imported (by
:mod:`saml_ros.user_code`: the core imports no code by name) and called on a probe batch when the system is loaded; an import failure, a non-tensor result, a wrong shape, non-finite values or a
result that depends on the batch composition raise :class:`BaseModelError` there, not later in a node.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from saml_ros.core.errors import SamlError

if TYPE_CHECKING:
    import torch

#: entry point group of installed base models (``base_model: {entry_point: NAME}``; see saml_ros.user_code)
ENTRY_POINT_GROUP = "saml_ros.systems"
BUILTINS: tuple[str, ...] = ("zero", "hold", "constant_velocity", "double_integrator", "unicycle", "linear")


class BaseModelError(SamlError, ValueError):
    """A base model that cannot be used; the message names the model, the parameter or field and why."""


@dataclass(frozen=True)
class FieldInfo:
    """What a base model needs to know about one vector field."""

    name: str
    unit: str
    low: float
    high: float


@dataclass(frozen=True)
class Layouts:
    """The state and control fields of a system and its step ``dt`` (s)."""

    state: tuple[FieldInfo, ...]
    control: tuple[FieldInfo, ...]
    dt: float

    def state_index(self, name: Any, what: str) -> int:
        return _index(self.state, name, what, "state")

    def control_index(self, name: Any, what: str) -> int:
        return _index(self.control, name, what, "control")


def _index(fields: Sequence[FieldInfo], name: Any, what: str, kind: str) -> int:
    names = [f.name for f in fields]
    if name not in names:
        raise BaseModelError(f"{what}: {name!r} is not a {kind} field; {kind} fields are {names}")
    return names.index(name)


class BaseModel:
    """A callable f_hat with a JSON description; see the module docstring."""

    kind: str = ""

    def __call__(self, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        raise NotImplementedError

    def params(self) -> dict[str, Any]:
        """Parameters that rebuild this model exactly (fitted values included)."""
        return {}

    def fit(self, x: np.ndarray, u: np.ndarray, y: np.ndarray) -> None:
        """Fit to transitions (only the ``linear`` built-in without given coefficients does anything)."""


# ------------------------------------------------------------------------------------------ built-ins
class _Zero(BaseModel):
    kind = "zero"

    def __init__(self, lay: Layouts, params: Mapping[str, Any]) -> None:
        _no_params("zero", params)
        self.n = len(lay.state)

    def __call__(self, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        return x.new_zeros((x.shape[0], self.n))


class _Hold(BaseModel):
    kind = "hold"

    def __init__(self, lay: Layouts, params: Mapping[str, Any]) -> None:
        _no_params("hold", params)

    def __call__(self, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        return x.clone()


def _no_params(name: str, params: Mapping[str, Any]) -> None:
    if params:
        raise BaseModelError(f"base model {name!r} takes no parameters, got {sorted(params)}")


def _check_keys(name: str, params: Mapping[str, Any], allowed: set[str], required: set[str]) -> None:
    unknown = sorted(set(params) - allowed)
    if unknown:
        raise BaseModelError(f"base model {name!r}: unknown parameter(s) {unknown}; valid: {sorted(allowed)}")
    missing = sorted(required - set(params))
    if missing:
        raise BaseModelError(f"base model {name!r}: missing parameter(s) {missing}")


def _per_second(unit: str) -> str:
    return f"{unit}/s"


def _per_second2(unit: str) -> str:
    return f"{unit}/s^2"


def _unit_is(what: str, f: FieldInfo, want: str) -> None:
    if f.unit != want:
        raise BaseModelError(f"{what}: field {f.name!r} has unit {f.unit!r}, but this base model needs {want!r}")


class _Axes(BaseModel):
    """constant_velocity and double_integrator."""

    def __init__(self, kind: str, lay: Layouts, params: Mapping[str, Any]) -> None:
        self.kind = kind
        accel = kind == "double_integrator"
        _check_keys(kind, params, {"axes"}, {"axes"})
        axes = params["axes"]
        if not isinstance(axes, list) or not axes:
            raise BaseModelError(f"base model {kind!r}: 'axes' must be a non-empty list of "
                                 "{position, velocity" + (", acceleration}" if accel else "}"))
        self.dt = lay.dt
        self.p: list[int] = []
        self.v: list[int] = []
        self.a: list[int] = []
        keys = {"position", "velocity", "acceleration"} if accel else {"position", "velocity"}
        for k, ax in enumerate(axes):
            what = f"base model {kind!r} axes[{k}]"
            if not isinstance(ax, Mapping):
                raise BaseModelError(f"{what}: expected a mapping with {sorted(keys)}")
            _check_keys(kind, ax, keys, keys)
            ip, iv = lay.state_index(ax["position"], what + ".position"), lay.state_index(ax["velocity"], what + ".velocity")
            pf, vf = lay.state[ip], lay.state[iv]
            _unit_is(what + ".velocity", vf, _per_second(pf.unit))
            self.p.append(ip)
            self.v.append(iv)
            if accel:
                ia = lay.control_index(ax["acceleration"], what + ".acceleration")
                _unit_is(what + ".acceleration", lay.control[ia], _per_second2(pf.unit))
                self.a.append(ia)
        used = self.p + self.v
        if len(set(used)) != len(used):
            raise BaseModelError(f"base model {kind!r}: a state field is used by two axes")
        self._params = {"axes": [dict(a) for a in axes]}

    def params(self) -> dict[str, Any]:
        return dict(self._params)

    def __call__(self, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        dt = self.dt
        out = x.clone()
        p, v = x[:, self.p], x[:, self.v]
        if self.a:
            a = u[:, self.a]
            out[:, self.p] = p + v * dt + 0.5 * a * dt * dt
            out[:, self.v] = v + a * dt
        else:
            out[:, self.p] = p + v * dt
        return out


class _Unicycle(BaseModel):
    kind = "unicycle"

    def __init__(self, lay: Layouts, params: Mapping[str, Any]) -> None:
        _check_keys("unicycle", params, {"x", "y", "yaw", "v", "w", "v_state", "w_state", "tau"},
                    {"x", "y", "yaw", "v", "w"})
        w = "base model 'unicycle'"
        self.ix, self.iy = lay.state_index(params["x"], w + " x"), lay.state_index(params["y"], w + " y")
        self.iyaw = lay.state_index(params["yaw"], w + " yaw")
        self.iv, self.iw = lay.control_index(params["v"], w + " v"), lay.control_index(params["w"], w + " w")
        pos_unit = lay.state[self.ix].unit
        _unit_is(w + " y", lay.state[self.iy], pos_unit)
        _unit_is(w + " yaw", lay.state[self.iyaw], "rad")
        _unit_is(w + " v", lay.control[self.iv], _per_second(pos_unit))
        _unit_is(w + " w", lay.control[self.iw], "rad/s")
        self.ivs = lay.state_index(params["v_state"], w + " v_state") if "v_state" in params else None
        self.iws = lay.state_index(params["w_state"], w + " w_state") if "w_state" in params else None
        if self.ivs is not None:
            _unit_is(w + " v_state", lay.state[self.ivs], _per_second(pos_unit))
        if self.iws is not None:
            _unit_is(w + " w_state", lay.state[self.iws], "rad/s")
        tau = float(params.get("tau", 0.0))
        if not math.isfinite(tau) or tau < 0:
            raise BaseModelError(f"{w}: tau must be a finite number of seconds >= 0, got {params.get('tau')!r}")
        self.alpha = 1.0 if tau == 0 else 1.0 - math.exp(-lay.dt / tau)
        self.dt = lay.dt
        self._params = dict(params)

    def params(self) -> dict[str, Any]:
        return dict(self._params)

    def __call__(self, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        import torch

        dt = self.dt
        v, w = u[:, self.iv], u[:, self.iw]
        yaw = x[:, self.iyaw]
        mid = yaw + 0.5 * w * dt
        out = x.clone()
        out[:, self.ix] = x[:, self.ix] + v * torch.cos(mid) * dt
        out[:, self.iy] = x[:, self.iy] + v * torch.sin(mid) * dt
        out[:, self.iyaw] = yaw + w * dt
        if self.ivs is not None:
            out[:, self.ivs] = x[:, self.ivs] + self.alpha * (v - x[:, self.ivs])
        if self.iws is not None:
            out[:, self.iws] = x[:, self.iws] + self.alpha * (w - x[:, self.iws])
        return out


class _Linear(BaseModel):
    kind = "linear"

    def __init__(self, lay: Layouts, params: Mapping[str, Any]) -> None:
        import torch

        _check_keys("linear", params, {"A", "B", "c", "ridge"}, set())
        n, m = len(lay.state), len(lay.control)
        self.n, self.m = n, m
        self.ridge = float(params.get("ridge", 1e-6))
        given = [k for k in ("A", "B", "c") if k in params]
        self.coef: np.ndarray | None = None  # (n + m + 1, n): [A^T; B^T; c]
        if given:
            if len(given) != 3:
                raise BaseModelError(f"base model 'linear': give all of A, B, c or none (to fit them), got {given}")
            A, B, c = (np.asarray(params[k], dtype=np.float64) for k in ("A", "B", "c"))
            for name, arr, shape in (("A", A, (n, n)), ("B", B, (n, m)), ("c", c, (n,))):
                if arr.shape != shape:
                    raise BaseModelError(f"base model 'linear': {name} must have shape {shape}, got {arr.shape}")
                if not np.isfinite(arr).all():
                    raise BaseModelError(f"base model 'linear': {name} has non-finite entries")
            self.coef = np.concatenate([A.T, B.T, c[None, :]], axis=0)
        self._t: torch.Tensor | None = None if self.coef is None else torch.from_numpy(self.coef)

    @property
    def fitted(self) -> bool:
        return self.coef is not None

    def fit(self, x: np.ndarray, u: np.ndarray, y: np.ndarray) -> None:
        """Least squares (ridge ``ridge``) of ``y - x`` on ``[x, u, 1]``; once (later calls keep the fit)."""
        import torch

        if self.coef is not None:
            return
        z = np.concatenate([x, u, np.ones((len(x), 1))], axis=1)
        lhs = z.T @ z + self.ridge * np.eye(z.shape[1])
        self.coef = np.linalg.solve(lhs, z.T @ (np.asarray(y) - np.asarray(x)))
        self._t = torch.from_numpy(self.coef)

    def params(self) -> dict[str, Any]:
        if self.coef is None:
            return {"ridge": self.ridge}
        n, m = self.n, self.m
        return {"A": self.coef[:n].T.tolist(), "B": self.coef[n:n + m].T.tolist(), "c": self.coef[-1].tolist(),
                "ridge": self.ridge}

    def __call__(self, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        import torch

        if self._t is None:
            return x.clone()
        z = torch.cat([x, u, x.new_ones((x.shape[0], 1))], dim=1)
        return x + z @ self._t.to(x.dtype)


# ------------------------------------------------------------------------------------------ user code
class _UserFunction(BaseModel):
    kind = "function"

    def __init__(self, target: str, fn: Callable[..., Any], lay: Layouts, params: Mapping[str, Any],
                 source: Mapping[str, Any]) -> None:
        self.target = target
        self.fn = fn
        self.dt = lay.dt
        self.kw = dict(params)
        self.n = len(lay.state)
        self._source = dict(source)
        from saml_ros.core.dynamics.base_forms import is_form

        #: an array-namespace form (takes ``xp``, saml_ros.core.dynamics.base_forms) is called with torch here
        self.is_form = is_form(fn)

    def params(self) -> dict[str, Any]:
        return dict(self.kw)

    def __call__(self, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        import torch

        if self.is_form:
            from saml_ros.core.dynamics.base_forms import TORCH

            out = self.fn(x, u, dt=self.dt, xp=TORCH, **self.kw)
        else:
            out = self.fn(x, u, dt=self.dt, **self.kw)
        if not isinstance(out, torch.Tensor):
            raise BaseModelError(f"base model {self.target}: returned {type(out).__name__}, expected a torch.Tensor "
                                 f"of shape (B, {self.n})")
        return out.to(x.dtype)


# ------------------------------------------------------------------------------------------ factory
@dataclass
class BaseModelSpec:
    """The ``base_model`` section of a system file, normalised: exactly one of builtin / function / entry_point.

    ``path`` (``function`` only): the directories the function's module is imported from before the Python path;
    a system file's loader makes them absolute (default: the system file's folder), so a checkpoint that stores
    the definition finds the module from any working directory.
    """

    builtin: str | None = None
    function: str | None = None
    entry_point: str | None = None
    params: dict[str, Any] = field(default_factory=dict)
    path: list[str] = field(default_factory=list)

    @classmethod
    def parse(cls, raw: Any) -> BaseModelSpec:
        if raw is None:
            return cls(builtin="hold")
        if isinstance(raw, str):
            return cls(function=raw) if ":" in raw else cls(builtin=raw)
        if not isinstance(raw, Mapping):
            raise BaseModelError(f"base_model: expected a name or a mapping, got {type(raw).__name__}")
        unknown = sorted(set(raw) - {"builtin", "function", "entry_point", "params", "path"})
        if unknown:
            raise BaseModelError(f"base_model: unknown key(s) {unknown}; valid: builtin, function, entry_point, params, "
                                 "path")
        given = [k for k in ("builtin", "function", "entry_point") if raw.get(k) is not None]
        if len(given) != 1:
            raise BaseModelError(f"base_model: give exactly one of builtin, function, entry_point (got {given or 'none'})")
        params = raw.get("params") or {}
        if not isinstance(params, Mapping):
            raise BaseModelError("base_model.params: expected a mapping")
        path = raw.get("path") or []
        if isinstance(path, str):
            path = [path]
        if not isinstance(path, list | tuple) or not all(isinstance(d, str) and d for d in path):
            raise BaseModelError(f"base_model.path: expected a directory or a list of directories, got {path!r}")
        if path and given[0] != "function":
            raise BaseModelError("base_model.path: only a 'function' base model is imported from a directory")
        return cls(**{given[0]: str(raw[given[0]])}, params=dict(params), path=list(path))

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {k: v for k, v in (("builtin", self.builtin), ("function", self.function),
                                                 ("entry_point", self.entry_point)) if v is not None}
        out["params"] = dict(self.params)
        if self.path:
            out["path"] = list(self.path)
        return out


def build_base_model(spec: BaseModelSpec, lay: Layouts, *, probe: bool = True,
                     function: Callable[..., Any] | None = None) -> BaseModel:
    """The base model ``spec`` describes for ``lay``; with ``probe`` it is called on a probe batch first.

    A user's function (``spec.function`` / ``spec.entry_point``) must be given as ``function``: the core never
    imports code by name; :func:`saml_ros.user_code.resolve_base_model` does, for the learner node, ``train``,
    ``bag_info`` and :mod:`saml_ros.api`. Raises :class:`BaseModelError` (see the module docstring).
    """
    model: BaseModel
    if spec.builtin is not None:
        name = spec.builtin
        if name == "zero":
            model = _Zero(lay, spec.params)
        elif name == "hold":
            model = _Hold(lay, spec.params)
        elif name in ("constant_velocity", "double_integrator"):
            model = _Axes(name, lay, spec.params)
        elif name == "unicycle":
            model = _Unicycle(lay, spec.params)
        elif name == "linear":
            model = _Linear(lay, spec.params)
        else:
            raise BaseModelError(f"base_model.builtin: unknown built-in {name!r}; valid: {list(BUILTINS)}")
    else:
        label = spec.function if spec.function is not None else f"entry point {spec.entry_point!r}"
        if function is None:
            raise BaseModelError(f"base model {label}: user code is imported only when the system file is loaded "
                                 "through saml_ros.user_code (the learner node, train, bag_info, saml_ros.api)")
        model = _UserFunction(str(label), function, lay, spec.params, spec.to_dict())
    if probe:
        probe_base_model(model, lay)
    return model


def probe_base_model(model: BaseModel, lay: Layouts, batch: int = 5) -> None:
    """Call ``model`` on a probe batch inside the bounds and check the result (see the module docstring)."""
    import torch

    rng = np.random.default_rng(0)
    lo_x, hi_x = (np.array([getattr(f, a) for f in lay.state]) for a in ("low", "high"))
    lo_u, hi_u = (np.array([getattr(f, a) for f in lay.control]) for a in ("low", "high"))
    x = torch.from_numpy(rng.uniform(lo_x, hi_x, (batch, len(lay.state))))
    u = torch.from_numpy(rng.uniform(lo_u, hi_u, (batch, len(lay.control))))
    what = getattr(model, "target", None) or f"built-in {model.kind!r}"
    try:
        with torch.no_grad():
            y = model(x, u)
            y1 = model(x[:1], u[:1])
    except BaseModelError:
        raise
    except Exception as exc:  # noqa: BLE001 - the user's code failed on valid inputs
        raise BaseModelError(f"base model {what}: failed on a probe batch of {batch} states within the bounds: "
                             f"{type(exc).__name__}: {exc}") from None
    want = (batch, len(lay.state))
    if tuple(y.shape) != want:
        raise BaseModelError(f"base model {what}: returned shape {tuple(y.shape)} for {batch} states, expected {want} "
                             f"(one next state of {len(lay.state)} fields per row)")
    if not torch.isfinite(y).all():
        raise BaseModelError(f"base model {what}: returned non-finite values on states within the bounds")
    if tuple(y1.shape) != (1, want[1]) or not torch.allclose(y1[0], y[0], rtol=1e-9, atol=1e-12):
        raise BaseModelError(f"base model {what}: row 0 of a batch differs from the same state alone: it must treat "
                             "each row independently (batched over the first dimension)")
