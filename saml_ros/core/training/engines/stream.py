"""Online updates on the fast engine's path: :class:`StreamRun` takes ``S`` primal-dual steps on ``S`` minibatches
handed over at once (e.g. drawn from a replay buffer in one call), with the fast engine's step.

The plain online step (:func:`~saml_ros.core.training.engines.plain.primal_dual_step`) costs ~40 autograd nodes
and the optimizers' per-parameter bookkeeping per update, and f_hat, the region masks and the normalisation are
computed per minibatch. Here the ``S`` minibatches are prepared together (f_hat, masks, ``[z, 1]`` and ``f_hat - y``
in one pass over ``S x B`` rows), the flat state is read from the trainer once, ``S`` steps of
:meth:`FastRun._make_step` run, and the state is written back once: the trainer, its model, optimizers and dual
variables hold the result when :meth:`StreamRun.steps` returns, exactly as after ``S`` calls of
:meth:`~saml_ros.core.training.PrimalDualTrainer.step`.

The same as ``S`` plain steps on the same minibatches (float rounding aside, see :mod:`.fast`; bounded by
``test/test_online_fast.py``): every dual method and learning-rate schedule, history rows every ``log_every``
updates (the minibatch values in between averaged, as ``PrimalDualTrainer.log_point``), ``trainer.steps``
advanced by ``S`` (``epochs_done`` unchanged: online training has no epochs). The health checks are the fast
plain step's per update for the loss and the gradient (a bad minibatch is skipped before it changes anything),
and the weights per block of ``check_every`` steps (a bad block is put back and counted skipped;
:mod:`~saml_ros.core.training.health`).

Shapes: ``S`` minibatches, ``B`` samples each (shared by all ``E`` members), ``T = 1 + K`` spec terms.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

from saml_ros.core.training.dataset import Transitions
from saml_ros.core.training.engines.base import RunState
from saml_ros.core.training.engines.fast import FastRun, unsupported_reason

_vector_norm = torch.linalg.vector_norm


def stream_unsupported_reason(trainer: RunState, data: Transitions) -> str | None:
    """Why :class:`StreamRun` cannot run ``trainer`` on minibatches like ``data``'s rows, or ``None``."""
    if data.per_member:
        return "per-member minibatches"
    return unsupported_reason(trainer, data)


class StreamRun(FastRun):
    """Fast online updates of one trainer (see the module docstring).

    Args:
        trainer: the run (a :class:`~saml_ros.core.training.PrimalDualTrainer`).
        batch_size: samples per minibatch ``B``.
        log_every: updates between two history rows.
        like: a few rows of the data (a :class:`Transitions` of the trainer's model and spec) to check support on.

    Raises:
        ValueError: the fast path does not apply (:func:`stream_unsupported_reason`).
    """

    #: False: the torch path (the fused kernel's run, :class:`~.fused.FusedStreamRun`, says True)
    kernel_used = False
    #: why the fused kernel does not run these updates (set by :func:`~.fused.make_stream_run`)
    kernel_reason: str | None = None

    def __init__(self, trainer: RunState, batch_size: int, log_every: int, like: Transitions) -> None:
        why = stream_unsupported_reason(trainer, like)
        if why is not None:
            raise ValueError(f"fast online updates cannot run this trainer: {why}")
        super().__init__(trainer, like)
        self.bsz = batch_size
        self.log_every = log_every
        self._step = self._make_step(batch_size, self._gate)
        self._skipped_in_block = 0

    def _gate(self, row: Tensor, grad: Tensor) -> bool:
        """The plain step's loss and gradient checks, on the step's values and gradient (one sync); a skipped
        step's values become NaN."""
        health = self.tr.health
        values = row.tolist()  # E x T floats: summed here, cheaper than tensor reductions at these sizes
        obj, total = sum(v[0] for v in values), sum(sum(v) for v in values)
        norm = float(_vector_norm(grad))
        why = health.check_loss_values(total, obj) or health.check_gradient_norm(norm)
        if why is None:
            health.count_healthy()
            return True
        row.fill_(float("nan"))
        health.skip(why)
        self._skipped_in_block += 1
        return False

    def _check_weights(self, vals: Tensor, a: int, b: int, snap: Any) -> None:
        """The weights check after steps ``a:b``: on a problem the state from before them is put back, and their
        steps not skipped already are counted skipped (values NaN)."""
        health = self.tr.health
        skipped, self._skipped_in_block = self._skipped_in_block, 0
        why = health.check_weights_of([self.net.flat, self.lam])
        if why is None:
            return
        self._restore(snap)
        n_ok = b - a - skipped
        health.healthy_steps -= n_ok  # counted by the gate, undone by the restore
        vals[a:b] = float("nan")
        health.skip(why, n_ok)
        health.restores += 1

    def _take_minibatches(self, x: Any, u: Any, y: Any) -> int:
        """Make ``S`` minibatches ``(S, B, .)`` this run's data and prepare their sources; returns ``S``."""
        s, b = int(x.shape[0]), int(x.shape[1])
        if b != self.bsz:
            raise ValueError(f"minibatches of {b} samples, this run takes {self.bsz}")
        flat = [a.reshape(s * b, a.shape[-1]) for a in (x, u, y)]
        self.data = Transitions(self.tr.model, self.tr.spec, *flat)
        self._prepare_sources()
        return s

    def steps(self, x: Any, u: Any, y: Any) -> Tensor:
        """``S`` updates on the minibatches ``x, u, y`` ``(S, B, .)`` (numpy or torch, float64 or the model's dtype).

        Returns the minibatch term values before each update ``(S, E, T)`` (objective, then g_k; NaN for steps the
        health check skipped).
        """
        s = self._take_minibatches(x, u, y)
        tr = self.tr
        b = self.bsz
        idx = torch.arange(s * b).view(s, 1, b).expand(s, self.E, b)
        z_all, r_all, sg_all = self._gather(idx)
        vals = torch.empty(s, self.E, self.T, dtype=self.dtype)
        rows = vals.unbind(0)
        self.load_state()
        self._pending += self._pending_from_log()  # values of plain steps taken in between
        every, log_every = tr.health.config.check_every, self.log_every
        step, rates = self._step, self._rates
        start = block = 0
        snap = self._snapshot()
        for j in range(s):
            rates(tr.steps)
            step(z_all[j], r_all[j], sg_all[j], rows[j])
            tr.steps += 1
            logs = tr.steps % log_every == 0
            if j + 1 - block >= every or j + 1 == s or logs:
                self._check_weights(vals, block, j + 1, snap)
                block = j + 1
                if block < s:
                    snap = self._snapshot()
            if logs:
                self._pending.append(vals[start : j + 1])
                start = j + 1
                self._log_point()
        if start < s:
            self._pending.append(vals[start:s])
        self.store_state()
        return vals
