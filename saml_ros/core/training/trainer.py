"""Stochastic primal-dual training (the paper's Algorithm 1) for ensembles of dynamics models.

Per step, for every ensemble member independently:

1. sample a minibatch, evaluate the objective estimate ``f`` and constraint estimates ``g_k``;
2. descend on theta with the gradient of ``f + sum_k lambda_k g_k`` (lambda detached);
3. ascend on lambda with the *detached* minibatch constraint estimate ``g_k``;
4. project: ``lambda <- max(lambda, 0)``.

:class:`PrimalDualTrainer` holds the run's state (model, primal optimizer, :class:`~saml_ros.core.training.dual.
DualVariables`, generator, counters, :class:`~saml_ros.core.training.history.TrainingLog`); :meth:`~PrimalDualTrainer.
fit` hands it to an :class:`~saml_ros.core.training.engines.Engine`, :meth:`~PrimalDualTrainer.step` takes one
online step. The Uniformly Accurate baseline is the same trainer with a spec that has no constraints.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any

import numpy as np
import torch

from saml_ros.core.model.network import DynamicsModel
from saml_ros.core.spec import ProblemSpec, SpecValues
from saml_ros.core.training.config import TrainConfig, make_optimizer
from saml_ros.core.training.dataset import Transitions
from saml_ros.core.training.diagnosis import MET, FeasibilityDiagnosis, diagnose
from saml_ros.core.training.dual import DualVariables
from saml_ros.core.training.engines import ENGINES, PlainEngine, minibatch_plan, primal_dual_step
from saml_ros.core.training.evaluate import evaluate_spec
from saml_ros.core.training.health import HealthConfig, TrainingHealth
from saml_ros.core.training.history import FeasibilityReport, History, TrainingLog, check_feasibility, progress_bar
from saml_ros.core.training.schedule import LRSchedule, schedules_for

log = logging.getLogger("saml_ros.trainer")


class PrimalDualTrainer:
    """Algorithm 1 on a :class:`DynamicsModel` (any ensemble size) and a :class:`ProblemSpec`.

    Attributes (what engines read and update, :class:`~saml_ros.core.training.engines.RunState`):
        model, spec, config: the model (moved to ``config``'s dtype), the problem, the hyper-parameters.
        primal_opt: the optimizer of the network parameters.
        dual: the dual variables (lambda ``(E, K)``, their method and optimizer; :mod:`~saml_ros.core.training.dual`).
        schedules: the ``(primal, dual)`` learning-rate schedules (:mod:`~saml_ros.core.training.schedule`); their
            horizon is ``config.schedule_steps``, or, from :meth:`fit` on, ``config.epochs`` x the data's
            minibatches per epoch when that is 0 (online without it, ``"auto"`` schedules are constant and
            an explicit one is None until :meth:`fit`: :meth:`step` then raises ``ValueError``).
        rng: the generator minibatches are drawn from.
        log: the history and the minibatch values since its last row.
        health: the training-health checks and counters (:mod:`~saml_ros.core.training.health`).
        steps: primal-dual updates done so far; epochs_done: passes over the data of :meth:`fit` so far.
        engine_used: engine of the last :meth:`fit` (``"fast"`` or ``"plain"``), None before.
        kernel_used: True when the last :meth:`fit` ran its steps in the fused C++ kernel
            (:mod:`~saml_ros.core.training.engines.fused`; ``engine_used`` is then ``"fast"``).
        diagnosis: the feasibility diagnosis at the end of the last :meth:`fit` (None before).
        aim: how the bounds trained at were chosen when they are not the problem's (``spec`` is then the aimed
            problem and ``given_spec`` the problem as given, what checkpoints record): the ``meta["aim"]`` record
            of :class:`~saml_ros.core.training.verdict.AimReport` (:func:`~saml_ros.core.training.trainer_io.
            resume_trainer` re-applies a checkpoint's); None: training aims at eps.
        given_spec: the problem as given while ``spec`` is an aimed one; None otherwise.
    """

    def __init__(self, model: DynamicsModel, spec: ProblemSpec, config: TrainConfig | None = None,
                 health: HealthConfig | None = None) -> None:
        self.model = model
        self.spec = spec
        self.config = config or TrainConfig()
        self.model.to(self.config.torch_dtype)
        self.primal_opt = make_optimizer(self.config.primal_optimizer, list(model.net.parameters()),
                                         self.config.primal_lr, maximize=False)
        self.dual = DualVariables.for_config(self.config, model.n_models, spec.n_constraints,
                                             [t.eps for t in spec.constraints])
        self.schedules: tuple[LRSchedule, LRSchedule] | None = None
        try:
            self.schedules = schedules_for(self.config, 0)
        except ValueError:  # an explicit schedule without schedule_steps: fit() knows the horizon
            pass
        self.steps = 0
        self.epochs_done = 0.0
        self.log = TrainingLog(spec.constraint_names)
        self.health = TrainingHealth(health)
        self.rng = torch.Generator().manual_seed(int(self.config.seed))
        self.engine_used: str | None = None
        self.kernel_used = False
        self.diagnosis: FeasibilityDiagnosis | None = None
        self.aim: dict[str, Any] | None = None
        self.given_spec: ProblemSpec | None = None

    @property
    def lam(self) -> torch.Tensor:
        """Dual variables ``(E, K)`` (a detached view; always >= 0)."""
        return self.dual.value

    @property
    def history(self) -> History:
        """The training curve."""
        return self.log.history

    # ----------------------------------------------------------------------------------- online
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
        return primal_dual_step(self, x, u, y, base, masks)

    def log_point(self) -> None:
        """Append the mean of the minibatch values since the last log point to :attr:`history`."""
        self.log.point(self.steps, self.epochs_done, self.lam)

    # ----------------------------------------------------------------------------------- offline
    def fit(
        self,
        data: Transitions,
        epochs: int | None = None,
        progress: bool = False,
        desc: str = "training",
        callback: Callable[[PrimalDualTrainer], None] | None = None,
        diagnose: bool = True,
    ) -> History:
        """Run ``epochs`` passes of Algorithm 1 over a fixed dataset; every member sees its own shuffle.
        ``callback(self)`` runs after each epoch. The learning-rate schedules span ``config.epochs`` whatever
        ``epochs`` is, so a run may be fitted in parts (``diagnose=False`` for all but the last: no diagnosis, no
        warnings).

        Runs on the engine named by ``config.engine`` (see :class:`TrainConfig`), or on the plain one where that
        engine does not apply; :attr:`engine_used` says which one ran. At the end the feasibility diagnosis on
        ``data`` is kept in :attr:`diagnosis` and every constraint not met is logged as a warning (:meth:`diagnose`).
        """
        epochs = self.config.epochs if epochs is None else epochs
        self.schedules = schedules_for(self.config, self.config.epochs * minibatch_plan(self.config.batch_size,
                                                                                         len(data))[1])
        engine = ENGINES[self.config.engine]()
        why = engine.unsupported_reason(self, data)
        if why is not None:
            log.info("%s training engine not used (%s): running the plain loop", engine.name, why)
            engine = PlainEngine()
        self.engine_used = engine.name
        self.kernel_used = False
        bar = progress_bar(epochs * minibatch_plan(self.config.batch_size, len(data))[1], desc) if progress else None
        on_epoch = None if callback is None else (lambda: callback(self))
        try:
            engine.fit(self, data, epochs, bar, on_epoch)
            self.kernel_used = bool(getattr(engine, "kernel_used", False))
        finally:
            if bar is not None:
                bar.close()
        # the dataset-level values at the end: the fused kernel's own pass over the data where it ran
        if not diagnose:
            return self.history
        evaluation = getattr(engine, "evaluation", None) if self.kernel_used else None
        self.diagnosis = self.diagnose(data, evaluation)
        for c in self.diagnosis.constraints:
            if c.verdict != MET:
                log.warning(c.message)
        return self.history

    # ----------------------------------------------------------------------------------- evaluation
    @torch.no_grad()
    def evaluate(self, data: Transitions, chunk: int = 65536) -> dict[str, np.ndarray]:
        """Dataset-level objective ``(E,)``, constraints ``(E, K)`` and Lagrangian ``(E,)`` at the current
        theta and lambda (the quantity the convergence experiment reports)."""
        return evaluate_spec(self.model, self.spec, data, self.lam, chunk)

    def diagnose(self, data: Transitions | None = None,
                 evaluation: dict[str, np.ndarray] | None = None) -> FeasibilityDiagnosis:
        """Per constraint: met, smallest left-hand side, lambda rising, verdict
        (:mod:`~saml_ros.core.training.diagnosis`); with ``data`` the final constraint values are dataset-level,
        without it the means of the history's tail. ``evaluation``: :meth:`evaluate` of ``data`` at the current
        state when the caller has it already."""
        eps = [t.eps for t in self.spec.constraints]
        if data is not None:
            ev = self.evaluate(data) if evaluation is None else evaluation
            final, f = ev["constraints"], torch.as_tensor(ev["objective"])
        else:
            final = None
            h = self.history
            f = torch.as_tensor(h.objective[-1]) if h.objective else torch.ones(self.model.n_models)
        relax = self.dual.relaxation(f).double().numpy()
        limit = None
        if type(self.dual.optimizer) is torch.optim.Adam and self.schedules is not None:
            limit = self.schedules[1].total(self.steps)  # Adam moves lambda by at most about lr per update
        rho = getattr(self.dual, "rho", None)  # the augmented Lagrangian's penalty (E, K), alike over members
        rho_k = None if rho is None or not eps else rho.reshape(-1, len(eps))[0].double().numpy()
        return diagnose(self.history, eps, self.steps, self.model.hidden, final, relax, f.double().numpy(), limit,
                        rho_k)

    def feasibility(self, tail: float = 0.25, rel_tol: float = 0.02) -> FeasibilityReport:
        """Flag constraints whose mean g over the last ``tail`` of the history exceeds ``rel_tol * eps``
        while lambda kept growing over that window (a converged saddle point hovers at g ~ 0)."""
        return check_feasibility(self.history, [t.eps for t in self.spec.constraints], tail, rel_tol)

    # ----------------------------------------------------------------------------------- state
    def state(self) -> dict[str, Any]:
        """Everything needed to resume: model weights, normalisation, lambda, optimizer states, counters."""
        dual = self.dual.state_dict()
        return {
            "model": self.model.state_dict(),
            "lam": dual["lam"],
            "primal_opt": self.primal_opt.state_dict(),
            "dual_opt": dual["optimizer"],
            "steps": self.steps,
            "epochs_done": self.epochs_done,
            "rng": self.rng.get_state(),
        }

    def load_state(self, st: dict[str, Any]) -> None:
        """Restore what :meth:`state` returned (``rng`` and ``epochs_done`` optional; ``dual_opt`` None: lambda only)."""
        self.model.load_state_dict(st["model"])
        self.primal_opt.load_state_dict(st["primal_opt"])
        if st.get("dual_opt") is None:  # keep the fresh optimizer (e.g. the checkpoint's was another method's)
            self.dual.assign_(st["lam"])
        else:
            self.dual.load_state_dict({"lam": st["lam"], "optimizer": st["dual_opt"]})
        self.steps = int(st["steps"])
        self.epochs_done = float(st.get("epochs_done", 0.0))
        if "rng" in st:
            self.rng.set_state(torch.as_tensor(st["rng"], dtype=torch.uint8))
