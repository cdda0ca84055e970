"""The generic planner's prediction model: ``x' = f_hat(x, u) + phi(x, u)`` with exact Jacobians, for any robot.

* **f_hat** (:func:`make_base`): a built-in base model or a user's array-namespace form
  (:mod:`saml_ros.core.dynamics.base_forms`) is evaluated with numpy and differentiated by CasADi: its symbolic
  Jacobians are built once and evaluated for a whole batch in one call (:class:`SymbolicBase`). A user's plain torch
  function is differentiated by torch autograd (:class:`TorchBase`; exact, about ten times slower). Nobody derives
  a Jacobian by hand.
* **phi**: the learned network's frozen float64 copy (:class:`~saml_ros.core.mpc.mlp_np.NumpyMLP`: normalisation
  folded in, exact Jacobians of the PReLU network); a hot swap copies new numbers into it, nothing is rebuilt. With
  a residual bound (the guard's ``bound_residual``) phi is clipped per field and its Jacobian is zero where clipped.
* **angles**: the model is evaluated at the state with its angle fields wrapped into [-pi, pi] (what it was trained
  on) and the wrapped-off turns are added back to the prediction, so a predicted trajectory is continuous (a yaw
  past pi keeps growing) while the model sees what it saw in training. The wrap's derivative is 1 almost everywhere.

Shapes: ``x (B, n)``, ``u (B, m)`` -> ``(B, n)``; Jacobians ``(B, n, n)``, ``(B, n, m)``.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from saml_ros.core.dynamics.base_forms import CASADI, NUMPY, SCALAR, Form, Row, base_form
from saml_ros.core.dynamics.system import System
from saml_ros.core.mpc.generic.horizon import BufferedFunction, HorizonRollout, mlp_dims, mlp_numbers
from saml_ros.core.mpc.mlp_np import NumpyMLP

if TYPE_CHECKING:
    from saml_ros.core.model.network import DynamicsModel

Jac3 = tuple[np.ndarray, np.ndarray, np.ndarray]
#: sequences per call of the whole-horizon batched rollout (the SQP's line search tries 4 shorter steps at once)
HORIZON_BATCH = 4


def wrap_angle(a: np.ndarray) -> np.ndarray:
    """Angles into [-pi, pi)."""
    return (a + np.pi) % (2.0 * np.pi) - np.pi


class SymbolicBase:
    """f_hat from an array-namespace form: numpy evaluation, CasADi Jacobians (see the module docstring).

    Args:
        form: the form ``(x, u, *, dt, xp, **params) -> (B, n)``.
        params: its keyword parameters.
        n, m: state and control sizes; dt: the step (s).
        label: what it is, for /diagnostics (``built-in 'unicycle'``, ``my_pkg.dyn:f_hat``).
    """

    derivatives = "CasADi (symbolic)"

    def __init__(self, form: Form, params: dict[str, Any], n: int, m: int, dt: float, label: str) -> None:
        import casadi as ca

        self.form, self.params, self.n, self.m, self.dt, self.label = form, dict(params), n, m, float(dt), label
        xs, us = ca.SX.sym("x", n), ca.SX.sym("u", m)
        y = ca.reshape(form(xs.T, us.T, dt=self.dt, xp=CASADI, **self.params), n, 1)
        #: ``(x (n,), u (m,)) -> f_hat (n,)``, symbolic (the CasADi export and the NLP path build on it)
        self.function = ca.Function("f_hat", [xs, us], [y], ["x", "u"], ["y"])
        self._jac = ca.Function("f_hat_jac", [xs, us], [y, ca.jacobian(y, xs), ca.jacobian(y, us)])
        self._maps: dict[int, BufferedFunction] = {}
        self._horizons: dict[tuple[Any, ...], HorizonRollout] = {}
        self.scalar = self._scalar_ok()

    def _scalar_ok(self) -> bool:
        """Whether the form also runs on floats (:data:`SCALAR`) and agrees with numpy there (a probe)."""
        rng = np.random.default_rng(0)
        x, u = rng.normal(size=(1, self.n)), rng.normal(size=(1, self.m))
        try:
            got = self.step1_list(x[0].tolist(), u[0].tolist())
            return bool(np.allclose(got, self.step(x, u)[0], rtol=1e-12, atol=1e-12))
        except Exception:  # noqa: BLE001 - a form using something floats lack: numpy it is
            return False

    def step(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        return np.asarray(self.form(x, u, dt=self.dt, xp=NUMPY, **self.params), dtype=np.float64)

    def step1_list(self, x: list[float], u: list[float]) -> list[float]:
        """One next state from one state and control as floats (:data:`SCALAR`)."""
        return [float(v) for v in self.form(Row(x), Row(u), dt=self.dt, xp=SCALAR, **self.params)]

    def step_jac(self, x: np.ndarray, u: np.ndarray) -> Jac3:
        b = x.shape[0]
        fun = self._maps.get(b)
        if fun is None:
            fun = self._maps[b] = self._jac_buffer(b)
        y, jx, ju = fun(x, u)
        return y.copy(), jx.copy(), ju.copy()

    def _jac_buffer(self, b: int) -> BufferedFunction:
        """:attr:`_jac` mapped over a batch of ``b``, on numpy buffers (:class:`BufferedFunction`: no DM
        conversions); the Jacobians come out transposed per sample, i.e. in numpy's ``(b, n, n)`` C order."""
        import casadi as ca

        n, m = self.n, self.m
        xs, us = ca.SX.sym("x", n), ca.SX.sym("u", m)
        y, jx, ju = self._jac(xs, us)
        one = ca.Function("f_hat_jac_t", [xs, us], [ca.densify(y), ca.densify(jx.T), ca.densify(ju.T)])
        fun = one.map(b) if b > 1 else one
        return BufferedFunction(fun, [(b, n), (b, m)], [(b, n), (b, n, n), (b, n, m)])

    def horizon(self, T: int, angles: tuple[int, ...], dims: tuple[int, ...] | None, full: bool = False,
                compile: bool = False, members: int = 1) -> HorizonRollout:
        """The whole-horizon rollout (:class:`HorizonRollout`) for horizon ``T``, wrapped ``angles`` and a network of
        widths ``dims`` (or None; the mean of ``members`` such networks); ``full``: phi alone (no f_hat);
        ``compile``: see :class:`HorizonRollout`. Built on first use and kept (a hot swap of the network's numbers
        reuses it)."""
        key = (int(T), tuple(angles), dims, bool(full), bool(compile), int(members))
        roll = self._horizons.get(key)
        if roll is None:
            roll = self._horizons[key] = HorizonRollout(None if full else self.function, self.n, self.m, T,
                                                        angles, dims, HORIZON_BATCH, compile, members)
        return roll


class TorchBase:
    """f_hat as a plain torch function (the system's ``base_step``): evaluated under ``no_grad``, differentiated by
    torch autograd in one vectorised call per batch (each row is independent, which loading the file checked)."""

    derivatives = "torch autograd"

    def __init__(self, fn: Any, label: str) -> None:
        self.fn, self.label = fn, label

    def step(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        import torch

        with torch.no_grad():
            return self.fn(torch.from_numpy(np.ascontiguousarray(x, np.float64)),
                           torch.from_numpy(np.ascontiguousarray(u, np.float64))).numpy().astype(np.float64)

    def step_jac(self, x: np.ndarray, u: np.ndarray) -> Jac3:
        import torch
        from torch.autograd.functional import jacobian

        xt = torch.from_numpy(np.ascontiguousarray(x, np.float64))
        ut = torch.from_numpy(np.ascontiguousarray(u, np.float64))
        jx, ju = jacobian(lambda a, b: self.fn(a, b).sum(0), (xt, ut), vectorize=True)  # (n, B, n), (n, B, m)
        return self.step(x, u), jx.permute(1, 0, 2).numpy().copy(), ju.permute(1, 0, 2).numpy().copy()


def make_base(system: System) -> SymbolicBase | TorchBase:
    """f_hat of ``system`` for the planner: its array-namespace form when it has one (every built-in base model of a
    system file, a user's function taking ``xp``), else torch autograd of ``system.base_step``."""
    base = getattr(system, "base_model", None)
    n, m = system.state.size, system.control.size
    found = base_form(base) if base is not None else None
    if found is not None:
        form, params = found
        label = getattr(base, "target", None) or f"built-in {getattr(base, 'kind', '?')!r}"
        return SymbolicBase(form, params, n, m, system.dt, str(label))
    label = getattr(base, "target", None) or f"{system.name}.base_step"
    return TorchBase(system.base_step, str(label))


class SmoothMLP:
    """The network of a :class:`~saml_ros.core.mpc.mlp_np.NumpyMLP` with **exact values and rounded derivatives**:
    phi is the network's own (what the plan predicts and the robot flies is the trained model, with no offset), while
    its Jacobians are those of the network with its PReLU kinks rounded by ``eps`` (in the units of the
    pre-activations, which the folded input normalisation makes order 1): ``act'(h) = 0.5 (1 + a) + 0.5 (1 - a) h /
    sqrt(h^2 + eps^2)``. Smooth Jacobians let the Gauss-Newton SQP converge where the exact kinks make it zig-zag.

    Rounding the values too (``act(h) = 0.5 (1 + a) h + 0.5 (1 - a) sqrt(h^2 + eps^2)``, what this planner did before)
    shifts every unit up by as much as ``0.5 (1 - a) eps``: at the diff-drive's dock with ``eps = 0.2`` it moved the
    model's one-step bias in v from 1.3 to 5.3 mm/s and in yaw from -0.12 to +0.30 mrad per step
    (``examples/diff_drive/evaluate.py --diagnose --rounds 1``). Same interface."""

    def __init__(self, mlp: NumpyMLP, eps: float) -> None:
        self.mlp, self.eps2 = mlp, float(eps) ** 2
        self.w_x, self.w_u, self.weights, self.biases, self.slopes = mlp.w_x, mlp.w_u, mlp.weights, mlp.biases, mlp.slopes
        self._wt = [np.ascontiguousarray(w.T) for w in mlp.weights]
        self._wxt, self._wut = np.ascontiguousarray(mlp.w_x.T), np.ascontiguousarray(mlp.w_u.T)

    def forward(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """The exact network's phi (:meth:`NumpyMLP.forward`)."""
        return self.mlp.forward(x, u)

    def forward_jac(self, x: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The exact phi and the rounded network's Jacobians ``(B, n_y)``, ``(B, n_y, n_x)``, ``(B, n_y, n_u)``."""
        h = np.dot(x, self.w_x) + np.dot(u, self.w_u) + self.biases[0]
        grads = []
        for i in range(1, len(self.weights)):
            a = self.slopes[i - 1]
            grads.append(0.5 * (1 + a) + 0.5 * (1 - a) * h / np.sqrt(h * h + self.eps2))
            h = np.dot(np.where(h >= 0.0, h, a * h), self.weights[i]) + self.biases[i]
        g = self._wt[-1] * grads[-1][:, None, :]
        for i in range(len(self.weights) - 2, 0, -1):
            g = np.dot(g, self._wt[i]) * grads[i - 1][:, None, :]
        return h, np.dot(g, self._wxt), np.dot(g, self._wut)


class EnsembleMeanMLP:
    """The **mean of an ensemble's members** as one network: ``phi(x, u) = (1/E) sum_e phi_e(x, u)`` and its
    Jacobians (the mean of the members'), the members evaluated together in stacked matrix products. Planning the
    mean averages out the members' idiosyncratic errors (each member's own bias, which a planner would exploit
    over its horizon). ``smoothing`` (``eps``, > 0): each member's Jacobians with its PReLU kinks rounded as
    :class:`SmoothMLP` does (values exact). :meth:`members_jac` gives every member's phi and Jacobians (the
    planner's disagreement cost). Same interface as :class:`~saml_ros.core.mpc.mlp_np.NumpyMLP` for the planner.

    Shapes: ``x (B, n_x)``, ``u (B, n_u)`` -> ``(B, n_y)``; members ``(E, B, n_y)``, ``(E, B, n_y, n_x)``, ...
    """

    def __init__(self, model: DynamicsModel, smoothing: float = 0.0) -> None:
        self.members = [NumpyMLP(model, i) for i in range(model.n_models)]
        first = self.members[0]
        self.n_models = len(self.members)
        self.n_x, self.n_u, self.n_y = first.n_x, first.n_u, first.n_y
        self.eps2 = float(smoothing) ** 2
        ms = self.members
        self.w_x = np.stack([m.w_x for m in ms])  # (E, n_x, d)
        self.w_u = np.stack([m.w_u for m in ms])
        self.weights = [np.stack([m.weights[i] for m in ms]) for i in range(len(first.weights))]  # [0]: unused
        self.biases = [np.stack([m.biases[i] for m in ms])[:, None, :] for i in range(len(first.biases))]
        self.slopes = np.array([m.slopes for m in ms], dtype=np.float64).reshape(self.n_models, -1)  # (E, L-1)
        self._wt = [np.ascontiguousarray(np.swapaxes(w, 1, 2))[:, None] for w in self.weights]  # (E, 1, d', d)
        self._wxt = np.ascontiguousarray(np.swapaxes(self.w_x, 1, 2))[:, None]  # (E, 1, d, n_x)
        self._wut = np.ascontiguousarray(np.swapaxes(self.w_u, 1, 2))[:, None]

    def members_forward(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """Every member's phi ``(E, B, n_y)`` (or ``(E, n_y)`` for one sample)."""
        single = np.ndim(x) == 1
        h = np.matmul(np.atleast_2d(x), self.w_x) + np.matmul(np.atleast_2d(u), self.w_u) + self.biases[0]
        for i in range(1, len(self.weights)):
            a = self.slopes[:, i - 1][:, None, None]
            h = np.matmul(np.where(h >= 0.0, h, a * h), self.weights[i]) + self.biases[i]
        return h[:, 0] if single else h

    def forward(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """The members' mean phi: ``(B, n_y)``, or ``(n_y,)`` for one sample."""
        return self.members_forward(x, u).mean(0)

    def members_jac(self, x: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Every member's phi and Jacobians: ``(E, B, n_y)``, ``(E, B, n_y, n_x)``, ``(E, B, n_y, n_u)``."""
        h = np.matmul(x, self.w_x) + np.matmul(u, self.w_u) + self.biases[0]  # (E, B, d)
        grads = []
        for i in range(1, len(self.weights)):
            a = self.slopes[:, i - 1][:, None, None]
            if self.eps2 > 0:
                grads.append(0.5 * (1 + a) + 0.5 * (1 - a) * h / np.sqrt(h * h + self.eps2))
            else:
                grads.append(np.where(h >= 0.0, 1.0, a))
            h = np.matmul(np.where(h >= 0.0, h, a * h), self.weights[i]) + self.biases[i]
        g = self._wt[-1] * grads[-1][:, :, None, :]  # (E, B, n_y, d_{L-1})
        for i in range(len(self.weights) - 2, 0, -1):
            g = np.matmul(g, self._wt[i]) * grads[i - 1][:, :, None, :]
        return h, np.matmul(g, self._wxt), np.matmul(g, self._wut)

    def forward_jac(self, x: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The mean phi and its Jacobians ``(B, n_y)``, ``(B, n_y, n_x)``, ``(B, n_y, n_u)``."""
        h, jx, ju = self.members_jac(x, u)
        return h.mean(0), jx.mean(0), ju.mean(0)


class GenericDynamics:
    """``f_hat + phi`` (``kind`` ``"residual"``), ``phi`` alone (``"full"``) or ``f_hat`` alone (``"base"``, no model);
    see the module docstring.

    Args:
        system: the robot (its ``angle_indices`` are wrapped).
        base: f_hat (:func:`make_base`); also used for ``"full"`` models only as a label.
        model: the learned model, or None.
        member: the ensemble member planned with.
        bound: per-field residual bound ``(n,)`` (phi clipped to +-bound), or None.
        smoothing: the network's Jacobians with its PReLU kinks rounded by this (:class:`SmoothMLP`: its values
            stay exact; 0 = the exact Jacobians).
        ensemble_mean: plan with the mean of all the ensemble's members (:class:`EnsembleMeanMLP`; ``member`` is
            then unused); a model of one member is planned as itself.
        with_members: keep the members of an ensemble at hand for :meth:`deviations` (the planner's disagreement
            cost) also when one member is planned.
    """

    def __init__(self, system: System, base: SymbolicBase | TorchBase, model: DynamicsModel | None = None,
                 member: int = 0, bound: np.ndarray | None = None, smoothing: float = 0.0,
                 compile: bool = False, ensemble_mean: bool = False, with_members: bool = False) -> None:
        self.system = system
        self.compile = bool(compile)
        self.base = base
        self.kind = "base" if model is None else model.kind
        mlp: Any = None
        #: the ensemble's members (None: a model of one member, or neither planned by their mean nor asked for)
        self.ensemble: EnsembleMeanMLP | None = None
        if model is not None and model.n_models > 1 and (ensemble_mean or with_members):
            self.ensemble = EnsembleMeanMLP(model, smoothing)
        if self.ensemble is not None and ensemble_mean:
            mlp = self.ensemble
        elif model is not None:
            mlp = NumpyMLP(model, member)
            if smoothing > 0:
                mlp = SmoothMLP(mlp, smoothing)
        self.mlp = mlp
        self.smoothing = float(smoothing) if mlp is not None else 0.0
        self.bound = None if bound is None or self.mlp is None else np.asarray(bound, dtype=np.float64)
        self.angles = np.asarray(getattr(system, "angle_indices", ()), dtype=int)
        # the whole-horizon rollouts in CasADi (one call per sequence, no Python per step) where f_hat has a
        # symbolic form; the network's numbers (exact values) go in as a parameter vector
        self._horizon_ok = isinstance(base, SymbolicBase)
        plain = mlp.mlp if isinstance(mlp, SmoothMLP) else mlp
        nets = plain.members if isinstance(plain, EnsembleMeanMLP) else [] if plain is None else [plain]
        self._members = max(len(nets), 1)
        self._dims = None if not nets else mlp_dims(nets[0])
        self._theta = None if not nets else np.concatenate([mlp_numbers(net) for net in nets])
        self._last_horizon: HorizonRollout | None = None
        self._angle_key = tuple(int(i) for i in self.angles)

    def _wrap(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        if not self.angles.size:
            return x, None
        xw = x.copy()
        xw[..., self.angles] = wrap_angle(x[..., self.angles])
        return xw, x[..., self.angles] - xw[..., self.angles]

    def _phi(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        assert self.mlp is not None
        phi = self.mlp.forward(x, u)
        return phi if self.bound is None else np.clip(phi, -self.bound, self.bound)

    def step(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """Next states ``(B, n)``."""
        xw, turns = self._wrap(np.asarray(x, dtype=np.float64))
        u = np.asarray(u, dtype=np.float64)
        if self.kind == "full":
            y = self._phi(xw, u)
        else:
            y = self.base.step(xw, u)
            if self.mlp is not None:
                y = y + self._phi(xw, u)
        if turns is not None:
            y[..., self.angles] += turns
        return y

    def step1(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """One next state ``(n,)`` from ``(n,), (m,)``."""
        return self.step(np.asarray(x, dtype=np.float64)[None], np.asarray(u, dtype=np.float64)[None])[0]

    def step_jac(self, x: np.ndarray, u: np.ndarray) -> Jac3:
        """Next states and the exact Jacobians ``(B, n), (B, n, n), (B, n, m)``."""
        xw, turns = self._wrap(np.asarray(x, dtype=np.float64))
        u = np.asarray(u, dtype=np.float64)
        b, n, m = xw.shape[0], xw.shape[1], u.shape[1]
        if self.kind == "full":
            y, a, bm = np.zeros((b, n)), np.zeros((b, n, n)), np.zeros((b, n, m))
        else:
            y, a, bm = self.base.step_jac(xw, u)
        if self.mlp is not None:
            phi, px, pu = self.mlp.forward_jac(xw, u)
            if self.bound is not None:
                keep = (np.abs(phi) < self.bound)[:, :, None]
                phi, px, pu = np.clip(phi, -self.bound, self.bound), px * keep, pu * keep
            y, a, bm = y + phi, a + px, bm + pu
        if turns is not None:
            y[:, self.angles] += turns
        return y, a, bm

    def _horizon(self, T: int) -> HorizonRollout | None:
        if not self._horizon_ok:
            return None
        assert isinstance(self.base, SymbolicBase)
        roll = self.base.horizon(T, self._angle_key, self._dims, self.kind == "full", self.compile, self._members)
        if roll.owner is not self:  # the rollout is shared with the dynamics of other models: write ours in
            roll.set_model(self._theta, self.bound)
            roll.owner = self
        self._last_horizon = roll
        return roll

    def prepare(self, T: int) -> None:
        """Build (and with ``compile``, compile or load) the whole-horizon functions for horizon ``T`` now, not in
        the first solve."""
        self._horizon(T)

    def sensitivities(self, xs: np.ndarray, us: np.ndarray) -> np.ndarray | None:
        """``S (T, n, T m)``, ``S[t] = d x_{t+1} / d U``, along a plan's states ``xs (T, n)`` (x_0 .. x_{T-1}) and
        controls ``us (T, m)`` in one call where the horizon has that function (``compile``), else
        None (the caller condenses :meth:`step_jac`; always with ``smoothing``)."""
        if self.smoothing > 0:  # the planner rounds the network's Jacobians: its numpy copy does that
            return None
        roll = self._horizon(us.shape[0])
        return None if roll is None else roll.sensitivities(xs, us)

    def rollout(self, x0: np.ndarray, us: np.ndarray) -> np.ndarray:
        """Predicted states ``(T+1, n)`` from ``x0 (n,)`` under ``us (T, m)``: one CasADi call for the whole
        horizon where f_hat has a symbolic form (:class:`HorizonRollout`), else step by step (on floats where
        f_hat's form runs on floats)."""
        us = np.asarray(us, dtype=np.float64)
        roll = self._horizon(us.shape[0])
        if roll is not None:
            return roll.rollout(np.asarray(x0, dtype=np.float64), us)
        xs = np.empty((us.shape[0] + 1, x0.shape[0]))
        xs[0] = x0
        if not getattr(self.base, "scalar", False) or self.kind == "full":
            for t in range(us.shape[0]):
                xs[t + 1] = self.step(xs[t][None], us[t][None])[0]
            return xs
        base, mlp, bound = self.base, self.mlp, self.bound
        assert isinstance(base, SymbolicBase)
        angles = [int(i) for i in self.angles]
        two_pi = 2.0 * np.pi
        xl = [float(v) for v in x0]
        ul = us.tolist()
        for t in range(us.shape[0]):
            turns = []
            for i in angles:
                w = (xl[i] + np.pi) % two_pi - np.pi
                turns.append(xl[i] - w)
                xl[i] = w
            y = base.step1_list(xl, ul[t])
            if mlp is not None:
                phi = mlp.forward(np.array(xl), us[t])
                if bound is not None:
                    phi = np.clip(phi, -bound, bound)
                y = [a + b for a, b in zip(y, phi.tolist(), strict=True)]
            for i, turn in zip(angles, turns, strict=True):
                y[i] += turn
            xs[t + 1] = y
            xl = y
        return xs

    def rollout_batch(self, x0: np.ndarray, us: np.ndarray) -> np.ndarray:
        """Predicted states ``(K, T+1, n)`` of ``K`` control sequences ``us (K, T, m)`` from ``x0 (n,)``: one batched
        step per time step (as cheap for a few sequences as for one)."""
        k, horizon = us.shape[0], us.shape[1]
        roll = self._horizon(horizon)
        if roll is not None:
            return roll.rollout_batch(np.asarray(x0, dtype=np.float64), np.asarray(us, dtype=np.float64))
        xs = np.empty((k, horizon + 1, x0.shape[0]))
        xs[:, 0] = x0
        for t in range(horizon):
            xs[:, t + 1] = self.step(xs[:, t], us[:, t])
        return xs

    def deviations(self, xs: np.ndarray, us: np.ndarray) -> np.ndarray | None:
        """Each member's phi minus the members' mean at states ``xs (B, n)`` and controls ``us (B, m)`` (angle
        fields wrapped as the model sees them, unclipped): ``(E, B, n)``; None without :attr:`ensemble`."""
        if self.ensemble is None:
            return None
        xw, _ = self._wrap(np.asarray(xs, dtype=np.float64))
        phi = self.ensemble.members_forward(xw, np.asarray(us, dtype=np.float64))
        return phi - phi.mean(0, keepdims=True)

    def deviations_jac(self, xs: np.ndarray, us: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """:meth:`deviations` and their Jacobians ``(E, B, n)``, ``(E, B, n, n)``, ``(E, B, n, m)`` (with
        ``smoothing``, the members' kinks rounded as the planner's model's are); None without :attr:`ensemble`."""
        if self.ensemble is None:
            return None
        xw, _ = self._wrap(np.asarray(xs, dtype=np.float64))
        phi, jx, ju = self.ensemble.members_jac(xw, np.asarray(us, dtype=np.float64))
        return (phi - phi.mean(0, keepdims=True), jx - jx.mean(0, keepdims=True), ju - ju.mean(0, keepdims=True))

    def clipped(self, xs: np.ndarray, us: np.ndarray) -> bool:
        """Whether the residual bound clips phi anywhere along states ``xs (T, n)`` and controls ``us (T, m)``."""
        if self.bound is None or self.mlp is None:
            return False
        xw, _ = self._wrap(np.asarray(xs, dtype=np.float64))
        return bool(np.any(np.abs(self.mlp.forward(xw, np.asarray(us, dtype=np.float64))) >= self.bound))

    def describe(self) -> str:
        """Which f_hat and phi this is and how they are differentiated (for /diagnostics)."""
        phi = {"base": "no phi (f_hat alone)", "residual": "phi: numpy PReLU network (exact Jacobians)",
               "full": "phi alone (full model), numpy PReLU network"}[self.kind]
        if isinstance(self.mlp, EnsembleMeanMLP):
            phi += f", the mean of the ensemble's {self.mlp.n_models} members"
        bound = ", phi clipped to the residual bound" if self.bound is not None else ""
        if self.smoothing > 0:
            bound += f", its Jacobians with the PReLU kinks rounded by {self.smoothing:g}"
        out = f"f_hat {self.base.label} ({self.base.derivatives} derivatives); {phi}{bound}"
        roll = self._last_horizon
        if roll is not None:
            out += ("; whole-horizon rollouts and sensitivities compiled to C (CasADi)" if roll.compiled is None
                    else f"; whole-horizon rollouts in CasADi's virtual machine ({roll.compiled})")
        return out
