"""The plain engine: Algorithm 1 with autograd and ``torch.optim`` (the reference the fast engine is tested
against), and the single primal-dual step online training takes (:func:`primal_dual_step`)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import torch

from saml_ros.core.spec import SpecValues
from saml_ros.core.training.dataset import Transitions
from saml_ros.core.training.engines.base import Engine, RunState, minibatch_plan


def primal_dual_step(
    run: RunState,
    x: torch.Tensor,
    u: torch.Tensor,
    y: torch.Tensor,
    base: torch.Tensor | None = None,
    masks: list[torch.Tensor | None] | None = None,
) -> SpecValues:
    """One primal-dual update of ``run`` on a minibatch (``(B, .)`` shared or ``(E, B, .)`` per member).

    Descends on theta along the dual method's primal loss (members are independent: their losses are summed),
    then lets the dual variables ascend on the detached constraint estimates; the learning rates follow
    ``run.schedules`` at update ``run.steps``. Returns the detached minibatch spec values *before* the update
    (also added to ``run.log``, unless ``run.health`` skipped the step: see :mod:`~saml_ros.core.training.health`).

    Raises:
        ValueError: ``run.schedules`` is None (a schedule whose horizon is not known yet).
    """
    apply_schedules(run)
    pred = run.model(x, u, base)
    if masks is None:
        masks = run.spec.masks(x, u, y)
    vals = run.spec.evaluate_with_masks(y, pred, masks)
    loss = run.dual.lagrangian(vals).sum()
    health = run.health
    why = health.check_loss(loss, vals.objective)
    if why is None:
        run.primal_opt.zero_grad(set_to_none=True)
        loss.backward()
        why = health.check_gradients(list(run.model.net.parameters()))
    if why is None:
        health.ensure_snapshot(run)
        run.primal_opt.step()
        run.dual.step(vals.constraints.detach(), vals.objective.detach())
        why = health.check_weights(run)
        if why is not None:
            health.restore(run)
    run.steps += 1
    out = SpecValues(vals.objective.detach(), vals.constraints.detach(), vals.region_fraction.detach())
    if why is None:
        health.healthy(run)
        run.log.add(out)
    else:
        run.primal_opt.zero_grad(set_to_none=True)
        health.skip(why)
    return out


def apply_schedules(run: RunState) -> None:
    """Set both optimizers' learning rates for update ``run.steps`` (nothing to do for constant schedules)."""
    if run.schedules is None:
        raise ValueError("a learning-rate schedule other than constant needs its horizon: set schedule_steps > 0 "
                         "(the horizon in updates) or train with fit()")
    primal, dual = run.schedules
    if not primal.constant:
        for group in run.primal_opt.param_groups:
            group["lr"] = primal.lr(run.steps)
    if not dual.constant:
        run.dual.set_lr(dual.lr(run.steps))


class PlainEngine(Engine):
    """Epochs of :func:`primal_dual_step` on minibatches of a fixed dataset (runs every trainer)."""

    name = "plain"

    def fit(self, run: RunState, data: Transitions, epochs: int, bar: Any = None,
            on_epoch: Callable[[], None] | None = None) -> None:
        n = len(data)
        bsz, per_epoch = minibatch_plan(run.config.batch_size, n)
        e = run.model.n_models
        log_every = run.config.log_every or per_epoch
        run.model.train()
        for _ in range(epochs):
            perm = torch.argsort(torch.rand(e, n, generator=run.rng), dim=1)
            for j in range(per_epoch):
                idx = perm[:, j * bsz : (j + 1) * bsz]
                x, u, y, base = data.take(idx)
                primal_dual_step(run, x, u, y, base, data.take_masks(idx))
                run.epochs_done += 1.0 / per_epoch
                if run.steps % log_every == 0:
                    run.log.point(run.steps, run.epochs_done, run.dual.value)
                    if bar is not None:
                        bar.set_postfix_str(run.log.postfix(), refresh=False)
                if bar is not None:
                    bar.update(1)
            run.epochs_done = round(run.epochs_done, 9)
            if on_epoch is not None:
                on_epoch()
        run.log.point(run.steps, run.epochs_done, run.dual.value)
