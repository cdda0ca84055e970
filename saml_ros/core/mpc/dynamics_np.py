"""The MPC's prediction model ``f_hat + phi`` on float64 numpy arrays, with exact Jacobians.

The base models f_hat of the systems are re-implemented in numpy with hand-derived Jacobians, one module per
system beside its torch model (``saml_ros/systems/<name>/dynamics_np.py``, named by the registry entry's
``base_model_np``; the torch versions stay the single source of truth: ``test/unit/core/mpc/test_mpc.py`` checks
values and Jacobians against them and torch autograd). A system without a numpy twin falls back to torch autograd
(:class:`TorchBaseNP`: ``torch.func.jacrev``), which is exact but slow.

The *oracle* is the true dynamics ``f`` as the MPC's model (``NumpyDynamics(system, "oracle")``,
``make_controller(system, "oracle")``): the best any learned model can do inside the same MPC, used to measure
how much a model can matter on a task (the headroom, docs/experiments.md). Its numpy twins (in the same system
modules) are named by the registry entry's ``true_model_np``; their Jacobians are exact wherever ``f`` is
differentiable (friction: except where the friction just holds the cart, ``|w| = b(p)``; quadrotor: at the level
attitude the tilt has a cone-shaped kink and the derivative 0 is used, as torch's ``tilt_angle``).

Shapes: ``x`` ``(B, n_x)``, ``u`` ``(B, n_u)`` -> ``y`` ``(B, n_y)``, ``A = dy/dx`` ``(B, n_y, n_x)``,
``Bu = dy/du`` ``(B, n_y, n_u)``.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Literal, Protocol, Union

import numpy as np

from saml_ros.core.dynamics.system import System
from saml_ros.core.mpc.mlp_np import NumpyMLP

if TYPE_CHECKING:  # torch only where a model or the autograd fallback is used
    import torch

    from saml_ros.core.model.network import DynamicsModel

Jac3 = tuple[np.ndarray, np.ndarray, np.ndarray]
#: :meth:`NumpyDynamics.fused_jacobians` tabulates the Jacobians of every activation pattern of up to this many
#: hidden units (2^10 = 1024 patterns; the friction model's 4-2 net has 64)
JAC_TABLE_UNITS = 10
#: one hidden layer's step of the fused rollout: (matrix, input rows, pre-activation rows, relu rows)
_FusedLayer = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]
#: the fused rollout's buffer and views (:meth:`NumpyDynamics._fused_plan`): z, per step (hidden layers, the
#: step's block, the rows of x_{t+1}), the rows of x_0, of all controls and of all states
_FusedPlan = tuple[np.ndarray, list[tuple[list[_FusedLayer], np.ndarray, np.ndarray]], np.ndarray, np.ndarray,
                   np.ndarray]

#: the model name that makes the MPC predict with the TRUE dynamics (see the module docstring)
ORACLE: Literal["oracle"] = "oracle"
#: what an MPC predicts with: a learned model (residual or full), the oracle, or None (f_hat alone)
PredictionModel = Union["DynamicsModel", Literal["oracle"], None]  # noqa: UP007 (a string: no torch here)


class BaseModelNP(Protocol):
    def step(self, x: np.ndarray, u: np.ndarray) -> np.ndarray: ...
    def step1(self, x: np.ndarray, u: np.ndarray) -> np.ndarray: ...
    def step_jac(self, x: np.ndarray, u: np.ndarray) -> Jac3: ...


class TorchBaseNP:
    """Any system's ``base_step`` through torch autograd (exact but slow: the fallback for unknown systems)."""

    def __init__(self, system: System) -> None:
        self.system = system

    def step(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        import torch

        with torch.no_grad():
            return self.system.base_step(torch.from_numpy(x), torch.from_numpy(u)).numpy()

    def step1(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        return self.step(x[None], u[None])[0]

    def step_jac(self, x: np.ndarray, u: np.ndarray) -> Jac3:
        import torch

        def one(xi: torch.Tensor, ui: torch.Tensor) -> torch.Tensor:
            return self.system.base_step(xi[None], ui[None])[0]

        xt, ut = torch.from_numpy(np.ascontiguousarray(x)), torch.from_numpy(np.ascontiguousarray(u))
        ja, jb = torch.func.vmap(torch.func.jacrev(one, argnums=(0, 1)))(xt, ut)
        return self.step(x, u), ja.numpy(), jb.numpy()


class TorchTrueNP(TorchBaseNP):
    """Any system's ``true_step`` through torch autograd (the oracle's fallback for systems without a twin)."""

    def step(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        import torch

        with torch.no_grad():
            return self.system.true_step(torch.from_numpy(x), torch.from_numpy(u)).numpy()

    def step_jac(self, x: np.ndarray, u: np.ndarray) -> Jac3:
        import torch

        def one(xi: torch.Tensor, ui: torch.Tensor) -> torch.Tensor:
            return self.system.true_step(xi[None], ui[None])[0]

        xt, ut = torch.from_numpy(np.ascontiguousarray(x)), torch.from_numpy(np.ascontiguousarray(u))
        ja, jb = torch.func.vmap(torch.func.jacrev(one, argnums=(0, 1)))(xt, ut)
        return self.step(x, u), ja.numpy(), jb.numpy()


class NumpyDynamics:
    """The model the MPC predicts with: ``f_hat + phi`` (residual), ``phi`` (full), ``f_hat`` (no model) or the
    true dynamics ``f`` (``model = "oracle"``, :data:`ORACLE`).

    The learned part is a frozen copy of ensemble member ``member`` taken when this object is built. ``base`` is
    the numpy twin of ``system.base_step`` (:func:`saml_ros.core.mpc.factory.base_model_np` finds the system's
    own); without one, the exact but slower autograd :class:`TorchBaseNP` serves. ``true`` is the twin of
    ``system.true_step`` the oracle uses (:func:`saml_ros.core.mpc.factory.true_model_np`; fallback
    :class:`TorchTrueNP`).
    """

    def __init__(self, system: System, model: PredictionModel = None, member: int = 0,
                 base: BaseModelNP | None = None, true: BaseModelNP | None = None) -> None:
        self.system = system
        self.base: BaseModelNP | None = None
        self.mlp: NumpyMLP | None = None
        #: "residual", "full", "base" (f_hat alone) or "oracle"
        self.kind: str
        #: rollout_batch's stacked weights, row blocks and rows of ones (:meth:`_fused_layout`), made on first use
        self._fused: tuple[list[np.ndarray], list[tuple[int, int, int, int, int]], list[int]] | None = None
        #: per (batch size, horizon): the buffer and row views of :meth:`_rollout_fused` (:meth:`_fused_plan`)
        self._fused_plans: dict[tuple[int, int], _FusedPlan] = {}
        #: fused rollouts made so far; :attr:`_fused_stamps` holds, per buffer, the count at its last fill
        self.fused_calls = 0
        self._fused_stamps: dict[tuple[int, int], int] = {}
        #: :meth:`rollout_batch` is fused (one product per layer and step for all K sequences): K sequences cost
        #: about as much as one, so callers may batch what they would otherwise roll out one by one
        self.fused_rollout = False
        #: :meth:`fused_jacobians`' code weights and tables (:meth:`_jac_table`), False if too wide; made on first use
        self._jac_tab: tuple[np.ndarray, np.ndarray, np.ndarray] | Literal[False] | None = None
        if isinstance(model, str):
            if model != ORACLE:
                raise ValueError(f"unknown prediction model {model!r}; a DynamicsModel, None or {ORACLE!r}")
            self.kind = ORACLE
            self.base = true if true is not None else TorchTrueNP(system)
            return
        self.kind = "base" if model is None else model.kind
        if model is None or model.kind == "residual":
            self.base = base if base is not None else TorchBaseNP(system)
        if model is not None:
            if model.system.schema_hash() != system.schema_hash():
                raise ValueError(
                    f"model is for system {model.system.name!r} (schema {model.system.schema_hash()}), "
                    f"not {system.name!r} (schema {system.schema_hash()})"
                )
            self.mlp = NumpyMLP(model, member)
        self.fused_rollout = self.mlp is not None and (self.base is None or getattr(self.base, "linear", None)
                                                       is not None)

    def step(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """Predicted target ``(B, n_y)``."""
        return self._plus_phi(None if self.base is None else self.base.step(x, u), x, u)

    def step1(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """Prediction for one sample ``(n_x,), (n_u,) -> (n_y,)`` (the rollout's hot path)."""
        return self._plus_phi(None if self.base is None else self.base.step1(x, u), x, u)

    def rollout(self, x0: np.ndarray, us: np.ndarray) -> np.ndarray:
        """Predicted states ``(T+1, n)`` from ``x0`` ``(n,)`` under ``us`` ``(T, m)``: :meth:`step1` T times (by the
        base model's own ``rollout1`` when it has one and there is no network: the same values, faster)."""
        roll = getattr(self.base, "rollout1", None) if self.mlp is None else None
        if roll is not None:
            return np.asarray(roll(x0, us))
        return rollout_steps(self.step1, x0, us)

    def _plus_phi(self, y: np.ndarray | None, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """The base prediction ``y`` plus phi (in place), phi alone for a full model (``y`` None), or ``y``."""
        if y is None:
            assert self.mlp is not None
            return self.mlp.forward(x, u)
        if self.mlp is not None:
            y += self.mlp.forward(x, u)
        return y

    def rollout_batch(self, x0: np.ndarray, us: np.ndarray) -> np.ndarray:
        """Predicted states ``(K, T+1, n)`` of control sequences ``us`` ``(K, T, m)`` from ``x0`` ``(n,)``, batched
        over the K sequences (the start scoring of the shooting MPC: ~40 sequences at every friction solve).

        With a linear base model (``base.linear``) or none (a full model) and a network, the rollout is fused:
        states are kept as columns ``(n, K)``, the controls' share of the first layer and of the base model is
        computed for all steps at once, and the base model's ``A x`` comes out of the same product as the first
        layer's ``W_x x``: about 10 numpy calls per step instead of about 20. Otherwise: T calls of :meth:`step`.
        """
        k, horizon = us.shape[0], us.shape[1]
        if self.fused_rollout:
            return self._rollout_fused(x0, us, None if self.base is None else getattr(self.base, "linear", None))
        xs = np.empty((k, horizon + 1, x0.shape[0]))
        xs[:, 0] = x0
        x = xs[:, 0]
        for t in range(horizon):
            x = self.step(x, us[:, t])
            xs[:, t + 1] = x
        return xs

    def _rollout_fused(self, x0: np.ndarray, us: np.ndarray, lin: tuple[np.ndarray, np.ndarray] | None) -> np.ndarray:
        """:meth:`rollout_batch` for ``y = A x + B u + phi(x, u)`` (``lin`` = (A, B), or None for ``y = phi``).

        Layout: one buffer ``z`` ``(T+1, R, K)`` whose step-t block holds the columns
        ``[x_t; u_t; 1 | h_1; relu(h_1); 1 | ... | h_L; relu(h_L); 1]`` (controls and ones filled in before the
        loop). Since ``PReLU_a(h) = a h + (1 - a) relu(h)`` for every slope a, the next layer's pre-activation is
        ONE product of ``[a W, (1 - a) W, b]`` with the previous block; the last product also carries the base
        model ``A x + B u`` (zero weights elsewhere) and writes ``x_{t+1}`` in place. Per step: one product and
        one ``maximum`` per hidden layer, one final product (5 numpy calls for two hidden layers, was 8)."""
        k, horizon, n = us.shape[0], us.shape[1], x0.shape[0]
        m = us.shape[2]
        if self._fused is None:
            self._fused = self._fused_layout(lin, n, m)
        plan = self._fused_plans.get((k, horizon))
        if plan is None:
            plan = self._fused_plans[(k, horizon)] = self._fused_plan(k, horizon, n, m)
        self.fused_calls += 1
        self._fused_stamps[(k, horizon)] = self.fused_calls
        z, steps, x_first, u_all, x_all = plan
        x_first[...] = x0[:, None]
        u_all[...] = us.transpose(1, 2, 0)
        last = self._fused[0][-1]
        # np.dot into a C-contiguous row block: ~1 us a call here; np.matmul with out= checks the overlap of
        # out and input (same buffer) and costs ~3.5 us. The row blocks are views made once per batch size
        # (numpy 2.4: ~0.2 us per slice, as much as the products themselves on these sizes)
        dot, maximum = np.dot, np.maximum
        for layers, zt, x_next in steps:
            for mat, z_in, h, relu in layers:
                dot(mat, z_in, out=h)
                maximum(h, 0.0, out=relu)
            dot(last, zt, out=x_next)
        return x_all.transpose(2, 0, 1).copy()

    def _fused_plan(self, k: int, horizon: int, n: int, m: int) -> _FusedPlan:
        """:meth:`_rollout_fused`'s buffer ``z`` ``(T+1, R, K)`` (rows of ones filled in) and its views: per step
        t the hidden layers' ``(matrix, input rows, h rows, relu(h) rows)``, the whole block and the rows of
        ``x_{t+1}``; then the rows of ``x_0``, of all controls ``(T, m, K)`` and of all states ``(T+1, n, K)``."""
        assert self._fused is not None
        mats, blocks, ones = self._fused
        z = np.empty((horizon + 1, mats[-1].shape[1], k))
        z[:, ones] = 1.0
        steps: list[tuple[list[_FusedLayer], np.ndarray, np.ndarray]] = []
        for t in range(horizon):
            zt = z[t]
            layers: list[_FusedLayer] = [(mat, zt[i0:i1], zt[o0:o1], zt[o1:r1])
                                         for mat, (i0, i1, o0, o1, r1) in zip(mats, blocks, strict=False)]
            steps.append((layers, zt, z[t + 1, :n]))
        return z, steps, z[0, :n], z[:horizon, n : n + m], z[:, :n]

    def _fused_layout(self, lin: tuple[np.ndarray, np.ndarray] | None, n: int,
                      m: int) -> tuple[list[np.ndarray], list[tuple[int, int, int, int, int]], list[int]]:
        """:meth:`_rollout_fused`'s matrices (one per hidden layer, then the output one over the whole block),
        each hidden layer's ``(input start, input end, h start, h end = relu start, relu end)`` rows, and the
        rows that hold ones."""
        mlp = self.mlp
        assert mlp is not None
        w, b, slopes = mlp.weights, mlp.biases, mlp.slopes
        a_mat, b_mat = lin if lin is not None else (np.zeros((n, n)), np.zeros((n, m)))
        ones = [n + m]
        if len(w) == 1:  # no hidden layer: phi is affine, fold it into the base rows
            last = np.hstack((a_mat + mlp.w_x.T, b_mat + mlp.w_u.T, (b[0])[:, None]))
            return [np.ascontiguousarray(last)], [], ones
        mats: list[np.ndarray] = []
        blocks: list[tuple[int, int, int, int, int]] = []
        i0, i1 = 0, n + m + 1
        prev: np.ndarray | None = None  # the previous hidden layer's slope-split weights [a W; (1 - a) W]
        for i in range(len(w) - 1):
            d = w[i].shape[1]
            if i == 0:
                mat = np.hstack((mlp.w_x.T, mlp.w_u.T, b[0][:, None]))
            else:
                assert prev is not None
                mat = np.hstack((prev, b[i][:, None]))
            o0 = i1
            blocks.append((i0, i1, o0, o0 + d, o0 + 2 * d))
            mats.append(np.ascontiguousarray(mat))
            a = slopes[i]
            nxt = w[i + 1].T
            prev = np.hstack((a * nxt, (1.0 - a) * nxt))
            i0, i1 = o0, o0 + 2 * d
            if i < len(w) - 2:  # a ones row for the next hidden layer's bias
                ones.append(i1)
                i1 += 1
        assert prev is not None
        last = np.zeros((n, i1))
        last[:, :n], last[:, n : n + m], last[:, n + m] = a_mat, b_mat, b[-1]
        last[:, i0:i1] = prev
        mats.append(np.ascontiguousarray(last))
        return mats, blocks, ones

    def fused_jacobians(self, k: int, horizon: int, i: int, stamp: int) -> tuple[np.ndarray, np.ndarray] | None:
        """The Jacobians ``A (T, n, n)``, ``B (T, n, m)`` along sequence ``i`` of the fused :meth:`rollout_batch` of
        ``k`` sequences over ``horizon`` steps that was call number ``stamp`` (:attr:`fused_calls` right after it),
        read from the activation pattern its pre-activations left in the fused buffer (:meth:`_jac_table`): 5 numpy
        calls instead of the ~20 of :meth:`jacobians` (a forward pass and the reverse products). The values are
        :meth:`jacobians`' at that sequence's states and controls (a pre-activation within rounding of 0 may fall on
        the other side of the kink). None when that buffer has been refilled since (or never filled), or the
        network has more than :data:`JAC_TABLE_UNITS` hidden units."""
        plan = self._fused_plans.get((k, horizon))
        if plan is None or self._fused_stamps.get((k, horizon)) != stamp:
            return None
        if self._jac_tab is None:
            self._jac_tab = self._jac_table()
        if self._jac_tab is False:
            return None
        weights, tab_a, tab_b = self._jac_tab
        codes = np.dot(plan[0][:horizon, :, i] >= 0.0, weights).astype(np.intp)
        return tab_a[codes], tab_b[codes]

    def _jac_table(self) -> tuple[np.ndarray, np.ndarray, np.ndarray] | Literal[False]:
        """For :meth:`fused_jacobians`: the code weights over the fused buffer's rows ``(R,)`` (``2^j`` on hidden
        unit j's pre-activation row, 0 elsewhere: the dot with ``h >= 0`` numbers the activation pattern), and the
        Jacobians of ``f_hat + phi`` of every pattern, ``A (2^H, n, n)`` and ``B (2^H, n, m)`` (a PReLU unit with
        ``h >= 0`` passes its input, otherwise scales it by its slope, as :meth:`NumpyMLP.forward_jac`). False when
        the H hidden units exceed :data:`JAC_TABLE_UNITS`."""
        mlp = self.mlp
        assert mlp is not None and self._fused is not None
        mats, blocks, _ = self._fused
        widths = [o1 - o0 for _, _, o0, o1, _ in blocks]
        units = sum(widths)
        if units > JAC_TABLE_UNITS:
            return False
        n, m = mlp.n_x, mlp.n_u
        weights = np.zeros(mats[-1].shape[1])
        bits = (np.arange(2**units)[:, None] >> np.arange(units)) & 1  # (2^H, H): pattern c's unit j is on
        masks, j = [], 0
        for (_, _, o0, o1, _), width, slope in zip(blocks, widths, mlp.slopes, strict=False):
            weights[o0:o1] = 2.0 ** np.arange(j, j + width)
            masks.append(np.where(bits[:, j : j + width] == 1, 1.0, slope))
            j += width
        # reverse mode, as NumpyMLP._jac: W_L' M_{L-1} ... W_1' M_0 W_0' for every pattern at once
        w = mlp.weights
        g = np.broadcast_to(w[-1].T, (2**units, *w[-1].T.shape)).copy()
        for layer in range(len(w) - 2, -1, -1):
            g = (g * masks[layer][:, None, :]) @ w[layer].T
        lin = None if self.base is None else getattr(self.base, "linear", None)
        if lin is not None:
            g[:, :, :n] += lin[0]
            g[:, :, n:] += lin[1]
        return weights, np.ascontiguousarray(g[:, :, :n]), np.ascontiguousarray(g[:, :, n : n + m])

    def jacobians(self, x: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The Jacobians of :meth:`step_jac` alone (the SQP has the prediction from its rollout): with a linear
        base model (``base.linear``) neither the base step nor the network's output is computed."""
        lin = None if self.base is None else getattr(self.base, "linear", None)
        base_jac = None if self.base is None else getattr(self.base, "jacobians", None)
        if self.base is not None and lin is None and base_jac is not None:
            a, b = base_jac(x, u)
            if self.mlp is not None:
                ap, bp = self.mlp.jacobians(x, u)
                a += ap
                b += bp
            return a, b
        if self.mlp is None or (self.base is not None and lin is None):
            _, a, b = self.step_jac(x, u)
            return a, b
        ap, bp = self.mlp.jacobians(x, u)
        if lin is not None:
            ap += lin[0]
            bp += lin[1]
        return ap, bp

    def step_jac(self, x: np.ndarray, u: np.ndarray) -> Jac3:
        """Prediction and its Jacobians ``(B, n_y)``, ``(B, n_y, n_x)``, ``(B, n_y, n_u)``."""
        if self.base is None:
            assert self.mlp is not None
            return self.mlp.forward_jac(x, u)
        y, a, b = self.base.step_jac(x, u)
        if self.mlp is not None:
            yp, ap, bp = self.mlp.forward_jac(x, u)
            yp += y
            ap += a
            bp += b
            return yp, ap, bp
        return y, a, b


def rollout_steps(step1: Callable[[np.ndarray, np.ndarray], np.ndarray], x0: np.ndarray,
                  us: np.ndarray) -> np.ndarray:
    """States ``(T+1, n)`` from ``x0`` ``(n,)`` under ``us`` ``(T, m)`` by T calls of a one-sample ``step1``."""
    xs = np.empty((us.shape[0] + 1, x0.shape[0]))
    xs[0] = x0
    for t in range(us.shape[0]):
        xs[t + 1] = step1(xs[t], us[t])
    return xs


