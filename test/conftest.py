"""Shared pytest fixtures."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from saml_ros.core.layout import make_layout
from saml_ros.core.systems.base import System

# One intra-op thread, as the nodes and scripts use: on this shared 2-core machine torch's default of one thread
# per core made a small network's training step 25x slower under load (150 ms instead of 6 ms, measured).
torch.set_num_threads(1)


def pytest_sessionstart(session: pytest.Session) -> None:
    """Before any test (in the controller, not in each xdist worker): remove the Fast DDS shared-memory files no
    live process uses, left by processes killed earlier (benchmarks cut short, crashes; 1,174 of them here once).
    Two suite runs made beside such leftovers (3 December) had 2 failures each, processes that heard nothing from
    another for 60-90 s; the next run after removing them passed 930 of 930 (one run: a correlation, not a proof).
    Each test also removes what its own processes leave (ros_helpers.clean_shm)."""
    if hasattr(session.config, "workerinput"):
        return
    from ros_helpers import clean_shm

    removed = clean_shm(set(), min_age=5.0)
    if removed:
        print(f"\nremoved {len(removed)} unused Fast DDS shared-memory files from /dev/shm", flush=True)


class ToySystem(System):
    """A 1-d toy system used by trainer tests: a full model sees a constant input, so it can only
    predict one constant c for every sample — the learning problem is convex in c."""

    name = "toy"
    state = make_layout("state", [("s", "1")])
    control = make_layout("control", [("a", "1")])
    target = make_layout("target", [("y", "1")])
    dt = 0.1
    paper_hidden = ()

    @property
    def control_low(self) -> np.ndarray:
        return np.array([-1.0])

    @property
    def control_high(self) -> np.ndarray:
        return np.array([1.0])

    def true_step(self, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        return x

    def base_step(self, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        return torch.zeros_like(x)

    def sample_inputs(self, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        return np.ones((n, 1)), np.zeros((n, 1))

    def paper_spec(self) -> dict:
        return {"objective": {"loss": "squared_l2"}}


@pytest.fixture
def toy_system() -> ToySystem:
    return ToySystem()
