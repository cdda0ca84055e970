"""Follow a learner's checkpoints and hand new models to a controller between two control steps (ROS-free).

A :class:`ModelWatcher` learns about new checkpoints in two ways:

* **notifications** (:meth:`ModelWatcher.notify`): the MPC node forwards every ``learner/checkpoint``
  announcement (path, version, schema hash);
* **polling** a run directory every ``poll_period`` seconds: its ``latest`` pointer and the checkpoint files
  themselves (a file newer than the pointer exists only if a writer died between its two renames, and it is
  complete, exactly as :meth:`~saml_ros.core.model.checkpoint.CheckpointStore.load_latest_valid` assumes).

Loading (:func:`saml_ros.core.model.io.load_model` with ``expect=system``, plus an optional ``prepare`` step)
runs on a **background thread**. The control thread calls :meth:`ModelWatcher.take` before each solve, which
never blocks on I/O: it returns the newest model that finished loading since the last call (or ``None``), and
the caller swaps it in between two solves.

A checkpoint that cannot be used is **refused** and the current model is kept. Every refusal is counted by
reason and logged once per file (a file is identified by path, size and modification time, so a file that is
replaced is looked at again, an unchanged one never twice):

* ``incompatible``: another system, another schema hash or inconsistent contents
  (:class:`~saml_ros.core.model.io.IncompatibleCheckpoint`, or an announcement whose schema hash differs);
* ``corrupt``: truncated, damaged, not a checkpoint, a malformed ``latest`` pointer
  (:class:`~saml_ros.core.model.checkpoint.CheckpointError`);
* ``missing``: an announced file that does not exist (e.g. pruned before it could be read);
* ``error``: anything else raised while loading or preparing (never propagated: the watcher keeps going);
* ``non_finite``, ``implausible``, ``residual``: the model fails the ``vet`` hook's acceptance check (the MPC's:
  :func:`saml_ros.core.mpc.acceptance.check_model`: non-finite weights, predictions outside the plausible range
  or further from the base model than the training data ever showed).

An optional ``accept(loaded) -> reason | None`` hook can hold back checkpoints that are *valid but not good
enough yet* (e.g. the learner's own estimate says the accuracy constraints are not met): they are counted as
``gated`` (not refused) and the current model is kept; newer checkpoints are still considered.

:func:`checkpoint_gate` is the MPC node's hook (parameters ``gate.max_constraint`` and ``gate.min_updates``).

Only checkpoints *newer* than the newest one loaded are considered: a higher version in the same directory,
or any version in a directory other than the current model's (a new learner run starts again at 1).

**The model in use** (:meth:`ModelWatcher.set_in_use`, told by the controller's side whenever it changes):

* a checkpoint whose weights are those of the model in use (a re-announcement, a copy in another directory) is a
  no-op: neither loaded again nor vetted nor refused (counted ``reannounced``);
* the model in use is re-checked with the ``vet`` hook every :data:`RECHECK_PERIOD_S` s on the background thread,
  as a new checkpoint is: the MPC's hook probes it on the states it flies (the recent states answered). A model that
  no longer passes is refused (``in_use_refused``, its reason counted like a checkpoint's) and handed to the control
  side once (:meth:`ModelWatcher.take_retired`), which stops planning with it.
"""

from __future__ import annotations

import contextlib
import hashlib
import math
import os
import threading
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

from saml_ros.core.dynamics.system import System
from saml_ros.core.model.checkpoint import CheckpointError, CheckpointStore
from saml_ros.core.model.io import IncompatibleCheckpoint, LoadedModel, load_model
from saml_ros.core.mpc.acceptance import ACCEPTANCE_REASONS

#: refusal reasons, in the order the counters are reported
REFUSAL_REASONS: tuple[str, ...] = ("incompatible", "corrupt", "missing", "error", *ACCEPTANCE_REASONS)
#: seconds between two re-checks of the model in use (see the module docstring)
RECHECK_PERIOD_S = 1.0


class Logger(Protocol):
    """What the watcher logs through (``logging.Logger`` and rclpy's node logger both fit)."""

    def info(self, msg: str) -> Any: ...
    def warning(self, msg: str) -> Any: ...


@dataclass(frozen=True)
class ReadyModel:
    """A checkpoint loaded (and prepared) on the background thread, waiting to be swapped in.

    Attributes:
        loaded: the rebuilt model with its spec, meta and arrays.
        path: the checkpoint file.
        version: checkpoint version (``meta["version"]``; >= 1).
        prepared: what ``prepare(loaded)`` returned (``None`` without a ``prepare`` hook).
        load_seconds: wall time of load + prepare on the background thread (s).
        source: ``"notification"``, ``"poll"`` or ``"initial"``.
    """

    loaded: LoadedModel
    path: Path
    version: int
    prepared: Any
    load_seconds: float
    source: str


@dataclass(frozen=True)
class Refusal:
    """One refused checkpoint: ``reason`` is one of :data:`REFUSAL_REASONS`, ``message`` says why."""

    path: str
    version: int | None
    reason: str
    message: str
    time: float


_FileId = tuple[str, int, int]  # (resolved path, size, mtime_ns)


def model_digest(model: Any) -> str:
    """A digest of a model's weights and normalisation (its ``state_dict``: names, dtypes, shapes, values) and kind:
    equal for the same model read from two files."""
    h = hashlib.sha256(str(getattr(model, "kind", "")).encode())
    for name, value in sorted(model.state_dict().items()):
        t = value.detach().cpu().contiguous()
        h.update(f"{name}:{t.dtype}:{tuple(t.shape)}".encode())
        h.update(t.numpy().tobytes())
    return h.hexdigest()


@dataclass(frozen=True)
class Retired:
    """The model in use failed its re-check: ``version`` (its tag), ``reason`` (one of :data:`REFUSAL_REASONS`)
    and ``message``."""

    version: int
    reason: str
    message: str


class ModelWatcher:
    """Watches ``run_dir`` and/or receives checkpoint notifications; loads new models off the control thread.

    Args:
        system: the system the controller runs; a checkpoint of any other system or schema is refused.
        run_dir: run directory to poll (``None``: notifications only). It need not exist yet.
        poll_period: seconds between polls of ``run_dir`` (> 0).
        prepare: optional ``prepare(loaded) -> Any`` run on the background thread after loading (e.g. copy
            the weights into the solver's format); an exception in it refuses the checkpoint (``error``).
        loader: ``loader(path, system) -> LoadedModel``; :func:`~saml_ros.core.model.io.load_model` by default.
        logger: where refusals and loads are logged (``None``: silent).
        accept: optional ``accept(loaded) -> reason | None`` run after loading; a returned reason holds the
            checkpoint back (counted as ``gated``, logged).
        vet: optional ``vet(loaded) -> (reason, message) | None`` run right after loading; a returned pair
            refuses the checkpoint under ``reason`` (one of :data:`REFUSAL_REASONS`).

    Thread safety: :meth:`notify`, :meth:`take`, :meth:`stats` may be called from any thread.
    """

    def __init__(
        self,
        system: System,
        run_dir: str | Path | None = None,
        *,
        poll_period: float = 0.5,
        prepare: Callable[[LoadedModel], Any] | None = None,
        loader: Callable[[Path, System], LoadedModel] | None = None,
        logger: Logger | None = None,
        accept: Callable[[LoadedModel], str | None] | None = None,
        vet: Callable[[LoadedModel], tuple[str, str] | None] | None = None,
    ) -> None:
        if not poll_period > 0:
            raise ValueError(f"poll_period must be > 0 s, got {poll_period}")
        self.system = system
        self.run_dir = Path(run_dir) if run_dir else None
        self.poll_period = float(poll_period)
        self._prepare = prepare
        self._loader = loader or (lambda path, system: load_model(path, expect=system))
        self._log = logger
        self._accept = accept
        self._vet = vet
        self._cond = threading.Condition()
        self._work = threading.Lock()  # one load at a time (background thread or a synchronous call)
        self._notes: list[tuple[str, int | None, str | None]] = []
        self._ready: ReadyModel | None = None
        self._stop = False
        self._thread: threading.Thread | None = None
        self._seen: set[_FileId] = set()
        self._newest: tuple[Path, int] | None = None  # (directory, version) of the newest model loaded
        self.refusals: Counter[str] = Counter()
        self.last_refusal: Refusal | None = None
        self.loaded = 0
        self.superseded = 0
        self.notifications = 0
        self.gated = 0
        self.last_gated = ""
        self.reannounced = 0
        self.in_use_refused = 0
        self._in_use: tuple[LoadedModel, int, str] | None = None  # (model, version, digest)
        self._retired: Retired | None = None
        self._next_recheck = 0.0

    # ------------------------------------------------------------------------------------ lifecycle
    def start(self) -> None:
        """Start the background thread (idempotent)."""
        with self._cond:
            if self._thread is not None:
                return
            self._stop = False
            self._thread = threading.Thread(target=self._run, name="model_watch", daemon=True)
            self._thread.start()

    def stop(self, timeout: float = 5.0) -> None:
        """Stop the background thread and wait up to ``timeout`` seconds for it."""
        with self._cond:
            self._stop = True
            self._cond.notify_all()
            thread, self._thread = self._thread, None
        if thread is not None:
            thread.join(timeout)

    def __enter__(self) -> ModelWatcher:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # --------------------------------------------------------------------------------- control side
    def notify(self, path: str | Path, version: int | None = None, schema_hash: str | None = None) -> None:
        """A checkpoint was announced (non-blocking): it is loaded on the background thread if it is newer."""
        with self._cond:
            self.notifications += 1
            self._notes.append((str(path), version, schema_hash))
            self._cond.notify_all()

    def take(self) -> ReadyModel | None:
        """The newest model loaded since the last call, or ``None`` (never blocks on loading)."""
        with self._cond:
            ready, self._ready = self._ready, None
            return ready

    def set_in_use(self, loaded: LoadedModel | None, version: int = 0) -> None:
        """The model the controller plans with from now on (``None``: the base model f_hat), with its ``version``;
        the watcher skips checkpoints holding it and re-checks it (see the module docstring)."""
        entry = None if loaded is None else (loaded, int(version), model_digest(loaded.model))
        with self._cond:
            self._in_use = entry
            self._next_recheck = time.monotonic() + RECHECK_PERIOD_S

    def take_retired(self) -> Retired | None:
        """The model in use that failed its re-check since the last call, or ``None`` (never blocks)."""
        with self._cond:
            retired, self._retired = self._retired, None
            return retired

    def wait_ready(self, timeout: float) -> ReadyModel | None:
        """Like :meth:`take`, but waits up to ``timeout`` seconds for a model (for start-up and tests)."""
        deadline = time.monotonic() + timeout
        with self._cond:
            while self._ready is None and (left := deadline - time.monotonic()) > 0:
                self._cond.wait(left)
            ready, self._ready = self._ready, None
            return ready

    def stats(self) -> dict[str, Any]:
        """Counters: ``loaded``, ``superseded``, ``notifications``, ``refused`` (total), ``refused/<reason>``,
        ``gated``, ``newest_version`` (newest loaded, 0 = none), ``last_refusal`` and ``last_gated`` (their
        messages, or "")."""
        with self._cond:
            out: dict[str, Any] = {
                "loaded": self.loaded,
                "superseded": self.superseded,
                "notifications": self.notifications,
                "refused": sum(self.refusals.values()),
            }
            out.update({f"refused/{r}": self.refusals[r] for r in REFUSAL_REASONS})
            out["newest_version"] = self._newest[1] if self._newest else 0
            out["last_refusal"] = self.last_refusal.message if self.last_refusal else ""
            out["gated"] = self.gated
            out["last_gated"] = self.last_gated
            out["reannounced"] = self.reannounced
            out["in_use_refused"] = self.in_use_refused
            return out

    # ------------------------------------------------------------------------------- loading side
    def poll_once(self, source: str = "poll") -> ReadyModel | None:
        """Process pending notifications, then poll ``run_dir``, in the calling thread.

        The background thread calls this; call it directly (e.g. once at start-up, before the first solve)
        to load synchronously. Returns the model it loaded (also left for :meth:`take`), or ``None``.
        """
        with self._work:
            with self._cond:
                notes, self._notes = self._notes, []
            got: ReadyModel | None = None
            # newest announcement first: an older one that is still pending is superseded by it
            for path, version, schema_hash in sorted(notes, key=lambda n: -(n[1] or 0)):
                got = self._try_notified(Path(path), version, schema_hash) or got
                if got is not None:
                    break
            if self.run_dir is not None:
                got = self._poll_dir(source) or got
            self._recheck_in_use()
            return got

    def _recheck_in_use(self) -> None:
        """Vet the model in use again (every :data:`RECHECK_PERIOD_S` s); a refusal retires it."""
        with self._cond:
            entry = self._in_use
            if entry is None or self._vet is None or time.monotonic() < self._next_recheck:
                return
            self._next_recheck = time.monotonic() + RECHECK_PERIOD_S
        loaded, version, _ = entry
        try:
            refused = self._vet(loaded)
        except Exception as exc:  # noqa: BLE001 - a check that cannot run says nothing against the model
            if self._log is not None:
                self._log.warning(f"re-check of the model in use (version {version}) raised {type(exc).__name__}: {exc}")
            return
        if refused is None:
            return
        reason, message = refused
        with self._cond:
            if self._in_use is not entry:  # the controller changed models meanwhile
                return
            self._in_use = None
            self._retired = Retired(version, reason, message)
            self.in_use_refused += 1
            self.refusals[reason] += 1
            self.last_refusal = Refusal(str(loaded.path or "?"), version, reason,
                                        f"the model in use: {message}", time.time())
        if self._log is not None:
            self._log.warning(f"the model in use (version {version}) no longer passes the acceptance check on the "
                              f"states it flies ({reason}): {message}; it is not used any more")

    def _run(self) -> None:
        next_poll = 0.0
        while True:
            with self._cond:
                while not self._stop and not self._notes and time.monotonic() < next_poll:
                    self._cond.wait(max(0.0, next_poll - time.monotonic()))
                if self._stop:
                    return
            try:
                self.poll_once()
            except Exception as exc:  # noqa: BLE001 - the watcher must outlive any surprise
                self._refuse("?", None, "error", f"model watcher: unexpected {type(exc).__name__}: {exc}")
            next_poll = time.monotonic() + self.poll_period

    def _is_newer(self, path: Path, version: int | None) -> bool:
        if self._newest is None:
            return True
        directory, newest = self._newest
        if path.parent.resolve() != directory:
            return True
        return version is None or version > newest

    def _try_notified(self, path: Path, version: int | None, schema_hash: str | None) -> ReadyModel | None:
        if not self._is_newer(path, version):
            return None
        fid = _file_id(path)
        if fid is None:
            key: _FileId = (str(path), -1, version or -1)
            if key not in self._seen:
                self._seen.add(key)
                self._refuse(str(path), version, "missing", f"{path}: announced checkpoint does not exist")
            return None
        if fid in self._seen:
            return None
        if schema_hash is not None and schema_hash != self.system.schema_hash():
            self._seen.add(fid)
            self._refuse(str(path), version, "incompatible",
                         f"{path}: announced schema hash {schema_hash} does not match {self.system.name!r} "
                         f"({self.system.schema_hash()})")  # fmt: skip
            return None
        return self._load(path, fid, "notification")

    def _poll_dir(self, source: str) -> ReadyModel | None:
        assert self.run_dir is not None
        if not self.run_dir.is_dir():
            return None
        store = CheckpointStore(self.run_dir)  # only reads: the directory exists, nothing is written
        candidates: dict[int, Path] = {}
        try:
            pointed = store.latest()
        except CheckpointError as exc:
            pfid = _file_id(store.latest_path)
            if pfid is not None and pfid not in self._seen:
                self._seen.add(pfid)
                self._refuse(str(store.latest_path), None, "corrupt", str(exc))
            pointed = None
        if pointed is not None:
            candidates[pointed[1]] = pointed[0]
        try:
            for v in store.versions():
                candidates.setdefault(v, store.path_for(v))
        except OSError:
            pass
        for version in sorted(candidates, reverse=True):
            path = candidates[version]
            if not self._is_newer(path, version):
                break
            fid = _file_id(path)
            if fid is None or fid in self._seen:
                continue
            ready = self._load(path, fid, source)
            if ready is not None:
                return ready
        return None

    def _load(self, path: Path, fid: _FileId, source: str) -> ReadyModel | None:
        self._seen.add(fid)
        t0 = time.perf_counter()
        try:
            loaded = self._loader(path, self.system)
            if self._is_in_use(loaded):
                self._noop(path, loaded.version)
                return None
            refused = self._vet(loaded) if self._vet is not None else None
            if refused is not None:
                self._refuse(str(path), loaded.version, *refused)
                return None
            held_back = self._accept(loaded) if self._accept is not None else None
            if held_back is not None:
                self._hold_back(path, loaded.version, held_back)
                return None
            prepared = self._prepare(loaded) if self._prepare is not None else None
        except IncompatibleCheckpoint as exc:
            self._refuse(str(path), None, "incompatible", str(exc))
            return None
        except CheckpointError as exc:
            reason = "missing" if not path.exists() else "corrupt"
            self._refuse(str(path), None, reason, str(exc))
            return None
        except Exception as exc:  # noqa: BLE001 - a bad file must never take the controller down
            self._refuse(str(path), None, "error", f"{path}: {type(exc).__name__}: {exc}")
            return None
        version = loaded.version
        if version < 1:
            self._refuse(str(path), None, "incompatible", f"{path}: checkpoint has no version in its metadata")
            return None
        if not self._is_newer(path, version):  # e.g. a stale announcement naming an older file
            return None
        ready = ReadyModel(loaded, path, version, prepared, time.perf_counter() - t0, source)
        with self._cond:
            if self._ready is not None:
                self.superseded += 1
            self._ready = ready
            self._newest = (path.parent.resolve(), version)
            self.loaded += 1
            self._cond.notify_all()
        if self._log is not None:
            self._log.info(f"loaded checkpoint version {version} from {path} ({1e3 * ready.load_seconds:.1f} ms, "
                           f"via {source})")
        return ready

    def _is_in_use(self, loaded: LoadedModel) -> bool:
        with self._cond:
            entry = self._in_use
        return entry is not None and model_digest(loaded.model) == entry[2]

    def _noop(self, path: Path, version: int) -> None:
        with self._cond:
            self.reannounced += 1
            in_use = self._in_use[1] if self._in_use is not None else 0
        if self._log is not None:
            self._log.info(f"{path} (version {version}) holds the model in use (version {in_use}): nothing to do")

    def _hold_back(self, path: Path, version: int, reason: str) -> None:
        text = f"{path.name} (version {version}) held back: {reason}"
        with self._cond:
            self.gated += 1
            self.last_gated = text
        if self._log is not None:
            self._log.info(f"checkpoint {text}; keeping the current model")

    def _refuse(self, path: str, version: int | None, reason: str, message: str) -> None:
        with self._cond:
            self.refusals[reason] += 1
            self.last_refusal = Refusal(path, version, reason, message, time.time())
        if self._log is not None:
            self._log.warning(f"refused checkpoint ({reason}), keeping the current model: {message}")


def _file_id(path: Path) -> _FileId | None:
    with contextlib.suppress(OSError):
        st = os.stat(path)
        return (str(path.resolve()), st.st_size, st.st_mtime_ns)
    return None


def checkpoint_gate(max_constraint: float, min_updates: int) -> Callable[[LoadedModel], str | None] | None:
    """The ``accept`` hook holding back checkpoints with fewer than ``min_updates`` learner updates, or whose
    recorded constraint estimates (``metrics["constraint/<k>"]``, the learner's E[l | region] - eps on its live
    window) exceed ``max_constraint``; it returns why, or ``None`` to accept. ``None`` when both are disabled
    (``inf`` and 0)."""
    if math.isinf(max_constraint) and max_constraint > 0 and min_updates <= 0:
        return None

    def accept(loaded: LoadedModel) -> str | None:
        updates = int(loaded.meta.get("updates", 0))
        if updates < min_updates:
            return f"{updates} learner updates < gate.min_updates = {min_updates}"
        if not math.isinf(max_constraint):
            metrics = loaded.meta.get("metrics") or {}
            cons = {k: v for k, v in metrics.items() if k.startswith("constraint/")}
            if not cons:
                return "its metrics hold no constraint estimate (constraint/<k>)"
            bad = {k: round(float(v), 6) for k, v in cons.items()
                   if not (isinstance(v, int | float) and math.isfinite(v) and v <= max_constraint)}
            if bad:
                return f"constraint estimate {bad} > gate.max_constraint = {max_constraint:g}"
        return None

    return accept
