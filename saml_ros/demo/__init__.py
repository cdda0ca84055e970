"""The main job, ``./dev demo``: online learning that measurably improves control (see :mod:`.cli`).

Modules: :mod:`.cli` (the executable: the closed loop over ROS 2, then the evaluation), :mod:`.landing` (the task,
start states, metrics), :mod:`.evaluation` (the paired evaluation of base, learned and oracle arms),
:mod:`.figures` (the PNGs), :mod:`.offline` (``demo --offline``, the double-integrator comparison).
"""

from __future__ import annotations

from saml_ros.demo.cli import main

__all__ = ["main"]
