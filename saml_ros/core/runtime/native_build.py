"""Where saml_ros keeps the native code it compiles on first use, and what identifies a build.

Two kernels are compiled on the user's machine rather than shipped: the fused training kernel
(:mod:`saml_ros.core.training.engines.fused`, through torch's extension builder) and the shooting SQP's numerics
(:mod:`saml_ros.core.mpc.shooting.native`, a plain C library loaded with ctypes). Both are built with
``-march=native``, so a build is named after a hash that includes this CPU (:func:`cpu_id`): a cache shared
between machines never loads a build made for another CPU.
"""

from __future__ import annotations

import fcntl
import os
import platform
import shutil
import subprocess
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path


def cpu_id() -> str:
    """This CPU's model name and feature flags (what ``-march=native`` compiles for)."""
    try:
        text = Path("/proc/cpuinfo").read_text()
    except OSError:
        return f"{platform.machine()} {platform.processor()}"
    keep = [ln for ln in text.splitlines() if ln.split(":")[0].strip() in ("model name", "flags", "Features")]
    return "\n".join(sorted(set(keep)))


def cache_root() -> Path:
    """Where builds go: ``$SAML_KERNEL_CACHE``, else ``$XDG_CACHE_HOME/saml_ros/fused_kernel`` or
    ``~/.cache/saml_ros/fused_kernel`` (the name is historical: the MPC's kernel lives there too)."""
    env = os.environ.get("SAML_KERNEL_CACHE")
    if env:
        return Path(env)
    xdg = os.environ.get("XDG_CACHE_HOME")
    return (Path(xdg) if xdg else Path.home() / ".cache") / "saml_ros" / "fused_kernel"


def build_locked(cc: str, source: Path, so: Path, lock_name: str, cflags: Sequence[str],
                 timeout: float) -> float | None:
    """Compile the C file ``source`` with ``cc`` into the shared library ``so`` unless it exists, under an exclusive
    lock ``so.parent / lock_name`` (several processes may start at once; the lock file is writable by every user of
    a shared cache), written to a temporary file and moved into place (a reader never loads half a library).
    Returns the build's seconds, None when ``so`` already existed. Raises RuntimeError when the compiler fails."""
    with open(so.parent / lock_name, "a") as lock:
        try:
            os.fchmod(lock.fileno(), 0o666)  # a cache shared between users: all of them may build
        except OSError:
            pass
        fcntl.flock(lock, fcntl.LOCK_EX)
        if so.is_file():
            return None
        t0 = time.perf_counter()
        fd, tmp = tempfile.mkstemp(suffix=".so", dir=so.parent)
        os.close(fd)
        try:
            run = subprocess.run([cc, *cflags, "-o", tmp, str(source), "-lm"], capture_output=True, text=True,
                                 timeout=timeout)
            if run.returncode != 0:
                raise RuntimeError(f"{cc} failed: {run.stderr.strip()[:500]}")
            os.chmod(tmp, 0o755)  # mkstemp's 0600 would keep other users of a shared cache out
            os.replace(tmp, so)
        finally:
            Path(tmp).unlink(missing_ok=True)
        return time.perf_counter() - t0


def compiler() -> str | None:
    """The C compiler to build with: ``$CC``, else ``cc``, as found on PATH (None: none)."""
    return shutil.which(os.environ.get("CC") or "cc")


def build_cached(source: Path, so: Path, lock_name: str, cflags: Sequence[str], timeout: float) -> float | None:
    """:func:`build_locked` for a library ``so`` in the cache (its folder created): None when ``so`` is built
    already (no compiler needed then), else the build's seconds. Raises RuntimeError without a C compiler."""
    so.parent.mkdir(parents=True, exist_ok=True)
    if so.is_file():
        return None
    cc = compiler()
    if cc is None:
        raise RuntimeError("no C compiler (cc, or $CC) on PATH")
    return build_locked(cc, source, so, lock_name, cflags, timeout)
