"""The training ``device`` option: checked when a configuration is made, a clear error where it cannot be used."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
import torch
from helpers import REPO
from helpers.ros_helpers import RosDomain

from saml_ros.core.runtime.device import DeviceError
from saml_ros.core.training import TrainConfig

NO_CUDA = not torch.cuda.is_available()


@pytest.mark.skipif(not NO_CUDA, reason="this machine has CUDA")
def test_cuda_without_cuda_is_a_clear_configuration_error(tmp_path: Path) -> None:
    for name in ("cuda", "cuda:1"):
        with pytest.raises(DeviceError, match="CUDA is not available"):
            TrainConfig(device=name)
    proc = subprocess.run([sys.executable, "-m", "saml_ros.executables", "train", "--system", "friction",
                           "--device", "cuda", "--out", str(tmp_path / "run")], capture_output=True, text=True,
                          timeout=120, cwd=REPO)
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.startswith("train: device 'cuda' asked for, but CUDA is not available")
    assert not (tmp_path / "run").exists()


@pytest.mark.skipif(not NO_CUDA, reason="this machine has CUDA")
def test_learner_with_train_device_cuda_exits_2_at_start_up(ros_env: RosDomain, tmp_path: Path) -> None:
    learner = ros_env.launch("learner", "-p", "system:=friction", "-p", "train.device:=cuda",
                             "-p", f"run_dir:={tmp_path / 'run'}", namespace="/friction")
    assert learner.wait(90) == 2, learner.output()
    out = learner.output()
    assert "configuration error" in out and "CUDA is not available" in out and "Traceback" not in out
