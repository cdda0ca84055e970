"""Managed (lifecycle) nodes without ROS: the ``autostart`` parameter and how a transition's work ends.

The learner and the MPC are ROS 2 managed nodes (docs/nodes.md, "Lifecycle"): ``configure`` reads and validates
their parameters, ``activate`` starts training or control, ``deactivate`` pauses it, ``cleanup`` and
``shutdown`` release everything. What each step does is the node's; here is what all of them share:

* :data:`AUTOSTART`: a node that nobody manages walks ``configure`` and ``activate`` itself at start-up (the
  default, so ``ros2 run``, the tests and the benches need no lifecycle client); ``autostart: false`` starts it
  unconfigured, waiting for ``lifecycle_msgs/srv/ChangeState`` (``bringup``, the launch files'
  ``lifecycle_manager``, ``ros2 lifecycle set``).
* :func:`run_transition`: a step that raises :class:`TransitionRefused` (bad parameter, spec, run directory)
  *fails*: the node stays where it was (``configure``: unconfigured, ready for a corrected parameter); any other
  exception is an *error* (rclpy then runs ``on_error`` and the node ends unconfigured). Both are logged with
  the reason; rclpy itself swallows the exception of a transition callback without a word.
"""

from __future__ import annotations

import traceback
from collections.abc import Callable
from typing import Any, Literal

from saml_ros.core.errors import SamlError
from saml_ros.core.params import START, Param, Problems, read_params

AUTOSTART = Param(
    "autostart", True,
    "walk configure and activate at start-up (a node nobody manages); false: start unconfigured and wait for "
    "lifecycle transitions (lifecycle_msgs/srv/ChangeState: bringup, lifecycle_manager, ros2 lifecycle set)",
    when=START)
#: the parameters every managed saml_ros node declares besides its own table
LIFECYCLE_PARAMS: tuple[Param, ...] = (AUTOSTART,)

#: how a transition's work ended (rclpy's ``TransitionCallbackReturn`` by name)
Outcome = Literal["success", "failure", "error"]


class TransitionRefused(SamlError):
    """The transition cannot be made as configured; the message says which parameter or file and why."""


def run_transition(name: str, step: Callable[[], None], log_error: Callable[[str], None]) -> Outcome:
    """Run ``step`` (the work of transition ``name``) and say how it ended; failures and errors are logged."""
    try:
        step()
    except TransitionRefused as exc:
        log_error(f"{name} failed: {exc}")
        return "failure"
    except Exception as exc:  # noqa: BLE001 - reported as the transition's error, the node keeps running
        log_error(f"{name} raised {type(exc).__name__}: {exc}\n{traceback.format_exc()}")
        return "error"
    return "success"


#: transition labels a lifecycle client may request (``lifecycle_msgs`` labels, valid from the primary state
#: they leave: ``shutdown`` from any of them)
TRANSITION_LABELS = ("configure", "activate", "deactivate", "cleanup", "shutdown")

#: parameters of the ``lifecycle_manager`` executable
MANAGER_PARAMS: tuple[Param, ...] = (
    Param("node_names", ["learner", "mpc"], "managed nodes to drive: names relative to this node's namespace, or "
                                            "absolute", item_type=str),
    Param("transitions", ["configure", "activate"], f"transitions requested in order, each of every node at once "
                                                    f"({', '.join(TRANSITION_LABELS)})", item_type=str),
    Param("timeout", 120.0, "s to wait for the nodes' lifecycle services, and for each transition"),
)


def check_manager_params(values: dict[str, Any]) -> list[str]:
    """The ``lifecycle_manager``'s parameters (:data:`MANAGER_PARAMS`) converted and checked: the transitions
    (:func:`check_transitions`); ``ParamErrors`` naming every bad one."""
    problems = Problems()
    p = read_params(MANAGER_PARAMS, values, problems)
    transitions: list[str] = []
    with problems.capture("transitions", prefix="parameter 'transitions': "):
        transitions = check_transitions(list(p["transitions"]))
    problems.check(p["timeout"] > 0, "timeout", "> 0", p["timeout"])
    problems.raise_if_any()
    return transitions


def check_transitions(labels: list[str]) -> list[str]:
    """``labels`` if every one is a :data:`TRANSITION_LABELS` entry; ``ValueError`` naming the bad one."""
    for label in labels:
        if label not in TRANSITION_LABELS:
            raise ValueError(f"unknown transition {label!r}; valid: {', '.join(TRANSITION_LABELS)}")
    return list(labels)
