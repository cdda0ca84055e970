"""Bag I/O, offline pairing and bag errors (saml_ros.bags.io, saml_ros.bags.transitions, bag_info, train --bag); no ROS graph.

Bags are written with :class:`saml_ros.bags.io.BagWriter` from roll-outs of the systems' true dynamics
(``bag_publisher.rollout``, the same events the publisher process sends), and checked with the independent
``mcap`` + ``mcap-ros2-support`` readers as well as with our reader.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from helpers import REPO
from helpers.bag_test_helpers import expected


# ------------------------------------------------------------------------------------------ train --bag
def test_train_from_bags_fails_cleanly_on_bad_bags_and_trains_on_a_good_one(
    bad_bags: dict, friction_bag: tuple[Path, list[dict]], tmp_path: Path
) -> None:
    """``train --bag`` as a process: bad bag -> non-zero exit, the message, no checkpoint; good bag -> checkpoint.
    (Eight processes, seven bad bags and the good one, start at once: 120 s ran out once at load ~19.)"""
    runs = {}
    for kind, (path, _) in bad_bags.items():
        out = tmp_path / kind
        runs[kind] = subprocess.Popen(
            [sys.executable, "-m", "saml_ros.executables", "train", "--system", "friction", "--bag", str(path),
             "--out", str(out)], cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    good = subprocess.run(
        [sys.executable, "-m", "saml_ros.executables", "train", "--system", "friction", "--bag", str(friction_bag[0]),
         "--out", str(tmp_path / "good"), "--epochs", "2", "--no-progress"],
        cwd=REPO, capture_output=True, text=True, timeout=300)
    for kind, proc in runs.items():
        _, err = proc.communicate(timeout=300)
        path, fragment = bad_bags[kind]
        assert proc.returncode != 0, kind
        assert fragment in err and str(path) in err, (kind, err)
        out = tmp_path / kind
        assert not out.exists() or not any(out.glob("ckpt-*")) and not (out / "latest").exists()
    assert good.returncode == 0, good.stderr
    assert (tmp_path / "good" / "latest").read_text().strip().startswith("ckpt-")
    metrics = json.loads((tmp_path / "good" / "metrics.json").read_text())
    n = len(expected(friction_bag[1])[0])
    assert metrics["source"] == f"{n} transitions from 1 bag(s)"
    # the verdicts are read on two whole stretches of the recording (a fifth), never a random split
    held = metrics["test"]["n"]
    assert held + metrics["n_train"] == n and abs(held - n / 5) <= 2
    assert metrics["verdict"]["heldout"].startswith(f"{held} transitions of the recordings never trained on (two "
                                                    "whole stretches of time")
