"""ROS-free simulator cores: what the simulator nodes and the experiments step.

* :mod:`.sim_core`: the event-driven simulator core (commands, lockstep / realtime stepping, episodes, stamps),
  the time-stepped core :class:`~.sim_core.SteppedSim` and :func:`~.sim_core.build_stepped_sim` (a system's
  stepped simulator from its registry entry);
* :mod:`.pacing`: the realtime loop's wall-clock pacing.

Each system's own world (start states, ground contact, the paddle ball's MuJoCo world and its core) lives in its
folder, ``saml_ros.systems.<name>``.
"""
