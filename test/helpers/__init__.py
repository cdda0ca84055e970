"""Code the tests share (not tests themselves; pytest collects nothing here). ``test/`` is on ``sys.path`` under
pytest (``pythonpath`` in pyproject.toml), so a test imports ``from helpers.ros_helpers import RosDomain``.

* :mod:`helpers.ros_helpers`: private ROS domains, launched node processes, a stock rclpy test node.
* :mod:`helpers.bag_publisher`: rollouts of the simulators as message events; a stock rclpy publisher process.
* :mod:`helpers.bag_test_helpers`: recorder / publisher processes and bags written like ``record`` writes them.
* :mod:`helpers.launch_parse`: evaluates the package's XML launch files without the ``launch`` package.
* :mod:`helpers.node_params`: the parameters each node declares, asked from running nodes.
* :mod:`helpers.models`: quadrotor models and checkpoints (good, biased, poisoned, hover-only) the MPC tests share.
* :mod:`helpers.training`: small training problems and the engine comparisons of the training tests.
* :mod:`helpers.learner_node`, :mod:`helpers.mpc_node`: a learner / MPC node process and the test's side of it.
* :mod:`helpers.your_robot`: the example robot defined outside the package (examples/diff_drive).
"""

from __future__ import annotations

from pathlib import Path

#: the repository root
REPO = Path(__file__).resolve().parents[2]
