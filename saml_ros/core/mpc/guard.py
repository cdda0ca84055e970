"""Safe use of learned models in the shooting MPC (ROS-free): :class:`GuardedController`.

A learned residual phi is only trustworthy where it has data. Three remedies, each optional
(:class:`GuardConfig`), all counted:

* **ensemble disagreement** (an out-of-distribution signal): the members of the checkpoint's ensemble were trained
  from different initialisations and minibatches on the same data; where they disagree the data did not pin
  phi down. The disagreement of a predicted state is ``sigma = sqrt(mean_k ||phi_k - mean_k phi_k||^2)``
  (state units; :class:`EnsembleNP`). When the plan the learned model would fly from here (its previous plan
  shifted, then the new plan) reaches a state with ``sigma > max_disagreement``, this step is planned with f_hat
  alone (``fallbacks``), warm-started from the learned plan;
* **a bounded residual**: ``phi`` clipped per target field to ``+-bound``, the largest residual
  ``|y - f_hat(x, u)|`` in the learner's buffer times a margin (the learner records it in the checkpoint's meta,
  ``learner.residual_bound``): outside its data a network can extrapolate to any size, the physics cannot
  (:class:`BoundedDynamics`);
* **a live monitor with roll back** (:class:`~saml_ros.core.mpc.monitor.LiveErrorMonitor`): every live
  transition :meth:`GuardedController.observe` is given scores the active model and f_hat; the steps the learned
  model planned (not those planned with f_hat on disagreement) enter the monitor's window, and when the active
  model is worse there, the controller rolls back to the previous model (if it had one that was not rolled back itself),
  otherwise to f_hat, and that model version is never used again (``rollbacks``). A new model is scored the same
  way *before* it is flown, on the newest live transitions already seen (the last ``window`` of each stream
  that the model in use planned, or f_hat when no model was in use): one worse than f_hat there is refused,
  never flown and never used again (:meth:`GuardedController.offer_model` returns False; counted in ``rollbacks``
  and ``refused_before_flight``).

The *task check* (:mod:`~saml_ros.core.mpc.task_check`, ``GuardConfig.task``): a plan flown while a learned model
is in use that breaks a constraint some control could keep is re-planned by f_hat from a cold start; when f_hat's
own plan keeps the constraints it is flown instead (a strike), and ``task.strikes`` strikes within the last
``task.window`` such steps roll the model back (:meth:`GuardedController._task_step`).

With the roll back, an optional *constraint watch* (``MonitorConfig.constraint_strikes``, off by default) also rolls
back a model whose flown steps break a state bound of the task that its own prediction kept and f_hat's saw coming
(:meth:`GuardedController._constraint_strike`).

The unguarded MPC is the same controller with every remedy off. The roll back alone works around any controller of
the :class:`~saml_ros.core.mpc.contract.Controller` protocol (the one-shot paddle-ball MPC too: its live transition is
the pre-impact state, the command and the post-impact velocity): the monitor predicts with the controller's numpy
model (``dyn.step1``) where it has one, else with the model itself and the system's f_hat; the other remedies
need the shooting MPC.
"""

from __future__ import annotations

import math
from collections import Counter, OrderedDict, deque
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from saml_ros.core.dynamics.system import System
from saml_ros.core.mpc.contract import MPCResult
from saml_ros.core.mpc.dynamics_np import Jac3, NumpyDynamics
from saml_ros.core.mpc.mlp_np import NumpyMLP
from saml_ros.core.mpc.monitor import MAX_STREAMS, LiveErrorMonitor, MonitorConfig, data_scale
from saml_ros.core.mpc.shooting.controller import ShootingMPC
from saml_ros.core.mpc.task_check import TaskCheck, TaskCheckConfig

if TYPE_CHECKING:
    from saml_ros.core.model.network import DynamicsModel

#: the ``meta["learner"]`` key of a checkpoint's per-field residual bound (list of n_y floats)
RESIDUAL_BOUND_KEY = "residual_bound"


@dataclass(frozen=True)
class GuardConfig:
    """Which remedies :class:`GuardedController` applies (see the module docstring).

    Attributes:
        max_disagreement: ensemble disagreement sigma (state units) above which a step is planned with f_hat;
            ``inf`` = off (also off for a single model).
        bound_residual: clip phi to the checkpoint's recorded residual bound (off when it records none).
        rollback: run the live monitor and roll back (``monitor`` says when).
        monitor: the monitor's window and threshold.
        infeasible: when the learned model's plan violates a constraint some control could keep (not only rows
            the current state fixes), plan this step with f_hat too and fly f_hat's plan if it satisfies the
            constraints or violates them less.
        task: the task check (:mod:`~saml_ros.core.mpc.task_check`): fly f_hat's own plan where the learned
            model's breaks a constraint f_hat's keeps, and roll the model back after ``task.strikes`` such steps.
    """

    max_disagreement: float = math.inf
    bound_residual: bool = False
    rollback: bool = False
    monitor: MonitorConfig = MonitorConfig()
    infeasible: bool = False
    task: TaskCheckConfig = TaskCheckConfig()

    def __post_init__(self) -> None:
        if not self.max_disagreement > 0:
            raise ValueError(f"guard: max_disagreement must be > 0 (inf = off), got {self.max_disagreement}")

    @property
    def enabled(self) -> bool:
        return (math.isfinite(self.max_disagreement) or self.bound_residual or self.rollback or self.infeasible
                or self.task.enabled)

    @property
    def needs_shooting(self) -> bool:
        """Whether a remedy other than the roll back is on (those need the shooting MPC's plans and warm starts)."""
        return math.isfinite(self.max_disagreement) or self.bound_residual or self.infeasible or self.task.enabled


class EnsembleNP:
    """phi of every member of an ensemble in one batched pass: ``(B, n_x), (B, n_u) -> (E, B, n_y)``."""

    def __init__(self, model: DynamicsModel) -> None:
        members = [NumpyMLP(model, i) for i in range(model.n_models)]
        self.n_models = len(members)
        self.w_x = np.stack([m.w_x for m in members])  # (E, n_x, d)
        self.w_u = np.stack([m.w_u for m in members])
        self.weights = [np.stack([m.weights[i] for m in members]) for i in range(1, len(members[0].weights))]
        self.biases = [np.stack([m.biases[i] for m in members])[:, None, :] for i in range(len(members[0].biases))]
        self.slopes = np.array([m.slopes for m in members]).reshape(self.n_models, -1)  # (E, L-1)

    def forward(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        h = x @ self.w_x + u @ self.w_u + self.biases[0]
        for i, w in enumerate(self.weights):
            a = self.slopes[:, i][:, None, None]
            h = np.where(h >= 0.0, h, a * h) @ w + self.biases[i + 1]
        return h

    def disagreement(self, x: np.ndarray, u: np.ndarray, bound: np.ndarray | None = None) -> np.ndarray:
        """sigma ``(B,)``: RMS over members of ``||phi_k - mean_k phi_k||`` (phi clipped to ``+-bound`` if given)."""
        phi = self.forward(x, u)
        if bound is not None:
            phi = np.clip(phi, -bound, bound)
        d = phi - phi.mean(0, keepdims=True)
        return np.sqrt(np.einsum("ebj,ebj->b", d, d) / self.n_models)


class BoundedDynamics:
    """``f_hat + clip(phi, -bound, bound)`` (per target field) of a residual :class:`NumpyDynamics`; the
    Jacobian of a clipped output is f_hat's. Same interface as :class:`NumpyDynamics`."""

    #: what the SQP's C kernel (:mod:`~saml_ros.core.mpc.shooting.native`) reads from a model with this marker:
    #: ``base``, ``mlp`` and the per-field ``bound`` of ``y = base(x, u) + clip(mlp(x, u), -bound, bound)``
    clips_phi = True

    def __init__(self, dyn: NumpyDynamics, bound: np.ndarray) -> None:
        if dyn.kind != "residual" or dyn.base is None or dyn.mlp is None:
            raise ValueError(f"a residual bound needs a residual model, got kind {dyn.kind!r}")
        self.system = dyn.system
        self.kind = "residual"
        self.base, self.mlp = dyn.base, dyn.mlp
        self.bound = np.asarray(bound, dtype=np.float64)
        self._neg = -self.bound

    def _clip(self, phi: np.ndarray) -> np.ndarray:
        # np.clip's Python wrapper cost 6 % of a guarded solve (one call per predicted step): the same values
        return np.minimum(np.maximum(phi, self._neg, out=phi), self.bound, out=phi)

    def step(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        return self.base.step(x, u) + self._clip(self.mlp.forward(x, u))

    def step1(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        return self.base.step1(x, u) + self._clip(self.mlp.forward(x, u))

    def _phi_jac(self, x: np.ndarray, u: np.ndarray) -> Jac3:
        """phi and its Jacobians, zero in the fields the bound clips."""
        phi, ax, au = self.mlp.forward_jac(x, u)
        keep = (np.abs(phi) < self.bound)[:, :, None]
        return phi, ax * keep, au * keep

    def step_jac(self, x: np.ndarray, u: np.ndarray) -> Jac3:
        y, a, b = self.base.step_jac(x, u)
        phi, ax, au = self._phi_jac(x, u)
        return y + np.clip(phi, -self.bound, self.bound), a + ax, b + au

    def jacobians(self, x: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The Jacobians of :meth:`step_jac` alone (which fields are clipped needs phi, so it is computed; f_hat's
        prediction is not, when the base model has Jacobians of its own)."""
        base_jac = getattr(self.base, "jacobians", None)
        a, b = base_jac(x, u) if base_jac is not None else self.base.step_jac(x, u)[1:]
        _, ax, au = self._phi_jac(x, u)
        return a + ax, b + au

    def rollout_batch(self, x0: np.ndarray, us: np.ndarray) -> np.ndarray:
        """Predicted states ``(K, T+1, n)`` of control sequences ``us`` ``(K, T, m)`` from ``x0`` ``(n,)``."""
        k, horizon = us.shape[0], us.shape[1]
        xs = np.empty((k, horizon + 1, x0.shape[0]))
        xs[:, 0] = x0
        for t in range(horizon):
            xs[:, t + 1] = self.step(xs[:, t], us[:, t])
        return xs


def residual_bound(meta: dict[str, Any], n_y: int) -> np.ndarray | None:
    """The per-field residual bound ``(n_y,)`` a checkpoint's meta records (``meta["learner"]["residual_bound"]``),
    or None when it records none (or a malformed one)."""
    learner = meta.get("learner") if isinstance(meta, dict) else None
    raw = learner.get(RESIDUAL_BOUND_KEY) if isinstance(learner, dict) else None
    if raw is None:
        return None
    b = np.asarray(raw, dtype=np.float64).reshape(-1)
    if b.shape != (n_y,) or not np.all(np.isfinite(b)) or np.any(b <= 0):
        return None
    return b


@dataclass
class _Active:
    """A model the guarded controller plans with: the model, its tag (checkpoint version), bound, ensemble."""

    model: DynamicsModel | None
    tag: int
    bound: np.ndarray | None
    ensemble: EnsembleNP | None
    scale: float = math.nan  #: f_hat's mean squared one-step error over its data (the monitor's margin)


class GuardedController:
    """The MPC with the guards of :class:`GuardConfig` around a learned-model controller (see the module docstring).

    Args:
        learned: the controller that plans with the learned model (its model is set by :meth:`set_model`); a
            :class:`ShootingMPC`, or for the roll back alone any :class:`~saml_ros.core.mpc.contract.Controller`.
        base: a controller of the same problem planning with f_hat alone (fallback and roll-back target).
        config: the remedies.

    ``counters``: ``solves``, ``solves_base`` (planned with f_hat: fallbacks, after a roll back or without a
    model), ``fallbacks`` (disagreement above the threshold), ``rollbacks``, ``bounded`` (solves whose model has a
    residual bound), ``clipped`` (learned plans flown on which the bound clipped phi). :attr:`tag` is the tag of the model in use (0 = f_hat); :attr:`last_disagreement` the largest
    sigma of the last learned plan checked.
    """

    def __init__(self, learned: ShootingMPC, base: ShootingMPC, config: GuardConfig) -> None:
        if learned.horizon != base.horizon or learned.system is not base.system:
            raise ValueError("guarded MPC: the learned and the base controller must solve the same problem")
        #: both plan over a horizon with warm starts (shooting MPCs, the generic planner of a robot's ``mpc:``
        #: section); otherwise only the roll back applies
        self.shooting = all(isinstance(c, ShootingMPC) or (hasattr(c, "warm_start_plan") and
                                                           hasattr(c, "set_warm_start")) for c in (learned, base))
        if not self.shooting and config.needs_shooting:
            raise ValueError(f"guarded MPC: only guard.rollback applies to the {learned.system.name} MPC (one-shot); "
                             "the other remedies need the shooting MPC")
        self.learned, self.base = learned, base
        self.config = config
        self.system: System = learned.system
        self.horizon = learned.horizon
        self.monitor = LiveErrorMonitor(config.monitor)
        self.task_check = TaskCheck(config.task)
        self.counters: Counter[str] = Counter()
        self._active = _Active(None, 0, None, None)
        self._previous: _Active | None = None
        self._banned: set[int] = set()
        self.last_disagreement = math.nan
        self.last_source = "base"
        #: squared one-step errors of the model in use and of f_hat on the last live transition observed
        self.live_error_model = math.nan
        self.live_error_base = math.nan
        #: stream -> the newest live transitions (x, u, target) a new model is scored on before it flies
        self._recent: OrderedDict[int, deque[tuple[np.ndarray, np.ndarray, np.ndarray]]] = OrderedDict()
        #: (the refused model's mean squared error, f_hat's, transitions) of the last refusal before flight
        self.last_refusal: tuple[float, float, int] | None = None
        #: the constraint watch: stream -> the last ``constraint_steps`` learned-planned steps ``(x, u)`` and the
        #: strikes among the last ``window`` of them (see :meth:`_constraint_strike`)
        self._watch: dict[int, tuple[deque[tuple[np.ndarray, np.ndarray]], deque[bool]]] = {}
        #: (realised violation, the model's predicted one, f_hat's) of the last strike of the constraint watch
        self.last_strike: tuple[float, float, float] | None = None

    # ------------------------------------------------------------------------------------------ models
    @property
    def task(self) -> Any:
        return self.learned.task

    @property
    def tag(self) -> int:
        """Tag (checkpoint version) of the model in use; 0 = f_hat."""
        return self._active.tag

    @property
    def model(self) -> DynamicsModel | None:
        return self._active.model

    @property
    def banned(self) -> frozenset[int]:
        """Tags rolled back (never used again)."""
        return frozenset(self._banned)

    def set_model(self, model: DynamicsModel | None, tag: int = 0, meta: dict[str, Any] | None = None) -> None:
        """:meth:`offer_model` (the Controller protocol's ``set_model``; whether it was taken is not returned)."""
        self.offer_model(model, tag, meta)

    def offer_model(self, model: DynamicsModel | None, tag: int = 0, meta: dict[str, Any] | None = None) -> bool:
        """Plan with ``model`` (tag ``tag``, e.g. its checkpoint version; ``meta`` its checkpoint meta, where the
        residual bound is read) from the next solve on; the model in use becomes the roll-back target. With the
        roll back on, a model that predicts the newest live transitions worse than f_hat is refused instead
        (False; :attr:`last_refusal` says by how much, the tag is never used again)."""
        if model is not None and self.config.rollback:
            worse = self._worse_on_recent(model, meta)
            if worse is not None:
                self.last_refusal = worse
                self._banned.add(tag)
                self.counters["rollbacks"] += 1
                self.counters["refused_before_flight"] += 1
                return False
        if self._active.model is not None and self._active.tag not in self._banned:
            self._previous = self._active
        self._activate(self._make_active(model, tag, meta or {}))
        return True

    def _worse_on_recent(self, model: DynamicsModel, meta: dict[str, Any] | None) -> tuple[float, float, int] | None:
        """The monitor's verdict on ``model`` over the newest live transitions of each stream: ``(its mean squared
        one-step error, f_hat's, transitions)`` of a stream where it says roll back, else None."""
        rows = [(stream, x, u, y) for stream, window in self._recent.items() for x, u, y in window]
        if not rows:
            return None
        xs, us = np.stack([r[1] for r in rows]), np.stack([r[2] for r in rows])
        if getattr(self.learned, "plans_mean", False):  # a planner of the members' mean: judge what it flies
            pred = np.mean([model.predict_np(xs, us, i) for i in range(model.n_models)], axis=0)
        else:
            pred = np.asarray(model.predict_np(xs, us, int(getattr(self.learned, "member", 0))), dtype=np.float64)
        monitor = self.monitor.sibling(data_scale(meta))
        for (stream, x, u, y), p in zip(rows, pred, strict=True):
            e_model, e_base = y - p, y - self._one_step(self.base, None, x, u)
            if monitor.add(float(e_model @ e_model), float(e_base @ e_base), stream):
                return monitor.mean_model, monitor.mean_base, monitor.samples
        return None

    def _make_active(self, model: DynamicsModel | None, tag: int, meta: dict[str, Any]) -> _Active:
        if model is None:
            return _Active(None, 0, None, None)
        bound = residual_bound(meta, self.system.target.size) if self.config.bound_residual else None
        if model.kind != "residual":
            bound = None
        ens = EnsembleNP(model) if model.n_models > 1 and math.isfinite(self.config.max_disagreement) else None
        return _Active(model, tag, bound, ens, data_scale(meta))

    def _activate(self, act: _Active) -> None:
        self._active = act
        self._watch.clear()
        self.learned.set_model(act.model)
        if act.bound is not None:
            set_bound = getattr(self.learned, "set_residual_bound", None)  # the generic planner clips phi itself
            if set_bound is not None:
                set_bound(act.bound)
            else:
                self.learned.dyn = BoundedDynamics(self.learned.dyn, act.bound)  # type: ignore[assignment]
        self.monitor.reset()
        self.task_check.reset()
        self.monitor.data_scale = act.scale

    def reset(self) -> None:
        """Drop both warm starts (the model in use and the roll-back state are kept)."""
        self.learned.reset()
        self.base.reset()

    def reset_models(self) -> None:
        """Back to f_hat with no history and no banned tags (a fresh evaluation run)."""
        self._previous = None
        self._banned.clear()
        self._recent.clear()
        self.last_refusal = None
        self._activate(_Active(None, 0, None, None))

    # ------------------------------------------------------------------------------------------ solve
    def _too_uncertain(self, plan_x: np.ndarray, plan_u: np.ndarray) -> bool:
        ens = self._active.ensemble
        if ens is None:
            return False
        if not np.all(np.isfinite(plan_x)):
            return True
        sigma = float(ens.disagreement(plan_x[:-1], plan_u, self._active.bound).max())
        self.last_disagreement = sigma
        return sigma > self.config.max_disagreement

    def solve(self, x0: np.ndarray, goal: Any | None = None) -> MPCResult:
        res = self._solve(x0, goal)
        if self.config.task.enabled and self._active.model is not None:
            res = self._task_step(x0, goal, res)
        return res

    def _task_step(self, x0: np.ndarray, goal: Any | None, res: MPCResult) -> MPCResult:
        """The task check on one step planned with a learned model in use (``res``, the plan chosen so far): when
        it breaks a constraint some control could keep, f_hat plans from ``x0`` from a cold start, and its plan is
        flown if it keeps every constraint (a strike, counted ``task_fallbacks``); ``task.strikes`` strikes in the
        window roll the model back (``task_rollbacks``). See :mod:`~saml_ros.core.mpc.task_check`."""
        strike = False
        if not res.success and not res.unavoidable:
            self.counters["task_checks"] += 1
            self.base.reset()  # f_hat's own plan: not warm-started from the learned model's
            own = self.base.solve(x0, goal)
            if own.success:
                strike = True
                self.counters["task_fallbacks"] += 1
                if self.last_source == "learned":
                    self.counters["solves_base"] += 1
                self.last_source = "base"
                if self.shooting:
                    _hand_over(own, self.learned)
                res = own
        if self.task_check.add(strike):
            self.counters["rollbacks"] += 1
            self.counters["task_rollbacks"] += 1
            self.retire()
        return res

    def _solve(self, x0: np.ndarray, goal: Any | None = None) -> MPCResult:
        self.counters["solves"] += 1
        if self._active.bound is not None:
            self.counters["bounded"] += 1
        use_learned = self._active.model is not None
        if use_learned and self._active.ensemble is not None:
            prev = self.learned.warm_start_plan()
            if prev is not None and self._too_uncertain(prev[1], prev[0]):
                use_learned = False
                self.counters["fallbacks"] += 1
        if use_learned:
            res = self.learned.solve(x0, goal)
            if self._active.ensemble is not None and self._too_uncertain(res.plan_x, res.plan_u):
                self.counters["fallbacks"] += 1
                _hand_over(res, self.base)
                use_learned = False
            elif self.config.infeasible and not res.success and not res.unavoidable:
                base = self._infeasible_fallback(x0, goal, res)
                if base is not None:
                    self.last_source = "base"
                    return base
            elif self.shooting:
                _hand_over(res, self.base)
        if not use_learned:
            self.counters["solves_base"] += 1
            res = self.base.solve(x0, goal)
            if self.shooting:
                _hand_over(res, self.learned)
        elif self._active.bound is not None and self._clipped(res):
            self.counters["clipped"] += 1
        self.last_source = "learned" if use_learned else "base"
        return res

    def _infeasible_fallback(self, x0: np.ndarray, goal: Any | None, learned: MPCResult) -> MPCResult | None:
        """The learned plan ``learned`` violates a constraint a control could keep: f_hat's plan from ``x0``
        (warm-started from the learned plan) when it keeps the constraints or violates them less (counted
        ``infeasible_fallbacks``), else None (fly the learned plan)."""
        _hand_over(learned, self.base)
        base = self.base.solve(x0, goal)
        if not (base.success or base.constraint_violation < learned.constraint_violation):
            return None
        _hand_over(base, self.learned)
        self.counters["infeasible_fallbacks"] += 1
        self.counters["solves_base"] += 1
        return base

    def _clipped(self, res: MPCResult) -> bool:
        """Whether the bound clipped phi anywhere on the learned plan ``res`` flies."""
        dyn = self.learned.dyn
        bound = self._active.bound
        clipped = getattr(self.learned, "phi_clipped", None)  # the generic planner
        if clipped is not None and bound is not None:
            return bool(clipped(res))
        if not isinstance(dyn, BoundedDynamics) or bound is None or not np.all(np.isfinite(res.plan_x)):
            return False
        return bool(np.any(np.abs(dyn.mlp.forward(res.plan_x[:-1], res.plan_u)) >= bound))

    # ------------------------------------------------------------------------------------------ monitor
    def observe(self, x: np.ndarray, u: np.ndarray, x_next: np.ndarray, stream: int = 0) -> bool:
        """One live transition ``(x, u) -> x_next`` (``(n,), (m,), (n_y,)``; ``u`` the command solved for ``x``;
        ``x_next`` the target: the next state, or the paddle ball's post-impact velocity): scores the model in use
        and f_hat on it (:attr:`live_error_model`, :attr:`live_error_base`) and keeps it for :meth:`offer_model`;
        with ``rollback`` on, True when it made the controller roll back (to the previous model or f_hat; the
        rolled-back tag is banned). Only steps the learned model planned enter the monitor's window: a step
        planned with f_hat on disagreement is counted in ``monitor_skipped``. ``stream``: which stream of
        transitions it belongs to (a robot among several on one topic; each has its own window in the monitor)."""
        y = np.asarray(x_next, dtype=np.float64)
        x = np.asarray(x, dtype=np.float64)
        u = np.asarray(u, dtype=np.float64)
        if not np.all(np.isfinite(y)) or not np.all(np.isfinite(x)):
            return False
        if self._active.model is None or self.last_source == "learned":  # what a new model is scored on first
            recent = self._recent.pop(stream, None) or deque(maxlen=self.config.monitor.window)
            recent.append((x.copy(), u.copy(), y.copy()))
            self._recent[stream] = recent
            while len(self._recent) > MAX_STREAMS:
                self._recent.popitem(last=False)
        e_base = y - self._one_step(self.base, None, x, u)
        self.live_error_base = float(e_base @ e_base)
        self.monitor.note_base(self.live_error_base)
        if self._active.model is None:
            self.live_error_model = self.live_error_base
            return False
        e_model = y - self._one_step(self.learned, self._active.model, x, u)
        self.live_error_model = float(e_model @ e_model)
        if self.last_source != "learned":
            # the step was planned with f_hat (the ensemble disagreed): the learned model did not fly it, and its
            # error where its members disagree is why it did not. Scoring it here rolled good models back on the
            # far starts they never planned (docs/demo.md, "The monitor scores the steps the model planned").
            self.counters["monitor_skipped"] += 1
            return False
        if not self.config.rollback:
            return False
        if self._constraint_strike(x, u, y, stream):
            self.counters["rollbacks"] += 1
            self.counters["constraint_rollbacks"] += 1
            self.retire()
            return True
        if not self.monitor.add(self.live_error_model, self.live_error_base, stream):
            return False
        self.counters["rollbacks"] += 1
        self.retire()
        return True

    def _state_violation(self, x: np.ndarray) -> float:
        """The largest violation (> 0) of the task's state bounds by the state ``x`` ``(n,)`` (``sign * x[idx] -
        bound`` over the task's linear rows); ``-inf`` when the task has none."""
        task = getattr(self.learned, "task", None)
        idx = getattr(task, "cons_idx", None)
        if task is None or idx is None or not np.size(idx):
            return -math.inf
        return float(np.max(task.cons_sign * x[idx] - task.cons_bound))

    def _constraint_strike(self, x: np.ndarray, u: np.ndarray, y: np.ndarray, stream: int) -> bool:
        """The constraint watch, on one learned-planned live step ``(x, u) -> y``: a *strike* when ``y`` breaks a
        state bound of the task by more than ``constraint_tol`` that the model's prediction over the last
        ``constraint_steps`` flown commands kept (short of it by more than ``constraint_tol``) and f_hat's
        prediction of the same steps saw coming (within ``constraint_tol``); True (roll back) once the last
        ``window`` steps hold ``constraint_strikes`` strikes.

        Why: the one-step error monitor compares how well the model and f_hat predict, summed over the state; a
        model can predict better on that sum and still steer the vehicle through a bound, because the sign of its
        error matters there (measured on the capacity sweep's 4-4 nets in the wind world: they over-predict the
        ground effect's lift, so the vehicle sinks 1-2.5 cm below the height bound and circles the pad for the
        rest of the episode, every plan failing where the state fixes it; f_hat under-predicts the lift, so its
        vehicle stays above the bound). Off by default (``constraint_strikes = 0``): with 2 strikes of 5 mm it also
        rolls back the demo's well-trained ensembles in the wind world, whose landings are then worse, and looser
        settings lose most of what it buys on the 4-4 nets (docs/demo.md, the constraint watch)."""
        c = self.config.monitor
        if c.constraint_strikes <= 0 or y.shape != x.shape:
            return False
        viol = self._state_violation(y)
        if viol == -math.inf:
            return False
        steps, strikes = self._watch.setdefault(
            stream, (deque(maxlen=c.constraint_steps), deque(maxlen=max(c.window, c.constraint_strikes))))
        steps.append((x.copy(), u.copy()))
        if len(steps) < c.constraint_steps:
            return False
        strike = False
        if viol > c.constraint_tol:
            xm = xb = steps[0][0]
            for _, uk in steps:  # open loop from the oldest state, through the commands flown since
                xm = self._one_step(self.learned, self._active.model, xm, uk)
                xb = self._one_step(self.base, None, xb, uk)
            vm, vb = self._state_violation(xm), self._state_violation(xb)
            strike = vm < viol - c.constraint_tol and vb >= viol - c.constraint_tol
            if strike:
                self.last_strike = (viol, vm, vb)
        strikes.append(strike)
        return sum(strikes) >= c.constraint_strikes

    def retire(self) -> int:
        """Stop planning with the model in use for good (its tag is banned): back to the previous model, else f_hat.
        Returns the tag now in use (0 = f_hat). What a roll back does; also called when the model in use fails the
        acceptance re-check (:mod:`saml_ros.core.mpc.follower`)."""
        if self._active.model is not None:
            self._banned.add(self._active.tag)
        prev, self._previous = self._previous, None
        self._activate(prev if prev is not None and prev.tag not in self._banned else _Active(None, 0, None, None))
        return self._active.tag

    def _one_step(self, controller: Any, model: DynamicsModel | None, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """The prediction ``controller`` plans with for ``(x, u)``: its numpy model's (``dyn.step1``), else
        ``model``'s (its planning member) or, without a model, the system's f_hat."""
        dyn = getattr(controller, "dyn", None)
        if dyn is not None and hasattr(dyn, "step1"):
            return np.asarray(dyn.step1(x, u), dtype=np.float64)
        if model is None:
            return np.asarray(self.system.base_step_np(x, u), dtype=np.float64)
        return np.asarray(model.predict_np(x, u, int(getattr(controller, "member", 0))), dtype=np.float64)

    def values(self) -> dict[str, float]:
        """The guard's counters and the monitor's window means, for ``mpc/status`` (floats)."""
        c = self.counters
        return {
            "guard_fallbacks": float(c["fallbacks"]),
            "guard_base_solves": float(c["solves_base"]),
            "guard_rollbacks": float(c["rollbacks"]),
            "guard_clipped_solves": float(c["clipped"]),
            "guard_disagreement": float(self.last_disagreement),
            "monitor_error_model": float(self.monitor.mean_model),
            "monitor_error_base": float(self.monitor.mean_base),
            "monitor_margin": float(self.monitor.margin),
            "live_error_model": self.live_error_model,
            "live_error_base": self.live_error_base,
        }


def _hand_over(res: MPCResult, to: Any) -> None:
    """Warm-start the planner ``to`` from the plan ``res`` (when its states are finite): the guard's two planners
    start each solve from the plan last flown, whichever of them made it."""
    if np.all(np.isfinite(res.plan_x)):
        to.set_warm_start(res.plan_u, res.plan_x)


def make_guarded_controller(system: System, solver: str = "fast", config: GuardConfig | None = None,
                            **options: Any) -> GuardedController:
    """A :class:`GuardedController` of two :func:`~saml_ros.core.mpc.factory.make_controller` controllers of the
    same problem (``options`` as there; ``member`` is the planning member); it starts on f_hat. The controllers are
    shooting MPCs (friction, quadrotor) or the generic planner of a robot's ``mpc:`` section; a one-shot
    controller (the paddle ball's) can only have the roll back (``ValueError`` otherwise)."""
    from saml_ros.core.mpc.factory import make_controller

    config = config or GuardConfig()
    learned = make_controller(system, None, solver, **options)
    base_opts = {k: v for k, v in options.items() if k != "member"}
    base = make_controller(system, None, solver, **base_opts)
    return GuardedController(learned, base, config)  # type: ignore[arg-type]
