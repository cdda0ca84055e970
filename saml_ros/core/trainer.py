"""Stochastic primal-dual training (the paper's Algorithm 1) for ensembles of dynamics models.

Per step, for every ensemble member independently:

1. sample a minibatch, evaluate the objective estimate ``f`` and constraint estimates ``g_k``;
2. descend on theta with the gradient of ``f + sum_k lambda_k g_k`` (lambda detached);
3. ascend on lambda with the *detached* minibatch constraint estimate ``g_k``;
4. project: ``lambda <- max(lambda, 0)``.

The Uniformly Accurate baseline is the same trainer with a spec that has no constraints.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
import torch

from saml_ros.core import fast_train
from saml_ros.core.models import DynamicsModel
from saml_ros.core.spec import ProblemSpec, SpecValues

log = logging.getLogger("saml_ros.trainer")

OPTIMIZERS = ("adam", "sgd")
ENGINES = ("fast", "plain")


@dataclass
class TrainConfig:
    """Hyper-parameters of Algorithm 1 (defaults: the paper's double-integrator settings).

    Attributes:
        epochs: passes over a fixed dataset (offline mode).
        batch_size: minibatch size M per ensemble member.
        primal_lr: alpha_theta.
        dual_lr: alpha_lambda.
        primal_optimizer / dual_optimizer: ``"adam"`` (the paper) or ``"sgd"`` (plain Algorithm 1).
        log_every: steps between history points (0: once per epoch); values are averaged in between.
        seed: seeds minibatch sampling.
        dtype: ``"float32"`` or ``"float64"`` for parameters and data.
        engine: how :meth:`PrimalDualTrainer.fit` runs: ``"fast"`` (hand-written forward/backward and flat
            Adam, :mod:`saml_ros.core.fast_train`; same results up to float rounding, falls back to the plain
            loop where it does not apply) or ``"plain"`` (autograd and ``torch.optim``).
        device: ``"cpu"`` (default) or ``"cuda[:N]"``; checked here (:func:`saml_ros.core.device.resolve_device`),
            so a device that cannot be used fails when the configuration is made, not mid-run.
    """

    epochs: int = 200
    batch_size: int = 128
    primal_lr: float = 1e-3
    dual_lr: float = 1e-4
    primal_optimizer: str = "adam"
    dual_optimizer: str = "adam"
    log_every: int = 0
    seed: int = 0
    dtype: str = "float32"
    engine: str = "fast"
    device: str = "cpu"

    def __post_init__(self) -> None:
        if self.primal_optimizer not in OPTIMIZERS or self.dual_optimizer not in OPTIMIZERS:
            raise ValueError(f"optimizers must be one of {OPTIMIZERS}")
        if self.batch_size < 1 or self.epochs < 0:
            raise ValueError("batch_size must be >= 1 and epochs >= 0")
        if not (self.primal_lr > 0 and self.dual_lr >= 0):
            raise ValueError("primal_lr must be > 0 and dual_lr >= 0")
        if self.dtype not in ("float32", "float64"):
            raise ValueError("dtype must be float32 or float64")
        if self.engine not in ENGINES:
            raise ValueError(f"engine must be one of {ENGINES}")
        from saml_ros.core.device import resolve_device

        resolve_device(self.device)

    @property
    def torch_dtype(self) -> torch.dtype:
        return torch.float32 if self.dtype == "float32" else torch.float64

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> TrainConfig:
        known = set(cls.__dataclass_fields__)
        extra = sorted(set(d) - known)
        if extra:
            raise ValueError(f"unknown training option(s) {extra}; known: {sorted(known)}")
        return cls(**d)


class Transitions:
    """A fixed dataset of transitions as tensors, with f_hat and region masks precomputed.

    ``x, u, y`` are ``(N, .)`` (shared by every member) or ``(E, N, .)`` (one dataset per member, equal N).
    """

    def __init__(self, model: DynamicsModel, spec: ProblemSpec, x: Any, u: Any, y: Any) -> None:
        dt = model.in_mean.dtype
        x64, u64, y64 = (torch.as_tensor(np.asarray(a), dtype=torch.float64) for a in (x, u, y))
        if not (x64.shape[:-1] == u64.shape[:-1] == y64.shape[:-1]):
            raise ValueError(f"x, u, y disagree on the number of samples: {x64.shape}, {u64.shape}, {y64.shape}")
        with torch.no_grad():
            base = model.base(x64, u64)  # f_hat in float64, then cast
        self.x, self.u, self.y, self.base = (t.to(dt) for t in (x64, u64, y64, base))
        self.per_member = self.x.dim() == 3
        self.masks = [None if m is None else m for m in spec.masks(x64, u64, y64)]

    def __len__(self) -> int:
        return int(self.x.shape[-2])

    def take(self, idx: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """Gather ``idx`` ``(E, B)``: returns x, u, y, base as ``(E, B, .)``."""
        if self.per_member:
            rows = torch.arange(idx.shape[0]).unsqueeze(1)
            return tuple(t[rows, idx] for t in (self.x, self.u, self.y, self.base))
        return tuple(t[idx] for t in (self.x, self.u, self.y, self.base))

    def take_masks(self, idx: torch.Tensor) -> list[torch.Tensor | None]:
        if self.per_member:
            rows = torch.arange(idx.shape[0]).unsqueeze(1)
            return [None if m is None else m[rows, idx] for m in self.masks]
        return [None if m is None else m[idx] for m in self.masks]


@dataclass
class History:
    """Training curve: one row per log point. Arrays are ``(E,)`` or ``(E, K)`` per row."""

    constraint_names: list[str]
    step: list[int] = field(default_factory=list)
    epoch: list[float] = field(default_factory=list)
    objective: list[np.ndarray] = field(default_factory=list)
    constraints: list[np.ndarray] = field(default_factory=list)
    lambdas: list[np.ndarray] = field(default_factory=list)
    lagrangian: list[np.ndarray] = field(default_factory=list)
    wall_time: list[float] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        for k in ("objective", "constraints", "lambdas", "lagrangian"):
            d[k] = [np.asarray(v).tolist() for v in d[k]]
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> History:
        h = cls(list(d["constraint_names"]))
        h.step, h.epoch, h.wall_time = list(d["step"]), list(d["epoch"]), list(d["wall_time"])
        for k in ("objective", "constraints", "lambdas", "lagrangian"):
            setattr(h, k, [np.asarray(v) for v in d[k]])
        return h

    def as_arrays(self) -> dict[str, np.ndarray]:
        """Stacked curves: objective ``(T, E)``, constraints/lambdas ``(T, E, K)``, lagrangian ``(T, E)``."""
        return {
            "step": np.asarray(self.step),
            "epoch": np.asarray(self.epoch),
            "objective": np.stack(self.objective) if self.objective else np.zeros((0, 0)),
            "constraints": np.stack(self.constraints) if self.constraints else np.zeros((0, 0, 0)),
            "lambdas": np.stack(self.lambdas) if self.lambdas else np.zeros((0, 0, 0)),
            "lagrangian": np.stack(self.lagrangian) if self.lagrangian else np.zeros((0, 0)),
        }


@dataclass
class FeasibilityReport:
    """Constraints that stayed violated while their multiplier kept growing (likely infeasible)."""

    violated: list[tuple[int, str, float, float, float]]  # (member, name, mean g, lambda start, lambda end)

    @property
    def ok(self) -> bool:
        return not self.violated

    def messages(self) -> list[str]:
        return [
            f"member {m}: constraint '{n}' still violated at the end of training (mean g = {g:+.4g} > 0) "
            f"while lambda grew {a:.4g} -> {b:.4g}: the constraint may be infeasible for this model and data "
            f"(raise eps, enlarge the network, or train longer)"
            for m, n, g, a, b in self.violated
        ]


class PrimalDualTrainer:
    """Algorithm 1 on a :class:`DynamicsModel` (any ensemble size) and a :class:`ProblemSpec`.

    Attributes:
        lam: dual variables ``(E, K)``, always >= 0.
        steps: primal-dual updates done so far.
        history: the training curve.
    """

    def __init__(self, model: DynamicsModel, spec: ProblemSpec, config: TrainConfig | None = None) -> None:
        self.model = model
        self.spec = spec
        self.config = config or TrainConfig()
        self.model.to(self.config.torch_dtype)
        dt = self.config.torch_dtype
        e, k = model.n_models, spec.n_constraints
        self._lam_param = torch.nn.Parameter(torch.zeros(e, k, dtype=dt))
        self.primal_opt = self._make_opt(self.config.primal_optimizer, list(model.net.parameters()),
                                         self.config.primal_lr, maximize=False)
        self.dual_opt = self._make_opt(self.config.dual_optimizer, [self._lam_param],
                                       self.config.dual_lr, maximize=True)
        self.steps = 0
        self.epochs_done = 0.0
        self.history = History(spec.constraint_names)
        self.rng = torch.Generator().manual_seed(int(self.config.seed))
        self._acc: list[SpecValues] = []
        self._t0 = time.monotonic()
        self.engine_used: str | None = None  # engine of the last fit(): "fast" or "plain"

    @staticmethod
    def _make_opt(kind: str, params: list[torch.nn.Parameter], lr: float, maximize: bool) -> torch.optim.Optimizer:
        if kind == "adam":
            return torch.optim.Adam(params, lr=lr, maximize=maximize, foreach=True)
        return torch.optim.SGD(params, lr=lr, maximize=maximize, foreach=True)

    @property
    def lam(self) -> torch.Tensor:
        """Dual variables ``(E, K)`` (a detached view; always >= 0)."""
        return self._lam_param.detach()

    # ----------------------------------------------------------------------------------- one step
    def step(
        self,
        x: torch.Tensor,
        u: torch.Tensor,
        y: torch.Tensor,
        base: torch.Tensor | None = None,
        masks: list[torch.Tensor | None] | None = None,
    ) -> SpecValues:
        """One primal-dual update on a minibatch (``(B, .)`` shared or ``(E, B, .)`` per member).

        Returns the detached minibatch spec values *before* the update.
        """
        pred = self.model(x, u, base)
        if masks is None:
            masks = self.spec.masks(x, u, y)
        vals = self.spec.evaluate_with_masks(y, pred, masks)
        loss = vals.lagrangian(self.lam).sum()  # members are independent: sum their Lagrangians
        self.primal_opt.zero_grad(set_to_none=True)
        loss.backward()
        self.primal_opt.step()
        if self.spec.n_constraints:
            g = vals.constraints.detach()
            self._lam_param.grad = g.clone()
            self.dual_opt.step()
            with torch.no_grad():
                self._lam_param.clamp_(min=0.0)
        self.steps += 1
        out = SpecValues(vals.objective.detach(), vals.constraints.detach(), vals.region_fraction.detach())
        self._acc.append(out)
        return out

    def log_point(self) -> None:
        """Append the mean of the minibatch values since the last log point to :attr:`history`."""
        if not self._acc:
            return
        obj = torch.stack([v.objective for v in self._acc]).mean(0)
        con = torch.stack([v.constraints for v in self._acc]).mean(0)
        self._acc.clear()
        self._record(obj, con, self.lam.clone())

    def _record(self, obj: torch.Tensor, con: torch.Tensor, lam: torch.Tensor) -> None:
        """Append one history row: mean objective ``(E,)``, constraints ``(E, K)`` and lambda ``(E, K)``."""
        h = self.history
        h.step.append(self.steps)
        h.epoch.append(self.epochs_done)
        h.objective.append(obj.double().numpy())
        h.constraints.append(con.double().numpy())
        h.lambdas.append(lam.double().numpy())
        h.lagrangian.append((obj + (lam * con).sum(-1)).double().numpy())
        h.wall_time.append(time.monotonic() - self._t0)

    # ----------------------------------------------------------------------------------- offline
    def fit(
        self,
        data: Transitions,
        epochs: int | None = None,
        progress: bool = False,
        desc: str = "training",
        callback: Callable[[PrimalDualTrainer], None] | None = None,
    ) -> History:
        """Run ``epochs`` passes of Algorithm 1 over a fixed dataset; every member sees its own shuffle.

        Runs on the engine named by ``config.engine`` (see :class:`TrainConfig`); :attr:`engine_used` says
        which one ran.
        """
        epochs = self.config.epochs if epochs is None else epochs
        if self.config.engine == "fast":
            why = fast_train.unsupported_reason(self, data)
            if why is None:
                self.engine_used = "fast"
                return fast_train.fit_fast(self, data, epochs, progress, desc, callback)
            log.info("fast training engine not used (%s): running the plain loop", why)
        self.engine_used = "plain"
        n = len(data)
        bsz = min(self.config.batch_size, n)
        per_epoch = max(1, n // bsz)
        e = self.model.n_models
        log_every = self.config.log_every or per_epoch
        bar = _progress(epochs * per_epoch, desc) if progress else None
        self.model.train()
        for _ in range(epochs):
            perm = torch.argsort(torch.rand(e, n, generator=self.rng), dim=1)
            for j in range(per_epoch):
                idx = perm[:, j * bsz : (j + 1) * bsz]
                x, u, y, base = data.take(idx)
                self.step(x, u, y, base, data.take_masks(idx))
                self.epochs_done += 1.0 / per_epoch
                if self.steps % log_every == 0:
                    self.log_point()
                    if bar is not None:
                        bar.set_postfix_str(self._postfix(), refresh=False)
                if bar is not None:
                    bar.update(1)
            self.epochs_done = round(self.epochs_done, 9)
            if callback is not None:
                callback(self)
        self.log_point()
        return self.finish_fit(bar)

    def finish_fit(self, bar: Any = None) -> History:
        """End of an offline run (either engine): close the progress bar, warn about constraints that look
        infeasible, return the history."""
        if bar is not None:
            bar.close()
        for msg in self.feasibility().messages():
            log.warning(msg)
        return self.history

    def _postfix(self) -> str:
        h = self.history
        s = f"obj={float(np.mean(h.objective[-1])):.4g}"
        for k, name in enumerate(h.constraint_names):
            s += f" g[{name}]={float(np.mean(h.constraints[-1][..., k])):+.3g}"
            s += f" lam={float(np.mean(h.lambdas[-1][..., k])):.3g}"
        return s

    # ----------------------------------------------------------------------------------- online
    def train_steps(
        self, sample: Callable[[], tuple[Any, Any, Any]], n_steps: int
    ) -> SpecValues | None:
        """Online mode: ``n_steps`` updates on minibatches drawn by ``sample() -> (x, u, y)`` (numpy or
        torch ``(B, .)``), e.g. from a growing :class:`~saml_ros.core.buffer.ReplayBuffer`."""
        last = None
        dt = self.config.torch_dtype
        log_every = self.config.log_every or 100
        for _ in range(n_steps):
            x, u, y = (torch.as_tensor(np.asarray(a), dtype=dt) for a in sample())
            last = self.step(x, u, y)
            if self.steps % log_every == 0:
                self.log_point()
        return last

    # ----------------------------------------------------------------------------------- evaluation
    @torch.no_grad()
    def evaluate(self, data: Transitions, chunk: int = 65536) -> dict[str, np.ndarray]:
        """Dataset-level objective ``(E,)``, constraints ``(E, K)`` and Lagrangian ``(E,)`` at the current
        theta and lambda (the quantity the convergence experiment reports)."""
        return evaluate_spec(self.model, self.spec, data, self.lam, chunk)

    def feasibility(self, tail: float = 0.25, rel_tol: float = 0.02) -> FeasibilityReport:
        """Flag constraints whose mean g over the last ``tail`` of the history exceeds ``rel_tol * eps``
        while lambda kept growing over that window (a converged saddle point hovers at g ~ 0)."""
        h = self.history
        if len(h.step) < 4 or not h.constraint_names:
            return FeasibilityReport([])
        a = h.as_arrays()
        start = int(len(h.step) * (1 - tail))
        g = a["constraints"][start:].mean(0)  # (E, K)
        lam0, lam1 = a["lambdas"][start], a["lambdas"][-1]
        eps = [t.eps for t in self.spec.constraints]
        bad = []
        for m in range(g.shape[0]):
            for k, name in enumerate(h.constraint_names):
                if g[m, k] > rel_tol * eps[k] and lam1[m, k] > lam0[m, k]:
                    bad.append((m, name, float(g[m, k]), float(lam0[m, k]), float(lam1[m, k])))
        return FeasibilityReport(bad)

    # ----------------------------------------------------------------------------------- state
    def state(self) -> dict[str, Any]:
        """Everything needed to resume: model weights, normalisation, lambda, optimizer states, counters."""
        return {
            "model": self.model.state_dict(),
            "lam": self.lam.clone(),
            "primal_opt": self.primal_opt.state_dict(),
            "dual_opt": self.dual_opt.state_dict(),
            "steps": self.steps,
            "epochs_done": self.epochs_done,
            "rng": self.rng.get_state(),
        }

    def load_state(self, st: dict[str, Any]) -> None:
        self.model.load_state_dict(st["model"])
        with torch.no_grad():
            self._lam_param.copy_(torch.as_tensor(st["lam"], dtype=self.lam.dtype))
        self.primal_opt.load_state_dict(st["primal_opt"])
        self.dual_opt.load_state_dict(st["dual_opt"])
        self.steps = int(st["steps"])
        self.epochs_done = float(st.get("epochs_done", 0.0))
        if "rng" in st:
            self.rng.set_state(torch.as_tensor(st["rng"], dtype=torch.uint8))


@torch.no_grad()
def evaluate_spec(
    model: DynamicsModel, spec: ProblemSpec, data: Transitions, lam: torch.Tensor | None = None,
    chunk: int = 65536,
) -> dict[str, np.ndarray]:
    """Full-dataset spec values for every member (chunked so memory stays bounded).

    Conditional terms are exact ratios over the whole dataset, not means of chunk ratios.
    """
    e, k = model.n_models, spec.n_constraints
    n = len(data)
    terms = [spec.objective, *spec.constraints]
    sums = torch.zeros(e, k + 1, dtype=torch.float64)
    counts = torch.zeros(e, k + 1, dtype=torch.float64)
    for s in range(0, n, chunk):
        sl = slice(s, min(n, s + chunk))
        idx = torch.arange(sl.start, sl.stop).unsqueeze(0).expand(e, -1)
        x, u, y, base = data.take(idx)
        pred = model(x, u, base)
        masks = data.take_masks(idx)
        for j, (t, m) in enumerate(zip(terms, masks)):
            loss = t.per_sample(pred, y).double()
            mm = torch.ones_like(loss) if m is None else m.double().expand_as(loss)
            sums[:, j] += (loss * mm).sum(-1)
            counts[:, j] += mm.sum(-1) if (m is not None and t.mean == "conditional") else loss.shape[-1]
    vals = sums / counts.clamp_min(1.0)
    eps = torch.tensor([0.0] + [t.eps for t in spec.constraints], dtype=torch.float64)
    has = counts > 0
    g = torch.where(has, vals - eps, torch.zeros_like(vals))
    lam64 = torch.zeros(e, k, dtype=torch.float64) if lam is None else lam.detach().double()
    obj, cons = g[:, 0], g[:, 1:]
    return {
        "objective": obj.numpy(),
        "constraints": cons.numpy(),
        "lagrangian": (obj + (lam64 * cons).sum(-1)).numpy(),
        "lambdas": lam64.numpy(),
    }


def _progress(total: int, desc: str) -> Any:
    from tqdm import tqdm

    return tqdm(total=total, desc=desc, unit="step", mininterval=0.5, dynamic_ncols=True,
                disable=None if not math.isinf(total) else True)
