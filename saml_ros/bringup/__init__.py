"""``ros2 run saml_ros bringup``: a whole closed loop (simulator, learner, MPC) as separate processes.

:func:`run` runs one loop from a configuration, :func:`main` is the executable (``saml_ros.bringup:main``; its
usage is :mod:`.cli`'s docstring).

Modules: :mod:`.config` (defaults, YAML, ``--set``, ROS parameter files), :mod:`.supervisor` (ROS-free process
groups: start, stop by escalation, child environment), :mod:`.results` (episodes, task error, summary),
:mod:`.monitor` (the ROS node watching the topics), :mod:`.closed_loop` (:func:`run`), :mod:`.cli` (:func:`main`).
"""

from __future__ import annotations

from saml_ros.bringup.cli import build_parser, main
from saml_ros.bringup.closed_loop import RunOptions, make_run_dir, run
from saml_ros.bringup.config import (
    NODE_SECTIONS,
    apply_sets,
    default_config,
    load_config,
    merge_config,
    node_params,
    ros_params_file,
)
from saml_ros.bringup.results import (
    BringupResult,
    Episode,
    EpisodeTracker,
    format_summary,
    goal_position,
    task_error,
)
from saml_ros.bringup.supervisor import Child, ProcessGroup, child_env, node_argv

__all__ = [
    "NODE_SECTIONS",
    "BringupResult",
    "Child",
    "Episode",
    "EpisodeTracker",
    "ProcessGroup",
    "RunOptions",
    "apply_sets",
    "build_parser",
    "child_env",
    "default_config",
    "format_summary",
    "goal_position",
    "load_config",
    "main",
    "make_run_dir",
    "merge_config",
    "node_argv",
    "node_params",
    "ros_params_file",
    "run",
    "task_error",
]
