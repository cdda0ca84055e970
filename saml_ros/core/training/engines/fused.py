"""The fused training kernel: blocks of the fast engine's primal-dual steps in one C++ call.

The fast engine (:mod:`~saml_ros.core.training.engines.fast`) computes a step with ~43 small tensor operations;
at the paper's sizes that is dispatch-bound (a 16-8 net reaches a few per cent of the one-thread arithmetic
ceiling). ``kernels/fused_step.cpp`` does the same step (gather of the minibatch, forward, spec values,
closed-form loss gradient, backward, Adam / SGD of the flat parameters, the dual method's update of the
multipliers, for every ensemble member) as plain C++ loops over the fast engine's flat tensors, for a block
of steps per call; the health check runs on the block's outputs (:meth:`TrainingHealth.check_block_values`).

* :func:`load_kernel` compiles it once per machine with :func:`torch.utils.cpp_extension.load`
  (``-O3 -march=native``) into ``~/.cache/saml_ros/fused_kernel/<name>`` (``$SAML_KERNEL_CACHE`` instead of
  that directory, or ``$XDG_CACHE_HOME`` instead of ``~/.cache``), where the name holds a hash of the source,
  the torch and Python versions, the compiler flags and this CPU's model and flags: a build from another CPU or
  torch is never loaded. A trainer's :class:`FusedRun` is kept between its fits while what it was built from is
  unchanged (:func:`_reusable_run`). A build that fails leaves :func:`kernel_reason` / :func:`build_error` and one warning, and
  training runs the torch path.
* ``SAML_FUSED_KERNEL=0`` (:func:`switched_off`) or ``TrainConfig(engine="fast_torch")`` run the torch path.
* :class:`FusedEngine` is ``TrainConfig.engine="fast"``: the kernel where it loaded and applies
  (:func:`kernel_unsupported_reason`), else the fast engine's torch path; ``trainer.kernel_used`` says which.

The results are the fast engine's up to float rounding (summation order in the matmuls and reductions):
``test/test_fused_kernel.py`` bounds them with ``test/test_fast_train.py``'s tolerances against the torch path
and the plain engine. This module is the only one that imports the kernel; :mod:`.fast` does not know it.
"""

from __future__ import annotations

import fcntl
import hashlib
import importlib.util
import logging
import os
import sys
import time
import warnings
import weakref
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from saml_ros.core.runtime.native_build import cache_root, cpu_id
from saml_ros.core.training.dataset import Transitions
from saml_ros.core.training.dual import AugmentedDual, NuPIDual, ResilientDual
from saml_ros.core.training.engines.base import RunState, minibatch_plan
from saml_ros.core.training.engines.fast import FastEngine, FastRun
from saml_ros.core.training.engines.stream import StreamRun
from saml_ros.core.training.evaluate import spec_values

log = logging.getLogger("saml_ros.trainer")

#: the kernel's source (package data: setup.py installs it with the package)
KERNEL_SOURCE = Path(__file__).resolve().parent / "kernels" / "fused_step.cpp"
#: ``SAML_FUSED_KERNEL=0`` runs the torch path
SWITCH_ENV = "SAML_FUSED_KERNEL"
#: the compiler flags (part of the build's name)
CFLAGS = ("-O3", "-march=native", "-fno-math-errno", "-std=c++17")
_LOSS_CODES = {"l2": 0, "squared_l2": 1, "l1": 2, "huber": 3, "normalized": 4}


class _KernelState:
    def __init__(self) -> None:
        self.tried = False
        self.module: Any = None
        self.reason: str | None = None
        self.error: str | None = None
        self.seconds: float | None = None
        self.cached = False
        self.warned = False


_STATE = _KernelState()


def switched_off() -> bool:
    """True when ``SAML_FUSED_KERNEL`` is ``0`` / ``false`` / ``off`` / ``no``: training runs the torch path."""
    return os.environ.get(SWITCH_ENV, "1").strip().lower() in ("0", "false", "off", "no")


def build_name(source: Path = KERNEL_SOURCE) -> str:
    """The extension's name: ``saml_fused_step_<hash>`` of the source, torch version, flags and CPU."""
    h = hashlib.sha256()
    # the torch installation's path too: two environments (venvs) sharing the cache would otherwise rewrite each
    # other's build.ninja (other include paths) and rebuild in turn
    for part in (source.read_bytes(), torch.__version__.encode(), " ".join(CFLAGS).encode(), cpu_id().encode(),
                 sys.version.encode(), str(Path(torch.__file__).resolve().parent).encode()):
        h.update(part)
        h.update(b"\0")
    return f"saml_fused_step_{h.hexdigest()[:16]}"


def _ensure_ninja_on_path() -> None:
    """torch's builder runs ``ninja``: the PyPI wheel's binary lives beside this Python (a venv not activated)."""
    dirs = [str(Path(sys.executable).parent)]
    try:
        import ninja  # type: ignore[import-not-found,unused-ignore]

        dirs.insert(0, str(ninja.BIN_DIR))
    except Exception:  # noqa: BLE001 - the wheel is optional when ninja is installed system-wide
        pass
    path = os.environ.get("PATH", "").split(os.pathsep)
    missing = [d for i, d in enumerate(dirs) if d not in path and d not in dirs[:i]]
    if missing:
        os.environ["PATH"] = os.pathsep.join([*missing, *path])


def _load_built(name: str, build_dir: Path) -> Any:
    """The module of a finished build in ``build_dir``, imported directly (no ninja, no lock), or None when there
    is none or it does not import (a build killed while linking: it is rebuilt)."""
    so = build_dir / f"{name}.so"
    if not so.is_file():
        return None
    try:
        spec = importlib.util.spec_from_file_location(name, so)
        if spec is None or spec.loader is None:
            return None
        mod = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(mod)
        return mod
    except ImportError:
        return None


def _build(name: str, src: Path, build_dir: Path, verbose: bool) -> Any:
    """Build with :func:`torch.utils.cpp_extension.load` under an exclusive ``flock`` on ``build_dir/saml.lock``:
    the kernel holds it until the build ends and it dies with the process. torch's own lock file (``lock``,
    which waits forever once a process is killed while holding it: Ctrl-C during the first build) is therefore
    stale whenever it exists here, and is removed. Another process's finished build is loaded instead."""
    _ensure_ninja_on_path()
    from torch.utils.cpp_extension import load

    with open(build_dir / "saml.lock", "w") as lock_file:
        fcntl.flock(lock_file, fcntl.LOCK_EX)
        try:
            mod = _load_built(name, build_dir)
            if mod is not None:
                return mod
            (build_dir / "lock").unlink(missing_ok=True)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                return load(name=name, sources=[str(src)], extra_cflags=list(CFLAGS), build_directory=str(build_dir),
                            verbose=verbose)
        finally:
            fcntl.flock(lock_file, fcntl.LOCK_UN)


def load_kernel(source: Path | None = None, verbose: bool = False, build: bool = True) -> Any:
    """The compiled kernel module (built on the first call on this machine, then loaded from the cache), or
    ``None`` when it is switched off or cannot be built (:func:`kernel_reason`, :func:`build_error`; one warning
    per process). The result is cached for the process; ``source`` (tests) builds another copy of the source.
    ``build=False`` only loads a finished build: without one it returns ``None`` and a later call still builds."""
    if switched_off():
        return None
    if source is None and _STATE.tried:
        return _STATE.module
    state = _STATE if source is None else _KernelState()
    src = KERNEL_SOURCE if source is None else Path(source)
    try:
        name = build_name(src)
        build_dir = cache_root() / name
        build_dir.mkdir(parents=True, exist_ok=True)
        t0 = time.perf_counter()
        mod = _load_built(name, build_dir)
        if mod is None and not build:
            return None  # nothing finished to load; the state is untouched, so a later call builds
        state.tried = True
        state.cached = mod is not None
        if mod is None:
            mod = _build(name, src, build_dir, verbose)
        state.seconds = None if state.cached else time.perf_counter() - t0
        if not hasattr(mod, "FusedKernel"):
            raise RuntimeError("the built module has no FusedKernel")
        state.module, state.reason, state.error = mod, None, None
    except Exception as exc:  # noqa: BLE001 - any build or load problem means: the torch path
        state.tried, state.module = True, None
        state.error = f"{type(exc).__name__}: {exc}"
        first = str(exc).strip().splitlines()
        state.reason = f"build failed: {type(exc).__name__}: {first[0] if first else ''}"[:300]
        if not _STATE.warned:
            _STATE.warned = True
            warnings.warn(f"saml_ros fused training kernel not available ({state.reason}); training runs the "
                          "torch path", RuntimeWarning, stacklevel=2)
    if source is not None:
        _STATE.reason, _STATE.error = state.reason, state.error
    return state.module


def kernel_reason() -> str | None:
    """Why the kernel is not used (``None`` when it loaded): switched off, not loaded yet, or the build failure."""
    if switched_off():
        return f"switched off ({SWITCH_ENV}=0)"
    if not _STATE.tried:
        return "not loaded yet"
    return _STATE.reason


def build_error() -> str | None:
    """The full error of a failed build or load (``None`` otherwise)."""
    return _STATE.error


def build_seconds() -> float | None:
    """Seconds this process spent compiling the kernel (``None``: loaded from the cache, or not loaded)."""
    return _STATE.seconds


def kernel_unsupported_reason(run: RunState, data: Transitions) -> str | None:
    """Why the kernel cannot run ``run`` on ``data`` (beyond :func:`~.fast.unsupported_reason`), or ``None``."""
    dt = run.config.torch_dtype
    if dt not in (torch.float32, torch.float64):
        return f"dtype {dt}"
    if any(p.device.type != "cpu" for p in run.model.net.parameters()) or data.x.device.type != "cpu":
        return "tensors not on the CPU"
    return None


# ------------------------------------------------------------------------------------------------- engine
class FusedEngine(FastEngine):
    """``TrainConfig.engine="fast"``: the fast engine with its steps in the fused kernel where it loaded and
    applies, else its torch path; :attr:`kernel_used` says which ran (the trainer copies it)."""

    name = "fast"

    def __init__(self) -> None:
        self.kernel_used = False
        self.kernel_reason: str | None = None
        #: :func:`~saml_ros.core.training.evaluate.evaluate_spec` of the data at the end of the last kernel fit
        self.evaluation: dict[str, Any] | None = None

    def fit(self, run: RunState, data: Transitions, epochs: int, bar: Any = None,
            on_epoch: Callable[[], None] | None = None) -> None:
        mod = load_kernel()
        why = kernel_reason() if mod is None else kernel_unsupported_reason(run, data)
        self.kernel_reason = why
        if why is not None:
            log.debug("fused training kernel not used (%s): the fast engine's torch path", why)
            self.kernel_used = False
            FastRun(run, data).fit(epochs, bar, on_epoch)
            return
        try:  # set-up only: nothing of the run's state has changed if it fails
            frun = _reusable_run(run, data, mod)
            frun.prepare()
        except Exception as exc:  # noqa: BLE001 - a configuration the kernel refuses: the torch path
            self.kernel_reason = f"kernel set-up failed: {type(exc).__name__}: {exc}"
            log.warning("fused training kernel not used (%s): the fast engine's torch path", self.kernel_reason)
            _RUNS.pop(run, None)
            self.kernel_used = False
            FastRun(run, data).fit(epochs, bar, on_epoch)
            return
        self.kernel_used = True
        frun.fit(epochs, bar, on_epoch)
        self.evaluation = frun.evaluation


#: the last FusedRun of each trainer, with the signature it was built for (see _reusable_run)
_RUNS: weakref.WeakKeyDictionary[Any, tuple[tuple[Any, ...], FusedRun]] = weakref.WeakKeyDictionary()


def _signature(run: RunState, data: Transitions) -> tuple[Any, ...]:
    """What a :class:`FusedRun` is built from, beyond the state it reads at every fit: the data (the Transitions
    object and its tensors' identities and versions: an in-place edit shows; its f_hat and masks are computed once,
    so a Transitions is not edited through the numpy arrays it was made from), the model's normalisation and
    parameter objects, the optimizers' and dual's objects and hyper-parameters, the config and schedules, the spec
    and its bounds."""
    m = run.model
    data_t = [data.x, data.u, data.y, data.base, *[mk for mk in data.masks if mk is not None]]
    norm = [m.in_mean, m.in_std, m.out_std]
    groups = tuple(tuple(sorted((k, repr(v)) for k, v in g.items() if k != "params"))
                   for opt in (run.primal_opt, run.dual.optimizer) for g in opt.param_groups)
    bounds = tuple(t.eps for t in run.spec.constraints)  # the bounds trained at (an aim may change them)
    return (id(data), tuple(id(t) for t in data_t + norm), tuple(t._version for t in data_t + norm),
            tuple(id(p) for p in m.net.parameters()), id(run.primal_opt), id(run.dual), id(run.dual.optimizer),
            groups, run.config, run.schedules, id(run.spec), bounds)


def _reusable_run(run: RunState, data: Transitions, module: Any) -> FusedRun:
    """The trainer's FusedRun of its last fit when nothing it was built from changed (as the online StreamRun is
    kept between calls: the set-up, sources and kernel object are then not rebuilt; the state is read at every
    fit, or skipped when no tensor of it changed), else a new one."""
    sig = _signature(run, data)
    cached = _RUNS.get(run)
    if cached is not None and cached[1].module is module and cached[0] == sig:
        return cached[1]
    frun = FusedRun(run, data, module)
    try:
        _RUNS[run] = (sig, frun)
    except TypeError:  # a run object that takes no weak reference: no reuse
        pass
    return frun


class _KernelSteps(FastRun):
    """What the fused runs (offline :class:`FusedRun`, online :class:`FusedStreamRun`) share: the kernel object
    over the run's flat tensors, the step counters and nuPI error exchanged with it, the per-step learning rates."""

    module: Any
    counts: Tensor
    xi: Tensor

    def _make_kernel(self, bsz: int, n: int, src_z: Tensor, src_r: Tensor, src_mask: Tensor, src_nyt: Tensor) -> Any:
        """The C++ object over this run's tensors and the sources given (``n`` rows per member; their storage is
        shared: it steps the state in place and reads the sources at every call)."""
        net, popt, dual = self.net, self.popt, self.dual
        empty = torch.empty(0, dtype=self.dtype)
        if not self.K:
            dkind = 0
        elif self.k_dual is not None:
            dkind = 1
        elif self.dnupi is not None:
            dkind = 4
        else:
            assert self.dopt is not None
            dkind = 2 if self.dopt.kind == "adam" else 3
        method = 1 if isinstance(dual, NuPIDual) else 2 if isinstance(dual, AugmentedDual) else \
            3 if isinstance(dual, ResilientDual) else 0
        adam = popt.kind == "adam"
        dopt = self.dopt if self.dopt is not None and self.dopt.kind == "adam" else None
        ostd = self.tr.model.out_std.detach().to(self.dtype).reshape(self.E, -1).contiguous()
        self._ostd = ostd
        tensors = [net.flat, net.grad, popt.m if adam else empty, popt.v if adam else empty, self.lam,
                   dopt.m if dopt is not None else empty, dopt.v if dopt is not None else empty, self.xi,
                   src_z.contiguous(), src_r.contiguous(), src_mask, src_nyt, ostd, self.counts]
        ints = [self.E, bsz, n, net.n_layers, *net.dims, self.T, src_r.shape[1], int(self.data.per_member),
                int(self.z_per_member), 0 if adam else 1, dkind, method, net.n_extra]
        for t in self.terms:
            ints += [_LOSS_CODES[t.loss], int(t.region is not None and t.mean == "conditional"), len(t.fields),
                     *[int(f) for f in t.fields]]
        d = self.dopt
        dbls = [popt.beta1, popt.beta2, popt.eps, d.beta1 if d else 0.0, d.beta2 if d else 0.0, d.eps if d else 0.0,
                float(self.k_dual or 0.0), self.dnupi.kp if self.dnupi else 0.0, self.dnupi.nu if self.dnupi else 0.0]
        for t in self.terms:
            dbls += [float(t.eps), float(t.huber_delta) if t.loss == "huber" else 0.0]
        rho = getattr(dual, "rho", None)
        eps2 = getattr(dual, "eps2", None)
        for k in range(self.K):
            dbls += [float(rho[k]) if rho is not None else 0.0, float(eps2[k]) if eps2 is not None else 0.0,
                     float(dual.eps[k])]
        return self.module.FusedKernel(tensors, ints, dbls)

    # ------------------------------------------------------------------------------ counters <-> flat optimizers
    def _to_kernel(self) -> None:
        nupi = self.dnupi
        self.counts[0] = self.popt.step_count
        self.counts[1] = self.dopt.step_count if self.dopt is not None else 0
        self.counts[2] = nupi.step_count if nupi is not None else 0
        self.counts[3] = int(nupi is not None and nupi.xi is not None)
        if nupi is not None and nupi.xi is not None:
            self.xi.copy_(nupi.xi)

    def _from_kernel(self) -> None:
        c = self.counts.tolist()
        self.popt.step_count = c[0]
        if self.dopt is not None:
            self.dopt.step_count = c[1]
        if self.dnupi is not None:
            self.dnupi.step_count = c[2]
            self.dnupi.xi = self.xi.clone() if c[3] else None

    def _lrs(self, t0: int, s: int) -> Tensor:
        """``(s, 2)`` float64: the primal and dual learning rates of updates ``t0 .. t0 + s - 1``."""
        ps, ds = self.schedules
        out = torch.empty(s, 2, dtype=torch.float64)
        dual_opt = self.dopt or self.dnupi
        if ps.constant:
            out[:, 0] = self.popt.lr
        else:
            out[:, 0] = torch.tensor([ps.lr(t) for t in range(t0, t0 + s)], dtype=torch.float64)
        if ds.constant or dual_opt is None:
            out[:, 1] = dual_opt.lr if dual_opt is not None else 0.0
        else:
            out[:, 1] = torch.tensor([ds.lr(t) for t in range(t0, t0 + s)], dtype=torch.float64)
        return out


class FusedRun(_KernelSteps):
    """One :meth:`Engine.fit` on the fused kernel: the fast engine's flat state and sources, stepped by
    ``kernels/fused_step.cpp`` in blocks of ``health.check_every`` steps (see the module docstring)."""

    def __init__(self, trainer: RunState, data: Transitions, module: Any) -> None:
        super().__init__(trainer, data)
        self.module = module
        rows = self.src_r.shape[0]
        # every term's mask column and ||y|| (1 where unused), in term order
        self.src_mask = torch.ones(rows, self.T, dtype=self.dtype)
        self.src_nyt = torch.ones(rows, self.T, dtype=self.dtype)
        for g, m, ny in zip(self.groups, self.src_masks, self.src_ny):
            self.src_mask[:, g.cols] = m
            if ny is not None:
                self.src_nyt[:, g.cols] = ny
        self.counts = torch.zeros(4, dtype=torch.int64)
        self.xi = torch.zeros(self.E, max(self.K, 1), dtype=self.dtype)
        self.stats = torch.zeros(3, dtype=torch.float64)
        self.evaluation: dict[str, Any] | None = None
        self._kern: Any = None
        self._kern_bsz = 0

    def _kernel(self, bsz: int) -> Any:
        """The C++ object over this run's tensors and sources."""
        return self._make_kernel(bsz, self.n, self.src_z, self.src_r, self.src_mask, self.src_nyt)

    def prepare(self) -> Any:
        """The kernel object for the configured batch size (built on the first call, or when that changed)."""
        bsz = minibatch_plan(self.tr.config.batch_size, self.n)[0]
        if self._kern is None or self._kern_bsz != bsz:
            self._kern, self._kern_bsz = self._kernel(bsz), bsz
        return self._kern

    # ------------------------------------------------------------------------------ training
    def fit(self, epochs: int, bar: Any = None, on_epoch: Callable[[], None] | None = None) -> None:
        """``epochs`` passes, with the contract of :meth:`Engine.fit` (history, counters, generator)."""
        tr = self.tr
        n, e = self.n, self.E
        bsz, per_epoch = minibatch_plan(tr.config.batch_size, n)
        log_every = tr.config.log_every or per_epoch
        tr.model.train()
        self.load_state()
        self._pending = self._pending_from_log()
        kern = self.prepare()
        self._to_kernel()
        # as FastRun.fit: several epochs drawn at once (rand(Q, E, N) consumes the generator like Q rand(E, N))
        per_ints = per_epoch * e * bsz
        chunk = 1 if on_epoch is not None else max(1, min(epochs, 1_000_000 // max(1, per_ints)))
        done = 0
        while done < epochs:
            q = min(chunk, epochs - done)
            perm = torch.argsort(torch.rand(q, e, n, generator=tr.rng), dim=-1)
            idx = perm[..., : per_epoch * bsz].reshape(q, e, per_epoch, bsz).transpose(1, 2)
            idx = idx.reshape(q * per_epoch, e, bsz).contiguous()
            vals = torch.empty(q * per_epoch, e, self.T, dtype=self.dtype)
            kern.set_chunk(idx, vals, self._lrs(tr.steps, q * per_epoch))
            for k in range(q):
                self._run_kernel(kern, vals, k * per_epoch, (k + 1) * per_epoch, per_epoch, log_every, bar)
                tr.epochs_done = round(tr.epochs_done, 9)
                if on_epoch is not None:
                    self._from_kernel()
                    self.store_state()
                    on_epoch()
                    self.load_state()
                    self._to_kernel()
            done += q
        self._from_kernel()
        self._log_point()
        self.store_state()
        # the dataset-level spec values at the final state (the trainer's end-of-fit diagnosis), in one pass here
        sums = torch.zeros(e, self.T, dtype=torch.float64)
        counts = torch.zeros(e, self.T, dtype=torch.float64)
        kern.evaluate(sums, counts)
        self.evaluation = spec_values(tr.spec, sums, counts, tr.dual.value)

    def _run_kernel(self, kern: Any, vals: Tensor, lo: int, hi: int, per_epoch: int, log_every: int,
                    bar: Any) -> None:
        """Steps ``lo:hi`` of the chunk in blocks: one kernel call and one health check per block (a block ends
        after ``check_every`` steps, at a log point and at ``hi``)."""
        tr = self.tr
        health = tr.health
        every = health.config.check_every
        next_log = tr.steps + (log_every - tr.steps % log_every)
        inc = 1.0 / per_epoch
        start = j = lo
        stats = self.stats
        while j < hi:
            b = min(hi, j + every, j + (next_log - tr.steps))
            kern.snapshot()
            kern.run(j, b, stats)
            n = b - j
            tr.steps += n
            for _ in range(n):  # the same float sum as one increment per step
                tr.epochs_done += inc
            worst, mean, biggest = stats.tolist()
            why = health.check_block_values(worst, mean, n, biggest)
            if why is not None:
                kern.restore()
                vals[j:b] = float("nan")
                health.skip(why, n)
                health.restores += 1
            j = b
            if tr.steps == next_log:
                next_log += log_every
                self._pending.append(vals[start:j])
                start = j
                self._log_point()
                if bar is not None:
                    bar.set_postfix_str(tr.log.postfix(), refresh=False)
        if start < hi:
            self._pending.append(vals[start:hi])
        if bar is not None:
            bar.update(hi - lo)


# ------------------------------------------------------------------------------------------------- online updates
def make_stream_run(trainer: RunState, batch_size: int, log_every: int, like: Transitions) -> StreamRun:
    """The online learner's update run: a :class:`FusedStreamRun` where the kernel loaded and applies (as
    :class:`FusedEngine`: not switched off, :func:`kernel_unsupported_reason` ``None``, engine not
    ``"fast_torch"``), else the torch-path :class:`~.stream.StreamRun`; ``run.kernel_used`` / ``run.kernel_reason``
    say which. Raises ``ValueError`` where neither applies (:func:`~.stream.stream_unsupported_reason`)."""
    mod = load_kernel()
    why = kernel_reason() if mod is None else kernel_unsupported_reason(trainer, like)
    if why is None and getattr(trainer.config, "engine", "fast") == "fast_torch":
        why = "engine 'fast_torch' configured"
    if why is None:
        try:
            return FusedStreamRun(trainer, batch_size, log_every, like, mod)
        except ValueError:
            raise
        except Exception as exc:  # noqa: BLE001 - a configuration the kernel refuses: the torch path
            why = f"kernel set-up failed: {type(exc).__name__}: {exc}"
            log.warning("fused kernel not used for online updates (%s): the torch path", why)
    run = StreamRun(trainer, batch_size, log_every, like)
    run.kernel_reason = why
    return run


class FusedStreamRun(StreamRun, _KernelSteps):
    """:class:`~.stream.StreamRun` with its steps in the fused kernel.

    One kernel object is kept for the run: it reads the minibatches from source buffers of this run (room for
    ``S x B`` rows, grown when a call brings more), into which each :meth:`steps` call copies its prepared
    minibatches, so a call costs the preparation of its ``S`` minibatches (as the torch path), a few copies and one
    kernel call per block.

    Health: the kernel runs a block (``check_every`` steps, ending at log points and at the call's end) and the
    block is then checked: every step's minibatch loss as the torch path's per-update gate does
    (:meth:`TrainingHealth.accept_loss_steps`: non-finite or exploding, with the running mean moved after each
    step) and the weights after the block. A block that passes counts its steps healthy. A block that fails is put
    back (the kernel's snapshot) and replayed on the torch path with its per-update gates and its weights check,
    so a bad minibatch is skipped and counted exactly as by :class:`~.stream.StreamRun`, and the block's good
    minibatches are applied (:attr:`blocks_replayed` counts such blocks). What the kernel path does not do is the
    gradient-norm test of blocks that pass: a non-finite gradient reaches the weights through Adam / SGD (then
    the block is replayed and the gate skips that step), a finite exploding gradient norm is not looked for, and
    the gradient's running mean only moves in replayed steps.
    """

    kernel_used = True

    def __init__(self, trainer: RunState, batch_size: int, log_every: int, like: Transitions, module: Any) -> None:
        super().__init__(trainer, batch_size, log_every, like)
        self.module = module
        self.counts = torch.zeros(4, dtype=torch.int64)
        self.xi = torch.zeros(self.E, max(self.K, 1), dtype=self.dtype)
        self.stats = torch.zeros(3, dtype=torch.float64)
        #: blocks that failed a check after the kernel ran them and were replayed on the torch path
        self.blocks_replayed = 0
        self._cap = 0
        self._kern: Any = None
        self._zpm = self.z_per_member
        self._grow(16)  # set-up errors show here (make_stream_run then runs the torch path)

    def _grow(self, s: int) -> None:
        """Source buffers for ``s`` minibatches and the kernel object over them."""
        rows, e, dt = s * self.bsz, self.E, self.dtype
        nz, ny = self.src_z.shape[1], self.src_r.shape[1]
        self._zpm = self.z_per_member
        self._bz = torch.zeros((e if self._zpm else 1) * rows, nz, dtype=dt)
        self._br = torch.zeros(rows, ny, dtype=dt)
        self._bm = torch.ones(rows, self.T, dtype=dt)
        self._bn = torch.ones(rows, self.T, dtype=dt)
        self._idx = torch.arange(rows).view(s, 1, self.bsz).expand(s, e, self.bsz).contiguous()
        self._kern = self._make_kernel(self.bsz, rows, self._bz, self._br, self._bm, self._bn)
        self._cap = s

    def _fill(self, s: int) -> None:
        """Copy the prepared sources of this call's ``s`` minibatches into the kernel's buffers."""
        if s > self._cap or self.z_per_member != self._zpm:
            self._grow(max(s, self._cap))
        rows, cap_rows = s * self.bsz, self._cap * self.bsz
        if self._zpm:
            self._bz.view(self.E, cap_rows, -1)[:, :rows].copy_(self.src_z.view(self.E, rows, -1))
        else:
            self._bz[:rows].copy_(self.src_z)
        self._br[:rows].copy_(self.src_r)
        for g, m, ny in zip(self.groups, self.src_masks, self.src_ny):
            self._bm[:rows, g.cols] = m
            if ny is not None:
                self._bn[:rows, g.cols] = ny

    def steps(self, x: Any, u: Any, y: Any) -> Tensor:
        """:meth:`StreamRun.steps <.stream.StreamRun.steps>` on the kernel (see the class docstring)."""
        s = self._take_minibatches(x, u, y)
        tr = self.tr
        self._fill(s)
        kern = self._kern
        vals = torch.empty(s, self.E, self.T, dtype=self.dtype)
        self.load_state()
        self._pending += self._pending_from_log()  # values of plain steps taken in between
        self._to_kernel()
        kern.set_chunk(self._idx[:s], vals, self._lrs(tr.steps, s))
        health, stats, log_every = tr.health, self.stats, self.log_every
        every, max_weight = health.config.check_every, health.config.max_weight
        next_log = tr.steps + (log_every - tr.steps % log_every)
        start = j = 0
        while j < s:
            e = min(s, j + every, j + (next_log - tr.steps))
            kern.snapshot()
            kern.run(j, e, stats)
            biggest = float(stats[2])
            ok = biggest <= max_weight  # NaN fails this
            if ok:
                losses = [(sum(sum(v) for v in step), sum(v[0] for v in step)) for step in vals[j:e].tolist()]
                ok = health.accept_loss_steps(losses)
            if not ok:
                kern.restore()
                self._from_kernel()
                self._replay(vals, j, e)
                self._to_kernel()
                self.blocks_replayed += 1
            tr.steps += e - j
            j = e
            if tr.steps == next_log:
                next_log += log_every
                self._pending.append(vals[start:j])
                start = j
                self._log_point()
        if start < s:
            self._pending.append(vals[start:s])
        self._from_kernel()
        self.store_state()
        return vals

    def _replay(self, vals: Tensor, a: int, b: int) -> None:
        """Steps ``a:b`` of this call on the torch path (per-update gates, then the weights check of the block),
        from the state before them; ``trainer.steps`` is that of step ``a`` (the caller advances it)."""
        z_all, r_all, sg_all = self._gather(self._idx[a:b])
        rows = vals.unbind(0)
        t0 = self.tr.steps
        snap = self._snapshot()
        self._skipped_in_block = 0
        for k in range(b - a):
            self._rates(t0 + k)
            self._step(z_all[k], r_all[k], sg_all[k], rows[a + k])
        self._check_weights(vals, a, b, snap)


def main() -> int:
    """``python -m saml_ros.core.training.engines.fused``: build or load the kernel and say which (``./dev test``
    runs this before pytest, so no test pays for the compile)."""
    mod = load_kernel()
    if mod is not None:
        secs = build_seconds()
        how = "cached" if secs is None else f"built in {secs:.0f} s"
        print(f"[dev] fused training kernel: ready ({how})", flush=True)
    else:
        print(f"[dev] fused training kernel: not built ({kernel_reason()}) - torch path", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
