"""Viewers for a running or recorded loop: PlotJuggler / Foxglove layouts and a Foxglove WebSocket server.

* :mod:`.layouts`: the layouts (ROS-free), built from msg_schemas;
* :mod:`.render`: the layouts' panels drawn from a recorded bag (matplotlib);
* :mod:`.cli`: ``layouts write | render``;
* :mod:`.foxglove_server`: ``foxglove_server``, the loop's topics on a Foxglove WebSocket (``foxglove-sdk``), for
  pip-only set-ups without ``foxglove_bridge``.

Modules are imported by name; this face imports nothing.
"""
