"""The one list of saml_ros executables: name -> ``"module:function"``.

``setup.py`` turns it into console scripts (``ros2 run saml_ros <name>`` after a colcon build; it reads
this file with :mod:`ast`, so keep it a plain dict literal with no imports), and :mod:`saml_ros.entry`
uses it for ``./dev <name>`` / ``python -m saml_ros.entry <name>``. Every function takes no arguments,
reads ``sys.argv`` and returns an exit code (or ``None`` for 0).
"""

EXECUTABLES: dict[str, str] = {
    "learner": "saml_ros.learner_node:main",
    "mpc": "saml_ros.mpc_node:main",
    "friction_sim": "sim_nodes.friction_sim:main",
    "paddle_ball_sim": "sim_nodes.paddle_ball_sim:main",
    "quadrotor_sim": "sim_nodes.quadrotor_sim:main",
    "record": "saml_ros.record:main",
    "play": "saml_ros.play:main",
    "bringup": "saml_ros.bringup:main",
    "train": "saml_ros.train_cli:main",
    "experiment": "saml_ros.experiments.cli:main",
    "bag_info": "saml_ros.bag_info:main",
    "demo": "saml_ros.demo:main",
}
