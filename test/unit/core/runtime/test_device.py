"""The training ``device`` option: checked when a configuration is made, a clear error where it cannot be used."""

from __future__ import annotations

import pytest
import torch

from saml_ros.core.runtime.device import DeviceError, resolve_device
from saml_ros.core.training import TrainConfig


def test_cpu_is_the_default_and_bad_names_are_refused() -> None:
    assert TrainConfig().device == "cpu" and resolve_device("CPU") == torch.device("cpu")
    with pytest.raises(DeviceError, match="unknown; valid: cpu, cuda, cuda:<index>"):
        TrainConfig(device="gpu")
