"""Training health: a non-finite or exploding loss, gradient or weight never reaches the model.

Every primal-dual step is checked (:class:`TrainingHealth`, one per trainer, ``trainer.health``):

* ``loss``: the minibatch Lagrangian or objective is NaN / Inf, or the objective is more than ``explode_ratio``
  times its running mean (an exponential average of the healthy steps' objectives, after ``warmup`` of them);
* ``gradient``: the gradient's norm is NaN / Inf or more than ``explode_ratio`` times its running mean;
* ``weights``: after the update, a network weight or a multiplier is NaN / Inf or larger than ``max_weight`` in
  magnitude.

A ``loss`` or ``gradient`` problem skips the step before anything is updated; a ``weights`` problem restores the
last healthy snapshot (taken every ``snapshot_every`` healthy steps: weights, both optimizer states, the dual
variables). Skipped steps are counted per reason (the minibatch is used up; ``trainer.steps`` counts it), their
values stay out of the training history, and :attr:`TrainingHealth.streak` counts consecutive skipped steps: the
learner reports WARN on /diagnostics once a step was skipped and ERROR while the streak is ``error_after`` or
longer (:mod:`saml_ros.core.online.report`). A finite but exploding value in every step is a new scale, not an
accident: after ``rebase_after`` consecutive skipped steps the running means start again (a new warm-up), so a
real change of scale is learned from, while absurd minibatches among healthy ones never reach the model.

The plain step (:func:`~saml_ros.core.training.engines.plain.primal_dual_step`) checks every step exactly as
above; so do the fast online updates (:mod:`~saml_ros.core.training.engines.stream`) for the loss and the
gradient, with the weights checked per block of ``check_every`` steps (a bad block is put back and counted
skipped). The fast engine's offline ``fit`` checks every ``check_every`` steps (the losses of those steps and the
weights after them; a non-finite loss or gradient always reaches its weights through Adam) and on a problem
restores the state from before them and counts all of them skipped: one check per block keeps its speed.

:meth:`TrainingHealth.summary` goes into every checkpoint's metadata (``meta["health"]``), and a model with a
non-finite weight is never written (:func:`saml_ros.core.model.io.model_payload` refuses it).
"""

from __future__ import annotations

import math
from collections import Counter
from typing import Any, Protocol

import torch

from msg_schemas.telemetry import TRAINING_SKIP_REASONS
from saml_ros.core.model.network import DynamicsModel
from saml_ros.core.training.config import HealthConfig
from saml_ros.core.training.dual import DualVariables


class CheckedRun(Protocol):
    """What the checks read and restore of a run (a :class:`~saml_ros.core.training.PrimalDualTrainer`): a part of
    the engines' :class:`~saml_ros.core.training.engines.base.RunState`."""

    model: DynamicsModel
    primal_opt: torch.optim.Optimizer
    dual: DualVariables

#: reasons a step is skipped, in the order the counters are reported
SKIP_REASONS: tuple[str, ...] = TRAINING_SKIP_REASONS


def max_abs(tensors: list[torch.Tensor]) -> float:
    """The largest magnitude in ``tensors`` (NaN if any holds NaN, 0 if all are empty)."""
    with torch.no_grad():
        flat = [t.detach().reshape(-1) for t in tensors if t.numel()]
        return float(torch.cat(flat).abs().max()) if flat else 0.0


def _clone_tree(obj: Any) -> Any:
    """``obj`` (nested dicts / lists / tuples of tensors and plain values) with every tensor cloned."""
    if isinstance(obj, torch.Tensor):
        return obj.detach().clone()
    if isinstance(obj, dict):
        return {k: _clone_tree(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return type(obj)(_clone_tree(v) for v in obj)
    return obj


def _opt_params(opt: torch.optim.Optimizer) -> list[torch.Tensor]:
    return [p for g in opt.param_groups for p in g["params"]]


class _Mean:
    """Running mean of a positive quantity: the average of the first ``warmup`` values, then exponential."""

    def __init__(self) -> None:
        self.value = 0.0
        self.n = 0

    def add(self, v: float, warmup: int, smoothing: float) -> None:
        self.n += 1
        a = 1.0 / self.n if self.n <= max(warmup, 1) else smoothing
        self.value += a * (v - self.value)

    def exploding(self, v: float, cfg: HealthConfig) -> bool:
        return self.n >= cfg.warmup and self.value > 0 and v > cfg.explode_ratio * self.value


class TrainingHealth:
    """The health checks of one trainer (see the module docstring); counters are cumulative for the process."""

    def __init__(self, config: HealthConfig | None = None) -> None:
        self.config = config or HealthConfig()
        self.skipped: Counter[str] = Counter()
        self.restores = 0
        #: consecutive skipped steps (0 after a healthy step)
        self.streak = 0
        self.healthy_steps = 0
        self.last_problem = ""
        self._pending_loss = 0.0
        self._pending_grad: float | None = None
        self._loss = _Mean()
        self._grad = _Mean()
        self._snapshot: Any = None
        self._since_snapshot = 0

    # ------------------------------------------------------------------------------ checks (plain step)
    def check_loss(self, lagrangian: torch.Tensor, objective: torch.Tensor) -> str | None:
        """``"loss"`` (with the detail in :attr:`last_problem`) if the minibatch Lagrangian / objective (summed
        over members) is non-finite or the objective is exploding, else ``None``."""
        lag, obj = torch.stack((lagrangian.detach().sum(), objective.detach().sum())).tolist()
        return self.check_loss_values(lag, obj)

    def check_loss_values(self, lag: float, obj: float) -> str | None:
        """:meth:`check_loss` on the minibatch Lagrangian and objective, summed over members, as floats."""
        if not (math.isfinite(lag) and math.isfinite(obj)):
            return self._problem("loss", f"non-finite minibatch loss (Lagrangian {lag}, objective {obj})")
        if self._loss.exploding(obj, self.config):
            return self._problem("loss", f"exploding minibatch objective {obj:.4g} (running mean "
                                         f"{self._loss.value:.4g})")
        self._pending_loss = obj
        return None

    def check_gradients(self, params: list[torch.Tensor]) -> str | None:
        """``"gradient"`` if the gradients of ``params`` have a non-finite or exploding norm, else ``None``."""
        grads = [p.grad for p in params if p.grad is not None]
        if not grads:
            return None
        with torch.no_grad():
            norm = float(torch.linalg.vector_norm(torch.stack(torch._foreach_norm(grads))))
        return self.check_gradient_norm(norm)

    def check_gradient_norm(self, norm: float) -> str | None:
        """:meth:`check_gradients` on the gradient's norm."""
        if not math.isfinite(norm):
            return self._problem("gradient", f"non-finite gradient (norm {norm})")
        if self._grad.exploding(norm, self.config):
            return self._problem("gradient", f"exploding gradient norm {norm:.4g} (running mean "
                                             f"{self._grad.value:.4g})")
        self._pending_grad = norm
        return None

    def check_weights(self, run: CheckedRun) -> str | None:
        """``"weights"`` if a network weight or multiplier of ``run`` is non-finite or larger than ``max_weight``."""
        return self._weights_problem(max_abs([*run.model.net.parameters(), run.dual.value]))

    def check_weights_of(self, tensors: list[torch.Tensor]) -> str | None:
        """:meth:`check_weights` on ``tensors`` (e.g. a fast run's flat parameters and multipliers)."""
        return self._weights_problem(max_abs(tensors))

    def _weights_problem(self, biggest: float) -> str | None:
        if biggest <= self.config.max_weight:  # NaN fails this
            return None
        what = "exploding" if math.isfinite(biggest) else "non-finite"
        return self._problem("weights", f"{what} weights after the update (largest |w| = {biggest:.4g}, "
                                        f"health.max_weight = {self.config.max_weight:g})")

    # ------------------------------------------------------------------------------ outcomes
    def healthy(self, run: CheckedRun) -> None:
        """A healthy step: update the running means and, every ``snapshot_every`` such steps, the snapshot."""
        self.count_healthy()
        self._since_snapshot += 1
        if self._snapshot is None or self._since_snapshot >= self.config.snapshot_every:
            self.take_snapshot(run)

    def count_healthy(self) -> None:
        """:meth:`healthy` without the snapshot (a run that keeps its own, like the fast online updates)."""
        cfg = self.config
        self._loss.add(self._pending_loss, cfg.warmup, cfg.smoothing)
        if self._pending_grad is not None:
            self._grad.add(self._pending_grad, cfg.warmup, cfg.smoothing)
        self._pending_grad = None
        self.healthy_steps += 1
        self.streak = 0

    def skip(self, reason: str, n: int = 1) -> None:
        """Count ``n`` skipped steps for ``reason`` (one of :data:`SKIP_REASONS`)."""
        self.skipped[reason] += n
        self.streak += n
        self._pending_grad = None
        if self.streak >= self.config.rebase_after and self.streak - n < self.config.rebase_after:
            self._loss, self._grad = _Mean(), _Mean()  # every step explodes: a new scale, warm up again

    def ensure_snapshot(self, run: CheckedRun) -> None:
        """Take a snapshot of ``run`` if there is none yet (before the first update of a run or a resume)."""
        if self._snapshot is None:
            self.take_snapshot(run)

    def take_snapshot(self, run: CheckedRun) -> None:
        """Remember ``run``'s state (network parameters, the primal optimizer's state, the dual variables'
        ``state_dict``) as the last healthy one."""
        with torch.no_grad():
            params = [p.detach().clone() for p in run.model.net.parameters()]
            opt = run.primal_opt
            state = {i: {k: v.clone() if isinstance(v, torch.Tensor) else v for k, v in opt.state[p].items()}
                     for i, p in enumerate(_opt_params(opt)) if p in opt.state}
            dual = _clone_tree(run.dual.state_dict())
        self._snapshot = (params, state, dual)
        self._since_snapshot = 0

    def restore(self, run: CheckedRun) -> bool:
        """Put the last healthy snapshot back into ``run`` (False if there is none: :meth:`ensure_snapshot` was
        never called)."""
        if self._snapshot is None:
            return False
        params, state, dual = self._snapshot
        with torch.no_grad():
            for param, saved in zip(run.model.net.parameters(), params):
                param.copy_(saved)
            opt = run.primal_opt
            for i, p in enumerate(_opt_params(opt)):
                if i in state:
                    opt.state[p] = {k: v.clone() if isinstance(v, torch.Tensor) else v for k, v in state[i].items()}
                else:
                    opt.state.pop(p, None)
        run.dual.load_state_dict(_clone_tree(dual))
        self.restores += 1
        return True

    # ------------------------------------------------------------------------------ the fast engine's block
    def check_block(self, objectives: torch.Tensor, weights: list[torch.Tensor]) -> str | None:
        """The fast engine's check of a block of steps: ``objectives`` ``(S, E)`` (each step's minibatch objective
        per member) and the flat ``weights`` after them; the problem's reason, or ``None`` after counting the
        block's steps healthy."""
        obj = objectives.sum(-1)
        worst, mean = torch.stack((obj.max(), obj.mean())).tolist()
        return self.check_block_values(worst, mean, len(obj), max_abs(weights))

    def check_block_values(self, worst: float, mean: float, n: int, biggest: float) -> str | None:
        """:meth:`check_block` on floats: the largest and the mean over the block's ``n`` steps of the members'
        summed minibatch objective, and the largest weight magnitude after them (NaN: non-finite)."""
        if not math.isfinite(worst):
            return self._problem("loss", f"non-finite minibatch objective in the last {n} steps")
        if self._loss.exploding(worst, self.config):
            return self._problem("loss", f"exploding minibatch objective {worst:.4g} (running mean "
                                         f"{self._loss.value:.4g})")
        why = self._weights_problem(biggest)
        if why is not None:
            return why
        cfg = self.config
        self._loss.add(mean, cfg.warmup, cfg.smoothing)
        self.healthy_steps += n
        self.streak = 0
        return None

    def accept_loss_steps(self, losses: list[tuple[float, float]]) -> bool:
        """The fused online updates' loss checks of a block of steps already taken: ``losses`` holds each step's
        minibatch Lagrangian and objective (summed over members). When :meth:`check_loss_values` would pass every
        one of them in turn (the running mean moving after each, as the plain step's), they are counted healthy
        as :meth:`count_healthy` does (without a gradient norm) and True is returned; else nothing changes and
        False is returned (the caller puts the block back and takes it step by step)."""
        cfg = self.config
        mean = _Mean()
        mean.value, mean.n = self._loss.value, self._loss.n
        for lag, obj in losses:
            if not (math.isfinite(lag) and math.isfinite(obj)) or mean.exploding(obj, cfg):
                return False
            mean.add(obj, cfg.warmup, cfg.smoothing)
        if losses:
            self._loss = mean
            self._pending_grad = None
            self.healthy_steps += len(losses)
            self.streak = 0
        return True

    # ------------------------------------------------------------------------------ reporting
    def _problem(self, reason: str, detail: str) -> str:
        self.last_problem = f"{reason}: {detail}"
        return reason

    def counters(self) -> dict[str, int]:
        """``train_health/...`` values for the learner's status and /diagnostics."""
        out = {"train_health/skipped": sum(self.skipped.values())}
        out.update({f"train_health/skipped/{r}": self.skipped[r] for r in SKIP_REASONS})
        out.update({"train_health/restores": self.restores, "train_health/unhealthy_streak": self.streak,
                    "train_health/healthy_steps": self.healthy_steps})
        return out

    def summary(self, run: CheckedRun) -> dict[str, Any]:
        """What a checkpoint records about the model's health (``meta["health"]``): whether it is healthy (finite
        weights within ``max_weight``), the largest weight, the counters (with the current streak of skipped
        steps) and the last problem."""
        biggest = max_abs([*run.model.net.parameters(), run.dual.value])
        finite = math.isfinite(biggest)
        return {
            "healthy": bool(finite and biggest <= self.config.max_weight),
            "finite": finite,
            "max_abs_weight": biggest if finite else None,
            "healthy_steps": self.healthy_steps,
            "skipped": {r: self.skipped[r] for r in SKIP_REASONS},
            "restores": self.restores,
            "unhealthy_streak": self.streak,
            "last_problem": self.last_problem,
            "limits": {"explode_ratio": self.config.explode_ratio, "max_weight": self.config.max_weight},
        }
