"""A frozen float64 numpy copy of one member of a :class:`~saml_ros.core.model.network.DynamicsModel`'s network.

The MPC evaluates the learned correction phi(x, u) thousands of times per second on batches of 1-40 samples,
where PyTorch's per-call overhead (several microseconds per op) would dominate. This copy folds the input
normalisation into the first layer and the output scale into the last, and returns exact Jacobians of the
piecewise-linear PReLU network (the derivative at a kink is taken from the ``h >= 0`` side, as PyTorch does).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # a model exists (and torch is imported) where one is copied
    from saml_ros.core.model.network import DynamicsModel


class NumpyMLP:
    """phi(x, u) of ensemble member ``member`` of ``model``, frozen at construction time.

    Shapes: ``x`` ``(B, n_x)``, ``u`` ``(B, n_u)`` -> ``(B, n_y)``; Jacobians ``(B, n_y, n_x)`` and ``(B, n_y, n_u)``.
    """

    _wt: list[np.ndarray] | None = None  # transposed weights for :meth:`jac_u1`, made on first use
    #: transposed weights for :meth:`forward_jac` (all layers, and W_x', W_u'), made on first use
    _jt: tuple[list[np.ndarray], np.ndarray, np.ndarray] | None = None

    def __init__(self, model: DynamicsModel, member: int = 0) -> None:
        if not 0 <= member < model.n_models:
            raise ValueError(f"member {member} out of range for an ensemble of {model.n_models}")
        import torch

        from saml_ros.core.model.network import dense_input_layer

        net = model.net
        n_x = model.system.state.size
        with torch.no_grad():
            ws = [w[member].double().numpy().copy() for w in net.weights]
            bs = [b[member, 0].double().numpy().copy() for b in net.biases]
            self.slopes = [float(s[member].item()) for s in net.slopes]
            mean, std, ws[0] = dense_input_layer(model, member)  # every [x, u] field (zero rows: not seen)
            ostd = model.out_std[member, 0].double().numpy()
        # ((z - mean) / std) @ W0 + b0 == z @ (W0 / std) + (b0 - (mean / std) @ W0)
        w0 = ws[0] / std[:, None]
        bs[0] = bs[0] - (mean / std) @ ws[0]
        ws[0] = w0
        ws[-1] = ws[-1] * ostd[None, :]
        bs[-1] = bs[-1] * ostd
        self.w_x = np.ascontiguousarray(ws[0][:n_x])
        self.w_u = np.ascontiguousarray(ws[0][n_x:])
        self.weights = ws
        self.biases = bs
        self.n_x, self.n_u, self.n_y = n_x, ws[0].shape[0] - n_x, ws[-1].shape[1]
        # max(h, a h) == PReLU(h) exactly when 0 <= a <= 1, and is one numpy call instead of three
        self._max_ok = [0.0 <= a <= 1.0 for a in self.slopes]

    def _act(self, h: np.ndarray, i: int) -> np.ndarray:
        a = self.slopes[i]
        if self._max_ok[i]:
            return np.maximum(h, a * h)
        return np.where(h >= 0.0, h, a * h)

    def forward(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """phi(x, u): ``(B, n_x), (B, n_u) -> (B, n_y)``, or one sample ``(n_x,), (n_u,) -> (n_y,)``."""
        n, dot = len(self.weights), np.dot  # np.dot: 1-2.5 us less a call than @ on these sizes (numpy 2.4)
        h = dot(x, self.w_x)
        h += dot(u, self.w_u)
        h += self.biases[0]
        for i in range(1, n):
            h = dot(self._act(h, i - 1), self.weights[i])
            h += self.biases[i]
        return h

    def forward_jac(self, x: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """phi and its Jacobians: ``(B, n_y)``, ``(B, n_y, n_x)``, ``(B, n_y, n_u)``.

        Reverse mode from the output, ``W_L' M_{L-1} ... W_1' M_0 W_0'`` with ``M_i`` the diagonal PReLU
        derivatives: the Jacobians come out in their final layout (no transpose of a broadcast copy)."""
        h, ja, jb = self._jac(x, u, True)
        assert h is not None
        return h, ja, jb

    def jacobians(self, x: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The Jacobians of :meth:`forward_jac` without phi itself (skips the last layer's forward product)."""
        _, ja, jb = self._jac(x, u, False)
        return ja, jb

    def _jac(self, x: np.ndarray, u: np.ndarray, want_y: bool) -> tuple[np.ndarray | None, np.ndarray, np.ndarray]:
        if self._jt is None:
            self._jt = ([np.ascontiguousarray(w.T) for w in self.weights],
                        np.ascontiguousarray(self.w_x.T), np.ascontiguousarray(self.w_u.T))  # fmt: skip
        wt, wxt, wut = self._jt
        n = len(self.weights)
        dot = np.dot
        h = dot(x, self.w_x)
        h += dot(u, self.w_u)
        h += self.biases[0]
        if n == 1:  # affine: constant Jacobians
            bsz = x.shape[0]
            return h, np.broadcast_to(wxt, (bsz, *wxt.shape)).copy(), np.broadcast_to(wut, (bsz, *wut.shape)).copy()
        masks = []
        for i in range(1, n):
            mask = np.where(h >= 0.0, 1.0, self.slopes[i - 1])
            masks.append(mask)
            if i < n - 1 or want_y:
                h *= mask
                h = dot(h, self.weights[i])
                h += self.biases[i]
        g = wt[-1] * masks[-1][:, None, :]  # (B, n_y, d_{L-1})
        for i in range(n - 2, 0, -1):
            g = dot(g, wt[i])
            g *= masks[i - 1][:, None, :]
        return (h if want_y else None), dot(g, wxt), dot(g, wut)

    def state_part(self, x: np.ndarray) -> np.ndarray:
        """The first layer's pre-activation from the state alone, ``x @ W_x + b_0`` ``(d,)``, for
        :meth:`forward_pre1` when many controls are tried at one state."""
        return np.dot(x, self.w_x) + self.biases[0]

    def forward_pre1(self, x: np.ndarray, u: np.ndarray,
                     x_part: np.ndarray | None = None) -> tuple[np.ndarray, list[np.ndarray]]:
        """phi for one sample ``(n_x,), (n_u,) -> (n_y,)`` and the hidden layers' pre-activations, from which
        :meth:`jac_u1` takes the Jacobian (so that a trial point whose Jacobian turns out not to be needed costs
        one forward pass). ``x_part``: :meth:`state_part` of ``x``, if already known."""
        dot = np.dot
        h = (dot(x, self.w_x) + self.biases[0] if x_part is None else x_part) + dot(u, self.w_u)
        pre = [h]
        for i in range(1, len(self.weights)):
            a = self.slopes[i - 1]
            h = dot(np.maximum(h, a * h) if self._max_ok[i - 1] else np.where(h >= 0.0, h, a * h), self.weights[i])
            h += self.biases[i]
            pre.append(h)
        pre.pop()
        return h, pre

    def jac_u1(self, pre: list[np.ndarray]) -> np.ndarray:
        """``d phi / d u`` ``(n_y, n_u)`` at the sample whose pre-activations :meth:`forward_pre1` returned (reverse
        mode; the PReLU derivative at a kink is taken from the ``h >= 0`` side, as in :meth:`forward_jac`)."""
        if self._wt is None:  # transposed copies for the reverse pass, made on first use
            self._wt = [np.ascontiguousarray(w.T) for w in self.weights[1:]]
            self._wt.insert(0, np.ascontiguousarray(self.w_u.T))
        n = len(self.weights)
        g = self._wt[-1] * np.where(pre[-1] >= 0.0, 1.0, self.slopes[n - 2])
        for i in range(n - 2, 0, -1):
            g = np.dot(g, self._wt[i]) * np.where(pre[i - 1] >= 0.0, 1.0, self.slopes[i - 1])
        return np.dot(g, self._wt[0])
