"""Flat storage for the fast engine: every weight, bias and PReLU slope of an ensemble in one contiguous tensor
(:class:`FlatNet`), and ``torch.optim``'s Adam / SGD as a few element-wise operations on such a tensor
(:class:`FlatOptimizer`), with its state moved to and from the torch optimizer so engines can be mixed.

:func:`merged_dual_scale` says when the dual Adam can ride in the primal flat tensor (see docs/performance.md).
Shapes: ``E`` ensemble members.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

from saml_ros.core.model.network import EnsembleMLP
from saml_ros.core.training.nupi import nupi_update


class FlatOptimizer:
    """The state of one ``torch.optim`` Adam or SGD optimizer, over one flat tensor ``param``.

    Maximizing (the dual ascent) keeps the *negated* first moment: ``lerp`` and ``addcdiv`` commute exactly
    with negation, so ascent costs no extra operation. State moves to and from the ``torch.optim`` optimizer
    with :meth:`load` / :meth:`store`; ``views(buf)`` gives one view of a flat buffer per optimizer parameter.
    """

    def __init__(self, opt: torch.optim.Optimizer, param: Tensor, maximize: bool) -> None:
        g = opt.param_groups[0]
        self.kind = "adam" if type(opt) is torch.optim.Adam else "sgd"
        self.lr = float(g["lr"])
        self.maximize = maximize
        self.param = param
        self.step_count = 0
        self.beta1, self.beta2, self.eps = 0.0, 0.0, 0.0
        self.m = self.v = param
        if self.kind == "adam":
            self.beta1, self.beta2 = (float(b) for b in g["betas"])
            self.eps = float(g["eps"])
            self.m = torch.zeros_like(param, memory_format=torch.contiguous_format)
            self.v = torch.zeros_like(param, memory_format=torch.contiguous_format)

    def load(self, opt: torch.optim.Optimizer, views: Callable[[Tensor], list[Tensor]]) -> None:
        if self.kind != "adam":
            return
        states = [opt.state.get(p, {}) for p in opt.param_groups[0]["params"]]
        self.m.zero_()
        self.v.zero_()
        self.step_count = 0
        if not any("step" in s for s in states):
            return
        steps = {int(float(s["step"])) for s in states}
        if len(steps) != 1:
            raise RuntimeError("optimizer parameters disagree on the step count")
        self.step_count = steps.pop()
        sign = -1.0 if self.maximize else 1.0
        for s, vm, vv in zip(states, views(self.m), views(self.v)):
            vm.copy_(s["exp_avg"].reshape(vm.shape)).mul_(sign)
            vv.copy_(s["exp_avg_sq"].reshape(vv.shape))

    def store(self, opt: torch.optim.Optimizer, views: Callable[[Tensor], list[Tensor]]) -> None:
        if self.kind != "adam" or self.step_count == 0:
            return
        sign = -1.0 if self.maximize else 1.0
        for p, vm, vv in zip(opt.param_groups[0]["params"], views(self.m), views(self.v)):
            opt.state[p] = {
                "step": torch.tensor(float(self.step_count), dtype=torch.float32),
                "exp_avg": (vm * sign).reshape(p.shape).clone(),
                "exp_avg_sq": vv.reshape(p.shape).clone(),
            }

    def scalars(self) -> tuple[float, float]:
        """Advance the step count; return ``(step size, sqrt of the second-moment bias correction)``."""
        self.step_count += 1
        bc1 = 1 - self.beta1**self.step_count
        bc2 = 1 - self.beta2**self.step_count
        step_size = (self.lr / bc1) * -1  # torch.optim's expression, for identical rounding
        return (-step_size if self.maximize else step_size), bc2**0.5

    def step(self, grad: Tensor) -> None:
        """One update of :attr:`param` with ``grad`` (the ascent direction when maximizing)."""
        p = self.param
        if self.kind == "sgd":
            p.add_(grad, alpha=self.lr if self.maximize else -self.lr)
            return
        step_size, bc2_sqrt = self.scalars()
        self.m.lerp_(grad, 1 - self.beta1)
        self.v.mul_(self.beta2).addcmul_(grad, grad, value=1 - self.beta2)
        # lr / bc1 * m / (sqrt(v) / sqrt(bc2) + eps), with sqrt(bc2) moved out of the denominator (one op less)
        den = torch.sqrt(self.v).add_(self.eps * bc2_sqrt)
        p.addcdiv_(self.m, den, value=step_size * bc2_sqrt)


class FlatNuPI:
    """The state of a :class:`~saml_ros.core.training.nupi.NuPI` optimizer over one tensor ``param`` (lambda),
    moved to and from the torch optimizer with :meth:`load` / :meth:`store`; :meth:`step` is its update."""

    def __init__(self, opt: torch.optim.Optimizer, param: Tensor) -> None:
        g = opt.param_groups[0]
        self.lr, self.kp, self.nu = float(g["lr"]), float(g["kp"]), float(g["nu"])
        self.param = param
        self.xi: Tensor | None = None
        self.step_count = 0

    def load(self, opt: torch.optim.Optimizer) -> None:
        st = opt.state.get(opt.param_groups[0]["params"][0], {})
        self.xi = st["xi"].clone() if "xi" in st else None
        self.step_count = int(float(st.get("step", 0)))

    def store(self, opt: torch.optim.Optimizer) -> None:
        if self.xi is None:
            return
        opt.state[opt.param_groups[0]["params"][0]] = {
            "xi": self.xi.clone(), "step": torch.tensor(float(self.step_count))}

    def step(self, error: Tensor) -> None:
        """One ascending nuPI update of :attr:`param` with ``error``."""
        self.xi = nupi_update(self.param, error, self.xi, self.lr, self.kp, self.nu, maximize=True)
        self.step_count += 1


def merged_dual_scale(primal: torch.optim.Optimizer, dual: torch.optim.Optimizer,
                      base_lrs: tuple[float, float] | None = None) -> float | None:
    """``-dual_lr / primal_lr`` when the dual Adam can ride in the primal Adam's flat tensor, else ``None``.

    ``base_lrs``: ``(primal, dual)`` starting rates of learning-rate schedules that scale both alike (the ratio
    is theirs; the optimizers' current rates are the schedule's of some update).

    Adam's update of a parameter is ``lr * m / (sqrt(v) + eps)`` with moments of its gradient, so lambda's
    update equals the primal lr's update of ``u = lambda / k`` with ``k = -dual_lr / primal_lr`` and gradient
    ``g`` (the minus sign turns descent on u into ascent on lambda; ``lambda >= 0`` is ``u <= 0``). This needs
    the same betas, eps and step count, which the trainer's optimizers have
    (both created together and stepped together).
    """
    if type(primal) is not torch.optim.Adam or type(dual) is not torch.optim.Adam:
        return None
    gp, gd = primal.param_groups[0], dual.param_groups[0]
    lr_p, lr_d = (float(gp["lr"]), float(gd["lr"])) if base_lrs is None else base_lrs
    if tuple(gp["betas"]) != tuple(gd["betas"]) or gp["eps"] != gd["eps"] or not (lr_d > 0 and lr_p > 0):
        return None

    def steps(opt: torch.optim.Optimizer) -> set[int]:
        return {int(float(opt.state[p]["step"])) if "step" in opt.state.get(p, {}) else 0
                for p in opt.param_groups[0]["params"]}

    if len(steps(primal) | steps(dual)) != 1:
        return None
    return -lr_d / lr_p


class FlatNet:
    """The ensemble's parameters in one flat tensor ``flat`` (gradients in ``grad``, same layout).

    Layer ``i`` is ``w[i]`` ``(E, d_in + 1, d_out)`` (its last row is the bias); the PReLU slopes of all hidden
    layers follow, ``slopes`` ``(L - 1, E)``, so one operation negates them all; then ``n_extra`` slots per
    member (``extra`` ``(E, n_extra)``: the scaled dual variables when the dual Adam is merged in).
    """

    def __init__(self, net: EnsembleMLP, dtype: torch.dtype, n_extra: int = 0) -> None:
        self.net = net
        e = net.n_models
        self.dims = [net.in_dim, *net.hidden, net.out_dim]
        self.n_layers = len(self.dims) - 1
        self.w_offsets = []
        total = 0
        for a, b in zip(self.dims[:-1], self.dims[1:]):
            self.w_offsets.append(total)
            total += e * (a + 1) * b
        self.s_offset = total
        total += e * (self.n_layers - 1)
        self.x_offset = total
        self.n_extra = n_extra
        total += e * n_extra
        self.size = total
        self.flat = torch.zeros(total, dtype=dtype)
        self.grad = torch.zeros(total, dtype=dtype)
        self.w, self.slopes = self._views(self.flat)
        self.gw, self.gslopes = self._views(self.grad)
        self.extra, self.gextra = self.extra_view(self.flat), self.extra_view(self.grad)
        self.params = list(net.parameters())
        names = {id(q): n for n, q in net.named_parameters()}
        kinds = {"weights": "w", "biases": "b", "slopes": "s"}
        self._index = [(kinds[names[id(p)].split(".")[0]], int(names[id(p)].split(".")[1])) for p in self.params]

    def _views(self, buf: Tensor) -> tuple[list[Tensor], Tensor]:
        e = self.net.n_models
        ws = [
            buf[o : o + e * (a + 1) * b].view(e, a + 1, b)
            for o, a, b in zip(self.w_offsets, self.dims[:-1], self.dims[1:])
        ]
        return ws, buf[self.s_offset : self.x_offset].view(self.n_layers - 1, e)

    def extra_view(self, buf: Tensor) -> Tensor:
        return buf[self.x_offset :].view(self.net.n_models, self.n_extra)

    def views(self, buf: Tensor) -> list[Tensor]:
        """One view of flat buffer ``buf`` per network parameter, shaped like the parameter."""
        ws, ss = self._views(buf)
        out = []
        for kind, i in self._index:
            a = self.dims[i]
            out.append(ws[i][:, :a] if kind == "w" else ws[i][:, a:] if kind == "b" else ss[i].view(-1, 1, 1))
        return out

    @torch.no_grad()
    def load(self) -> None:
        for p, v in zip(self.params, self.views(self.flat)):
            v.copy_(p)

    @torch.no_grad()
    def store(self) -> None:
        for p, v in zip(self.params, self.views(self.flat)):
            p.copy_(v)
