"""A learned model as CasADi expressions with the network's weights as a *parameter vector*.

``y = f_hat(x, u) + phi(x, u; theta)``, where ``theta`` (:func:`mlp_theta`) holds one ensemble member's normalisation,
weights, biases and PReLU slopes in a documented order (:func:`theta_layout`). A controller built on these
expressions (the IPOPT path of the generic planner, :mod:`.nlp`; a user's acados / CasADi controller fed by
``./dev export --format casadi``) takes a new checkpoint by passing new numbers for ``theta``: the expression graph,
and any solver or generated code built on it, stays as it is.

The PReLU is written ``0.5 (1 + a) h + 0.5 (1 - a) |h|`` (equal to ``h`` for ``h >= 0`` and ``a h`` below, for any
slope ``a``), so the graph has no branch. Its kinks defeat an interior point method with exact Hessians (IPOPT:
3000 iterations without convergence on the export test's OCP, docs/your_robot.md); with ``smooth = eps > 0`` the
kinks are rounded, ``|h| -> sqrt(h^2 + eps^2)`` (IPOPT: 13 iterations at eps = 1e-3, the same plan to 1e-5 m). An
SQP with a Gauss-Newton Hessian (the generic planner's, acados' SQP / RTI) takes the exact network.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from saml_ros.core.model.network import DynamicsModel


def theta_layout(n_in: int, hidden: Sequence[int], n_out: int) -> list[tuple[str, tuple[int, ...]]]:
    """The blocks of ``theta`` in order, ``(name, shape)``: ``in_mean (n_in,)``, ``in_std (n_in,)``, then per layer
    ``W{l} (d_l, d_{l+1})`` (column-major), ``b{l} (d_{l+1},)``, ``slope{l} (1,)`` (hidden layers only), then
    ``out_std (n_out,)``."""
    dims = [n_in, *hidden, n_out]
    out: list[tuple[str, tuple[int, ...]]] = [("in_mean", (n_in,)), ("in_std", (n_in,))]
    for i, (a, b) in enumerate(zip(dims[:-1], dims[1:], strict=True)):
        out += [(f"W{i}", (a, b)), (f"b{i}", (b,))]
        if i < len(dims) - 2:
            out.append((f"slope{i}", (1,)))
    out.append(("out_std", (n_out,)))
    return out


def theta_size(n_in: int, hidden: Sequence[int], n_out: int) -> int:
    return sum(int(np.prod(s)) for _, s in theta_layout(n_in, hidden, n_out))


def mlp_theta(model: DynamicsModel, member: int = 0) -> np.ndarray:
    """``theta`` of ensemble member ``member`` (float64, :func:`theta_layout`'s order)."""
    if not 0 <= member < model.n_models:
        raise ValueError(f"member {member} out of range for an ensemble of {model.n_models}")
    net = model.net
    parts: list[np.ndarray] = [model.in_mean[member, 0].detach().double().numpy().ravel(),
                               model.in_std[member, 0].detach().double().numpy().ravel()]
    n = len(net.weights)
    for i in range(n):
        parts.append(net.weights[i][member].detach().double().numpy().ravel(order="F"))
        parts.append(net.biases[i][member, 0].detach().double().numpy().ravel())
        if i < n - 1:
            parts.append(net.slopes[i][member].detach().double().numpy().ravel())
    parts.append(model.out_std[member, 0].detach().double().numpy().ravel())
    return np.concatenate(parts)


def casadi_mlp(z: Any, theta: Any, n_in: int, hidden: Sequence[int], n_out: int, smooth: Any = 0.0) -> Any:
    """phi as a CasADi column ``(n_out, 1)`` of the input column ``z (n_in, 1)`` and ``theta`` (SX or MX); ``smooth``
    (a number or a symbol): the PReLU's rounding ``eps`` (0 = exact; see the module docstring)."""
    import casadi as ca

    k = 0

    def take(size: int) -> Any:
        nonlocal k
        part = theta[k:k + size]
        k += size
        return part

    mean, std = take(n_in), take(n_in)
    h = (z - mean) / std
    dims = [n_in, *hidden, n_out]
    for i, (a, b) in enumerate(zip(dims[:-1], dims[1:], strict=True)):
        w = ca.reshape(take(a * b), a, b)
        h = ca.mtimes(w.T, h) + take(b)
        if i < len(dims) - 2:
            s = take(1)
            mag = ca.fabs(h) if isinstance(smooth, int | float) and smooth == 0 else ca.sqrt(h * h + smooth * smooth)
            h = 0.5 * (1 + s) * h + 0.5 * (1 - s) * mag
    return h * take(n_out)


def wrap_casadi(x: Any, angles: Sequence[int]) -> Any:
    """``x`` (column) with the fields ``angles`` wrapped into [-pi, pi] (``atan2(sin, cos)``: derivative 1)."""
    import casadi as ca

    if not angles:
        return x
    parts = [ca.atan2(ca.sin(x[i]), ca.cos(x[i])) if i in angles else x[i] for i in range(x.shape[0])]
    return ca.vertcat(*parts)


def casadi_dynamics(system: Any, kind: str | None, hidden: Sequence[int], *, symbolic: str = "SX",
                    wrap: bool = True, smooth: float = 0.0) -> Any:
    """``F(x (n,), u (m,), theta, bound (n,)) -> y (n,)``: the model ``kind`` (``residual``: f_hat + phi, ``full``:
    phi, None: f_hat alone; theta and bound unused then) of ``system`` as a CasADi Function, with phi clipped to
    ``+-bound`` (pass ``inf`` for none) and the angle fields handled as the planner does (the model sees them
    wrapped, the prediction keeps the turns). ``ValueError`` when f_hat has no symbolic form (a plain torch
    function: write it as an array-namespace form, saml_ros.core.dynamics.base_forms)."""
    import casadi as ca

    from saml_ros.core.mpc.generic.dynamics import SymbolicBase, make_base

    n, m = system.state.size, system.control.size
    sym: Any = ca.SX if symbolic == "SX" else ca.MX
    x, u, b = sym.sym("x", n), sym.sym("u", m), sym.sym("bound", n)
    n_theta = theta_size(n + m, hidden, n) if kind is not None else 0
    theta = sym.sym("theta", n_theta)
    angles = [int(i) for i in getattr(system, "angle_indices", ())] if wrap else []
    xw = wrap_casadi(x, angles)
    y: Any = 0
    if kind != "full":
        base = make_base(system)
        if not isinstance(base, SymbolicBase):
            raise ValueError(f"f_hat of {system.name} ({base.label}) is a plain torch function: it has no CasADi "
                             "form (give it the keyword 'xp' to write it once for torch, numpy and CasADi; "
                             "docs/your_robot.md)")
        y = base.function(xw, u)
    if kind is not None:
        phi = casadi_mlp(ca.vertcat(xw, u), theta, n + m, hidden, n, smooth)
        y = y + ca.fmin(ca.fmax(phi, -b), b)
    y = y + (x - xw)
    return ca.Function("model", [x, u, theta, b], [y], ["x", "u", "theta", "bound"], ["y"])


def export_function(model: DynamicsModel, member: int = 0, *, smooth: bool = False) -> tuple[Any, np.ndarray, bool, str]:
    """The CasADi export of ``model`` (member ``member``): ``(F, theta, base_exported, why_not)`` with
    ``F(x (n,), u (m,), theta) -> (y, residual)`` (``y`` = f_hat + phi, or phi alone when f_hat has no symbolic
    form: ``base_exported`` False and ``why_not`` says why; a ``full`` model's ``y`` is phi), exactly the model's
    prediction for the inputs as given (no angle wrapping). With ``smooth``, ``F`` takes a fourth input ``eps``, the
    PReLU's rounding (module docstring; ``eps = 0`` is the exact network)."""
    import casadi as ca

    from saml_ros.core.mpc.generic.dynamics import SymbolicBase, make_base

    system = model.system
    n, m = system.state.size, system.control.size
    hidden = tuple(model.hidden)
    x, u = ca.SX.sym("x", n), ca.SX.sym("u", m)
    theta = ca.SX.sym("theta", theta_size(n + m, hidden, n))
    eps = ca.SX.sym("eps")
    phi = casadi_mlp(ca.vertcat(x, u), theta, n + m, hidden, n, eps if smooth else 0.0)
    y, base_ok, why = phi, model.kind == "full", ""
    if model.kind == "residual":
        try:
            base = make_base(system)
        except Exception as exc:  # noqa: BLE001 - a system without a system file's base model
            base, why = None, f"{type(exc).__name__}: {exc}"
        if isinstance(base, SymbolicBase):
            y, base_ok = base.function(x, u) + phi, True
        elif not why:
            why = (f"f_hat ({getattr(base, 'label', system.name)}) has no CasADi form: only the array-namespace forms "
                   "of a system file's base models have one (saml_ros.core.dynamics.base_forms)")
    if smooth:
        fn = ca.Function("model_smooth", [x, u, theta, eps], [y, phi], ["x", "u", "theta", "eps"], ["y", "residual"])
    else:
        fn = ca.Function("model", [x, u, theta], [y, phi], ["x", "u", "theta"], ["y", "residual"])
    return fn, mlp_theta(model, member), base_ok, why
