"""saml_ros: online Sufficiently Accurate Model Learning for ROS 2.

``saml_ros.core`` is ROS-free (numpy / torch only); the node modules wrap it. Importing the package registers the
built-in systems (:mod:`saml_ros.systems`, which imports neither torch, MuJoCo nor the MPC) in the core's registry.
"""

from saml_ros import systems as _systems  # noqa: F401 - registers the built-in systems

__version__ = "0.1.0"
