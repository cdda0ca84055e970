"""bringup's process supervisor (ROS-free): children in their own process groups, stopped by escalation.

:class:`ProcessGroup` starts each child in a new process group (``pgid == pid``) with its output in a log
file, and stops them all: SIGINT to every group, then SIGTERM, then SIGKILL for what is left. A child also gets
SIGTERM from the kernel when bringup itself dies (``PR_SET_PDEATHSIG``), so no child outlives it.
:func:`child_env` is the children's environment, :func:`node_argv` the command line of a saml_ros executable.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import IO

# Run in the child before the node: ask the kernel to SIGTERM it when bringup dies (even by SIGKILL), give up
# if bringup is already gone, then exec the node (same pid, so it stays the leader of its process group).
_PDEATHSIG_SHIM = (
    "import ctypes, os, signal, sys\n"
    "ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGTERM, 0, 0, 0)\n"
    "os.getppid() == int(sys.argv[1]) or os._exit(1)\n"
    "os.execv(sys.executable, [sys.executable, *sys.argv[2:]])\n"
)


@dataclass
class Child:
    """A child process in its own process group (``pgid == pid``)."""

    name: str
    proc: subprocess.Popen[bytes]
    log_path: Path
    log: IO[bytes]

    @property
    def pid(self) -> int:
        return self.proc.pid

    def tail(self, lines: int = 20) -> str:
        """The last ``lines`` lines of the child's log."""
        if not self.log.closed:
            self.log.flush()
        try:
            text = self.log_path.read_text(errors="replace")
        except OSError:
            return ""
        return "\n".join(text.splitlines()[-lines:])


class ProcessGroup:
    """Starts children, each in a new process group, and stops them all: SIGINT, SIGTERM, then SIGKILL."""

    def __init__(self) -> None:
        self.children: list[Child] = []

    def start(self, name: str, argv: Sequence[str], env: Mapping[str, str], log_path: Path) -> Child:
        """Start ``argv`` (a Python module invocation: ``[python, -m, ...]``) with output to ``log_path``."""
        log_path.parent.mkdir(parents=True, exist_ok=True)
        log = open(log_path, "ab")  # noqa: SIM115 - closed in stop()
        cmd = [argv[0], "-c", _PDEATHSIG_SHIM, str(os.getpid()), *argv[1:]]
        proc = subprocess.Popen(cmd, env=dict(env), stdin=subprocess.DEVNULL, stdout=log, stderr=subprocess.STDOUT,
                                process_group=0)
        child = Child(name, proc, log_path, log)
        self.children.append(child)
        return child

    def exited(self) -> list[Child]:
        """Children that have exited."""
        return [c for c in self.children if c.proc.poll() is not None]

    def stop(self, grace_int: float = 10.0, grace_term: float = 5.0) -> dict[str, int]:
        """Stop every child (newest first gets SIGINT first); returns ``{name: returncode}``.

        Each stage signals the whole process group of every child still running, then waits up to its grace
        period; a last ``SIGKILL`` to every group catches stragglers (e.g. a grandchild whose leader is gone).
        """
        for sig, grace in ((signal.SIGINT, grace_int), (signal.SIGTERM, grace_term), (signal.SIGKILL, 5.0)):
            running = [c for c in reversed(self.children) if c.proc.poll() is None]
            if not running:
                break
            for c in running:
                _killpg(c.pid, sig)
            deadline = time.monotonic() + grace
            for c in running:
                try:
                    c.proc.wait(max(0.0, deadline - time.monotonic()))
                except subprocess.TimeoutExpired:
                    pass
        for c in self.children:
            _killpg(c.pid, signal.SIGKILL)  # stragglers in the group; harmless when it is empty
            if not c.log.closed:
                c.log.close()
        return {c.name: c.proc.returncode for c in self.children}


def _killpg(pgid: int, sig: int) -> None:
    try:
        os.killpg(pgid, sig)
    except (ProcessLookupError, PermissionError):
        pass


def child_env(domain_id: int | None) -> dict[str, str]:
    """The environment of the children: ours, with ``ROS_DOMAIN_ID`` if given, discovery on this host unless the
    user chose otherwise, unbuffered output and this package on ``PYTHONPATH``."""
    env = dict(os.environ)
    if domain_id is not None:
        env["ROS_DOMAIN_ID"] = str(domain_id)
    env.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    env["PYTHONUNBUFFERED"] = "1"
    root = str(Path(__file__).resolve().parents[2])
    parts = [p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p]
    if root not in parts:
        env["PYTHONPATH"] = os.pathsep.join([root, *parts])
    return env


def node_argv(executable: str, namespace: str, params_file: Path | None, extra: Sequence[str] = ()) -> list[str]:
    """``python -m saml_ros.executables <executable> [extra] --ros-args -r __ns:=<ns> [--params-file F]``."""
    argv = [sys.executable, "-m", "saml_ros.executables", executable, *extra, "--ros-args", "-r", f"__ns:={namespace}"]
    if params_file is not None:
        argv += ["--params-file", str(params_file)]
    return argv
