"""The rclpy nodes of saml_ros: thin wiring of parameters, topics and timers over the ROS-free core.

* :mod:`.learner`: the online learner (``ros2 run saml_ros learner``);
* :mod:`.mpc`: the MPC controller (``ros2 run saml_ros mpc``);
* :mod:`.runtime`: what every rclpy executable shares around its ``main`` (signals, spin, shutdown).

Modules are imported by name (``saml_ros.nodes.learner``); this face imports nothing, so that importing one
node never imports rclpy for another.
"""
