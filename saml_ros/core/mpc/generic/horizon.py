"""Whole-horizon CasADi functions of the generic planner, called through numpy buffers (:class:`HorizonRollout`,
:class:`BufferedFunction`).

A CasADi ``Function`` called from Python converts every argument to a ``DM`` and every result back (about 50-100 us
a call, most of a 13-state rollout's cost); evaluated through :meth:`casadi.Function.buffer` on preallocated
numpy arrays the same SX virtual machine runs in a few microseconds. Nothing is compiled: no C compiler is needed
at run time, and the expression graph is built once per planner (a hot swap of the network writes new numbers
into the weight vector ``theta``; see :mod:`saml_ros.core.mpc.generic.casadi_model` for its layout).

Layout: CasADi matrices are column-major, so a numpy C-order ``(B, n)`` array is the CasADi ``(n, B)`` matrix
with the same memory; every output is densified (a buffer receives only the structural nonzeros otherwise).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np


class BufferedFunction:
    """``fn`` evaluated on preallocated numpy arrays: ``ins`` / ``outs`` (C-order, each the transpose of the CasADi
    argument's shape); :meth:`__call__` copies the given arrays in and returns the outputs (views: copy them
    before the next call)."""

    def __init__(self, fn: Any, in_shapes: Sequence[tuple[int, ...]], out_shapes: Sequence[tuple[int, ...]]) -> None:
        self.fn = fn
        self.ins = [np.zeros(s) for s in in_shapes]
        self.outs = [np.zeros(s) for s in out_shapes]
        self._buf, self._trigger = fn.buffer()
        for i, a in enumerate(self.ins):
            if a.size != fn.nnz_in(i):
                raise ValueError(f"{fn.name()}: input {i} has {fn.nnz_in(i)} numbers, buffer {a.shape}")
            self._buf.set_arg(i, memoryview(a))  # type: ignore[arg-type]
        for i, a in enumerate(self.outs):
            if a.size != fn.nnz_out(i):
                raise ValueError(f"{fn.name()}: output {i} has {fn.nnz_out(i)} numbers, buffer {a.shape}")
            self._buf.set_res(i, memoryview(a))  # type: ignore[arg-type]

    def __call__(self, *args: np.ndarray | None) -> list[np.ndarray]:
        for dst, src in zip(self.ins, args, strict=False):
            if src is not None:
                dst[...] = src
        self._trigger()
        return self.outs


def prelu_mlp_casadi(z: Any, theta: Any, dims: Sequence[int]) -> Any:
    """A PReLU network as a CasADi column of input ``z (dims[0], 1)`` with all its numbers in ``theta``: per layer
    ``W (d_in, d_out)`` (row-major, i.e. ``W'`` column-major), ``b (d_out,)``, then the slope (hidden layers);
    the layout of :func:`mlp_numbers`. The PReLU as ``0.5 (1 + a) h + 0.5 (1 - a) |h|`` (exact for any slope)."""
    import casadi as ca

    k, h = 0, z
    for i, (a, b) in enumerate(zip(dims[:-1], dims[1:], strict=True)):
        w_t = ca.reshape(theta[k:k + a * b], b, a)  # W' (b, a): W row-major is W' column-major
        k += a * b
        h = ca.mtimes(w_t, h) + theta[k:k + b]
        k += b
        if i < len(dims) - 2:
            s = theta[k]
            k += 1
            h = 0.5 * (1 + s) * h + 0.5 * (1 - s) * ca.fabs(h)
    return h


def mean_mlp_casadi(z: Any, theta: Any, dims: Sequence[int], members: int = 1) -> Any:
    """The mean of ``members`` networks of widths ``dims`` (:func:`prelu_mlp_casadi`), their numbers one after the
    other in ``theta`` (each :func:`mlp_numbers`' layout)."""
    if members == 1:
        return prelu_mlp_casadi(z, theta, dims)
    size = len(mlp_zeros(dims))
    total = prelu_mlp_casadi(z, theta[0:size], dims)
    for e in range(1, members):
        total = total + prelu_mlp_casadi(z, theta[e * size:(e + 1) * size], dims)
    return total / members


def mlp_numbers(mlp: Any) -> np.ndarray:
    """The numbers of a :class:`~saml_ros.core.mpc.mlp_np.NumpyMLP` (normalisation folded in) in
    :func:`prelu_mlp_casadi`'s layout."""
    parts: list[np.ndarray] = []
    n = len(mlp.weights)
    for i in range(n):
        w = np.vstack([mlp.w_x, mlp.w_u]) if i == 0 else mlp.weights[i]
        parts += [np.ascontiguousarray(w).ravel(), np.asarray(mlp.biases[i], dtype=np.float64).ravel()]
        if i < n - 1:
            parts.append(np.array([mlp.slopes[i]], dtype=np.float64))
    return np.concatenate(parts)


def mlp_dims(mlp: Any) -> tuple[int, ...]:
    """The layer widths of a :class:`~saml_ros.core.mpc.mlp_np.NumpyMLP`, input first."""
    return (mlp.n_x + mlp.n_u, *(w.shape[1] for w in mlp.weights))


class HorizonRollout:
    """The predicted states ``(T+1, n)`` of a whole control sequence in one call, and of ``K`` sequences at once
    (the line search's step lengths): ``x_{t+1} = f_hat(x_t, u_t) [+ clip(phi(x_t, u_t), -bound, bound)]`` with the
    angle fields wrapped as :class:`~saml_ros.core.mpc.generic.dynamics.GenericDynamics` does (the model sees them
    wrapped, the prediction keeps the turns).

    Args:
        f_hat: ``(x (n,), u (m,)) -> (n,)`` symbolic (SX) CasADi Function, or None (a ``full`` model: phi alone).
        n, m, T: sizes; angles: wrapped state fields.
        dims: the network's layer widths (:func:`mlp_dims`) or None (no network).
        batch: K, the sequences of :meth:`rollout_batch`.
        members: phi is the mean of this many networks of widths ``dims`` (an ensemble planned by its mean; their
            numbers one after the other in ``theta``).
        compile: also the sensitivities ``d x_{t+1} / d U`` of a plan in one call (:meth:`sensitivities`), and all
            three functions compiled to C (:func:`~.codegen.compiled`; without a compiler CasADi's virtual machine
            runs them and :attr:`compiled` says why). f_hat alone is written in scalar expressions (SX); with a
            network the functions are written with CasADi's matrix expressions (MX: the generated C loops over the
            weight matrices, so it stays small and compiles in seconds; scalar expressions through a network
            generate megabytes). The network's Jacobians are the exact ones (a planner rounding them,
            ``smoothing``, does not use these sensitivities).
    """

    def __init__(self, f_hat: Any, n: int, m: int, T: int, angles: Sequence[int], dims: Sequence[int] | None,
                 batch: int, compile: bool = False, members: int = 1) -> None:
        import casadi as ca

        from saml_ros.core.mpc.generic.codegen import compiled

        self.n, self.m, self.T, self.batch = n, m, T, int(batch)
        self.dims = None if dims is None else tuple(int(d) for d in dims)
        self.members = int(members)
        n_theta = 0 if self.dims is None else self.members * len(mlp_zeros(self.dims))
        x0, us = ca.SX.sym("x0", n), ca.SX.sym("U", m, T)
        theta, bound = ca.SX.sym("theta", n_theta), ca.SX.sym("bound", n)
        x: Any = x0
        xs = [x0]
        for t in range(T):
            u = us[:, t]
            xw = ca.vertcat(*[ca.atan2(ca.sin(x[i]), ca.cos(x[i])) if i in angles else x[i] for i in range(n)]) \
                if angles else x
            y = f_hat(xw, u) if f_hat is not None else 0
            if self.dims is not None:
                phi = mean_mlp_casadi(ca.vertcat(xw, u), theta, self.dims, self.members)
                y = y + ca.fmin(ca.fmax(phi, -bound), bound)
            x = y + (x - xw) if angles else y
            xs.append(x)
        fn = ca.Function("rollout", [x0, us, theta, bound], [ca.densify(ca.horzcat(*xs))])
        fk = fn.map("rollout_batch", "serial", self.batch, [0, 2, 3], [])
        fns = [fn, fk]
        #: None: compiled to C; else why not (for /diagnostics)
        self.compiled: str | None = "solver option compile: false"
        if compile:
            if self.dims is None:
                fns.append(_sensitivity_function(f_hat, n, m, T, angles))
                tag = f"generic_T{T}_n{n}_m{m}"
            else:
                fns = _network_functions(f_hat, n, m, T, angles, self.dims, self.batch, self.members)
                tag = f"generic_T{T}_n{n}_m{m}_net{'x'.join(map(str, self.dims))}"
                if self.members > 1:
                    tag += f"_mean{self.members}"
            fns, why = compiled(fns, tag)
            self.compiled = None if why is None else f"not compiled: {why}"
            if why is not None and self.dims is not None:
                # uncompiled, the sensitivities through the network are slower than numpy's: the planner condenses
                fns = fns[:2]
        self._one = BufferedFunction(fns[0], [(n,), (T, m), (n_theta,), (n,)], [(T + 1, n)])
        self._many = BufferedFunction(fns[1], [(n,), (self.batch, T, m), (n_theta,), (n,)],
                                      [(self.batch, T + 1, n)])
        self._sens = BufferedFunction(fns[2], [(T, n), (T, m), (n_theta,), (n,)], [(T, n, T * m)]) \
            if len(fns) > 2 else None
        # theta and bound are shared by the K sequences (map's repeated inputs): one copy each
        for f in self._buffers():
            f.ins[3][:] = np.inf
        #: the prediction model whose numbers the buffers hold (set by its user after :meth:`set_model`)
        self.owner: Any = None

    def _buffers(self) -> list[BufferedFunction]:
        return [f for f in (self._one, self._many, self._sens) if f is not None]

    def set_model(self, theta: np.ndarray | None, bound: np.ndarray | None) -> None:
        """New network numbers (:func:`mlp_numbers`) and residual bound (None: unclipped); nothing is rebuilt."""
        for f in self._buffers():
            if theta is not None:
                f.ins[2][:] = theta
            f.ins[3][:] = np.inf if bound is None else bound

    def rollout(self, x0: np.ndarray, us: np.ndarray) -> np.ndarray:
        return self._one(x0, us)[0].copy()

    def sensitivities(self, xs: np.ndarray, us: np.ndarray) -> np.ndarray | None:
        """``S (T, n, T m)``, ``S[t] = d x_{t+1} / d U`` along states ``xs (T, n)`` (x_0 .. x_{T-1}) and controls
        ``us (T, m)``, or None when this rollout has no such function (see ``compile``)."""
        if self._sens is None:
            return None
        return self._sens(xs, us)[0].copy()

    def rollout_batch(self, x0: np.ndarray, us: np.ndarray) -> np.ndarray:
        """``us (k, T, m)`` -> ``(k, T+1, n)`` (K sequences per call)."""
        k, kk = us.shape[0], self.batch
        out = np.empty((k, self.T + 1, self.n))
        buf = self._many.ins[1]
        for i in range(0, k, kk):
            j = min(k, i + kk)
            buf[: j - i] = us[i:j]
            buf[j - i:] = us[j - 1]
            out[i:j] = self._many(x0)[0][: j - i]
        return out


def mlp_zeros(dims: Sequence[int]) -> np.ndarray:
    """A zero vector of the size of :func:`mlp_numbers` for layer widths ``dims``."""
    size = sum(a * b + b for a, b in zip(dims[:-1], dims[1:], strict=True)) + len(dims) - 2
    return np.zeros(size)


def _network_functions(f_hat: Any, n: int, m: int, T: int, angles: Sequence[int], dims: Sequence[int],
                       batch: int, members: int = 1) -> list[Any]:
    """The rollout, its batch of ``batch`` and the sensitivities of f_hat (or none: ``f_hat`` None, a full model) +
    the clipped network (the mean of ``members`` networks), in CasADi's matrix expressions (MX), with
    :class:`HorizonRollout`'s inputs and outputs."""
    import casadi as ca

    n_theta = members * len(mlp_zeros(dims))
    x, u = ca.MX.sym("x", n), ca.MX.sym("u", m)
    theta, bound = ca.MX.sym("theta", n_theta), ca.MX.sym("bound", n)
    xw = ca.vertcat(*[ca.atan2(ca.sin(x[i]), ca.cos(x[i])) if i in angles else x[i] for i in range(n)]) \
        if angles else x
    y = ca.fmin(ca.fmax(mean_mlp_casadi(ca.vertcat(xw, u), theta, dims, members), -bound), bound)
    if f_hat is not None:
        y = y + f_hat(xw, u)
    if angles:
        y = y + (x - xw)
    step = ca.Function("step", [x, u, theta, bound], [y])
    ab = ca.Function("ab", [x, u, theta, bound], [ca.jacobian(y, x), ca.jacobian(y, u)])
    x0, us = ca.MX.sym("x0", n), ca.MX.sym("U", m, T)
    cur, states = x0, [x0]
    for t in range(T):
        cur = step(cur, us[:, t], theta, bound)
        states.append(cur)
    roll = ca.Function("rollout", [x0, us, theta, bound], [ca.densify(ca.horzcat(*states))])
    many = roll.map("rollout_batch", "serial", batch, [0, 2, 3], [])
    xs = ca.MX.sym("X", n, T)
    rows: list[Any] = []
    prev: Any = None
    for t in range(T):
        a, b = ab(xs[:, t], us[:, t], theta, bound)
        head = [ca.mtimes(a, prev[:, : t * m])] if t else []
        cur = ca.horzcat(*head, b, ca.MX.zeros(n, (T - t - 1) * m))
        rows.append(cur.T)
        prev = cur
    sens = ca.Function("sensitivities", [xs, us, theta, bound], [ca.densify(ca.horzcat(*rows))])
    return [roll, many, sens]


def _sensitivity_function(f_hat: Any, n: int, m: int, T: int, angles: Sequence[int]) -> Any:
    """``(X (T, n), U (T, m)) -> S (T, n, T m)`` (numpy layouts) of f_hat alone: ``S_0 = [B_0 0 ..]``,
    ``S_t = [A_t S_{t-1} | B_t | 0]`` with ``A_t, B_t`` f_hat's Jacobians at ``(x_t, u_t)`` (the angle fields wrapped
    first, derivative 1)."""
    import casadi as ca

    x, u = ca.SX.sym("x", n), ca.SX.sym("u", m)
    xw = ca.vertcat(*[ca.atan2(ca.sin(x[i]), ca.cos(x[i])) if i in angles else x[i] for i in range(n)]) \
        if angles else x
    y = f_hat(xw, u) + (x - xw) if angles else f_hat(x, u)
    step = ca.Function("ab", [x, u], [ca.jacobian(y, x), ca.jacobian(y, u)])
    xs, us = ca.SX.sym("X", n, T), ca.SX.sym("U", m, T)
    rows: list[Any] = []
    prev: Any = None
    for t in range(T):
        a, b = step(xs[:, t], us[:, t])
        head = [ca.mtimes(a, prev[:, : t * m])] if t else []
        cur = ca.horzcat(*head, b, ca.SX.zeros(n, (T - t - 1) * m))
        rows.append(cur.T)  # numpy's C-order (T, n, T m) is CasADi's column-major (T m, T n) of the S_t'
        prev = cur
    unused = (ca.SX.sym("theta", 0), ca.SX.sym("bound", n))  # the network's inputs (none here)
    return ca.Function("sensitivities", [xs, us, *unused], [ca.densify(ca.horzcat(*rows))])
