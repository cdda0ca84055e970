"""A learned model as CasADi expressions with the network's weights as a *parameter vector*.

``y = f_hat(x, u) + phi(x, u; theta)``, where ``theta`` (:func:`mlp_theta`) holds one ensemble member's normalisation,
weights, biases and PReLU slopes in a documented order (:func:`theta_layout`). A controller built on these
expressions (the IPOPT path of the generic planner, :mod:`.nlp`; a user's acados / CasADi controller fed by
``./dev export --format casadi``) takes a new checkpoint by passing new numbers for ``theta``: the expression graph,
and any solver or generated code built on it, stays as it is.

The PReLU is written ``0.5 (1 + a) h + 0.5 (1 - a) |h|`` (equal to ``h`` for ``h >= 0`` and ``a h`` below, for any
slope ``a``), so the graph has no branch.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from saml_ros.core.models import DynamicsModel


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


def casadi_mlp(z: Any, theta: Any, n_in: int, hidden: Sequence[int], n_out: int) -> Any:
    """phi as a CasADi column ``(n_out, 1)`` of the input column ``z (n_in, 1)`` and ``theta`` (SX or MX)."""
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
            h = 0.5 * (1 + s) * h + 0.5 * (1 - s) * ca.fabs(h)
    return h * take(n_out)


def wrap_casadi(x: Any, angles: Sequence[int]) -> Any:
    """``x`` (column) with the fields ``angles`` wrapped into [-pi, pi] (``atan2(sin, cos)``: derivative 1)."""
    import casadi as ca

    if not angles:
        return x
    parts = [ca.atan2(ca.sin(x[i]), ca.cos(x[i])) if i in angles else x[i] for i in range(x.shape[0])]
    return ca.vertcat(*parts)


def casadi_dynamics(system: Any, kind: str | None, hidden: Sequence[int], *, symbolic: str = "SX") -> Any:
    """``F(x (n,), u (m,), theta, bound (n,)) -> y (n,)``: the model ``kind`` (``residual``: f_hat + phi, ``full``:
    phi, None: f_hat alone; theta and bound unused then) of ``system`` as a CasADi Function, with phi clipped to
    ``+-bound`` (pass ``inf`` for none) and the angle fields handled as the planner does (the model sees them
    wrapped, the prediction keeps the turns). ``ValueError`` when f_hat has no symbolic form (a plain torch
    function: write it as an array-namespace form, saml_ros.core.systems.base_forms)."""
    import casadi as ca

    from saml_ros.core.mpc.generic.dynamics import SymbolicBase, make_base

    n, m = system.state.size, system.control.size
    sym: Any = ca.SX if symbolic == "SX" else ca.MX
    x, u, b = sym.sym("x", n), sym.sym("u", m), sym.sym("bound", n)
    n_theta = theta_size(n + m, hidden, n) if kind is not None else 0
    theta = sym.sym("theta", n_theta)
    angles = [int(i) for i in getattr(system, "angle_indices", ())]
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
        phi = casadi_mlp(ca.vertcat(xw, u), theta, n + m, hidden, n)
        y = y + ca.fmin(ca.fmax(phi, -b), b)
    y = y + (x - xw)
    return ca.Function("model", [x, u, theta, b], [y], ["x", "u", "theta", "bound"], ["y"])
