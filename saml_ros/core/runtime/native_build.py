"""Where saml_ros keeps the native code it compiles on first use, and what identifies a build.

Two kernels are compiled on the user's machine rather than shipped: the fused training kernel
(:mod:`saml_ros.core.training.engines.fused`, through torch's extension builder) and the shooting SQP's numerics
(:mod:`saml_ros.core.mpc.shooting.native`, a plain C library loaded with ctypes). Both are built with
``-march=native``, so a build is named after a hash that includes this CPU (:func:`cpu_id`): a cache shared
between machines never loads a build made for another CPU.
"""

from __future__ import annotations

import os
import platform
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
