"""What the ROS benchmarks share: a private ROS domain id, and stopping a node process they started."""

from __future__ import annotations

import contextlib
import fcntl
import os
import signal
import subprocess
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

#: the same claim files as test/ros_helpers.py, so a benchmark never shares a ROS domain with a test run
CLAIM_DIR = Path(tempfile.gettempdir()) / "saml_ros_ros_domains"


@contextlib.contextmanager
def claimed_domain() -> Iterator[int]:
    """A ROS_DOMAIN_ID in 1..100 that no other claiming process uses (an flock per id, held while inside)."""
    CLAIM_DIR.mkdir(parents=True, exist_ok=True)
    start = os.getpid() % 100
    for i in range(100):
        domain = 1 + (start + i) % 100
        fd = os.open(CLAIM_DIR / f"{domain}.lock", os.O_CREAT | os.O_RDWR, 0o666)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            os.close(fd)
            continue
        try:
            yield domain
        finally:
            os.close(fd)
        return
    raise RuntimeError("every ROS domain id 1..100 is claimed")


def interrupt(proc: subprocess.Popen[Any], timeout: float = 10.0) -> None:
    """SIGINT ``proc`` (a node's clean shutdown) and wait up to ``timeout`` s for it; then SIGKILL its process
    group (``proc`` must have been started with ``start_new_session=True``)."""
    proc.send_signal(signal.SIGINT)
    try:
        proc.wait(timeout)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(10)
