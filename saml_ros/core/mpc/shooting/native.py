"""The fast SQP's numerics in C (``kernels/sqp_native.c``), for the quadrotor's models: :class:`NativeSQP`.

An iteration of :class:`~saml_ros.core.mpc.shooting.sqp.SQPShootingMPC` on the quadrotor spent ~0.45 ms in some
25 numpy calls of 1-30 us each (Jacobians along the plan, condensing, the cost model, merits, the line search's
rollouts) around one DAQP solve of 60-80 us. The C kernel does those numerics in three calls per iteration
(:meth:`NativeSQP.linearize`, :meth:`NativeSQP.line_search`, and :meth:`NativeSQP.merit` when the penalty
changes); the solver's control flow and the QP stay in Python. It applies to a Euclidean stage cost (the
quadrotor task) with the prediction models the quadrotor MPC flies:

* f_hat alone (:class:`~saml_ros.systems.quadrotor.dynamics_np.QuadrotorBaseNP`),
* f_hat + phi (a residual model) or phi alone (a full model), phi a PReLU network (:class:`NumpyMLP`'s folded
  weights: one ensemble member),
* the guard's bounded residual (:class:`~saml_ros.core.mpc.guard.BoundedDynamics`: phi clipped per field).

Anything else (the oracle, the friction task's exact l1 model, a base model without a C twin) runs the numpy
path; :func:`unsupported_reason` says why. The C quadrotor step performs ``QuadrotorBaseNP._step_floats``'
operations in the same order without fused multiply-adds, so f_hat rollouts are bit-identical; Jacobians and
the network differ from numpy's by summation order only (``test/test_sqp_native.py`` bounds both).

Building: :func:`load_library` compiles the source with the C compiler (``$CC``, else ``cc``) once per machine into
:func:`~saml_ros.core.runtime.native_build.cache_root` under a name hashing the source, flags and CPU (an atomic rename,
under a file lock), and loads it with ctypes. No compiler, or ``SAML_MPC_NATIVE=0``: the numpy path (one warning).
"""

from __future__ import annotations

import ctypes
import hashlib
import os
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from saml_ros.core.runtime.native_build import build_cached, cache_root, cpu_id

#: the kernel's source (package data)
SOURCE = Path(__file__).resolve().parent / "kernels" / "sqp_native.c"
#: ``-ffp-contract=off``: no fused multiply-adds, so the quadrotor step rounds as the Python floats do
CFLAGS = ("-O3", "-march=native", "-ffp-contract=off", "-fPIC", "-shared", "-std=c11")
#: ``SAML_MPC_NATIVE=0`` runs the numpy path
SWITCH_ENV = "SAML_MPC_NATIVE"
#: the base model the kernel holds in C (``Model.base``): a numpy twin declaring ``C_BASE = C_QUADROTOR`` in its
#: class body (the quadrotor's :class:`~saml_ros.systems.quadrotor.dynamics_np.QuadrotorBaseNP`, whose scalar step
#: the kernel's ``quad_step`` rounds as) is served by it; any other base model goes the numpy way
C_QUADROTOR = 1
#: the kernel's limits (``MAXW``, ``MAXL``, ``MAXZ`` in the source)
MAX_WIDTH, MAX_LAYERS, MAX_NZ = 512, 8, 48

_c_long_p = ctypes.POINTER(ctypes.c_long)
_c_double_p = ctypes.POINTER(ctypes.c_double)


class _Model(ctypes.Structure):
    _fields_ = [("n", ctypes.c_long), ("m", ctypes.c_long), ("base", ctypes.c_long), ("layers", ctypes.c_long),
                ("has_bound", ctypes.c_long), ("dt", ctypes.c_double), ("mass", ctypes.c_double),
                ("g", ctypes.c_double), ("inertia", ctypes.c_double * 3), ("jinv", ctypes.c_double * 3),
                ("dw_du", ctypes.c_double * 12), ("dims", ctypes.c_void_p), ("w", ctypes.c_void_p),
                ("b", ctypes.c_void_p), ("slopes", ctypes.c_void_p), ("bound", ctypes.c_void_p)]


class _Task(ctypes.Structure):
    _fields_ = [("horizon", ctypes.c_long), ("k", ctypes.c_long), ("res_idx", ctypes.c_void_p),
                ("target", ctypes.c_void_p), ("eps", ctypes.c_double), ("nlin", ctypes.c_long),
                ("cons_t", ctypes.c_void_p), ("cons_idx", ctypes.c_void_p), ("cons_sign", ctypes.c_void_p),
                ("cons_bound", ctypes.c_void_p), ("att", ctypes.c_long), ("att_r", ctypes.c_double),
                ("qv", ctypes.c_long * 3)]


class _State:
    def __init__(self) -> None:
        self.tried = False
        self.lib: ctypes.CDLL | None = None
        self.reason: str | None = "not loaded yet"
        self.warned = False
        self.seconds: float | None = None  # compile time in this process (None: loaded from the cache)


_STATE = _State()
#: :attr:`SQPShootingMPC.native_reason` before its first solve
NOT_SOLVED = "no solve yet"


def switched_off() -> bool:
    """True when ``SAML_MPC_NATIVE`` is ``0`` / ``false`` / ``off`` / ``no``."""
    return os.environ.get(SWITCH_ENV, "1").strip().lower() in ("0", "false", "off", "no")


def build_name(source: Path = SOURCE) -> str:
    """``sqp_native_<hash>.so`` of the source, the flags and this CPU."""
    h = hashlib.sha256()
    for part in (source.read_bytes(), " ".join(CFLAGS).encode(), cpu_id().encode()):
        h.update(part)
        h.update(b"\0")
    return f"sqp_native_{h.hexdigest()[:16]}.so"


def _declare(lib: ctypes.CDLL) -> ctypes.CDLL:
    p, lng, dbl = ctypes.c_void_p, ctypes.c_long, ctypes.c_double
    lib.sqp_rollout.argtypes = [p, p, p, lng, p]
    lib.sqp_rollout.restype = None
    lib.sqp_merit.argtypes = [p, p, lng, dbl, p]
    lib.sqp_merit.restype = dbl
    lib.sqp_linearize.argtypes = [p, p, p, p, p, dbl, p, p, p, p, p]
    lib.sqp_linearize.restype = dbl
    lib.sqp_line_search.argtypes = [p, p, p, p, p, p, lng, dbl, dbl, dbl, p, p, p, p]
    lib.sqp_line_search.restype = lng
    lib.sqp_step_batch.argtypes = [p, p, p, lng, p, p, p]
    lib.sqp_step_batch.restype = None
    return lib


def load_library() -> ctypes.CDLL | None:
    """The compiled kernel (built on first use on this machine), or None: switched off, no compiler, or the build
    failed (:func:`reason` says which; one warning per process)."""
    if switched_off():
        return None
    if _STATE.tried:
        return _STATE.lib
    try:
        so = cache_root() / build_name()
        seconds = build_cached(SOURCE, so, "sqp_native.lock", CFLAGS, timeout=120)
        if seconds is not None:
            _STATE.seconds = seconds
        _STATE.lib = _declare(ctypes.CDLL(str(so)))
        _STATE.reason = None
    except Exception as exc:  # noqa: BLE001 - any build or load problem means: the numpy path
        _STATE.lib = None
        _STATE.reason = f"build failed: {type(exc).__name__}: {exc}"[:400]
        if not _STATE.warned:
            _STATE.warned = True
            warnings.warn(f"saml_ros: the MPC's C kernel is not available ({_STATE.reason}); the fast SQP runs its "
                          "numpy path", RuntimeWarning, stacklevel=2)
    _STATE.tried = True
    return _STATE.lib


def reason() -> str | None:
    """Why the kernel is not loaded (None when it is)."""
    if switched_off():
        return f"switched off ({SWITCH_ENV}=0)"
    return _STATE.reason


def _addr(a: np.ndarray) -> int:
    return int(a.__array_interface__["data"][0])


def unsupported_reason(dyn: Any, task: Any) -> str | None:
    """Why :class:`NativeSQP` cannot serve this prediction model and task (None: it can)."""
    from saml_ros.core.mpc.dynamics_np import NumpyDynamics
    from saml_ros.core.mpc.mlp_np import NumpyMLP

    if task.res_idx.size < 2:
        return "a scalar stage cost (the exact l1 model runs in numpy)"
    if task.horizon * task.u_low.size > MAX_WIDTH or task.res_idx.size > MAX_NZ:
        return f"horizon {task.horizon} x {task.u_low.size} controls beyond the kernel's {MAX_WIDTH}"
    mlp: Any
    base: Any
    if getattr(type(dyn), "clips_phi", False):  # the guard's BoundedDynamics: f_hat + clip(phi, -bound, bound)
        mlp, base = dyn.mlp, dyn.base
    elif type(dyn) is NumpyDynamics:
        if dyn.kind not in ("base", "residual", "full"):
            return f"prediction model {dyn.kind!r}"
        mlp, base = dyn.mlp, dyn.base
    else:
        return f"prediction model {type(dyn).__name__}"
    if base is not None and type(base).__dict__.get("C_BASE") != C_QUADROTOR:
        return f"base model {type(base).__name__} has no C twin"
    if mlp is not None:
        if type(mlp) is not NumpyMLP:
            return f"network {type(mlp).__name__}"
        if len(mlp.weights) > MAX_LAYERS or max(w.shape[1] for w in mlp.weights) > MAX_WIDTH:
            return "network wider or deeper than the kernel's limits"
        if mlp.n_y != mlp.n_x:
            return "network output is not the state"
        n, m = mlp.n_x, mlp.n_u
    elif base is not None:
        n, m = dyn.system.state.size, dyn.system.control.size
    else:
        return "no model"
    if n + m > MAX_NZ:
        return "state and control too large"
    if task.u_low.size != m:
        return f"task has {task.u_low.size} controls, the model {m}"
    # the kernel reads these indices unchecked: anything out of range goes the numpy way (which raises)
    idx_ok = all(a.size == 0 or (int(a.min()) >= 0 and int(a.max()) < n)
                 for a in (np.asarray(task.res_idx), np.asarray(task.cons_idx), np.asarray(task.att_qv)))
    t_ok = task.cons_t.size == 0 or (int(task.cons_t.min()) >= 0 and int(task.cons_t.max()) <= task.horizon)
    if not (idx_ok and t_ok):
        return "task indices out of range"
    return None


class NativeSQP:
    """The C kernel bound to one prediction model and task layout; buffers are kept between calls.

    Shapes: ``x0`` ``(n,)``, controls ``U`` ``(T, m)``, states ``xs`` ``(T+1, n)``; outputs are views of this
    object's buffers, overwritten by the next call (copy what must outlive it)."""

    def __init__(self, lib: ctypes.CDLL, dyn: Any, task: Any, u_range: np.ndarray, radial: float) -> None:
        self.lib = lib
        self.dyn = dyn
        self._keep: list[Any] = []
        base, mlp = dyn.base, dyn.mlp
        mod = _Model()
        n, m = dyn.system.state.size, dyn.system.control.size
        mod.n, mod.m = n, m
        if base is not None:
            mod.base = 1
            mod.dt, mod.mass, mod.g = base.dt, base.mass, base.g
            mod.inertia[:] = list(base._inertia_f)
            mod.jinv[:] = list(base._dt_inv_inertia_f)
            mod.dw_du[:] = np.ascontiguousarray(base._dw_du, dtype=np.float64).ravel().tolist()
        if mlp is not None:
            ws = [np.ascontiguousarray(w, dtype=np.float64) for w in mlp.weights]  # the first: [W_x; W_u], folded
            bs = [np.ascontiguousarray(b, dtype=np.float64) for b in mlp.biases]
            dims = np.array([ws[0].shape[0]] + [w.shape[1] for w in ws], dtype=np.int64)
            slopes = np.array(mlp.slopes[: len(ws) - 1] or [0.0], dtype=np.float64)
            wp = (ctypes.c_void_p * len(ws))(*[_addr(w) for w in ws])
            bp = (ctypes.c_void_p * len(bs))(*[_addr(b) for b in bs])
            self._keep += [ws, bs, dims, slopes, wp, bp]
            mod.layers = len(ws)
            mod.dims, mod.slopes = _addr(dims), _addr(slopes)
            mod.w, mod.b = ctypes.cast(wp, ctypes.c_void_p), ctypes.cast(bp, ctypes.c_void_p)
            bound = getattr(dyn, "bound", None)
            if bound is not None:
                bnd = np.ascontiguousarray(bound, dtype=np.float64)
                self._keep.append(bnd)
                mod.has_bound, mod.bound = 1, _addr(bnd)
        self._model = mod
        self._pm = ctypes.addressof(mod)
        self.n, self.m, self.horizon = n, m, int(task.horizon)
        T, nu = self.horizon, self.horizon * m
        # the task layout (the goal is copied in by set_target at each solve)
        tk = _Task()
        self._res = np.ascontiguousarray(task.res_idx, dtype=np.int64)
        self._target = np.zeros(self._res.size)
        self._cons = [np.ascontiguousarray(task.cons_t, dtype=np.int64),
                      np.ascontiguousarray(task.cons_idx, dtype=np.int64),
                      np.ascontiguousarray(task.cons_sign, dtype=np.float64),
                      np.ascontiguousarray(task.cons_bound, dtype=np.float64)]
        tk.horizon, tk.k = T, self._res.size
        tk.res_idx, tk.target = _addr(self._res), _addr(self._target)
        tk.nlin = self._cons[0].size
        if tk.nlin:
            tk.cons_t, tk.cons_idx, tk.cons_sign, tk.cons_bound = (_addr(a) for a in self._cons)
        if task.att_tol is not None:
            tk.att = 1
            tk.att_r = float(np.sqrt(1.0 - (1.0 - task.att_tol) ** 2))
            tk.qv[:] = list(task.att_qv)
        self._task_key = (task.res_idx, task.cons_t, task.cons_idx, task.cons_sign, task.cons_bound,
                          task.att_tol, task.att_qv, task.horizon)
        self._tk = tk
        self._pt = ctypes.addressof(tk)
        self.nc = int(tk.nlin + tk.att)
        self.radial = float(radial)
        self.eps = 0.0
        # buffers
        self._urange = np.ascontiguousarray(u_range, dtype=np.float64)
        self._x0 = np.zeros(n)
        self._u = np.zeros((T, m))
        self._xs = np.zeros((T + 1, n))
        self._d = np.zeros(nu)
        self._sens = np.zeros((T + 1, n, nu))
        self._hess = np.zeros((nu, nu))
        self._grad = np.zeros(nu)
        self._gcon = np.zeros((self.nc, nu))
        self._reach = np.zeros(self.nc)
        self._c = np.zeros(max(self.nc, 1))
        self._alphas = np.zeros(8)
        self._u_all = np.zeros((8, T, m))
        self._xs_all = np.zeros((8, T + 1, n))
        self._merits = np.zeros(8)
        self._c_all = np.zeros((8, max(self.nc, 1)))
        a = _addr
        self._p = {k: a(v) for k, v in (("x0", self._x0), ("u", self._u), ("xs", self._xs), ("d", self._d),
                                        ("sens", self._sens), ("hess", self._hess), ("grad", self._grad),
                                        ("gcon", self._gcon), ("reach", self._reach), ("c", self._c),
                                        ("alphas", self._alphas), ("u_all", self._u_all), ("xs_all", self._xs_all),
                                        ("merits", self._merits), ("c_all", self._c_all),
                                        ("urange", self._urange))}

    def fits(self, dyn: Any, task: Any, radial: float) -> bool:
        """Whether this binding serves ``dyn``, ``task``'s layout (the goal may differ) and ``radial``."""
        key = self._task_key
        return dyn is self.dyn and radial == self.radial and task.horizon == key[7] and task.att_tol == key[5] and task.att_qv == key[6] \
            and all(a is b or np.array_equal(a, b) for a, b in zip(key[:5], (task.res_idx, task.cons_t,
                                                                            task.cons_idx, task.cons_sign,
                                                                            task.cons_bound), strict=True))

    def set_target(self, target: np.ndarray, eps: float) -> None:
        self._target[:] = target
        self._tk.eps = self.eps = float(eps)

    def rollout(self, x0: np.ndarray, u: np.ndarray) -> np.ndarray:
        """States ``(T+1, n)`` (a new array)."""
        self._x0[:] = x0
        self._u[:] = u
        xs = np.empty((self.horizon + 1, self.n))
        self.lib.sqp_rollout(self._pm, self._p["x0"], self._p["u"], self.horizon, _addr(xs))
        return xs

    def merit(self, xs: np.ndarray, penalty: float) -> tuple[float, np.ndarray]:
        """The SQP's merit of ``xs`` and its constraint values ``(nc,)`` (a new array)."""
        self._xs[:] = xs
        merit = self.lib.sqp_merit(self._pt, self._p["xs"], self.n, penalty, self._p["c"])
        return float(merit), self._c[: self.nc].copy()

    def linearize(self, xs: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray,
                                                                 float]:
        """At the plan: Hessian ``(T m, T m)``, gradient ``(T m,)``, constraint rows ``(nc, T m)``, their reach
        ``(nc,)`` (buffers) and the curvature scale."""
        self._xs[:] = xs
        self._u[:] = u
        p = self._p
        scale = self.lib.sqp_linearize(self._pm, self._pt, p["xs"], p["u"], p["urange"], self.radial, p["sens"],
                                       p["hess"], p["grad"], p["gcon"], p["reach"])
        return self._hess, self._grad, self._gcon, self._reach, float(scale)

    def line_search(self, x0: np.ndarray, u: np.ndarray, d: np.ndarray, alphas: tuple[float, ...], merit: float,
                    pred: float, penalty: float) -> tuple[int, tuple[np.ndarray, np.ndarray, float, np.ndarray]]:
        """Backtracking along ``d``: the index of the accepted step length (-1: none) and the last trial point
        tried (controls, states, merit, constraint values; new arrays)."""
        na = len(alphas)
        self._x0[:] = x0
        self._u[:] = u
        self._d[:] = d
        self._alphas[:na] = alphas
        p = self._p
        i = int(self.lib.sqp_line_search(self._pm, self._pt, p["x0"], p["u"], p["d"], p["alphas"], na, merit, pred,
                                         penalty, p["u_all"], p["xs_all"], p["merits"], p["c_all"]))
        j = i if i >= 0 else na - 1
        return i, (self._u_all[j].copy(), self._xs_all[j].copy(), float(self._merits[j]),
                   self._c_all[j, : self.nc].copy())

    def step_batch(self, x: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The model's prediction and Jacobians for a batch ``(B, n), (B, m)`` (tests and benchmarks)."""
        x = np.ascontiguousarray(x, dtype=np.float64)
        u = np.ascontiguousarray(u, dtype=np.float64)
        bsz = x.shape[0]
        y, a, b = np.empty((bsz, self.n)), np.empty((bsz, self.n, self.n)), np.empty((bsz, self.n, self.m))
        self.lib.sqp_step_batch(self._pm, _addr(x), _addr(u), bsz, _addr(y), _addr(a), _addr(b))
        return y, a, b


def main() -> int:
    """Build or load the kernel and say which (``./dev test`` runs this before pytest, so no test pays for the
    compile)."""
    lib = load_library()
    if lib is not None:
        how = "cached" if _STATE.seconds is None else f"built in {_STATE.seconds:.1f} s"
        print(f"[dev] MPC SQP kernel: ready ({how})", flush=True)
    else:
        print(f"[dev] MPC SQP kernel: not built ({reason()}) - numpy path", flush=True)
    return 0
