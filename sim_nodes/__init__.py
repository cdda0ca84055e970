"""Simulator nodes: thin rclpy wrappers over the ROS-free system dynamics in saml_ros.core.systems."""
