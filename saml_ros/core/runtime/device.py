"""The training device option (``device``: ``cpu`` | ``cuda`` | ``cuda:N``), checked when a run starts.

:func:`check_device` (or :func:`resolve_device`, which also returns the :class:`torch.device`) is called where a
configuration is read (``TrainConfig``, so the ``train`` and ``sweep`` command lines and the learner's
``train.device`` parameter; ``cpu`` is checked without importing torch): a device that cannot be used is a
:class:`DeviceError` naming the problem before any data is generated or any node starts, never a traceback in the
middle of training. The training engines (the fast engine, the plain loop and the online learner's buffer) keep
their tensors on the CPU, so ``cuda`` is refused even where torch sees a GPU, with a message saying so, rather
than accepted and then ignored.
"""

from __future__ import annotations

import re
from typing import TYPE_CHECKING

from saml_ros.core.errors import SamlError

if TYPE_CHECKING:
    import torch

DEVICES = ("cpu", "cuda", "cuda:<index>")
_CUDA = re.compile(r"^cuda(:(\d+))?$")


class DeviceError(SamlError, ValueError):
    """The requested training device cannot be used; the message says why and what is available."""


def cuda_summary() -> str:
    """What torch reports about CUDA here, for error messages."""
    import torch

    if not torch.backends.cuda.is_built():
        return f"this torch {torch.__version__} is built without CUDA"
    n = torch.cuda.device_count() if torch.cuda.is_available() else 0
    return f"torch {torch.__version__} (CUDA {torch.version.cuda}) sees {n} GPU(s)"


def resolve_device(name: str) -> torch.device:
    """The :class:`torch.device` for ``name``; :class:`DeviceError` when it cannot be trained on here."""
    check_device(name)
    import torch

    return torch.device("cpu")


def check_device(name: str) -> None:
    """:class:`DeviceError` when ``name`` cannot be trained on here (:func:`resolve_device` without its result);
    imports torch only to look for a GPU, so a configuration naming ``cpu`` is checked without it."""
    text = str(name).strip().lower()
    if text == "cpu":
        return
    match = _CUDA.match(text)
    if match is None:
        raise DeviceError(f"device {name!r}: unknown; valid: {', '.join(DEVICES)}")
    import torch

    if not torch.cuda.is_available():
        raise DeviceError(f"device {name!r} asked for, but CUDA is not available: {cuda_summary()}; use device cpu")
    index = int(match.group(2) or 0)
    if index >= torch.cuda.device_count():
        raise DeviceError(f"device {name!r}: no such GPU ({cuda_summary()})")
    raise DeviceError(f"device {name!r}: {cuda_summary()}, but saml_ros's training engines keep their tensors on "
                      "the CPU (fast engine, plain loop, online buffer); use device cpu")
