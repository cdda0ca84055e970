"""The fast engine of :meth:`PrimalDualTrainer.fit`: the same Algorithm 1, without autograd and optimizer overhead.

At the paper's batch and network sizes (a 16-8 net needs ~3 kFLOP per sample) a plain PyTorch step is almost
all Python and dispatcher overhead: ~40 autograd nodes, per-parameter optimizer bookkeeping, small allocations.
This engine computes the same step with ~43 tensor operations in all (docs/performance.md has the profiles):

* **hand-written forward/backward** for :class:`~saml_ros.core.model.network.EnsembleMLP`. Each layer's bias is stored as an extra weight row
  and every activation carries a column of ones, so one ``bmm`` gives the pre-activation and one ``bmm`` gives
  the weight *and* bias gradient. PReLU keeps its derivative ``d = where(a >= 0, 1, slope)`` from the forward
  pass, computed as ``prelu(copysign(1, a), -slope)`` (the plain model's tie rule ``a >= 0`` included; only a
  pre-activation of exactly -0.0, which a sum with a nonzero bias cannot produce, is treated as negative).
* **flat parameters**: all weights, biases and slopes of all members live in one contiguous tensor (gradients
  and Adam moments too), so an Adam step is 6 element-wise operations whatever the depth. The dual variables
  ride in the same tensor, rescaled (see :func:`~saml_ros.core.training.engines.flat.merged_dual_scale`), when both optimizers are Adam (the paper's).
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

Every dual method (:data:`FAST_DUALS`: the paper's and the Lagrangian, nuPI, augmented Lagrangian, resilient) and
learning-rate schedule runs here with its class's arithmetic: the augmented Lagrangian's weights
``relu(lambda + rho g)`` need the minibatch's g, so every group's term values come before any gradient
(:func:`group_step_fn`), and its multipliers take the method of multipliers' SGD step along ``rho g``; schedules set
the flat optimizers' rates per update, and the dual Adam stays merged only when both rates scale alike.

Where it does not apply (:func:`unsupported_reason`: another network or optimizer type, AMSGrad, a dual-variables
class it does not know, ...) the trainer runs the plain engine. The flat
storage and flat optimizers are in :mod:`~saml_ros.core.training.engines.flat`, the closed-form spec terms in
:mod:`~saml_ros.core.training.engines.closed_form`; this module holds the support check and the engine.

Shapes: ``E`` ensemble members, ``B`` minibatch size, ``T = 1 + K`` spec terms (objective first).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import torch
from torch import Tensor

from saml_ros.core.model.network import EnsembleMLP
from saml_ros.core.training.dataset import Transitions
from saml_ros.core.training.dual import AugmentedDual, DualVariables, LagrangianDual, NuPIDual, ResilientDual
from saml_ros.core.training.engines.base import Engine, RunState, minibatch_plan
from saml_ros.core.training.engines.closed_form import SUPPORTED_LOSSES, StepGroup, group_step_fn, term_groups
from saml_ros.core.training.engines.flat import FlatNet, FlatNuPI, FlatOptimizer, merged_dual_scale
from saml_ros.core.training.nupi import NuPI

# Floats gathered per chunk of epochs (at least one epoch): small enough to stay in cache (~4 MB in float32).
_CHUNK_FLOATS = 1_000_000
# PReLU forward kernel with a broadcastable weight (the public torch.prelu reshapes its weight first)
_prelu_kernel: Callable[[Tensor, Tensor], Tensor] = getattr(
    torch, "_prelu_kernel", torch.ops.aten._prelu_kernel.default
)
_Snapshot = tuple[list[Tensor], tuple[int, int, int], Tensor | None]
_Step = Callable[[Tensor, Tensor, list[StepGroup], Tensor], None]
#: ``gate(row, grad)``: called after the backward pass with the step's term values ``(E, T)`` and the network part
#: of the flat gradient; False skips the update (nothing of the run's state has changed by then)
Gate = Callable[[Tensor, Tensor], bool]
#: the dual methods with a flat implementation here (every one of :data:`~saml_ros.core.training.dual.DUAL_CLASSES`)
FAST_DUALS: tuple[type[DualVariables], ...] = (DualVariables, LagrangianDual, NuPIDual, AugmentedDual, ResilientDual)


# ------------------------------------------------------------------------------------------------- support
def unsupported_reason(trainer: RunState, data: Transitions) -> str | None:
    """Why the fast engine cannot run ``trainer`` on ``data`` exactly like the plain loop, or ``None`` if it can."""
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
    if type(trainer.dual) not in FAST_DUALS:
        return f"dual method {type(trainer.dual).__name__} has no fast implementation"
    if trainer.spec.n_constraints:
        dopt = trainer.dual.optimizer
        if len(dopt.param_groups) != 1 or [id(p) for p in dopt.param_groups[0]["params"]] != [id(trainer.dual.param)]:
            return "the dual optimizer does not hold exactly lambda in one group"
        if isinstance(trainer.dual, NuPIDual):
            why = None if type(dopt) is NuPI and dopt.param_groups[0]["maximize"] else "not an ascending nuPI"
        else:
            why = _optimizer_reason(dopt, maximize=True)
        if why:
            return f"dual optimizer: {why}"
    if trainer.schedules is None:
        return "a learning-rate schedule without a horizon"
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


# ------------------------------------------------------------------------------------------------- engine
class FastEngine(Engine):
    """The fast engine (see the module docstring); a :class:`FastRun` per :meth:`fit`."""

    name = "fast"

    def unsupported_reason(self, run: RunState, data: Transitions) -> str | None:
        return unsupported_reason(run, data)

    def fit(self, run: RunState, data: Transitions, epochs: int, bar: Any = None,
            on_epoch: Callable[[], None] | None = None) -> None:
        FastRun(run, data).fit(epochs, bar, on_epoch)


class FastRun:
    """One fast :meth:`Engine.fit` of ``trainer`` on ``data``: the flat copies of its state and the precomputed
    data (raises ``ValueError`` where the engine does not apply; see :func:`unsupported_reason`)."""

    def __init__(self, trainer: RunState, data: Transitions) -> None:
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
        self.groups = term_groups(self.terms)
        self.dual = dual = trainer.dual
        assert trainer.schedules is not None
        self.schedules = trainer.schedules
        # dual variables merged into the primal flat tensor as u = lambda / k (see merged_dual_scale), or separate;
        # under learning-rate schedules only when both rates scale alike (k then comes from the starting rates)
        self.k_dual = None
        ps, ds = self.schedules
        if self.K and not isinstance(dual, NuPIDual) and ps.same_factors(ds):
            base = None if ps.constant and ds.constant else (ps.lr0, ds.lr0)
            self.k_dual = merged_dual_scale(trainer.primal_opt, dual.optimizer, base)
        self.net = FlatNet(model.net, self.dtype, self.K if self.k_dual is not None else 0)
        self.popt = FlatOptimizer(trainer.primal_opt, self.net.flat, maximize=False)
        # coef = [1, w_1..K] per member: the weights of the constraint estimates in the primal gradient, lambda
        # itself (a view) except for the augmented Lagrangian, whose weights relu(lambda + rho g) are per step
        self.coef = torch.ones(self.E, self.T, dtype=self.dtype)
        self.augmented = isinstance(dual, AugmentedDual)
        self.lam = torch.zeros(self.E, self.K, dtype=self.dtype) if self.augmented else self.coef[:, 1:]
        self.dopt: FlatOptimizer | None = None
        self.dnupi: FlatNuPI | None = None
        if self.K and isinstance(dual, NuPIDual):
            self.dnupi = FlatNuPI(dual.optimizer, self.lam)
        elif self.K and self.k_dual is None:
            self.dopt = FlatOptimizer(dual.optimizer, self.lam, maximize=True)
        self.residual = model.kind == "residual"
        self._pending: list[Tensor] = []
        self._synced: tuple[list[Tensor], list[int]] | None = None
        self._prepare_sources()

    # ------------------------------------------------------------------------------ state exchange
    @torch.no_grad()
    def load_state(self) -> None:
        """Read parameters, lambda and optimizer states from the trainer (nothing to do when none of them changed
        since :meth:`store_state`)."""
        if self._synced is not None and self._in_sync(*self._synced):
            return
        self.net.load()
        self.popt.load(self.tr.primal_opt, self.net.views)
        self.lam.copy_(self.dual.value)
        if self.dopt is not None:
            self.dopt.load(self.dual.optimizer, lambda buf: [buf])
        if self.dnupi is not None:
            self.dnupi.load(self.dual.optimizer)
        if self.k_dual is not None:
            self.net.extra.copy_(self.lam / self.k_dual)
            st = self.dual.optimizer.state.get(self.dual.param, {})
            if "exp_avg" in st:  # moments of the gradient -g (maximize) -> of g
                self.net.extra_view(self.popt.m).copy_(-st["exp_avg"])
                self.net.extra_view(self.popt.v).copy_(st["exp_avg_sq"])

    def _trainer_tensors(self) -> list[Tensor]:
        """Every tensor of the trainer's state this run reads (parameters, lambda, both optimizers' states)."""
        ts: list[Tensor] = [*self.net.params, self.dual.param]
        for opt in (self.tr.primal_opt, self.dual.optimizer):
            for st in opt.state.values():
                ts += [v for v in st.values() if isinstance(v, Tensor)]
        return ts

    def _in_sync(self, tensors: list[Tensor], versions: list[int]) -> bool:
        """True when the trainer holds exactly ``tensors``, unchanged since (in-place changes bump ``_version``)."""
        now = self._trainer_tensors()
        return len(now) == len(tensors) and all(
            a is b and a._version == v for a, b, v in zip(now, tensors, versions))

    @torch.no_grad()
    def store_state(self) -> None:
        """Write parameters, lambda and optimizer states back to the trainer."""
        self.net.store()
        self.popt.store(self.tr.primal_opt, self.net.views)
        self.dual.assign_(self.lam)
        if self.dopt is not None:
            self.dopt.store(self.dual.optimizer, lambda buf: [buf])
        if self.dnupi is not None:
            self.dnupi.store(self.dual.optimizer)
        # the optimizers' learning rates: those of the last update, as the plain engine leaves them
        ps, ds = self.schedules
        if self.tr.steps and not ps.constant:
            for group in self.tr.primal_opt.param_groups:
                group["lr"] = ps.lr(self.tr.steps - 1)
        if self.tr.steps and not ds.constant:
            self.dual.set_lr(ds.lr(self.tr.steps - 1))
        if self.k_dual is not None and self.popt.step_count:
            self.dual.optimizer.state[self.dual.param] = {
                "step": torch.tensor(float(self.popt.step_count), dtype=torch.float32),
                "exp_avg": -self.net.extra_view(self.popt.m).clone(),
                "exp_avg_sq": self.net.extra_view(self.popt.v).clone(),
            }
        ts = self._trainer_tensors()
        self._synced = (ts, [t._version for t in ts])

    # ------------------------------------------------------------------------------ data
    def _prepare_sources(self) -> None:
        """Per-sample tensors the minibatches are gathered from, flattened to ``(rows, .)``.

        ``z`` (normalised ``[x, u]`` and a column of ones) is per member when the data or the normalisation
        differ between members; the rest follows the data (shared ``(N, .)`` or per member ``(E, N, .)``).
        """
        d, m = self.data, self.tr.model
        with torch.no_grad():
            z = m.select_inputs(torch.cat([d.x, d.u], -1))  # the fields the network sees
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

    def _gather(self, idx: Tensor) -> tuple[list[Tensor], list[Tensor], list[list[StepGroup]]]:
        """Per-minibatch tensors for indices ``idx`` ``(S, E, B)``: lists of S ``z`` and ``f_hat - y``
        ``(E, B, .)`` and, per minibatch, one :class:`StepGroup` per group."""
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
                    StepGroup(mk_j, den_j, wden_j, ne_j, None if ny is None else ny[j])
                    for j, (mk_j, den_j, wden_j, ne_j) in enumerate(
                        zip(mk.unbind(0), den.unbind(0), wden.unbind(0), negeps.unbind(0))
                    )
                ]
            )
        steps = [list(t) for t in zip(*per_group)]
        return list(z.unbind(0)), list(r.unbind(0)), steps

    # ------------------------------------------------------------------------------ training
    def fit(self, epochs: int, bar: Any = None, on_epoch: Callable[[], None] | None = None) -> None:
        """``epochs`` passes, with the contract of :meth:`Engine.fit` (history, counters, generator)."""
        tr = self.tr
        n, e = self.n, self.E
        bsz, per_epoch = minibatch_plan(tr.config.batch_size, n)
        log_every = tr.config.log_every or per_epoch
        tr.model.train()
        self.load_state()
        self._pending = self._pending_from_log()
        step = self._make_step(bsz)
        # Several epochs are drawn and gathered at once: rand(Q, E, N) consumes the generator exactly like Q
        # calls of rand(E, N). With on_epoch (which may look at the generator) one epoch at a time.
        per_floats = per_epoch * e * bsz * (self.src_z.shape[1] + self.src_r.shape[1] + self.T + 2)
        chunk = 1 if on_epoch is not None else max(1, min(epochs, _CHUNK_FLOATS // max(1, per_floats)))
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
                if on_epoch is not None:
                    self.store_state()
                    on_epoch()
                    self.load_state()
            done += q
        self._log_point()
        self.store_state()

    def _pending_from_log(self) -> list[Tensor]:
        """Minibatch values logged before this fit (e.g. online steps; they join the first log point)."""
        acc = self.tr.log.take_pending()
        if not acc:
            return []
        rows = torch.stack([torch.cat([v.objective.unsqueeze(-1), v.constraints], -1) for v in acc])
        return [rows.to(self.dtype)]

    def _log_point(self) -> None:
        if not self._pending:
            return
        rows = self._pending[0] if len(self._pending) == 1 else torch.cat(self._pending)
        self._pending = []
        skipped = torch.isnan(rows).flatten(1).any(1)  # NaN rows: steps skipped as unhealthy (see _check_block)
        if bool(skipped.any()):
            rows = rows[~skipped]
            if len(rows) == 0:
                return  # as the plain loop: no row without a healthy step
        tr = self.tr
        tr.log.record(tr.steps, tr.epochs_done, rows[:, :, 0].mean(0), rows[:, :, 1:].mean(0), self.lam)

    # ------------------------------------------------------------------------------ health (training/health.py)
    def _state_tensors(self) -> list[Tensor]:
        """The tensors a step changes: flat parameters (and merged dual), optimizer moments, lambda."""
        ts: list[Tensor] = [self.net.flat, self.popt.m, self.popt.v, self.lam]
        if self.dopt is not None:
            ts += [self.dopt.m, self.dopt.v]
        seen: set[int] = set()
        return [t for t in ts if not (id(t) in seen or seen.add(id(t)))]  # type: ignore[func-returns-value]

    def _rates(self, t: int) -> None:
        """Set update ``t``'s primal and dual learning rates from the schedules (constant ones are left alone)."""
        ps, ds = self.schedules
        if not ps.constant:
            self.popt.lr = ps.lr(t)
        dual_opt = self.dopt or self.dnupi
        if not ds.constant and dual_opt is not None:
            dual_opt.lr = ds.lr(t)

    def _snapshot(self) -> _Snapshot:
        """The state :meth:`_check_block` puts back: the step tensors, the step counts and nuPI's last error."""
        nupi = self.dnupi
        xi = None if nupi is None or nupi.xi is None else nupi.xi.clone()
        return ([t.clone() for t in self._state_tensors()],
                (self.popt.step_count, self.dopt.step_count if self.dopt is not None else 0,
                 nupi.step_count if nupi is not None else 0), xi)

    def _check_block(self, vals: Tensor, a: int, b: int, snap: _Snapshot) -> None:
        """Health check of steps ``a:b`` (values ``vals[a:b]``); on a problem the state from before them is put
        back, their values become NaN and they are counted skipped."""
        health = self.tr.health
        why = health.check_block(vals[a:b, :, 0], [self.net.flat, self.lam])
        if why is None:
            return
        self._restore(snap)
        vals[a:b] = float("nan")
        health.skip(why, b - a)
        health.restores += 1

    def _restore(self, snap: _Snapshot) -> None:
        """Put back the state of :meth:`_snapshot`."""
        with torch.no_grad():
            for dst, src in zip(self._state_tensors(), snap[0]):
                dst.copy_(src)
        self.popt.step_count = snap[1][0]
        if self.dopt is not None:
            self.dopt.step_count = snap[1][1]
        if self.dnupi is not None:
            self.dnupi.step_count, self.dnupi.xi = snap[1][2], snap[2]

    def _make_step(self, bsz: int, gate: Gate | None = None) -> _Step:
        """``step(z, r, groups, row)``: one primal-dual update on a minibatch of ``bsz`` samples per member, with
        normalised inputs ``z`` ``(E, B, n_in + 1)`` and ``r = f_hat - y`` ``(E, B, n_y)``; ``row`` ``(E, T)``
        receives the minibatch term values (objective, then g_k). With ``gate`` (see :data:`Gate`) the update
        happens only when it returns True.

        One closure on purpose (longer than 80 lines): the hot path binds every buffer and view once, so each
        step is straight-line tensor operations without attribute lookups or calls between them."""
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
        net_grad = grad[: net.x_offset]  # without the merged dual's slots
        popt, dopt, dnupi = self.popt, self.dopt, self.dnupi
        u, gu, k_dual = net.extra, net.gextra, self.k_dual
        fns = [group_step_fn(g, self.src_r.shape[-1], len(self.groups) == 1) for g in self.groups]
        (val0, grad0), rest = fns[0], fns[1:]
        # the dual method's arithmetic (the same operations as its class in saml_ros.core.training.dual)
        dual = self.dual
        rho = dual.rho if isinstance(dual, AugmentedDual) else None
        decay = dual.decay if isinstance(dual, ResilientDual) else None  # eps^2 / (alpha f) of the objective f
        eps = dual.eps
        w_con = coef[:, 1:]
        one = torch.ones((), dtype=self.dtype)
        bmm, mul, sum_, prelu = torch.bmm, torch.mul, torch.sum, _prelu_kernel
        copysign, clamp_max, neg, addcmul = torch.copysign, torch.clamp_max, torch.neg, torch.addcmul

        def step(z: Tensor, r: Tensor, sgs: list[StepGroup], row: Tensor) -> None:
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
            # spec values (into row), the weights of the constraint estimates, dL/dpred
            ctx0 = val0(err, sgs[0], row)
            ctxs = [vf(err, sg, row) for (vf, _), sg in zip(rest, sgs[1:])]
            if rho is not None:
                torch.addcmul(lam, rho, row[:, 1:], out=w_con).clamp_(min=0.0)
            dpred = grad0(ctx0, sgs[0], coef)
            for (_, gf), ctx, sg in zip(rest, ctxs, sgs[1:]):
                dpred = dpred + gf(ctx, sg, coef)
            # backward
            g = dpred.mul_(ostd)
            for i in range(n_hidden, 0, -1):
                bmm(h_t[i - 1], g, out=gw[i])
                gh = bmm(g, w_t[i])
                sum_(gh * an[i - 1], dim=(1, 2), keepdim=True, out=gs_v[i - 1])
                g = gh.mul_(dd[i - 1])
            bmm(z.transpose(1, 2), g, out=gw[0])
            if gate is not None and not gate(row, net_grad):
                return
            # primal step, dual step on the detached minibatch constraint estimates, projection on lambda >= 0
            if k_dual is not None:
                if rho is not None:
                    mul(row[:, 1:], rho, out=gu)
                elif decay is not None:
                    torch.sub(row[:, 1:], mul(lam, decay(row[:, 0])), out=gu)
                else:
                    gu.copy_(row[:, 1:])
                popt.step(grad)
                u.clamp_(max=0.0)
                mul(u, k_dual, out=lam)
            else:
                popt.step(grad)
                if dnupi is not None:
                    dnupi.step(torch.div(row[:, 1:], eps))
                    lam.clamp_(min=0.0)
                elif dopt is not None:
                    if rho is not None:
                        dopt.step(mul(row[:, 1:], rho))
                    elif decay is not None:
                        dopt.step(torch.sub(row[:, 1:], mul(lam, decay(row[:, 0]))))
                    else:
                        dopt.step(row[:, 1:])
                    lam.clamp_(min=0.0)

        return step

    def _run(
        self,
        step: _Step,
        batches: tuple[list[Tensor], list[Tensor], list[list[StepGroup]]],
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
        rates = self._rates
        every = tr.health.config.check_every
        block, snap = lo, self._snapshot()
        for j in range(lo, hi):
            rates(tr.steps)
            step(z_all[j], r_all[j], sg_all[j], rows[j])
            tr.steps += 1
            tr.epochs_done += inc
            if j + 1 - block >= every or j + 1 == hi or tr.steps == next_log:  # a health check per block
                self._check_block(vals, block, j + 1, snap)
                block = j + 1
                if block < hi:
                    snap = self._snapshot()
            if tr.steps == next_log:
                next_log += log_every
                self._pending.append(vals[start : j + 1])
                start = j + 1
                self._log_point()
                if bar is not None:
                    bar.set_postfix_str(tr.log.postfix(), refresh=False)
        if start < hi:
            self._pending.append(vals[start:hi])
        if bar is not None:
            bar.update(hi - lo)

