"""Starting the learner's training interpreter, standard library only (no torch), so that the learner node can
start it first thing and let it import torch while the node itself starts (see ``saml_ros.nodes.learner``).

The child runs :func:`saml_ros.core.online.child.child_entry` on its end of a socket pair;
:class:`~saml_ros.core.online.process.TrainingProcess` then sends it its setup.
"""

from __future__ import annotations

import os
import socket
import subprocess
import sys
from pathlib import Path
from typing import Any

#: a started training interpreter waiting for its :class:`~saml_ros.core.online.process.LearnerSetup`:
#: ``(process, connection)``
LaunchedChild = tuple["subprocess.Popen[bytes]", Any]
#: what the training interpreter runs (``argv[1]`` = its socket's file descriptor); it ignores SIGINT and SIGTERM
#: from its first line: a Ctrl-C reaches the whole process group, also while it still imports torch, and the parent
#: decides when training stops
CHILD_CODE = ("import signal, sys; signal.signal(signal.SIGINT, signal.SIG_IGN); "
              "signal.signal(signal.SIGTERM, signal.SIG_IGN); "
              "from saml_ros.core.online.child import child_entry; child_entry(int(sys.argv[1]))")


def launch_child() -> LaunchedChild:
    """Start a training interpreter now; it imports torch and saml_ros, then waits for its setup.

    A fresh interpreter through ``subprocess``, not ``multiprocessing``: multiprocessing's "spawn" re-imports the
    parent's ``__main__`` (slow, and fatal for scripts without a main guard) and "fork" is unsafe once rclpy's
    DDS threads run.
    """
    return launch_child_process(CHILD_CODE, Path(__file__).resolve().parents[2])


def launch_child_process(code: str, package_root: Path) -> LaunchedChild:
    """``python -c code FD`` with ``package_root`` on its path and a socket pair between us."""
    from multiprocessing.connection import Connection

    ours, theirs = socket.socketpair()
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(x for x in (str(package_root), env.get("PYTHONPATH", "")) if x)
    proc = subprocess.Popen([sys.executable, "-c", code, str(theirs.fileno())], pass_fds=[theirs.fileno()], env=env)
    theirs.close()
    return proc, Connection(ours.detach())


def discard_child(launched: LaunchedChild) -> None:
    """Let an unused training interpreter exit (it sees the connection close); kill it after 10 s."""
    proc, conn = launched
    conn.close()
    try:
        proc.wait(10)
    except Exception:  # noqa: BLE001
        proc.kill()
