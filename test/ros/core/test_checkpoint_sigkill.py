"""Checkpoint files, the run-directory store and torch state flattening (saml_ros.core.model.checkpoint)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from helpers import REPO

from saml_ros.core.model.checkpoint import (
    CheckpointStore,
)

CHILD = r"""
import sys
import numpy as np
from saml_ros.core.model.checkpoint import CheckpointStore

store = CheckpointStore(sys.argv[1], keep=4)
res = store.load_latest_valid()          # resume like a restarted learner
k = 0 if res is None else res.meta["k"] + 1
print("start", k, flush=True)
while True:
    store.save({"w": np.full(2_000_000, float(k)), "k": np.array(k)}, {"k": k})
    k += 1
"""


def test_sigkill_mid_write_leaves_a_loadable_store(tmp_path: Path) -> None:
    """A writer SIGKILLed while saving 16 MB checkpoints; each restart resumes from the last good one."""
    run = tmp_path / "run"
    run.mkdir()
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    killed_mid_write = 0
    resumed_from: list[int] = []
    for round_ in range(3):
        child = subprocess.Popen([sys.executable, "-c", CHILD, str(run)], stdout=subprocess.PIPE, env=env, text=True)
        try:
            assert child.stdout is not None
            resumed_from.append(int(child.stdout.readline().split()[1]))
            before = len(CheckpointStore(run).versions())
            deadline = time.monotonic() + 20
            # Wait for two new saves, then until a checkpoint temp file exists (a write in progress).
            while time.monotonic() < deadline:
                names = os.listdir(run)
                done = sum(n.startswith("ckpt-") for n in names)
                if (done >= min(before + 2, 4)) and any(n.startswith(".ckpt-") for n in names):
                    break
                time.sleep(0.001)
            time.sleep(0.005 * round_)  # vary the phase of the kill
            child.send_signal(signal.SIGKILL)
            child.wait(timeout=10)
        finally:
            if child.poll() is None:
                child.kill()
            if child.stdout is not None:
                child.stdout.close()
        killed_mid_write += any(n.startswith(".ckpt-") for n in os.listdir(run))
        res = CheckpointStore(run).load_latest_valid()
        assert res is not None and res.skipped == []
        assert int(res.arrays["k"]) == res.meta["k"] and np.all(res.arrays["w"] == res.meta["k"])
        latest = CheckpointStore(run).load_latest()
        assert latest is not None and latest[1]["k"] <= res.meta["k"]
    assert killed_mid_write >= 1
    assert resumed_from[0] == 0 and resumed_from[1] > 0 and resumed_from[2] > resumed_from[1]
    CheckpointStore(run).save({}, {})
    assert not any(n.endswith(".tmp") for n in os.listdir(run))
