"""Versioned checkpoints with an atomic ``latest`` pointer; loading never executes code from the file.

File format (``docs/checkpoints.md``): a ZIP archive (like ``numpy.savez``) holding

- ``meta.json``: UTF-8 JSON ``{"format": "saml_ros.checkpoint", "format_version": 1,
  "arrays": {name: {"dtype": "<f8", "shape": [...]}, ...}, "payload_sha256": hex,
  "meta_sha256": hex, "meta": {...caller's metadata...}}``;
- one ``arrays/<name>.npy`` member per array, numeric dtypes only (bool, int, uint, float, complex).

Arrays are parsed with ``numpy.load(..., allow_pickle=False)``, so an object array (a pickle) is refused
instead of being unpickled. ``payload_sha256`` covers every array's name, dtype, shape and bytes and
``meta_sha256`` the caller's metadata, so a corrupted file is refused even when the ZIP still opens.

A run directory (:class:`CheckpointStore`) holds ``ckpt-000001.saml``, ``ckpt-000002.saml``, ... and a
``latest`` text file (``"ckpt-000002.saml 2\\n"``). Every file is written to a temporary file in the same
directory, flushed, fsynced, renamed over the target with ``os.replace`` and the directory is fsynced;
a checkpoint file is durable before the pointer names it. A reader therefore sees either the old or the
new version of any file, never a partial one.
"""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import io
import json
import os
import re
import tempfile
import threading
import time
import zipfile
from collections import OrderedDict
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, TYPE_CHECKING, Any

import numpy as np

from saml_ros.core.errors import SamlError

if TYPE_CHECKING:
    import torch

FORMAT_NAME = "saml_ros.checkpoint"
FORMAT_VERSION = 1
SUPPORTED_FORMAT_VERSIONS = (1,)
META_MEMBER = "meta.json"
ARRAY_DIR = "arrays/"
CHECKPOINT_SUFFIX = ".saml"
LATEST_NAME = "latest"

_NUMERIC_KINDS = "biufc"
# Array names become ZIP member names: keep them portable and unable to escape the archive layout.
_NAME_RE = re.compile(r"[A-Za-z0-9_.:\-]+(/[A-Za-z0-9_.:\-]+)*")
_CKPT_RE = re.compile(r"ckpt-(\d{6,})\.saml")
_TMP_RE = re.compile(r"\.(ckpt-\d{6,}\.saml|latest)\..+\.tmp")
_ZIP_MAGIC = (b"PK\x03\x04", b"PK\x05\x06")


class CheckpointError(SamlError):
    """A checkpoint file is missing, truncated, foreign, corrupt or of an unsupported format.

    The message always starts with the path of the offending file.
    """


# --------------------------------------------------------------------------------------------------
# single files


def write_checkpoint(
    path: Path | str, arrays: Mapping[str, np.ndarray], meta: Mapping[str, Any], *, compress: bool = False
) -> None:
    """Atomically write a checkpoint file.

    Args:
        path: target file; its directory must exist. An existing file is replaced atomically.
        arrays: name -> numeric array (any shape, dtype kind bool/int/uint/float/complex). Names are
            ``/``-separated segments of ``[A-Za-z0-9_.:-]``.
        meta: JSON-serialisable metadata (str keys; dict, list, tuple, str, int, float, bool, None,
            numpy scalars). Tuples come back as lists. NaN and inf are allowed.
        compress: deflate the members (slower; float weights barely compress).

    Raises:
        ValueError: an array name or dtype is not allowed.
        TypeError: ``meta`` is not JSON-serialisable (the message names the offending key path).
    """
    path = Path(path)
    clean = _validate_arrays(arrays)
    plain_meta = _plain_meta(meta)
    header = {
        "format": FORMAT_NAME,
        "format_version": FORMAT_VERSION,
        "arrays": {k: {"dtype": a.dtype.str, "shape": list(a.shape)} for k, a in clean.items()},
        "payload_sha256": _payload_sha256(clean),
        "meta_sha256": _meta_sha256(plain_meta),
        "meta": plain_meta,
    }
    text = json.dumps(header, sort_keys=True, ensure_ascii=False)
    method = zipfile.ZIP_DEFLATED if compress else zipfile.ZIP_STORED

    def write(f: IO[bytes]) -> None:
        with zipfile.ZipFile(f, "w", compression=method, allowZip64=True) as zf:
            zf.writestr(META_MEMBER, text.encode("utf-8"))
            for name, a in clean.items():
                with zf.open(ARRAY_DIR + name + ".npy", "w", force_zip64=a.nbytes > 1 << 30) as fh:
                    np.lib.format.write_array(fh, a, allow_pickle=False)

    atomic_write(path, write)


def read_checkpoint(path: Path | str) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """Read and verify a checkpoint written by :func:`write_checkpoint`.

    Returns:
        ``(arrays, meta)``: name -> array (bit-exact, same dtype and shape as written) and the caller's
        metadata as parsed JSON.

    Raises:
        CheckpointError: naming the file and the problem (missing, empty, truncated, not a ZIP, a pickle,
            foreign ZIP such as a ``torch.save`` file, missing/invalid ``meta.json``, wrong format name,
            unsupported format version, unexpected or missing members, object/pickled or non-numeric
            arrays, checksum mismatch).

    One function on purpose (longer than 80 lines): the checks run in the order the file is read, each naming
    its failure, and the open file is needed by all of them.
    """
    path = Path(path)

    def fail(msg: str) -> CheckpointError:
        return CheckpointError(f"{path}: {msg}")

    try:
        f = open(path, "rb")  # noqa: SIM115 - closed by the ExitStack below
    except FileNotFoundError:
        raise fail("no such checkpoint file") from None
    except OSError as e:
        raise fail(f"cannot open: {e.strerror or e}") from None
    with contextlib.ExitStack() as stack:
        stack.enter_context(f)
        start = f.read(4)
        if not start:
            raise fail("empty file (0 bytes)")
        if start[:1] == b"\x80":
            raise fail("this is a Python pickle, not a saml_ros checkpoint; refusing to unpickle it")
        if start not in _ZIP_MAGIC:
            raise fail(f"not a ZIP archive (starts with {start!r}); not a saml_ros checkpoint")
        f.seek(0)
        try:
            zf = stack.enter_context(zipfile.ZipFile(f))
        except Exception as e:  # noqa: BLE001 - zipfile raises many types on hostile input
            raise fail(f"truncated or damaged ZIP archive ({type(e).__name__}: {e})") from None
        names = zf.namelist()
        if META_MEMBER not in names:
            shown = ", ".join(names[:5]) + (", ..." if len(names) > 5 else "")
            hint = " (looks like a torch.save file)" if any(n.endswith("data.pkl") for n in names) else ""
            raise fail(f"no {META_MEMBER} member{hint}; not a saml_ros checkpoint (members: {shown})")
        raw_meta = _read_member(zf, META_MEMBER, fail)
        try:
            doc = json.loads(raw_meta.decode("utf-8"))
        except (UnicodeDecodeError, ValueError, RecursionError) as e:
            raise fail(f"{META_MEMBER} is not valid UTF-8 JSON ({e})") from None
        if not isinstance(doc, dict):
            raise fail(f"{META_MEMBER} is not a JSON object")
        if doc.get("format") != FORMAT_NAME:
            raise fail(f"wrong format name {doc.get('format')!r} (expected {FORMAT_NAME!r})")
        version = doc.get("format_version")
        if type(version) is not int or version not in SUPPORTED_FORMAT_VERSIONS:
            raise fail(
                f"unsupported format version {version!r} (this reader supports {list(SUPPORTED_FORMAT_VERSIONS)});"
                " it was written by a newer saml_ros or is damaged"
            )
        spec = doc.get("arrays")
        meta = doc.get("meta")
        if not isinstance(spec, dict) or not isinstance(meta, dict):
            raise fail(f"{META_MEMBER} lacks the 'arrays' or 'meta' object")
        expected = {ARRAY_DIR + str(k) + ".npy" for k in spec}
        present = set(names) - {META_MEMBER}
        if present != expected:
            extra = sorted(present - expected)[:3]
            missing = sorted(expected - present)[:3]
            raise fail(f"members do not match {META_MEMBER}: unexpected {extra}, missing {missing}")
        arrays: dict[str, np.ndarray] = {}
        for name, info in spec.items():
            if not _NAME_RE.fullmatch(name):
                raise fail(f"{META_MEMBER} lists an invalid array name {name[:80]!r}")
            member = ARRAY_DIR + name + ".npy"
            data = _read_member(zf, member, fail)
            try:
                a = np.load(io.BytesIO(data), allow_pickle=False)
            except ValueError as e:
                if "pickle" in str(e).lower():
                    raise fail(f"array {name!r} is an object (pickled) array; refusing to unpickle it") from None
                raise fail(f"array {name!r} cannot be parsed ({e})") from None
            except Exception as e:  # noqa: BLE001 - numpy's header parser on hostile input
                raise fail(f"array {name!r} cannot be parsed ({type(e).__name__}: {e})") from None
            if not isinstance(a, np.ndarray):
                raise fail(f"array member {member!r} is not a single .npy array")
            if a.dtype.kind not in _NUMERIC_KINDS:
                raise fail(f"array {name!r} has non-numeric dtype {a.dtype}")
            if not isinstance(info, dict) or info.get("dtype") != a.dtype.str or info.get("shape") != list(a.shape):
                raise fail(f"array {name!r} is {a.dtype.str}{list(a.shape)}, {META_MEMBER} says {info}")
            arrays[name] = a
        if _payload_sha256(arrays) != doc.get("payload_sha256"):
            raise fail("array payload checksum mismatch (the file is corrupt)")
        if _meta_sha256(meta) != doc.get("meta_sha256"):
            raise fail("metadata checksum mismatch (the file is corrupt)")
    return arrays, meta


def atomic_write(path: Path, write: Callable[[IO[bytes]], object]) -> None:
    """Write ``path`` atomically: ``write(f)`` fills a temp file in the same directory, which is flushed,
    fsynced and renamed over ``path``; then the directory is fsynced so the rename itself is durable.

    The temp file is named ``.<name>.<random>.tmp`` (ignored by :class:`CheckpointStore`, which deletes
    leftovers of killed writers on its next save) and removed if ``write`` raises.
    """
    path = Path(path)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise
    _fsync_dir(path.parent)


# --------------------------------------------------------------------------------------------------
# run directory


@dataclass
class LoadedCheckpoint:
    """Result of :meth:`CheckpointStore.load_latest_valid`.

    Attributes:
        arrays, meta: as returned by :func:`read_checkpoint`.
        path, version: the file that was loaded.
        skipped: ``(path, reason)`` of every newer checkpoint that could not be read, newest first.
    """

    arrays: dict[str, np.ndarray]
    meta: dict[str, Any]
    path: Path
    version: int
    skipped: list[tuple[Path, str]] = field(default_factory=list)


class CheckpointStore:
    """Versioned checkpoints in one run directory with an atomic ``latest`` pointer.

    Several threads or processes may save into the same directory (an ``fcntl`` lock on
    ``<run_dir>/.lock`` serialises writers); any number may read concurrently without locking.

    Args:
        run_dir: directory (created if missing).
        keep: if set (>= 1), after each save delete all but the newest ``keep`` checkpoint files; the
            file ``latest`` names is never deleted. Readers racing a prune retry (see
            :meth:`load_latest`); ``keep >= 2`` leaves a slow reader a whole save period.
    """

    def __init__(self, run_dir: Path | str, keep: int | None = None) -> None:
        if keep is not None and keep < 1:
            raise ValueError(f"keep must be >= 1 or None, got {keep}")
        self.run_dir = Path(run_dir)
        self.keep = keep
        self.run_dir.mkdir(parents=True, exist_ok=True)
        self._lock = threading.Lock()

    @property
    def latest_path(self) -> Path:
        return self.run_dir / LATEST_NAME

    def path_for(self, version: int) -> Path:
        """File name of ``version``: ``ckpt-000042.saml``."""
        return self.run_dir / f"ckpt-{version:06d}{CHECKPOINT_SUFFIX}"

    def versions(self) -> list[int]:
        """Versions of the checkpoint files present, ascending (temp files are ignored)."""
        with os.scandir(self.run_dir) as it:
            return sorted(int(m.group(1)) for e in it if (m := _CKPT_RE.fullmatch(e.name)))

    def save(self, arrays: Mapping[str, np.ndarray], meta: Mapping[str, Any]) -> tuple[Path, int]:
        """Write the next version, then atomically point ``latest`` at it, then prune.

        ``meta`` is copied and gets ``"version"`` (int) and ``"time"`` (unix seconds, float); the
        version is 1 + the highest version on disk or in the pointer. Temp files left by killed
        writers are deleted first.

        Returns:
            ``(path, version)`` of the new checkpoint.
        """
        with self._lock, self._dir_lock():
            self._remove_temp_files()
            pointed = self._read_pointer_quiet()
            version = max([0, *self.versions(), pointed[1] if pointed else 0]) + 1
            full = dict(meta)
            full["version"] = version
            full["time"] = time.time()
            path = self.path_for(version)
            write_checkpoint(path, arrays, full)
            name = path.name
            atomic_write(self.latest_path, lambda f: f.write(f"{name} {version}\n".encode()))
            if self.keep is not None:
                self._prune(self.keep, version)
            return path, version

    def latest(self) -> tuple[Path, int] | None:
        """``(path, version)`` the ``latest`` pointer names, or None if there is no pointer yet.

        Raises:
            CheckpointError: the pointer file is malformed.
        """
        try:
            text = self.latest_path.read_bytes()
        except FileNotFoundError:
            return None
        return self._parse_pointer(text)

    def load_latest(self, retries: int = 3) -> tuple[dict[str, np.ndarray], dict[str, Any]] | None:
        """Read the checkpoint ``latest`` names; None if there is no pointer yet.

        If the named file vanished (pruned between reading the pointer and opening the file), the
        pointer is re-read up to ``retries`` times.

        Raises:
            CheckpointError: the pointer or the named file is bad (no fallback; see
                :meth:`load_latest_valid`).
        """
        for attempt in range(retries + 1):
            cur = self.latest()
            if cur is None:
                return None
            try:
                return read_checkpoint(cur[0])
            except CheckpointError:
                if attempt == retries or cur[0].exists():
                    raise
                again = self.latest()
                if again is None or again[1] == cur[1]:
                    raise
        raise AssertionError("unreachable")

    def load_latest_valid(self) -> LoadedCheckpoint | None:
        """Load the newest readable checkpoint, skipping corrupt newer ones.

        Candidates are all checkpoint files on disk, newest version first (a file newer than the
        pointer exists only if a writer died between its two renames; it is complete and is used).

        Returns:
            the loaded checkpoint with the list of skipped files and reasons, or None if the
            directory holds no checkpoint file.

        Raises:
            CheckpointError: checkpoint files exist but none is readable (the message lists each file
                and why).
        """
        skipped: list[tuple[Path, str]] = []
        for v in reversed(self.versions()):
            path = self.path_for(v)
            try:
                arrays, meta = read_checkpoint(path)
            except CheckpointError as e:
                skipped.append((path, str(e)))
                continue
            return LoadedCheckpoint(arrays, meta, path, v, skipped)
        if not skipped:
            return None
        why = "; ".join(reason for _, reason in skipped)
        raise CheckpointError(f"{self.run_dir}: no readable checkpoint ({why})")

    # -- internals ---------------------------------------------------------------------------------

    @contextlib.contextmanager
    def _dir_lock(self) -> Iterator[None]:
        fd = os.open(self.run_dir / ".lock", os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX)
            yield
        finally:
            os.close(fd)  # closing releases the flock

    def _parse_pointer(self, text: bytes) -> tuple[Path, int]:
        parts = text.decode("utf-8", "replace").split()
        m = _CKPT_RE.fullmatch(parts[0]) if len(parts) == 2 else None
        if m is None or not parts[1].isdigit() or int(parts[1]) != int(m.group(1)):
            raise CheckpointError(f"{self.latest_path}: malformed pointer {text[:80]!r}")
        return self.run_dir / parts[0], int(parts[1])

    def _read_pointer_quiet(self) -> tuple[Path, int] | None:
        try:
            return self.latest()
        except CheckpointError:
            return None

    def _remove_temp_files(self) -> None:
        with os.scandir(self.run_dir) as it:
            stale = [e.path for e in it if _TMP_RE.fullmatch(e.name)]
        for p in stale:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(p)

    def _prune(self, keep: int, current: int) -> None:
        have = self.versions()
        older = [v for v in have if v != current]  # ascending: oldest first
        for v in older[: max(0, len(have) - keep)]:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(self.path_for(v))


# --------------------------------------------------------------------------------------------------
# torch state dicts


def torch_state_to_arrays(prefix: str, state: Mapping[Any, Any]) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """Flatten a (nested) torch state dict into arrays plus a JSON skeleton, losslessly.

    Works for ``module.state_dict()`` and ``optimizer.state_dict()`` (int keys, tuples such as Adam's
    ``betas``, ``None``, 0-d ``step`` tensors). Every tensor becomes one array named
    ``<prefix>/<key path>``; everything else goes into the skeleton, which references the arrays by name.
    Tensors of dtypes numpy lacks (bfloat16, float8) are stored bit-for-bit as unsigned integers.

    Args:
        prefix: array name prefix, e.g. ``"model"`` or ``"optim"`` (one checkpoint can hold several).
        state: the state dict.

    Returns:
        ``(arrays, skeleton)``: put ``arrays`` into the checkpoint's arrays and ``skeleton`` anywhere
        into its meta; :func:`arrays_to_torch_state` inverts this.

    Raises:
        TypeError: a value is neither a tensor, a container nor a JSON scalar (names the key path).
    """
    import torch

    if not _NAME_RE.fullmatch(prefix):
        raise ValueError(f"prefix {prefix!r} is not a valid array name")
    arrays: dict[str, np.ndarray] = {}

    def name_for(path: list[str]) -> str:
        joined = ".".join(re.sub(r"[^A-Za-z0-9_.:\-]", "_", seg) for seg in path)
        base = prefix + "/" + ("_" + joined if set(joined) <= {"."} else joined)
        name, i = base, 1
        while name in arrays:  # two keys that sanitise to the same name
            name, i = f"{base}-{i}", i + 1
        return name

    def enc(obj: Any, path: list[str]) -> Any:
        if isinstance(obj, torch.Tensor):
            t = obj.detach().cpu().contiguous()
            name = name_for(path)
            try:
                arr = t.numpy()
            except TypeError:  # no numpy dtype (bfloat16, float8, ...): keep the bits
                arr = t.view(_uint_dtype(t.element_size())).numpy()
            arrays[name] = arr.copy()
            return {"__tensor__": name, "dtype": str(t.dtype).removeprefix("torch.")}
        if isinstance(obj, Mapping):
            for k in obj:
                if not isinstance(k, (str, int)) or isinstance(k, bool):
                    raise TypeError(f"{prefix}/{'.'.join(path)}: key {k!r} is not str or int")
            out: dict[str, Any] = {"__dict__": [[k, enc(v, [*path, str(k)])] for k, v in obj.items()]}
            md = getattr(obj, "_metadata", None)  # module state dicts carry per-module versions
            if md is not None:
                out["_metadata"] = enc(md, [*path, "_metadata"])
            return out
        if isinstance(obj, tuple):
            return {"__tuple__": [enc(v, [*path, str(i)]) for i, v in enumerate(obj)]}
        if isinstance(obj, list):
            return {"__list__": [enc(v, [*path, str(i)]) for i, v in enumerate(obj)]}
        if obj is None or isinstance(obj, (bool, int, float, str)):
            return obj
        raise TypeError(f"{prefix}/{'.'.join(path)}: cannot store a {type(obj).__name__} in a checkpoint")

    skeleton = enc(state, [])
    return arrays, {"prefix": prefix, "tree": skeleton}


def arrays_to_torch_state(arrays: Mapping[str, np.ndarray], skeleton: Mapping[str, Any]) -> dict[Any, Any]:
    """Rebuild the state dict :func:`torch_state_to_arrays` flattened (CPU tensors, bit-exact).

    Args:
        arrays: the checkpoint's arrays (may hold other prefixes too).
        skeleton: the skeleton :func:`torch_state_to_arrays` returned (as read back from meta).

    Raises:
        CheckpointError: the skeleton is malformed or names an array that is missing.
    """
    import torch

    def dec(obj: Any) -> Any:
        if isinstance(obj, dict):
            if "__tensor__" in obj:
                name = obj["__tensor__"]
                if name not in arrays:
                    raise CheckpointError(f"torch state: array {name!r} is missing")
                dtype = getattr(torch, str(obj.get("dtype")), None)
                if not isinstance(dtype, torch.dtype):
                    raise CheckpointError(f"torch state: unknown dtype {obj.get('dtype')!r} for {name!r}")
                t = torch.from_numpy(np.array(arrays[name], copy=True))
                return t if t.dtype == dtype else t.view(dtype)
            if "__dict__" in obj:
                out: dict[Any, Any] = OrderedDict((k, dec(v)) for k, v in obj["__dict__"])
                if "_metadata" in obj:
                    out._metadata = dec(obj["_metadata"])  # type: ignore[attr-defined]
                return out
            if "__tuple__" in obj:
                return tuple(dec(v) for v in obj["__tuple__"])
            if "__list__" in obj:
                return [dec(v) for v in obj["__list__"]]
            raise CheckpointError(f"torch state: malformed skeleton node {str(obj)[:80]}")
        return obj

    tree = skeleton.get("tree") if isinstance(skeleton, Mapping) else None
    result = dec(tree)
    if not isinstance(result, dict):
        raise CheckpointError("torch state: skeleton does not describe a dict")
    return result


# --------------------------------------------------------------------------------------------------
# helpers


def _uint_dtype(size: int) -> torch.dtype:
    import torch

    return {1: torch.uint8, 2: torch.uint16, 4: torch.uint32, 8: torch.uint64}[size]


def _validate_arrays(arrays: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    clean: dict[str, np.ndarray] = {}
    for name, value in arrays.items():
        if not isinstance(name, str) or not _NAME_RE.fullmatch(name) or ".." in name.split("/"):
            raise ValueError(f"array name {name!r} is not allowed (use '/'-separated [A-Za-z0-9_.:-] segments)")
        a = np.asarray(value)
        if a.dtype.kind not in _NUMERIC_KINDS:
            raise ValueError(f"array {name!r} has dtype {a.dtype}; only numeric arrays can be stored")
        clean[name] = a
    return clean


def _payload_sha256(arrays: Mapping[str, np.ndarray]) -> str:
    h = hashlib.sha256()
    for name in sorted(arrays):
        a = arrays[name]
        h.update(f"{name}\0{a.dtype.str}\0{list(a.shape)}\0".encode())
        h.update(np.ascontiguousarray(a).data)
    return h.hexdigest()


def _plain_meta(meta: Mapping[str, Any]) -> dict[str, Any]:
    """Copy of ``meta`` as plain JSON types; raises TypeError naming the first bad key path."""

    def conv(obj: Any, where: str) -> Any:
        if isinstance(obj, Mapping):
            out = {}
            for k, v in obj.items():
                if not isinstance(k, str):
                    raise TypeError(f"meta{where}: key {k!r} is not a str (JSON would change it)")
                out[k] = conv(v, f"{where}[{k!r}]")
            return out
        if isinstance(obj, (list, tuple)):
            return [conv(v, f"{where}[{i}]") for i, v in enumerate(obj)]
        if isinstance(obj, np.generic) and obj.dtype.kind in "biuf":
            return obj.item()
        if obj is None or isinstance(obj, (bool, int, float, str)):
            return obj
        raise TypeError(f"meta{where}: {type(obj).__name__} is not JSON-serialisable")

    if not isinstance(meta, Mapping):
        raise TypeError(f"meta must be a mapping, got {type(meta).__name__}")
    plain: dict[str, Any] = conv(meta, "")
    return plain


def _meta_sha256(meta: Mapping[str, Any]) -> str:
    # Canonical text: parsing and re-serialising gives the same bytes (floats round-trip via repr).
    text = json.dumps(meta, sort_keys=True, separators=(",", ":"), ensure_ascii=False)
    return hashlib.sha256(text.encode()).hexdigest()


def _read_member(zf: zipfile.ZipFile, member: str, fail: Callable[[str], CheckpointError]) -> bytes:
    try:
        return zf.read(member)  # checks the member's CRC-32
    except Exception as e:  # noqa: BLE001 - zipfile raises many types on hostile input
        raise fail(f"member {member!r} is truncated or damaged ({type(e).__name__}: {e})") from None


def _fsync_dir(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY | os.O_DIRECTORY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)
