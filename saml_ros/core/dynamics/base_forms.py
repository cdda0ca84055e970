"""f_hat written once, evaluated by numpy and torch and differentiated exactly by CasADi: *array-namespace forms*.

A form is a function ``f(x, u, *, dt, xp, **params) -> (B, n_x)`` on row batches ``x (B, n_x)``, ``u (B, n_u)`` that
uses only column reads ``x[:, i]``, arithmetic, and the functions of the namespace ``xp`` it is given
(:data:`NUMPY`, :data:`TORCH`, :data:`CASADI`): ``sin cos tan exp log sqrt tanh atan2 abs minimum maximum where
clip`` and ``stack(columns) -> (B, k)``. The planner evaluates it with numpy (batched, cheap) and builds its exact
Jacobians once with CasADi (``x`` is then a ``(1, n_x)`` symbol row); the learner calls it with torch.

* Every built-in base model of :mod:`saml_ros.core.dynamics.base_models` has a form here (:func:`builtin_form`),
  checked against the torch built-in on random inputs (``test/unit/core/mpc/test_generic_mpc.py``).
* A user's base model opts in by taking the keyword ``xp`` (:func:`is_form`); such a function is differentiated
  symbolically like a built-in. A plain torch function (the contract of docs/your_robot.md) is differentiated by
  torch autograd instead (:class:`saml_ros.core.mpc.generic.dynamics.TorchBase`): exact too, slower.
"""

from __future__ import annotations

import inspect
import math
from collections.abc import Callable, Sequence
from types import SimpleNamespace
from typing import Any

import numpy as np

#: a form: ``(x, u, *, dt, xp, **params) -> (B, n_x)``
Form = Callable[..., Any]


def _np_stack(cols: Sequence[Any]) -> np.ndarray:
    shape: tuple[int, ...] = ()
    for c in cols:
        if isinstance(c, np.ndarray) and c.ndim:
            shape = c.shape
            break
    out = np.empty((*shape, len(cols)))
    for j, c in enumerate(cols):
        out[..., j] = c
    return out


#: numpy namespace of a form
NUMPY = SimpleNamespace(
    name="numpy", sin=np.sin, cos=np.cos, tan=np.tan, exp=np.exp, log=np.log, sqrt=np.sqrt, tanh=np.tanh,
    atan2=np.arctan2, abs=np.abs, minimum=np.minimum, maximum=np.maximum, where=np.where, clip=np.clip,
    stack=_np_stack, pi=math.pi,
)


def _torch_ns() -> SimpleNamespace:
    import torch

    def stack(cols: Sequence[Any]) -> Any:
        return torch.stack(torch.broadcast_tensors(*cols), dim=-1)

    return SimpleNamespace(
        name="torch", sin=torch.sin, cos=torch.cos, tan=torch.tan, exp=torch.exp, log=torch.log, sqrt=torch.sqrt,
        tanh=torch.tanh, atan2=torch.atan2, abs=torch.abs, minimum=torch.minimum, maximum=torch.maximum,
        where=torch.where, clip=torch.clamp, stack=stack, pi=math.pi,
    )


def _casadi_ns() -> SimpleNamespace:
    import casadi as ca

    def where(cond: Any, a: Any, b: Any) -> Any:
        return ca.if_else(cond, a, b)

    def clip(v: Any, lo: Any, hi: Any) -> Any:
        return ca.fmin(ca.fmax(v, lo), hi)

    def stack(cols: Sequence[Any]) -> Any:
        return ca.horzcat(*cols)

    return SimpleNamespace(
        name="casadi", sin=ca.sin, cos=ca.cos, tan=ca.tan, exp=ca.exp, log=ca.log, sqrt=ca.sqrt, tanh=ca.tanh,
        atan2=ca.atan2, abs=ca.fabs, minimum=ca.fmin, maximum=ca.fmax, where=where, clip=clip, stack=stack,
        pi=math.pi,
    )


class Row:
    """One state (or control) as a row of Python floats for a form: ``x[:, i]`` is a float, ``x.shape`` is
    ``(1, n)``. With :data:`SCALAR` a form runs on floats (a single-step rollout, no numpy call per operation)."""

    __slots__ = ("values",)

    def __init__(self, values: Sequence[float]) -> None:
        self.values = values

    @property
    def shape(self) -> tuple[int, int]:
        return 1, len(self.values)

    def __getitem__(self, key: Any) -> float:
        return self.values[key[1]]


def _where(cond: Any, a: Any, b: Any) -> Any:
    return a if cond else b


#: the namespace of a form on :class:`Row` s of floats (``stack`` returns a list)
SCALAR = SimpleNamespace(
    name="scalar", sin=math.sin, cos=math.cos, tan=math.tan, exp=math.exp, log=math.log, sqrt=math.sqrt,
    tanh=math.tanh, atan2=math.atan2, abs=abs, minimum=min, maximum=max, where=_where,
    clip=lambda v, lo, hi: min(max(v, lo), hi), stack=list, pi=math.pi,
)


class _Lazy:
    """A namespace built on first attribute access (torch and CasADi are imported only when used)."""

    def __init__(self, make: Callable[[], SimpleNamespace]) -> None:
        self._make = make
        self._ns: SimpleNamespace | None = None

    def __getattr__(self, name: str) -> Any:
        if name.startswith("_"):
            raise AttributeError(name)
        if self._ns is None:
            self._ns = self._make()
        return getattr(self._ns, name)


#: torch namespace of a form (the learner's)
TORCH: Any = _Lazy(_torch_ns)
#: CasADi namespace of a form (symbolic: the planner's derivatives, the CasADi export)
CASADI: Any = _Lazy(_casadi_ns)


def is_form(fn: Callable[..., Any]) -> bool:
    """Whether a user's base model function is an array-namespace form (it takes the keyword ``xp``)."""
    try:
        params = inspect.signature(fn).parameters
    except (TypeError, ValueError):
        return False
    return "xp" in params and params["xp"].kind in (inspect.Parameter.KEYWORD_ONLY,
                                                    inspect.Parameter.POSITIONAL_OR_KEYWORD)


# ------------------------------------------------------------------------------------------ built-ins
def _replace(x: Any, xp: Any, n: int, new: dict[int, Any]) -> Any:
    """``x`` with columns ``new`` (index -> column) replaced: ``(B, n)``."""
    return xp.stack([new[i] if i in new else x[:, i] for i in range(n)])


def builtin_form(base: Any) -> Form:
    """The form of a built-in base model object (``saml_ros.core.dynamics.base_models``: ``zero``, ``hold``,
    ``constant_velocity``, ``double_integrator``, ``unicycle``, ``linear``), bound to its fields and parameters.

    Raises:
        ValueError: an object that is not a built-in base model.
    """
    kind = getattr(base, "kind", "")
    if kind == "zero":
        n = base.n

        def zero(x: Any, u: Any, *, dt: float, xp: Any) -> Any:
            return xp.stack([0.0 * x[:, 0]] * n)

        return zero
    if kind == "hold":

        def hold(x: Any, u: Any, *, dt: float, xp: Any) -> Any:
            return xp.stack([x[:, i] for i in range(x.shape[1])])

        return hold
    if kind in ("constant_velocity", "double_integrator"):
        p_idx, v_idx, a_idx = list(base.p), list(base.v), list(base.a)

        def axes(x: Any, u: Any, *, dt: float, xp: Any) -> Any:
            new: dict[int, Any] = {}
            for k, (ip, iv) in enumerate(zip(p_idx, v_idx, strict=True)):
                p, v = x[:, ip], x[:, iv]
                if a_idx:
                    a = u[:, a_idx[k]]
                    new[ip] = p + v * dt + 0.5 * a * dt * dt
                    new[iv] = v + a * dt
                else:
                    new[ip] = p + v * dt
            return _replace(x, xp, x.shape[1], new)

        return axes
    if kind == "unicycle":
        ix, iy, iyaw, iv, iw = base.ix, base.iy, base.iyaw, base.iv, base.iw
        ivs, iws, alpha = base.ivs, base.iws, base.alpha

        def unicycle(x: Any, u: Any, *, dt: float, xp: Any) -> Any:
            v, w, yaw = u[:, iv], u[:, iw], x[:, iyaw]
            mid = yaw + 0.5 * w * dt
            new = {ix: x[:, ix] + v * xp.cos(mid) * dt, iy: x[:, iy] + v * xp.sin(mid) * dt, iyaw: yaw + w * dt}
            if ivs is not None:
                new[ivs] = x[:, ivs] + alpha * (v - x[:, ivs])
            if iws is not None:
                new[iws] = x[:, iws] + alpha * (w - x[:, iws])
            return _replace(x, xp, x.shape[1], new)

        return unicycle
    if kind == "linear":
        model = base

        def linear(x: Any, u: Any, *, dt: float, xp: Any) -> Any:
            coef = model.coef  # read at call time: the learner fits it from the first transitions
            n = x.shape[1]
            if coef is None:
                return xp.stack([x[:, i] for i in range(n)])
            m = u.shape[1]
            cols = []
            for j in range(n):
                acc = x[:, j] + float(coef[-1, j])
                for i in range(n):
                    if coef[i, j] != 0.0:
                        acc = acc + float(coef[i, j]) * x[:, i]
                for i in range(m):
                    if coef[n + i, j] != 0.0:
                        acc = acc + float(coef[n + i, j]) * u[:, i]
                cols.append(acc)
            return xp.stack(cols)

        return linear
    raise ValueError(f"no array-namespace form for base model kind {kind!r}")


def base_form(base: Any) -> tuple[Form, dict[str, Any]] | None:
    """``(form, params)`` of a system file's base model object: a built-in's form, or a user's function that takes
    ``xp`` (with its parameters); ``None`` for a plain torch function (no symbolic form)."""
    if getattr(base, "kind", "") == "function":
        fn = base.fn
        return (fn, dict(base.kw)) if is_form(fn) else None
    try:
        return builtin_form(base), {}
    except ValueError:
        return None
