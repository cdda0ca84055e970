"""Time-stepped MPC problems as data: :class:`ShootingTask` (each system's own task is built in its folder,
``saml_ros/systems/<name>/task.py``, named by its registry entry's ``mpc_task``: the paper's double integrator with
friction and quadrotor landing).

They are single-shooting problems over the controls ``U = (u_0, ..., u_{T-1})`` of the form

    min_U  sum_{t=1..T} || x_t[res_idx] - target ||_2
    s.t.   u_low <= u_t <= u_high                       (t = 0..T-1)
           sign_i * x_{t_i}[idx_i] <= bound_i           (state constraints, one scalar each)
           x_{t+1} = f_hat(x_t, u_t) + phi(x_t, u_t),  x_0 = current state

The current state x_0 is not in the sum (no control can change it). See ``docs/mpc.md`` for how this maps
onto the paper's equations.

The quadrotor's attitude constraint ``|qw_T - 1| <= tol`` is handed to the fast solver as the equivalent
``||(qx, qy, qz)_T||_2 <= sqrt(1 - (1 - tol)^2)`` (equal for unit quaternions with ``qw >= 0``, which the
normalised Euler step keeps for any tilt below 180 degrees): near the level attitude ``qw = cos(tilt / 2)``
has a zero gradient, so its linearisation tells an SQP nothing, while the norm of the vector part grows
linearly with the tilt. Plans are always *checked* with the paper's form (:meth:`ShootingTask.violations`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np


@dataclass(frozen=True)
class ShootingTask:
    """One time-stepped MPC problem (see the module docstring); arrays are float64 unless stated."""

    name: str
    horizon: int
    u_low: np.ndarray  #: (m,)
    u_high: np.ndarray  #: (m,)
    res_idx: np.ndarray  #: (k,) int, state indices entering the stage cost
    target: np.ndarray  #: (k,) the goal of those indices
    u_default: np.ndarray  #: (m,) tail fill of the shifted warm start, last-resort control
    #: (G, T, m) candidate control sequences for the initial guess (see ``ShootingMPC._warm_start``): without a
    #: previous plan the one with the lowest :meth:`start_scores` is used
    u_starts: np.ndarray = field(default_factory=lambda: np.zeros((0, 0, 0)))
    #: also score the candidates against the shifted previous plan at EVERY solve (one batched rollout, ~50 us
    #: for the 4-2 friction model at T = 10), not only without a previous plan: needed where a local solver can be
    #: trapped (friction)
    starts_every_solve: bool = False
    cons_t: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=int))  #: (nc,) time index in 1..T
    cons_idx: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=int))  #: (nc,) state index
    cons_sign: np.ndarray = field(default_factory=lambda: np.zeros(0))  #: (nc,) +1 (upper) or -1 (lower bound)
    cons_bound: np.ndarray = field(default_factory=lambda: np.zeros(0))  #: (nc,)
    cons_name: tuple[str, ...] = ()  #: (nc,) for messages
    #: attitude constraint |qw_T - 1| <= att_tol at step T (quadrotor); None = no attitude constraint
    att_tol: float | None = None
    att_qw: int = 6  #: state index of qw
    att_qv: tuple[int, int, int] = (7, 8, 9)  #: state indices of (qx, qy, qz)

    @property
    def n_cons(self) -> int:
        """Number of state constraints (linear rows plus the attitude constraint)."""
        return int(self.cons_t.size) + (self.att_tol is not None)

    @property
    def names(self) -> tuple[str, ...]:
        return self.cons_name + ((f"attitude |qw_{self.horizon} - 1|",) if self.att_tol is not None else ())

    def with_target(self, target: np.ndarray) -> ShootingTask:
        target = np.asarray(target, dtype=np.float64).reshape(-1)
        if target.shape != self.target.shape or not np.all(np.isfinite(target)):
            raise ValueError(f"{self.name}: goal must be {self.target.size} finite number(s), got {target!r}")
        return replace(self, target=target)

    def stage_costs(self, xs: np.ndarray) -> np.ndarray:
        """``||x[res_idx] - target||_2`` for each state of ``xs`` ``(..., n)`` -> ``(...)``."""
        if self.res_idx.size == 1:  # a scalar residual: |r|
            return np.abs(xs[..., self.res_idx[0]] - self.target[0])
        r = xs[..., self.res_idx] - self.target
        return np.sqrt(np.einsum("...j,...j->...", r, r))

    def cost(self, xs: np.ndarray) -> float:
        """The exact objective of a predicted trajectory ``xs`` ``(T+1, n)`` (x_0 excluded)."""
        return float(self.stage_costs(xs[1:]).sum())

    def start_scores(self, xs: np.ndarray, penalty: float = 100.0) -> np.ndarray:
        """Score of candidate trajectories ``xs`` ``(K, T+1, n)`` -> ``(K,)``: the exact cost plus ``penalty``
        times the summed violation of the paper's constraints (:meth:`cost` and :meth:`violations`, batched)."""
        scores = self.stage_costs(xs[:, 1:]).sum(-1)
        if self.n_cons:
            scores += penalty * np.maximum(self.violations(xs), 0.0).sum(-1)
        return scores

    def violations(self, xs: np.ndarray) -> np.ndarray:
        """The paper's constraints ``g(x) <= 0`` of a trajectory (> 0 = violated): ``sign * x_t[idx] - bound``
        per linear row, then ``|qw_T - 1| - tol``; ``(..., T+1, n) -> (..., n_cons)``."""
        lin = self.cons_sign * xs[..., self.cons_t, self.cons_idx] - self.cons_bound
        if self.att_tol is None:
            return lin
        att = np.abs(xs[..., self.horizon, self.att_qw] - 1.0) - self.att_tol
        return np.concatenate((lin, att[..., None]), axis=-1)

    def solver_violations(self, xs: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        """The constraints in the form the SQP linearises: the linear rows as in :meth:`violations`, the
        attitude as ``||q_v,T|| - sqrt(1 - (1 - tol)^2)``; also returns ``d/dq_v`` of that row, shape (3,)."""
        lin = self.cons_sign * xs[self.cons_t, self.cons_idx] - self.cons_bound
        if self.att_tol is None:
            return lin, None
        i, j, k = self.att_qv
        qv = xs[self.horizon, i : k + 1] if j == i + 1 and k == i + 2 else xs[self.horizon, list(self.att_qv)]
        norm = math.sqrt(float(qv @ qv) + 1e-12)
        out = np.empty(lin.size + 1)
        out[:-1] = lin
        out[-1] = norm - math.sqrt(1.0 - (1.0 - self.att_tol) ** 2)
        return out, qv / norm


def push_brake_sequences(
    u_max: float, horizon: int, amplitudes: tuple[float, ...] = (1.0, 0.5, 0.25)
) -> np.ndarray:
    """Candidate controls ``(G, T, 1)`` for a scalar control bounded by ``|u| <= u_max``: the constant sequences
    ``{0, +-u_max/2, +-u_max}``, then for each sign s, amplitude a (fraction of ``u_max``) and push length k
    (1, 2, 4, ... with ``2 k <= T``; k = 1 when T = 1): "push at s a for k steps, then 0" and "push at s a for
    k steps, brake at -s a for k steps, then 0" (the bang-bang that stops a frictionless mass again).

    They let a local solver leave a dead zone (a model predicting that friction holds the mass for small
    |u|: zero gradient around u = 0) and end near a goal; duplicates (short horizons) are dropped, the
    order (rest first) is kept, so ties go to the earlier candidate. Depends only on ``u_max`` and T."""
    T = int(horizon)
    seqs = [np.full(T, c) for c in (0.0, 0.5, -0.5, 1.0, -1.0)]
    pushes = [k for k in (2**i for i in range(T.bit_length())) if 2 * k <= T] or [1]
    for s in (1.0, -1.0):
        for a in amplitudes:
            for k in pushes:
                for brake in (0, k):
                    u = np.zeros(T)
                    u[:k] = s * a
                    u[k : k + brake] = -s * a
                    seqs.append(u)
    unique = np.unique(np.array(seqs), axis=0, return_index=True)[1]
    return (np.array(seqs)[np.sort(unique)] * u_max)[:, :, None]


