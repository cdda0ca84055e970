"""Fast engine for :meth:`PrimalDualTrainer.fit`: the same Algorithm 1, without autograd and optimizer overhead.

At the paper's batch and network sizes (a 16-8 net needs ~3 kFLOP per sample) a plain PyTorch step is almost
all Python and dispatcher overhead: ~40 autograd nodes, per-parameter optimizer bookkeeping, small allocations.
This engine computes the same step with ~43 tensor operations in all (docs/performance.md has the profiles):

* **hand-written forward/backward** for :class:`EnsembleMLP`. Each layer's bias is stored as an extra weight row
  and every activation carries a column of ones, so one ``bmm`` gives the pre-activation and one ``bmm`` gives
  the weight *and* bias gradient. PReLU keeps its derivative ``d = where(a >= 0, 1, slope)`` from the forward
  pass, computed as ``prelu(copysign(1, a), -slope)`` (the plain model's tie rule ``a >= 0`` included; only a
  pre-activation of exactly -0.0, which a sum with a nonzero bias cannot produce, is treated as negative).
* **flat parameters**: all weights, biases and slopes of all members live in one contiguous tensor (gradients
  and Adam moments too), so an Adam step is 6 element-wise operations whatever the depth. The dual variables
  ride in the same tensor, rescaled (see :func:`_merge_dual`), when both optimizers are Adam (the paper's).
* **closed-form loss gradients** for every spec loss (l2, squared_l2, l1, huber, normalized). Terms that share
  a loss and fields form a group; a group's minibatch estimates are one ``bmm`` of the per-sample losses
  with the precomputed region masks, and its per-sample gradient weights (objective weight 1, constraint
  weights lambda_k, divided by the estimator's denominator) are one ``bmm`` back.
* **precomputation**: normalised inputs ``[z, 1]``, ``f_hat - y``, region masks and, per minibatch, the
  estimator denominators, gathered for one or more epochs at once in the plain loop's sample order.

Equality with the plain loop: the minibatch order is drawn from the trainer's generator with the same calls
(``torch.rand(Q, E, N)`` consumes it like Q calls of ``torch.rand(E, N)``), the updates are
``torch.optim.Adam`` / ``SGD``'s, and the optimizer states are read from and written back to the trainer's
optimizers, so plain and fast ``fit`` calls can be mixed and checkpoints are unchanged. The results differ from
the plain engine by float rounding only: summation order in matmuls and reductions, the error computed as
``phi + (f_hat - y)``, Adam's ``sqrt(bias correction)`` moved out of its denominator and lambda kept as
``k * u``. ``test/test_fast_train.py`` bounds the difference (float64: 1e-8 after 240 steps).

Shapes: ``E`` ensemble members, ``B`` minibatch size, ``T = 1 + K`` spec terms (objective first).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import torch
from torch import Tensor

from saml_ros.core.models import EnsembleMLP
from saml_ros.core.spec import LOSS_TYPES, Term

if TYPE_CHECKING:
    from saml_ros.core.trainer import History, PrimalDualTrainer, Transitions

SUPPORTED_LOSSES = frozenset(LOSS_TYPES)
# Below this l2 norm the l2 / normalized loss gradient e / ||e|| is taken as 0 (PyTorch masks exactly ||e|| = 0;
# a float32 error this small cannot occur unless the error is exactly zero).
_TINY = 1e-30
# Floats gathered per chunk of epochs (at least one epoch): small enough to stay in cache (~4 MB in float32).
_CHUNK_FLOATS = 1_000_000
# PReLU forward kernel with a broadcastable weight (the public torch.prelu reshapes its weight first)
_prelu_kernel: Callable[[Tensor, Tensor], Tensor] = getattr(
    torch, "_prelu_kernel", torch.ops.aten._prelu_kernel.default
)


# ------------------------------------------------------------------------------------------------- support
def unsupported_reason(trainer: PrimalDualTrainer, data: Transitions) -> str | None:
    """Why the fast engine cannot run this trainer exactly like the plain loop, or ``None`` if it can."""
    net = trainer.model.net
    if type(net) is not EnsembleMLP:
        return f"network type {type(net).__name__} is not EnsembleMLP"
    for t in (trainer.spec.objective, *trainer.spec.constraints):
        if t.loss not in SUPPORTED_LOSSES:
            return f"loss {t.loss!r} of term {t.name!r} has no fast implementation"
        if t.mean not in ("conditional", "unconditional"):
            return f"mean {t.mean!r} of term {t.name!r} has no fast implementation"
    params = list(net.parameters())
    groups = trainer.primal_opt.param_groups
    if len(groups) != 1 or [id(p) for p in groups[0]["params"]] != [id(p) for p in params]:
        return "the primal optimizer does not hold exactly the network parameters in one group"
    why = _optimizer_reason(trainer.primal_opt, maximize=False)
    if why:
        return f"primal optimizer: {why}"
    if trainer.spec.n_constraints:
        why = _optimizer_reason(trainer.dual_opt, maximize=True)
        if why:
            return f"dual optimizer: {why}"
    dt = trainer.config.torch_dtype
    if any(p.dtype != dt for p in params) or data.x.dtype != dt:
        return "model, data and config dtypes differ"
    if any(p.requires_grad is False for p in params):
        return "some network parameters are frozen"
    if data.per_member and data.x.shape[0] != trainer.model.n_models:
        return "per-member data does not have one dataset per ensemble member"
    return None


def _optimizer_reason(opt: torch.optim.Optimizer, maximize: bool) -> str | None:
    if len(opt.param_groups) != 1:
        return "more than one parameter group"
    g = opt.param_groups[0]
    if isinstance(g["lr"], Tensor):
        return "tensor learning rate"
    if bool(g.get("maximize", False)) != maximize:
        return "unexpected maximize flag"
    if g.get("weight_decay", 0) != 0:
        return "weight decay"
    if g.get("differentiable", False) or g.get("capturable", False) or g.get("fused", False):
        return "differentiable / capturable / fused mode"
    if type(opt) is torch.optim.Adam:
        if g.get("amsgrad", False) or g.get("decoupled_weight_decay", False):
            return "amsgrad / decoupled weight decay"
        if any(isinstance(b, Tensor) for b in g["betas"]):
            return "tensor betas"
        return None
    if type(opt) is torch.optim.SGD:
        if g.get("momentum", 0) != 0 or g.get("nesterov", False):
            return "momentum"
        return None
    return f"optimizer type {type(opt).__name__}"


# ------------------------------------------------------------------------------------------------- optimizers
class _FlatOptimizer:
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


def _merge_dual(primal: torch.optim.Optimizer, dual: torch.optim.Optimizer) -> float | None:
    """``-dual_lr / primal_lr`` when the dual Adam can ride in the primal Adam's flat tensor, else ``None``.

    Adam's update of a parameter is ``lr * m / (sqrt(v) + eps)`` with moments of its gradient, so lambda's
    update equals the primal lr's update of ``u = lambda / k`` with ``k = -dual_lr / primal_lr`` and gradient
    ``g`` (the minus sign turns descent on u into ascent on lambda; ``lambda >= 0`` is ``u <= 0``). This needs
    the same betas, eps and step count, which :class:`PrimalDualTrainer`'s optimizers have.
    """
    if type(primal) is not torch.optim.Adam or type(dual) is not torch.optim.Adam:
        return None
    gp, gd = primal.param_groups[0], dual.param_groups[0]
    if tuple(gp["betas"]) != tuple(gd["betas"]) or gp["eps"] != gd["eps"] or not (gd["lr"] > 0 and gp["lr"] > 0):
        return None

    def steps(opt: torch.optim.Optimizer) -> set[int]:
        return {int(float(opt.state[p]["step"])) if "step" in opt.state.get(p, {}) else 0
                for p in opt.param_groups[0]["params"]}

    if len(steps(primal) | steps(dual)) != 1:
        return None
    return -float(gd["lr"]) / float(gp["lr"])


# ------------------------------------------------------------------------------------------------- network
class _FlatNet:
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


# ------------------------------------------------------------------------------------------------- spec terms
@dataclass
class _Group:
    """Spec terms sharing loss, fields and Huber delta; ``cols`` are their indices among the T terms."""

    loss: str
    fields: tuple[int, ...]
    delta: float
    cols: list[int]
    terms: list[Term]


def _groups(terms: list[Term]) -> list[_Group]:
    out: dict[tuple[str, tuple[int, ...], float], _Group] = {}
    for j, t in enumerate(terms):
        key = (t.loss, tuple(t.fields), float(t.huber_delta) if t.loss == "huber" else 0.0)
        if key not in out:
            out[key] = _Group(key[0], key[1], key[2], [], [])
        out[key].cols.append(j)
        out[key].terms.append(t)
    return list(out.values())




@dataclass
class _StepGroup:
    """One group's tensors for one minibatch: masks ``(E, B, Tg)``, estimator denominators ``den`` and
    gradient-weight denominators ``wden`` ``(E, Tg)``, ``-eps`` (0 for an empty conditional region) and, for the
    normalized loss, ``||y||`` ``(E, B, 1)``."""

    mk: Tensor
    den: Tensor
    wden: Tensor
    negeps: Tensor
    ny: Tensor | None


def _group_fn(g: _Group, n_y: int, single: bool) -> Callable[[Tensor, _StepGroup, Tensor, Tensor], Tensor]:
    """``fn(err, step_group, row, coef) -> dL/dpred contribution`` for one group: writes the group's term
    values into ``row`` ``(E, T)`` and returns the gradient of ``sum_t coef_t * value_t`` w.r.t. ``pred``.

    Per-sample gradients are the closed forms of autograd's: l2 ``e / ||e||`` (0 at e = 0), squared_l2 ``2 e``,
    l1 ``sign(e)``, huber ``clamp(e, -delta, delta)``, normalized ``e / (||e|| ||y||)``.
    """
    loss, delta = g.loss, g.delta
    all_fields = g.fields == tuple(range(n_y))
    fidx = torch.tensor(g.fields, dtype=torch.long)
    cols = g.cols
    lo, hi = cols[0], cols[-1] + 1
    contiguous = cols == list(range(lo, hi))
    col_idx = torch.tensor(cols, dtype=torch.long)
    bmm, div = torch.bmm, torch.div

    def fn(err: Tensor, sg: _StepGroup, row: Tensor, coef: Tensor) -> Tensor:
        eg = err if all_fields else err.index_select(-1, fidx)
        nrm = eg  # placeholder for the norms of l2 / normalized
        if loss == "l2":
            nrm = torch.linalg.vector_norm(eg, dim=-1, keepdim=True)
            lval = nrm
        elif loss == "squared_l2":
            lval = (eg * eg).sum(-1, keepdim=True)
        elif loss == "normalized":
            assert sg.ny is not None
            nrm = torch.linalg.vector_norm(eg, dim=-1, keepdim=True)
            lval = nrm / sg.ny
        elif loss == "l1":
            lval = eg.abs().sum(-1, keepdim=True)
        else:
            ab = eg.abs()
            lval = torch.where(ab <= delta, 0.5 * eg * eg, delta * (ab - 0.5 * delta)).sum(-1, keepdim=True)
        sums = bmm(lval.transpose(1, 2), sg.mk).squeeze(1)  # (E, Tg)
        if single:
            torch.addcdiv(sg.negeps, sums, sg.den, out=row)
            cw = div(coef, sg.wden)
        elif contiguous:
            torch.addcdiv(sg.negeps, sums, sg.den, out=row[:, lo:hi])
            cw = div(coef[:, lo:hi], sg.wden)
        else:
            row[:, col_idx] = torch.addcdiv(sg.negeps, sums, sg.den)
            cw = div(coef.index_select(1, col_idx), sg.wden)
        wgt = bmm(sg.mk, cw.unsqueeze(-1))  # (E, B, 1): dL/dl per sample
        if loss == "l2":
            contrib = eg * (wgt / nrm.clamp_min(_TINY))
        elif loss == "squared_l2":
            contrib = eg * wgt  # the factor 2 is in wden
        elif loss == "normalized":
            assert sg.ny is not None
            contrib = eg * (wgt / sg.ny / nrm.clamp_min(_TINY))
        elif loss == "l1":
            contrib = torch.sign(eg) * wgt
        else:
            contrib = eg.clamp(-delta, delta) * wgt
        if all_fields:
            return contrib
        return torch.zeros_like(err).index_copy_(-1, fidx, contrib)

    return fn


_Step = Callable[[Tensor, Tensor, list[_StepGroup], Tensor], None]


# ------------------------------------------------------------------------------------------------- engine
class FastEngine:
    """Runs :meth:`PrimalDualTrainer.fit` for one trainer and dataset (see :func:`fit_fast`)."""

    def __init__(self, trainer: PrimalDualTrainer, data: Transitions) -> None:
        why = unsupported_reason(trainer, data)
        if why is not None:
            raise ValueError(f"fast engine cannot run this trainer: {why}")
        self.tr = trainer
        self.data = data
        model = trainer.model
        self.dtype = trainer.config.torch_dtype
        self.E = model.n_models
        self.terms = [trainer.spec.objective, *trainer.spec.constraints]
        self.T = len(self.terms)
        self.K = self.T - 1
        self.groups = _groups(self.terms)
        # dual variables merged into the primal flat tensor as u = lambda / k (see _merge_dual), or separate
        self.k_dual = _merge_dual(trainer.primal_opt, trainer.dual_opt) if self.K else None
        self.net = _FlatNet(model.net, self.dtype, self.K if self.k_dual is not None else 0)
        self.popt = _FlatOptimizer(trainer.primal_opt, self.net.flat, maximize=False)
        # coef = [1, lambda_1..K] per member; lambda is a view
        self.coef = torch.ones(self.E, self.T, dtype=self.dtype)
        self.lam = self.coef[:, 1:]
        self.dopt = None
        if self.K and self.k_dual is None:
            self.dopt = _FlatOptimizer(trainer.dual_opt, self.lam, maximize=True)
        self.residual = model.kind == "residual"
        self._pending: list[Tensor] = []
        self._prepare_sources()

    # ------------------------------------------------------------------------------ state exchange
    @torch.no_grad()
    def load_state(self) -> None:
        """Read parameters, lambda and optimizer states from the trainer."""
        self.net.load()
        self.popt.load(self.tr.primal_opt, self.net.views)
        self.lam.copy_(self.tr.lam)
        if self.dopt is not None:
            self.dopt.load(self.tr.dual_opt, lambda buf: [buf])
        if self.k_dual is not None:
            self.net.extra.copy_(self.lam / self.k_dual)
            st = self.tr.dual_opt.state.get(self.tr._lam_param, {})
            if "exp_avg" in st:  # moments of the gradient -g (maximize) -> of g
                self.net.extra_view(self.popt.m).copy_(-st["exp_avg"])
                self.net.extra_view(self.popt.v).copy_(st["exp_avg_sq"])

    @torch.no_grad()
    def store_state(self) -> None:
        """Write parameters, lambda and optimizer states back to the trainer."""
        self.net.store()
        self.popt.store(self.tr.primal_opt, self.net.views)
        self.tr._lam_param.copy_(self.lam)
        if self.dopt is not None:
            self.dopt.store(self.tr.dual_opt, lambda buf: [buf])
        if self.k_dual is not None and self.popt.step_count:
            self.tr.dual_opt.state[self.tr._lam_param] = {
                "step": torch.tensor(float(self.popt.step_count), dtype=torch.float32),
                "exp_avg": -self.net.extra_view(self.popt.m).clone(),
                "exp_avg_sq": self.net.extra_view(self.popt.v).clone(),
            }

    # ------------------------------------------------------------------------------ data
    def _prepare_sources(self) -> None:
        """Per-sample tensors the minibatches are gathered from, flattened to ``(rows, .)``.

        ``z`` (normalised ``[x, u]`` and a column of ones) is per member when the data or the normalisation
        differ between members; the rest follows the data (shared ``(N, .)`` or per member ``(E, N, .)``).
        """
        d, m = self.data, self.tr.model
        with torch.no_grad():
            z = torch.cat([d.x, d.u], -1)
            same_norm = bool((m.in_mean == m.in_mean[:1]).all() and (m.in_std == m.in_std[:1]).all())
            self.z_per_member = d.per_member or not same_norm
            if self.z_per_member:
                z = (z - m.in_mean) / m.in_std  # (E, N, n_in), as DynamicsModel.correction computes it
            else:
                z = (z - m.in_mean[0]) / m.in_std[0]
            z = torch.cat([z, torch.ones(*z.shape[:-1], 1, dtype=z.dtype)], -1)
            self.n = len(d)
            self.src_z = z.reshape(-1, z.shape[-1])
            # the error is pred - y = phi + (f_hat - y): f_hat - y is data
            r = d.base - d.y if self.residual else -d.y
            self.src_r = r.reshape(-1, r.shape[-1])
            ones = torch.ones(d.x.shape[:-1], dtype=self.dtype)
            self.src_masks: list[Tensor] = []
            self.src_ny: list[Tensor | None] = []
            for g in self.groups:
                cols = [ones if mc is None else mc.to(self.dtype).expand_as(ones) for mc in (d.masks[c] for c in g.cols)]
                self.src_masks.append(torch.stack(cols, -1).reshape(-1, len(cols)))
                if g.loss == "normalized":  # Term.per_sample's ||y|| on the same float data
                    ny = torch.linalg.vector_norm(d.y[..., list(g.fields)], dim=-1).clamp_min(1e-9)
                    self.src_ny.append(ny.reshape(-1, 1))
                else:
                    self.src_ny.append(None)
        self.member_offset = (torch.arange(self.E) * self.n).view(1, self.E, 1)

    def _gather(self, idx: Tensor) -> tuple[list[Tensor], list[Tensor], list[list[_StepGroup]]]:
        """Per-minibatch tensors for indices ``idx`` ``(S, E, B)``: lists of S ``z`` and ``f_hat - y``
        ``(E, B, .)`` and, per minibatch, one :class:`_StepGroup` per group."""
        s, e, b = idx.shape
        flat_member = (idx + self.member_offset).reshape(-1)
        rows = flat_member if self.data.per_member else idx.reshape(-1)
        z = self.src_z.index_select(0, flat_member if self.z_per_member else idx.reshape(-1)).view(s, e, b, -1)
        r = self.src_r.index_select(0, rows).view(s, e, b, -1)
        per_group = []
        for g, src_m, src_ny in zip(self.groups, self.src_masks, self.src_ny):
            mk = src_m.index_select(0, rows).view(s, e, b, -1)
            counts = mk.sum(2)  # (S, E, Tg): exact integers
            cond = torch.tensor([t.region is not None and t.mean == "conditional" for t in g.terms])
            den = torch.where(cond, counts.clamp_min(1.0), torch.full_like(counts, float(b)))
            valid = ~cond | (counts > 0)  # an empty conditional region contributes 0 (see Term.estimate)
            eps = torch.tensor([t.eps for t in g.terms], dtype=self.dtype)
            negeps = torch.where(valid, -eps, torch.zeros_like(counts))
            # squared_l2: d(e.e)/de = 2e; the 2 goes into the denominator (exact: a power of two)
            wden = den / 2 if g.loss == "squared_l2" else den
            ny = None if src_ny is None else src_ny.index_select(0, rows).view(s, e, b, 1)
            per_group.append(
                [
                    _StepGroup(mk_j, den_j, wden_j, ne_j, None if ny is None else ny[j])
                    for j, (mk_j, den_j, wden_j, ne_j) in enumerate(
                        zip(mk.unbind(0), den.unbind(0), wden.unbind(0), negeps.unbind(0))
                    )
                ]
            )
        steps = [list(t) for t in zip(*per_group)]
        return list(z.unbind(0)), list(r.unbind(0)), steps

    # ------------------------------------------------------------------------------ training
    def fit(
        self,
        epochs: int,
        progress: bool = False,
        desc: str = "training",
        callback: Callable[[PrimalDualTrainer], None] | None = None,
    ) -> History:
        """Same contract and side effects as :meth:`PrimalDualTrainer.fit` (history, counters, generator)."""
        from saml_ros.core.trainer import _progress

        tr = self.tr
        n, e = self.n, self.E
        bsz = min(tr.config.batch_size, n)
        per_epoch = max(1, n // bsz)
        log_every = tr.config.log_every or per_epoch
        bar = _progress(epochs * per_epoch, desc) if progress else None
        tr.model.train()
        self.load_state()
        self._pending = self._pending_from_trainer()
        step = self._make_step(bsz)
        # Several epochs are drawn and gathered at once: rand(Q, E, N) consumes the generator exactly like Q
        # calls of rand(E, N). With a callback (which may look at the generator) one epoch at a time.
        per_floats = per_epoch * e * bsz * (self.src_z.shape[1] + self.src_r.shape[1] + self.T + 2)
        chunk = 1 if callback is not None else max(1, min(epochs, _CHUNK_FLOATS // max(1, per_floats)))
        done = 0
        while done < epochs:
            q = min(chunk, epochs - done)
            perm = torch.argsort(torch.rand(q, e, n, generator=tr.rng), dim=-1)
            idx = perm[..., : per_epoch * bsz].reshape(q, e, per_epoch, bsz).permute(0, 2, 1, 3)
            batches = self._gather(idx.reshape(q * per_epoch, e, bsz))
            vals = torch.empty(q * per_epoch, e, self.T, dtype=self.dtype)
            rows = vals.unbind(0)
            for k in range(q):
                self._run(step, batches, vals, rows, k * per_epoch, (k + 1) * per_epoch, per_epoch, log_every, bar)
                tr.epochs_done = round(tr.epochs_done, 9)
                if callback is not None:
                    self.store_state()
                    callback(tr)
                    self.load_state()
            done += q
        self._log_point()
        self.store_state()
        return tr.finish_fit(bar)

    def _pending_from_trainer(self) -> list[Tensor]:
        """Minibatch values the trainer accumulated before this fit (they join the first log point)."""
        acc = self.tr._acc
        if not acc:
            return []
        rows = torch.stack([torch.cat([v.objective.unsqueeze(-1), v.constraints], -1) for v in acc])
        acc.clear()
        return [rows.to(self.dtype)]

    def _log_point(self) -> None:
        if not self._pending:
            return
        rows = self._pending[0] if len(self._pending) == 1 else torch.cat(self._pending)
        self._pending = []
        self.tr._record(rows[:, :, 0].mean(0), rows[:, :, 1:].mean(0), self.lam.clone())

    def _make_step(self, bsz: int) -> _Step:
        """``step(z, r, groups, row)``: one primal-dual update on a minibatch of ``bsz`` samples per member, with
        normalised inputs ``z`` ``(E, B, n_in + 1)`` and ``r = f_hat - y`` ``(E, B, n_y)``; ``row`` ``(E, T)``
        receives the minibatch term values (objective, then g_k)."""
        net, e = self.net, self.E
        n_hidden = net.n_layers - 1
        w, gw, gslopes = net.w, net.gw, net.gslopes
        w_t = [wi[:, :-1, :].transpose(1, 2) for wi in w]  # W without its bias row, transposed
        # activations with a trailing column of ones (the bias input), the views written, their transposes
        h_buf = [torch.ones(e, bsz, h + 1, dtype=self.dtype) for h in net.dims[1:-1]]
        h_view = [hb[..., :-1] for hb in h_buf]
        h_t = [hb.transpose(1, 2) for hb in h_buf]
        gs_v = [gslopes[i].view(e, 1, 1) for i in range(n_hidden)]
        neg_slopes = torch.empty_like(net.slopes)
        ns_v = [neg_slopes[i].view(e, 1, 1) for i in range(n_hidden)]
        an: list[Tensor] = list(h_view)  # min(a, 0) per hidden layer (placeholders until the first step)
        dd: list[Tensor] = list(h_view)  # PReLU derivative per hidden layer
        ostd = self.tr.model.out_std
        coef, grad, slopes, lam = self.coef, net.grad, net.slopes, self.lam
        popt, dopt = self.popt, self.dopt
        u, gu, k_dual = net.extra, net.gextra, self.k_dual
        fn0, *fns = [_group_fn(g, self.src_r.shape[-1], len(self.groups) == 1) for g in self.groups]
        one = torch.ones((), dtype=self.dtype)
        bmm, mul, sum_, prelu = torch.bmm, torch.mul, torch.sum, _prelu_kernel
        copysign, clamp_max, neg, addcmul = torch.copysign, torch.clamp_max, torch.neg, torch.addcmul

        def step(z: Tensor, r: Tensor, sgs: list[_StepGroup], row: Tensor) -> None:
            # forward; the PReLU derivative d = where(a >= 0, 1, slope) is prelu(copysign(1, a), -slope)
            neg(slopes, out=neg_slopes)
            h = z
            for i in range(n_hidden):
                a = bmm(h, w[i])
                an[i] = clamp_max(a, 0)
                d = dd[i] = prelu(copysign(one, a), ns_v[i])
                mul(a, d, out=h_view[i])
                h = h_buf[i]
            out = bmm(h, w[-1])
            err = addcmul(r, out, ostd)  # pred - y = phi + (f_hat - y)
            # spec values (into row) and dL/dpred
            dpred = fn0(err, sgs[0], row, coef)
            for fn, sg in zip(fns, sgs[1:]):
                dpred = dpred + fn(err, sg, row, coef)
            # backward
            g = dpred.mul_(ostd)
            for i in range(n_hidden, 0, -1):
                bmm(h_t[i - 1], g, out=gw[i])
                gh = bmm(g, w_t[i])
                sum_(gh * an[i - 1], dim=(1, 2), keepdim=True, out=gs_v[i - 1])
                g = gh.mul_(dd[i - 1])
            bmm(z.transpose(1, 2), g, out=gw[0])
            # primal step, dual step on the detached minibatch constraint estimates, projection on lambda >= 0
            if k_dual is not None:
                gu.copy_(row[:, 1:])
                popt.step(grad)
                u.clamp_(max=0.0)
                mul(u, k_dual, out=lam)
            else:
                popt.step(grad)
                if dopt is not None:
                    dopt.step(row[:, 1:])
                    lam.clamp_(min=0.0)

        return step

    def _run(
        self,
        step: _Step,
        batches: tuple[list[Tensor], list[Tensor], list[list[_StepGroup]]],
        vals: Tensor,
        rows: tuple[Tensor, ...],
        lo: int,
        hi: int,
        per_epoch: int,
        log_every: int,
        bar: Any,
    ) -> None:
        """Steps on minibatches ``lo:hi`` of ``batches``; ``rows[j] = vals[j]`` receives step j's values ``(E, T)``."""
        tr = self.tr
        z_all, r_all, sg_all = batches
        next_log = tr.steps + (log_every - tr.steps % log_every)
        inc = 1.0 / per_epoch
        start = lo
        for j in range(lo, hi):
            step(z_all[j], r_all[j], sg_all[j], rows[j])
            tr.steps += 1
            tr.epochs_done += inc
            if tr.steps == next_log:
                next_log += log_every
                self._pending.append(vals[start : j + 1])
                start = j + 1
                self._log_point()
                if bar is not None:
                    bar.set_postfix_str(tr._postfix(), refresh=False)
        if start < hi:
            self._pending.append(vals[start:hi])
        if bar is not None:
            bar.update(hi - lo)


def fit_fast(
    trainer: PrimalDualTrainer,
    data: Transitions,
    epochs: int | None = None,
    progress: bool = False,
    desc: str = "training",
    callback: Callable[[PrimalDualTrainer], None] | None = None,
) -> History:
    """:meth:`PrimalDualTrainer.fit` on the fast engine (raises ``ValueError`` where it does not apply; see
    :func:`unsupported_reason`)."""
    epochs = trainer.config.epochs if epochs is None else epochs
    return FastEngine(trainer, data).fit(epochs, progress, desc, callback)


__all__ = ["SUPPORTED_LOSSES", "FastEngine", "fit_fast", "unsupported_reason"]
