"""saml_ros: online Sufficiently Accurate Model Learning for ROS 2.

``saml_ros.core`` is ROS-free (numpy / torch only); the node modules wrap it.
"""

__version__ = "0.1.0"
