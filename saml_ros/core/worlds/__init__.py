"""ROS-free simulator worlds: what the simulator nodes and the experiments step.

* :mod:`.sim_core`: the event-driven simulator core (commands, lockstep / realtime stepping, episodes,
  stamps) and the time-stepped systems' cores;
* :mod:`.paddle_world`: the MuJoCo paddle-ball world (a kinematic paddle with a low-level impact controller);
* :mod:`.paddle_sim`: the paddle-ball simulator core (one protocol step per impact).

Modules are imported by name (``paddle_world`` imports MuJoCo).
"""
