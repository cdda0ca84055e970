"""How an online learner takes its primal-dual updates (:class:`OnlineUpdates`): ``n`` minibatches drawn from the
replay buffer in one call, then ``n`` steps of the fast engine's path
(:class:`~saml_ros.core.training.engines.stream.StreamRun`), or of the plain step where that path does not apply
(``TrainConfig.engine = "plain"``, an optimizer or network it does not know, ...).

Drawing ``n x B`` rows in one call gives the same minibatches as ``n`` draws of ``B`` (the generator is consumed
alike), so the engine is the only difference between the two paths (``test/test_online_fast.py``). The buffer's
rows at the start of a call are what its ``n`` minibatches are drawn from.
"""

from __future__ import annotations

import logging

import numpy as np
import torch

from saml_ros.core.data.buffer import ReplayBuffer
from saml_ros.core.online.telemetry import StepAverages
from saml_ros.core.training import PrimalDualTrainer
from saml_ros.core.training.dataset import Transitions
from saml_ros.core.training.engines.fused import make_stream_run
from saml_ros.core.training.engines.stream import StreamRun, stream_unsupported_reason

log = logging.getLogger("saml_ros.online")


class OnlineUpdates:
    """The update path of one trainer (see the module docstring).

    Args:
        trainer: the trainer (its config's ``batch_size``, ``log_every`` (0: 100) and ``engine``).
        history_rows: history rows kept (older ones are dropped: online training never ends).
        members: ensemble members that each get their own minibatch, ``(E, B, .)`` (plain steps: the fast path
            draws one minibatch for all members); 1: one minibatch ``(B, .)``.
    """

    def __init__(self, trainer: PrimalDualTrainer, history_rows: int, members: int = 1) -> None:
        self.trainer = trainer
        cfg = trainer.config
        self.batch_size = cfg.batch_size
        self.log_every = cfg.log_every or 100
        self.history_rows = history_rows
        self.members = members
        self.stream: StreamRun | None = None
        #: why the plain step runs (None: the fast path runs)
        self.plain_reason: str | None = ("engine 'plain' configured" if cfg.engine == "plain" else
                                         "a minibatch per ensemble member" if members > 1 else None)
        self._checked = self.plain_reason is not None

    @property
    def engine(self) -> str:
        """``"fast"`` or ``"plain"`` (before the first update: what the configuration asks for)."""
        return "plain" if self.plain_reason is not None else "fast"

    def run(self, n: int, buffer: ReplayBuffer, rng: np.random.Generator, averages: StepAverages) -> None:
        """``n`` updates on minibatches drawn from ``buffer`` with ``rng``; each healthy step's values (member 0)
        go into ``averages``."""
        tr, bsz, e = self.trainer, self.batch_size, self.members
        shape = (n, bsz) if e == 1 else (n, e, bsz)
        x, u, y = (a.reshape(*shape, a.shape[-1]) for a in buffer.sample(n * e * bsz, rng))
        if not self._checked:
            self._checked = True
            like = Transitions(tr.model, tr.spec, x[0, :2], u[0, :2], y[0, :2])
            self.plain_reason = stream_unsupported_reason(tr, like)
            if self.plain_reason is None:
                self.stream = make_stream_run(tr, bsz, self.log_every, like)
            else:
                log.info("fast online updates not used (%s): plain steps", self.plain_reason)
        if self.stream is not None:
            rows = self.stream.steps(x, u, y)[:, 0]
            averages.add_rows(rows[~torch.isnan(rows).any(-1)])
            if tr.steps // self.log_every != (tr.steps - n) // self.log_every:
                tr.history.keep_last(self.history_rows)
            return
        dt = tr.config.torch_dtype
        for j in range(n):
            healthy = tr.health.healthy_steps
            vals = tr.step(torch.from_numpy(x[j]).to(dt), torch.from_numpy(u[j]).to(dt), torch.from_numpy(y[j]).to(dt))
            if tr.health.healthy_steps > healthy:  # a skipped step's values are not the model's
                averages.add(vals)
            if tr.steps % self.log_every == 0:
                tr.log_point()
                tr.history.keep_last(self.history_rows)
