"""What the online learner reports on ``learner/model_error``: the names and order of the values
(:func:`assemble_telemetry`, :data:`EXTRA_METRICS`), the training averages since the previous report
(:class:`StepAverages`) and the live one-step error of the current model on the recent window
(:func:`model_metrics`)."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING

import numpy as np

from msg_schemas.telemetry import model_error_names
from saml_ros.core.spec import ProblemSpec, SpecValues
from saml_ros.core.training.diagnosis import MIN_ROWS, VERDICT_CODES
from saml_ros.core.training.heldout import MET, MET_ON_TRAINING_ONLY, NO_HELDOUT, NOT_MET, UNCONFIRMED

if TYPE_CHECKING:  # the learner node assembles telemetry without torch; the training process computes it
    import torch

    from saml_ros.core.model.network import DynamicsModel
    from saml_ros.core.training import PrimalDualTrainer

#: the number of each held-out verdict in telemetry (``heldout_verdict/<k>``; the words are
#: :mod:`saml_ros.core.training.heldout`'s)
VERDICT_NUMBERS: dict[str, int] = {MET: 0, UNCONFIRMED: 1, MET_ON_TRAINING_ONLY: 2, NOT_MET: 3, NO_HELDOUT: 4}

#: extra ``learner/model_error`` values appended after the canonical names
EXTRA_METRICS: tuple[tuple[str, str, str], ...] = (
    ("paired", "count", "transitions paired so far (all sources)"),
    ("window", "count", "recent transitions the live errors are computed on"),
    ("error_all", "loss", "live one-step error of the current model on the recent window (the objective's loss)"),
    ("training", "1", "1 while primal-dual updates run, 0 while waiting for min_transitions"),
    ("heldout_size", "count", "held-out transitions (whole stretches of the stream never trained on) the held-out "
                              "values are read on"),
    ("heldout_objective", "loss", "the objective on the held-out stretches (member 0)"),
    ("heldout_objective_base", "loss", "f_hat's objective on the same held-out stretches"),
    ("heldout_updates", "count", "the update count of the model the held-out values belong to"),
    ("heldout_average", "1", "1 when the exponential average of the weights did better on the held-out stretches "
                             "than the trainer's weights (checkpoints then publish the average), else 0"),
)
#: extra per-constraint values (``<name>/<k>``)
EXTRA_PER_CONSTRAINT: tuple[tuple[str, str, str], ...] = (
    ("n_in", "count", "recent transitions inside region k (error_in is NaN when 0)"),
    ("verdict", "code", "feasibility verdict of constraint k over the training history's tail: 0 met, 1 not "
                        "converged, 2 likely infeasible (NaN until the history has enough rows; docs/training.md)"),
    ("lhs_min", "loss", "smallest left-hand side g_k + eps_k of any training-history row"),
    ("lambda_rising", "1", "1 while lambda_k is still rising over the history's tail, else 0"),
    ("reachable", "loss", "the left-hand side g_k + eps_k the model reaches now (the tail's mean): the bound it "
                          "could meet"),
    ("heldout", "loss", "the left-hand side of constraint k (e.g. the in-region error) on the held-out stretches "
                        "(member 0; NaN: none in the region yet)"),
    ("heldout_se", "loss", "its standard error (batch means over the held-out stretches)"),
    ("heldout_upper", "loss", "the upper end of its one-sided 95 % interval, heldout + 1.645 heldout_se: met when "
                              "at most eps_k"),
    ("heldout_n", "count", "held-out transitions inside region k"),
    ("heldout_base", "loss", "f_hat's left-hand side on the same held-out stretches"),
    ("training_lhs", "loss", "the same left-hand side on the training buffer (a sample of it)"),
    ("heldout_verdict", "code", "the verdict on constraint k read on the held-out stretches: 0 met (upper end of the "
                                "95 % interval <= eps), 1 unconfirmed, 2 met on training data only, 3 not met, 4 no "
                                "held-out data (NaN before training)"),
)


def assemble_telemetry(
    constraint_names: Sequence[str], status: Mapping[str, float], counts: Mapping[str, int]
) -> dict[str, float]:
    """``learner/model_error`` values in order: :func:`~msg_schemas.telemetry.model_error_names` first, then
    :data:`EXTRA_METRICS` and the :data:`EXTRA_PER_CONSTRAINT` values of each constraint.

    Args:
        constraint_names: the spec's constraint names.
        status: an online learner's ``status()`` (missing model values are NaN).
        counts: pairing counters (the learner's ``counts()`` or :func:`~saml_ros.core.data.pairing.total_counts`).
    """
    out: dict[str, float] = {}
    for n in model_error_names(constraint_names):
        if n.startswith("rejected/"):
            out[n] = float(counts.get(n.removeprefix("rejected/"), 0))
        else:
            out[n] = float(status.get(n, math.nan))
    out["paired"] = float(counts.get("paired", 0))
    for n, _, _ in EXTRA_METRICS:
        if n != "paired":
            out[n] = float(status.get(n, math.nan))
    for c in constraint_names:
        for n, _, _ in EXTRA_PER_CONSTRAINT:
            out[f"{n}/{c}"] = float(status.get(f"{n}/{c}", 0.0 if n in ("n_in", "heldout_n") else math.nan))
    return out


def feasibility_metrics(trainer: PrimalDualTrainer | None, spec: ProblemSpec) -> dict[str, float]:
    """``verdict/<k>``, ``lhs_min/<k>``, ``lambda_rising/<k>``, ``reachable/<k>`` of the diagnosis of the
    trainer's history (:func:`~saml_ros.core.training.diagnosis.diagnose`; NaN before training or while the
    history is shorter than :data:`~saml_ros.core.training.diagnosis.MIN_ROWS` rows). Member 0."""
    names = spec.constraint_names
    out = {f"{n}/{c}": math.nan for c in names for n in ("verdict", "lhs_min", "lambda_rising", "reachable")}
    if trainer is None or len(trainer.history.step) < MIN_ROWS or not names:
        return out
    diag = trainer.diagnose()
    for c in diag.constraints:
        m = c.members[0]
        out[f"verdict/{c.name}"] = float(VERDICT_CODES[m.verdict])
        out[f"lhs_min/{c.name}"] = m.lhs_min
        out[f"lambda_rising/{c.name}"] = 1.0 if m.lam_rising else 0.0
        out[f"reachable/{c.name}"] = m.g + c.eps
    return out


class StepAverages:
    """Means of the minibatch objective and constraint estimates (ensemble member 0) since the last :meth:`take`."""

    def __init__(self, n_constraints: int) -> None:
        self._n = 0
        self._obj = 0.0
        self._con = np.zeros(n_constraints)
        self._last_obj = math.nan
        self._last_con = np.full(n_constraints, math.nan)

    def add(self, vals: SpecValues) -> None:
        self._n += 1
        self._obj += float(vals.objective[0])
        if len(self._con):
            self._con += vals.constraints[0].double().numpy()

    def add_rows(self, rows: torch.Tensor) -> None:
        """Add ``n`` steps' values of member 0 at once: ``rows`` ``(n, 1 + K)`` (objective, then g_k)."""
        if not len(rows):
            return
        total = rows.double().sum(0).numpy()
        self._n += len(rows)
        self._obj += float(total[0])
        if len(self._con):
            self._con += total[1:]

    def take(self) -> tuple[float, np.ndarray]:
        """``(objective, constraints (K,))`` averaged since the previous call; the previous values again when no
        step ran in between (NaN before the first step)."""
        if self._n:
            self._last_obj = self._obj / self._n
            self._last_con = self._con / self._n
            self._n, self._obj = 0, 0.0
            self._con = np.zeros(len(self._con))
        return self._last_obj, self._last_con


def model_metrics(
    model: DynamicsModel, spec: ProblemSpec, window: tuple[np.ndarray, np.ndarray, np.ndarray],
    averages: tuple[float, np.ndarray], lam: np.ndarray, updates: int, version: int,
) -> dict[str, float]:
    """The model part of the telemetry: the training averages (``objective``, ``constraint/<k>``, ``lagrangian``),
    ``lambda/<k>`` (``lam`` ``(K,)``), the ``updates`` and ``model_version`` they belong to and, on the recent ``window`` ``(x, u, y)``, the one-step errors of the current model inside /
    outside each constraint region (``error_in/<k>``, ``error_out/<k>``, ``n_in/<k>``, NaN / 0 when empty), over
    the whole window (``error_all``) and the window size."""
    import torch

    x, u, y = window
    obj, con = averages
    errs: dict[str, dict[str, torch.Tensor]] = {}
    err_all = math.nan
    if len(x):
        with torch.no_grad():
            xt, ut, yt = (torch.from_numpy(a) for a in (x, u, y))
            dt = model.in_mean.dtype
            pred = model(xt.to(dt), ut.to(dt)).double()
            errs = spec.region_errors(xt, ut, yt, pred)
            err_all = float(spec.objective.per_sample(pred, yt).mean())
    out: dict[str, float] = {}
    out["objective"] = obj
    out["lagrangian"] = obj + float(np.sum(lam * con)) if spec.n_constraints else obj
    out["updates"] = float(updates)
    out["model_version"] = float(version)
    for k, name in enumerate(spec.constraint_names):
        e = errs.get(name)
        out[f"constraint/{name}"] = float(con[k])
        out[f"lambda/{name}"] = float(lam[k])
        out[f"error_in/{name}"] = float(e["in"][0]) if e else math.nan
        out[f"error_out/{name}"] = float(e["out"][0]) if e else math.nan
        out[f"n_in/{name}"] = float(e["n_in"][0]) if e else 0.0
    out["window"] = float(len(x))
    out["error_all"] = err_all
    return out
