"""The built-in systems, one folder each, and robots described by a system file; the registry's built-in table.

A system's folder holds everything saml_ros knows about it: ``model.py`` (its ``System`` class: the torch f_hat
and true dynamics, layouts, bounds, the paper's spec), ``dynamics_np.py`` (the numpy twins the MPC predicts
with), ``task.py`` or ``mpc/`` (its MPC problem), ``world.py`` (its simulator world) and ``entry.py`` (its
:class:`~saml_ros.core.systems.entry.SystemEntry`: where each part lives, imported only when asked for, and its
experiment and bringup settings). Its message schema and simulator node stay in the package's top-level
``msg_schemas/`` and ``sim_nodes/``.

This package sits above the layers its entries wire (the MPC, the simulator worlds, the message schemas); the
table it fills (:mod:`saml_ros.core.systems.registry`) sits below them. ``saml_ros/__init__.py`` imports it, so the
built-in systems are registered before any module of saml_ros runs. Adding a built-in system: its folder and one
line in :data:`ENTRIES`. Importing this package imports neither torch, MuJoCo nor the MPC.
"""

from __future__ import annotations

from saml_ros.core.systems.entry import SystemEntry
from saml_ros.core.systems.registry import register_builtin
from saml_ros.systems import robot_entry  # noqa: F401 - installs the loader of robots' stored definitions
from saml_ros.systems.friction.entry import FRICTION
from saml_ros.systems.paddle_ball.entry import PADDLE_BALL
from saml_ros.systems.quadrotor.entry import QUADROTOR

# bringup defaults (each entry's ``bringup``): a lockstep loop runs as fast as the CPUs allow, so the learner's
# training process gets the default niceness (0), not the learner's own default (10, which protects realtime
# loops): at niceness 10 it starved (about 30 updates/s instead of ~270 on this 2-core machine) and the
# half-trained models made the MPC land worse than f_hat. config/bringup_quadrotor.yaml holds the quadrotor's values.

#: the built-in systems, in registration order: one line each
ENTRIES: tuple[SystemEntry, ...] = (
    FRICTION,
    QUADROTOR,
    PADDLE_BALL,
)
register_builtin(*ENTRIES)

__all__ = ["ENTRIES"]
