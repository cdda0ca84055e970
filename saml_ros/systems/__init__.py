"""The registry entries of the paper's three systems: double integrator with friction, quadrotor, paddle ball.

Each entry names where every part of its system lives; the small functions below import that part only when
called (so building the entries imports neither torch, MuJoCo nor the MPC). :mod:`.registry` registers
:data:`ENTRIES`.
"""

from __future__ import annotations

from saml_ros.core.systems.entry import SystemEntry
from saml_ros.systems.friction.entry import FRICTION
from saml_ros.systems.paddle_ball.entry import PADDLE_BALL
from saml_ros.systems.quadrotor.entry import QUADROTOR

# bringup defaults: a lockstep loop runs as fast as the CPUs allow, so the learner's training process gets the
# default niceness (0), not the learner's own default (10, which protects realtime loops): at niceness 10 it
# starved (about 30 updates/s instead of ~270 on this 2-core machine) and the half-trained models made the MPC
# land worse than f_hat. config/bringup_quadrotor.yaml holds the quadrotor's values.


#: the built-in entries, in registration order
ENTRIES: tuple[SystemEntry, ...] = (FRICTION, QUADROTOR, PADDLE_BALL)
