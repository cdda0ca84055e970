"""The generic planner's reference path: a robot's whole task as one CasADi NLP, solved by IPOPT (:class:`CasadiNLP`).

Multiple shooting over ``x_1 .. x_T`` and ``u_0 .. u_{T-1}`` with the dynamics as equality constraints, the model
written symbolically (:func:`~saml_ros.core.mpc.generic.casadi_model.casadi_dynamics`) with the network's weights a
*parameter* of the NLP: a hot swap passes new numbers, the NLP (and IPOPT's symbolic set-up) is built once per
network architecture. The cost and the constraints are those of
:class:`~saml_ros.core.mpc.generic.problem.GenericProblem`; the state constraints are soft with the same exact l1
penalty (a slack per row, ``c(x) <= s``, ``s >= 0``, ``penalty * sum s`` in the cost), so both paths optimise the
same function. IPOPT uses exact second derivatives (CasADi's), and the previous plan as its start.

It is the slower path (docs/mpc.md, "The generic planner": measured there) and needs f_hat in symbolic form (a
built-in, or a user's array-namespace form); the MPC node runs it with ``solver:=slsqp`` (the reference slot) or
``mpc.solver: ipopt``.
"""

from __future__ import annotations

import math
import time
from typing import Any

import numpy as np

from saml_ros.core.dynamics.system import System
from saml_ros.core.model.network import DynamicsModel
from saml_ros.core.mpc.contract import MPCResult
from saml_ros.core.mpc.generic.casadi_model import casadi_dynamics, mlp_theta
from saml_ros.core.mpc.generic.dynamics import GenericDynamics, make_base
from saml_ros.core.mpc.generic.problem import GenericProblem
from saml_ros.core.mpc.generic.section import MPCTask
from saml_ros.core.mpc.generic.sqp import _options, system_task


class CasadiNLP:
    """See the module docstring; the arguments are :class:`~saml_ros.core.mpc.generic.sqp.GenericSQP`'s, with
    ``max_iter`` (IPOPT iterations, 200), ``tol`` (IPOPT's ``tol``, 1e-8), ``max_time`` (IPOPT's ``max_cpu_time``),
    ``linear_solver`` (IPOPT's, default ``mumps``) and ``smoothing`` (the rounding of the network's PReLU kinks in the
    NLP, default 1e-3, :mod:`~saml_ros.core.mpc.generic.casadi_model`: IPOPT does not converge on the exact kinks;
    the returned plan is rolled out with the exact network)."""

    def __init__(self, system: System, model: DynamicsModel | None = None, horizon: int | None = None,
                 member: int = 0, *, task: MPCTask | None = None, max_iter: int | None = None,
                 tol: float | None = None, max_time: float | None = None, feas_tol: float | None = None,
                 linear_solver: str | None = None, smoothing: float | None = None, base: Any = None,
                 true: Any = None) -> None:
        self.system = system
        self.task = task if task is not None else system_task(system)
        if self.task.norm_cost or any(c.terminal for c in self.task.constraints) or self.task.w_disagreement.size:
            raise ValueError(f"{system.name} MPC: the IPOPT path does not take cost.norm, cost.disagreement or a "
                             "constraint 'at: terminal' yet; use solver: sqp")
        self.problem = GenericProblem(self.task, system.state.size, system.control.size, horizon)
        self.horizon = self.problem.T
        self.member = int(member)
        self.n, self.m = system.state.size, system.control.size
        opt = _options(self.task, max_iter=max_iter, tol=tol, max_time=max_time, feas_tol=feas_tol,
                       linear_solver=linear_solver, smoothing=smoothing)
        self.smoothing = float(opt.get("smoothing", 1e-3))
        self.max_iter, self.tol = int(opt.get("max_iter", 200)), float(opt.get("tol", 1e-8))
        self.max_time = None if opt.get("max_time") is None else float(opt["max_time"])
        self.feas_tol = float(opt.get("feas_tol", 1e-3))
        self.linear_solver = str(opt.get("linear_solver", "mumps"))
        self.penalty = float(self.task.penalty)
        self._base = make_base(system)
        casadi_dynamics(system, None, ())  # f_hat must have a symbolic form: fail here, naming why
        self._solvers: dict[tuple[Any, ...], Any] = {}
        self._bound: np.ndarray | None = None
        self.model: DynamicsModel | None = None
        self._theta = np.zeros(0)
        self.dyn = GenericDynamics(system, self._base)
        self.set_model(model)
        self._plan_u: np.ndarray | None = None
        self._plan_x: np.ndarray | None = None
        self._u_last: np.ndarray | None = None

    # ------------------------------------------------------------------------------------------ models
    def set_model(self, model: DynamicsModel | None) -> None:
        """Plan with ``model`` from the next solve on: new numbers for the NLP's weight parameter (a new NLP only for
        a new network architecture)."""
        if model is not None and model.system.state.names != self.system.state.names:
            raise ValueError(f"model of system {model.system.name!r} does not fit {self.system.name!r}")
        self.model = model
        self._theta = np.zeros(0) if model is None else mlp_theta(model, self.member)
        self._bound = None
        self.dyn = GenericDynamics(self.system, self._base, model, self.member)

    def set_residual_bound(self, bound: np.ndarray | None) -> None:
        self._bound = None if bound is None else np.asarray(bound, dtype=np.float64)
        self.dyn = GenericDynamics(self.system, self._base, self.model, self.member, self._bound)

    def phi_clipped(self, res: MPCResult) -> bool:
        if not np.all(np.isfinite(res.plan_x)):
            return False
        return self.dyn.clipped(res.plan_x[:-1], res.plan_u)

    def reset(self) -> None:
        self._plan_u = self._plan_x = None
        self._u_last = None

    def warm_start_plan(self) -> tuple[np.ndarray, np.ndarray] | None:
        if self._plan_u is None or self._plan_x is None:
            return None
        return self._plan_u.copy(), self._plan_x.copy()

    def set_warm_start(self, plan_u: np.ndarray, plan_x: np.ndarray) -> None:
        self._plan_u = np.array(plan_u, dtype=np.float64).reshape(self.horizon, self.m)
        self._plan_x = np.array(plan_x, dtype=np.float64).reshape(self.horizon + 1, self.n)
        self._u_last = self._plan_u[0].copy()

    def describe(self) -> str:
        return (f"generic CasADi NLP (IPOPT, exact Hessian, linear solver {self.linear_solver}, PReLU kinks rounded "
                f"by {self.smoothing:g}), T={self.horizon}; model as CasADi expressions with the network's weights a "
                f"parameter vector; {self.dyn.describe()}")

    # ------------------------------------------------------------------------------------------ the NLP
    def _solver(self) -> Any:
        """The IPOPT solver for the current architecture (built on first use)."""
        model = self.model
        key = (None, ()) if model is None else (model.kind, tuple(model.hidden))
        if key in self._solvers:
            return self._solvers[key]
        import casadi as ca

        pb, T, n, m, k = self.problem, self.horizon, self.n, self.m, self.problem.k
        f = casadi_dynamics(self.system, key[0], key[1], smooth=self.smoothing)
        n_theta = f.size1_in(2)
        R = pb.rows_per_step
        u, x, s = ca.SX.sym("u", m, T), ca.SX.sym("x", n, T), ca.SX.sym("s", R, T)
        x0, ref, u_prev = ca.SX.sym("x0", n), ca.SX.sym("ref", k, T), ca.SX.sym("u_prev", m)
        has_prev, theta, bound = ca.SX.sym("has_prev"), ca.SX.sym("theta", n_theta), ca.SX.sym("bound", n)
        gi = [int(i) for i in pb.g_idx]
        se, sr = np.sqrt(self.task.w_effort), np.sqrt(self.task.w_rate)
        cost = 0
        g = []
        prev = x0
        for t in range(T):
            g.append(x[:, t] - f(prev, u[:, t], theta, bound))
            e = x[gi, t] - ref[:, t]
            cost += ca.sumsqr(pb.sw[t] * e) + ca.sumsqr(se * u[:, t])
            du = u[:, t] - (u_prev if t == 0 else u[:, t - 1])
            cost += (has_prev if t == 0 else 1) * ca.sumsqr(sr * du)
            if R:
                g.append(_constraint_rows(pb, x[:, t]) - s[:, t])
                cost += self.penalty * ca.sum1(s[:, t])
            prev = x[:, t]
        w = ca.vertcat(ca.vec(u), ca.vec(x), ca.vec(s))
        p = ca.vertcat(x0, ca.vec(ref), u_prev, has_prev, theta, bound)
        opts: dict[str, Any] = {"ipopt.print_level": 0, "print_time": False, "ipopt.sb": "yes", "ipopt.max_iter": self.max_iter,
                "ipopt.tol": self.tol, "ipopt.linear_solver": self.linear_solver}
        if self.max_time is not None:
            opts["ipopt.max_cpu_time"] = self.max_time
        solver = ca.nlpsol("generic_mpc", "ipopt", {"x": w, "p": p, "f": cost, "g": ca.vertcat(*g)}, opts)
        lbx = np.concatenate([np.tile(pb.u_low, T), np.full(n * T, -np.inf), np.zeros(R * T)])
        ubx = np.concatenate([np.tile(pb.u_high, T), np.full(n * T, np.inf), np.full(R * T, np.inf)])
        ng = n * T + R * T
        lbg = np.concatenate([np.concatenate([np.zeros(n), np.full(R, -np.inf)]) for _ in range(T)])
        ubg = np.zeros(ng)
        self._solvers[key] = (solver, lbx, ubx, lbg, ubg)
        return self._solvers[key]

    def solve(self, x0: np.ndarray, goal: Any | None = None) -> MPCResult:
        """As :meth:`GenericSQP.solve <saml_ros.core.mpc.generic.sqp.GenericSQP.solve>`."""
        start = time.perf_counter()
        x0 = np.asarray(x0, dtype=np.float64)
        if x0.shape != (self.n,):
            raise ValueError(f"{self.system.name} MPC: x0 must have shape ({self.n},), got {x0.shape}")
        ref = self.problem.reference(x0, goal) if np.all(np.isfinite(x0)) else None
        if ref is None or not np.all(np.isfinite(ref)):
            return self._fallback(start, "non-finite state" if ref is None else "non-finite goal")
        pb, T, n, m = self.problem, self.horizon, self.n, self.m
        try:
            solver, lbx, ubx, lbg, ubg = self._solver()
            us0 = self._warm_start(x0)
            xs0 = self.dyn.rollout(x0, us0)
            s0 = np.maximum(pb.constraints(xs0), 0.0)
            w0 = np.concatenate([us0.reshape(-1), xs0[1:].reshape(-1), s0.reshape(-1)])
            u_prev = self._u_last
            bound = np.full(n, np.inf) if self._bound is None else self._bound
            p = np.concatenate([x0, ref.reshape(-1),
                                np.zeros(m) if u_prev is None else u_prev, [0.0 if u_prev is None else 1.0],
                                self._theta, bound])
            out = solver(x0=w0, p=p, lbx=lbx, ubx=ubx, lbg=lbg, ubg=ubg)
            stats = solver.stats()
            wv = np.asarray(out["x"]).reshape(-1)
            us = np.clip(wv[: m * T].reshape(T, m), pb.u_low, pb.u_high)
            xs = self.dyn.rollout(x0, us)  # the plan under the model in use (the NLP's gaps closed exactly)
            iters = int(stats.get("iter_count", 0))
            status = str(stats.get("return_status", ""))
            converged = bool(stats.get("success", False))
        except Exception as exc:  # noqa: BLE001 - any failure: keep flying on the last good plan
            return self._fallback(start, f"solver failure: {type(exc).__name__}: {exc}")
        if not (np.all(np.isfinite(xs)) and np.all(np.isfinite(us))):
            return self._fallback(start, f"non-finite plan ({status})", iters)
        cons = pb.constraints(xs).reshape(-1)
        worst = float(max(0.0, cons.max())) if cons.size else 0.0
        ok = worst <= self.feas_tol
        msg = "converged" if converged else status
        if not ok:
            msg += f"; {pb.violation_names()[int(np.argmax(cons))]} violated by {worst:.3g}"
        self._plan_u, self._plan_x = us, xs
        self._u_last = us[0].copy()
        return MPCResult(u=us[0].copy(), plan_u=us, plan_x=xs, cost=pb.cost(xs, us, ref, u_prev),
                         solve_time=time.perf_counter() - start, iterations=iters, success=ok, message=msg,
                         constraint_violation=worst, converged=converged)

    def _warm_start(self, x0: np.ndarray) -> np.ndarray:
        T, lo, hi = self.horizon, self.problem.u_low, self.problem.u_high
        if self._plan_u is None or self._plan_x is None:
            u = self._u_last if self._u_last is not None else self.task.u_safe
            return np.tile(np.clip(u, lo, hi), (T, 1))
        d1, d0 = x0 - self._plan_x[1], x0 - self._plan_x[0]
        shift = 1 if d1 @ d1 < d0 @ d0 else 0
        us = np.empty((T, self.m))
        us[: T - shift] = self._plan_u[shift:]
        us[T - shift:] = self._plan_u[-1]
        return np.clip(us, lo, hi)

    def _fallback(self, start: float, why: str, iters: int = 0) -> MPCResult:
        T = self.horizon
        if self._plan_u is not None and T > 1:
            plan_u = np.vstack((self._plan_u[1:], self._plan_u[-1:]))
        else:
            plan_u = np.tile(self.task.u_safe, (T, 1))
        plan_u = np.clip(plan_u, self.problem.u_low, self.problem.u_high)
        return MPCResult(u=plan_u[0].copy(), plan_u=plan_u, plan_x=np.full((T + 1, self.n), np.nan), cost=math.nan,
                         solve_time=time.perf_counter() - start, iterations=iters, success=False, message=why,
                         constraint_violation=math.inf, converged=False)


def _constraint_rows(pb: GenericProblem, x: Any) -> Any:
    """The constraint rows of :meth:`GenericProblem.constraints` for one state column (CasADi)."""
    import casadi as ca

    rows = []
    for c in pb.cons:
        if c.kind == "box":
            for i, lo, hi in zip(c.idx, c.low, c.high, strict=True):
                if math.isfinite(lo):
                    rows.append(lo - x[i])
                if math.isfinite(hi):
                    rows.append(x[i] - hi)
        elif c.kind == "norm":
            rows.append(ca.norm_2(ca.vertcat(*[x[i] for i in c.idx])) - c.max)
        else:
            z = ca.vertcat(*[(x[i] - ci) / ri for i, ci, ri in zip(c.idx, c.center, c.radius, strict=True)])
            rows.append(min(c.radius) * (1.0 - ca.norm_2(z)))
    return ca.vertcat(*rows)
