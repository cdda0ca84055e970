"""CasADi functions compiled to C for the generic planner (solver option ``compile``): :func:`compiled`.

CasADi writes C for a symbolic function (:class:`casadi.CodeGenerator`); this module compiles it with the system's
C compiler (``$CC``, else ``cc``) into :func:`~saml_ros.core.runtime.native_build.cache_root`, under a name hashing
the generated source, the flags and this CPU (built once per machine and problem shape, an atomic rename under a
file lock, as the hand-written SQP's kernel: :mod:`saml_ros.core.mpc.shooting.native`), and loads it with
:func:`casadi.external`. The compiled function has the same inputs and outputs as the symbolic one, so a caller
uses either the same way.

Without a compiler, when the build fails, or with ``SAML_MPC_NATIVE=0``, :func:`compiled` returns the symbolic
function (CasADi's virtual machine: the same numbers, slower) and the reason, which the planner reports on
``/diagnostics`` (:meth:`~saml_ros.core.mpc.generic.sqp.GenericSQP.describe`); one warning per process.
"""

from __future__ import annotations

import hashlib
import os
import tempfile
import warnings
from pathlib import Path
from typing import Any

from saml_ros.core.mpc.shooting.native import switched_off
from saml_ros.core.runtime.native_build import build_cached, cache_root, cpu_id

#: the flags of the generated code (no ``-march=native``: plain arithmetic, and a smaller hash surface)
CFLAGS = ("-O2", "-fPIC", "-shared")
_WARNED: set[str] = set()
#: seconds spent compiling in this process (for the bench and the log)
COMPILE_SECONDS: list[float] = []


def build_name(source: str, name: str) -> str:
    """``casadi_<name>_<hash>.so`` of the generated source, the flags and this CPU."""
    h = hashlib.sha256()
    for part in (source.encode(), " ".join(CFLAGS).encode(), cpu_id().encode()):
        h.update(part)
        h.update(b"\0")
    return f"casadi_{name}_{h.hexdigest()[:16]}.so"


def compiled(fns: list[Any], name: str) -> tuple[list[Any], str | None]:
    """``fns`` (CasADi Functions) compiled into one library, in order, and None; or ``fns`` themselves and why they
    are not compiled (no compiler, a failed build, switched off)."""
    if switched_off():
        return fns, "switched off (SAML_MPC_NATIVE=0)"
    import casadi as ca

    try:
        with tempfile.TemporaryDirectory() as tmp:
            gen = ca.CodeGenerator(f"{name}.c", {"with_header": False})
            for f in fns:
                gen.add(f)
            gen.generate(tmp + os.sep)
            src = Path(tmp, f"{name}.c")
            so = cache_root() / build_name(src.read_text(), name)
            seconds = build_cached(src, so, "casadi_codegen.lock", CFLAGS, timeout=600)
            if seconds is not None:
                COMPILE_SECONDS.append(seconds)
        return [ca.external(f.name(), str(so)) for f in fns], None
    except Exception as exc:  # noqa: BLE001 - any build or load problem: the symbolic functions
        why = f"{type(exc).__name__}: {exc}"[:400]
        if name not in _WARNED:
            _WARNED.add(name)
            warnings.warn(f"saml_ros: the generic planner's {name} functions are not compiled ({why}); CasADi's "
                          "virtual machine runs them (the same numbers, slower)", RuntimeWarning, stacklevel=3)
        return fns, why


