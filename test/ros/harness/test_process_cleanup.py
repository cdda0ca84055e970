"""The test helpers' own promise about the processes they start: none outlives the test process that started it."""

from __future__ import annotations

import os
import signal
import subprocess
import sys

import pytest
from helpers.ros_helpers import SETPRIV, process_alive, wait_for

#: a stand-in test process: starts a long sleeper the way the helpers start nodes (own session), prints its pid
PARENT = r"""
import subprocess, sys, time
from helpers.ros_helpers import dying_with_test
child = subprocess.Popen(dying_with_test([sys.executable, "-c", "import time; time.sleep(120)"]),
                         start_new_session=True)
print(child.pid, flush=True)
time.sleep(120)
"""


@pytest.mark.skipif(SETPRIV is None, reason="util-linux setpriv is not installed")
def test_a_started_process_dies_with_a_killed_test_process() -> None:
    """A pytest worker SIGKILLed mid-test (a run cut short) must not leave its nodes running in their own sessions
    (they did, for hours, with PPID 1)."""
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(sys.path))
    parent = subprocess.Popen([sys.executable, "-c", PARENT], stdout=subprocess.PIPE, text=True, env=env)
    assert parent.stdout is not None
    child = int(parent.stdout.readline())
    try:
        assert process_alive(child)
        parent.send_signal(signal.SIGKILL)
        parent.wait(timeout=30)
        wait_for(lambda: not process_alive(child), timeout=30, what=f"process {child} gone after its parent's SIGKILL")
    finally:
        if process_alive(child):
            os.kill(child, signal.SIGKILL)
