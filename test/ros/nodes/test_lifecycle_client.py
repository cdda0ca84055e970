"""``lifecycle_client.drive`` when DDS loses a ``change_state`` request or its answer (seen in loaded suite runs:
bringup waited 90 s for an MPC node that had configured 2.6 s after the request). Real rclpy nodes in this process,
in a private ROS domain; the loss is injected where it happens, in the node's service (the request never reaches
the transition, or the answer is never sent)."""

from __future__ import annotations

import time
from collections.abc import Iterator
from typing import Any

import pytest
from helpers.ros_helpers import ros_domain

rclpy = pytest.importorskip("rclpy")

from rclpy.executors import SingleThreadedExecutor  # noqa: E402

from saml_ros.nodes.lifecycle_client import drive, get_state  # noqa: E402
from saml_ros.nodes.managed import ManagedNode  # noqa: E402


class Counting(ManagedNode):
    def __init__(self, configure_s: float = 0.0, fail_activate: bool = False) -> None:
        super().__init__("counted", None)
        self.configured = 0
        self.configure_s = configure_s
        self.fail_activate = fail_activate

    def configure_node(self) -> None:
        time.sleep(self.configure_s)
        self.configured += 1

    def activate_node(self) -> None:
        if self.fail_activate:
            raise RuntimeError("this node does not activate")


@pytest.fixture
def env(request: pytest.FixtureRequest) -> Iterator[tuple[Any, SingleThreadedExecutor]]:
    with ros_domain(request.node.name):
        rclpy.init()
        try:
            client = rclpy.create_node("driver")
            ex = SingleThreadedExecutor()
            ex.add_node(client)
            yield client, ex
            ex.shutdown()
            client.destroy_node()
        finally:
            rclpy.shutdown()


def lose(node: ManagedNode, what: str) -> list[int]:
    """Make the node's change_state service lose its first request (``"request"``: no transition, no answer) or
    its first answer (``"answer"``: the transition happens, the answer is not sent). Returns the loss count."""
    srv = node._service_change_state
    lost: list[int] = []
    callback, send = srv.callback, srv.send_response
    if what == "request":
        def take(request: Any, response: Any) -> Any:
            if not lost:
                lost.append(1)
                response.success = False
                # drop this one answer (an instance attribute shadows the method)
                setattr(srv, "send_response", lambda *a: setattr(srv, "send_response", send))  # noqa: B010
                return response
            return callback(request, response)

        srv.callback = take
    else:
        def drop(*args: Any) -> None:
            if not lost:
                lost.append(1)
                return
            send(*args)

        setattr(srv, "send_response", drop)  # noqa: B010
    return lost


@pytest.mark.parametrize("what", ["request", "answer"])
def test_a_lost_request_or_answer_is_recovered(env: tuple[Any, SingleThreadedExecutor], what: str) -> None:
    client, ex = env
    node = Counting()
    ex.add_node(node)
    lost = lose(node, what)
    t0 = time.monotonic()
    problems = drive(client, lambda s: ex.spin_once(timeout_sec=s), ["/counted"], ["configure", "activate"],
                     timeout=30.0, recheck=1.0)
    assert problems == [] and lost == [1]
    assert node.configured == 1 and node.state_label == "active"
    assert time.monotonic() - t0 < 15.0
    node.destroy_node()


def test_a_slow_transition_is_waited_for_not_requested_twice(env: tuple[Any, SingleThreadedExecutor]) -> None:
    client, ex = env
    node = Counting(configure_s=2.5, fail_activate=True)  # longer than recheck: get_state goes unanswered
    ex.add_node(node)
    problems = drive(client, lambda s: ex.spin_once(timeout_sec=s), ["/counted"], ["configure"], timeout=30.0,
                     recheck=0.5)
    assert problems == [] and node.configured == 1 and node.state_label == "inactive"
    # a node already where the transition leads counts as done; one that cannot get there fails
    assert drive(client, lambda s: ex.spin_once(timeout_sec=s), ["/counted"], ["configure"], timeout=10.0) == []
    assert node.configured == 1
    bad = drive(client, lambda s: ex.spin_once(timeout_sec=s), ["/counted"], ["activate"], timeout=10.0)
    assert bad == ["/counted: activate failed (its log says why)"]
    # a raising step is an error: the node cleans up and waits unconfigured (ManagedNode.on_error)
    assert get_state(client, lambda s: ex.spin_once(timeout_sec=s), "/counted") == "unconfigured"
    node.destroy_node()
