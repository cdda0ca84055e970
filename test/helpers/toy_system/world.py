"""The drag cart's simulator world: starts at rest anywhere in [-2, 2] m, the safe command 0."""

from __future__ import annotations

import numpy as np

from helpers.toy_system.model import DragCart
from saml_ros.core.worlds.sim_core import SteppedModel


def drag_cart_model(system: DragCart) -> SteppedModel:
    return SteppedModel(system, system.safe_control(), lambda rng: np.array([rng.uniform(-2.0, 2.0), 0.0]))
