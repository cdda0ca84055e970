"""Requesting lifecycle transitions of managed nodes through their ``lifecycle_msgs`` services (:func:`drive`).

Used by ``bringup`` (its monitor node configures and activates the learner and the MPC) and by the
``lifecycle_manager`` executable the launch files start. Every node of a step gets its request at once (the
learner's ``configure`` starts its training process, a few seconds), and the next step begins when all answered.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from typing import Any

from lifecycle_msgs.msg import Transition
from lifecycle_msgs.srv import ChangeState, GetState
from rclpy.node import Node

#: ``spin_once(timeout_s)``: lets the caller's executor run while :func:`drive` waits
SpinOnce = Callable[[float], None]


#: the primary state each transition ends in when it succeeds
GOAL = {"configure": "inactive", "activate": "active", "deactivate": "inactive", "cleanup": "unconfigured",
        "shutdown": "finalized"}
#: the primary states a transition can start from (a node in one of them is not in the middle of a transition)
_STARTS = ("unconfigured", "inactive", "active")


def drive(node: Node, spin_once: SpinOnce, fqns: Sequence[str], transitions: Sequence[str], timeout: float,
          cancelled: Callable[[], bool] = lambda: False, recheck: float = 5.0) -> list[str]:
    """Request ``transitions`` (labels, e.g. ``["configure", "activate"]``) of the nodes ``fqns`` in order.

    A node that has not answered ``recheck`` s after a request is asked for its state (``get_state``): in the
    transition's goal state it counts as done (the answer was lost), in the state the transition starts from the
    request is sent again (the request was lost), in a transition state the wait goes on. Returns what went
    wrong (empty when every node made every transition): a service that did not appear within ``timeout`` s, a
    refused or failed transition (the node logs why), no answer within ``timeout`` s, or ``cancelled()``
    becoming true.
    """
    clients = {fqn: node.create_client(ChangeState, f"{fqn}/change_state") for fqn in fqns}
    try:
        deadline = time.monotonic() + timeout
        while not all(c.service_is_ready() for c in clients.values()):
            if cancelled():
                return ["cancelled"]
            if time.monotonic() > deadline:
                return [f"{fqn}: no lifecycle service {fqn}/change_state after {timeout:g} s"
                        for fqn, c in clients.items() if not c.service_is_ready()]
            spin_once(0.1)
        for label in transitions:
            def request(fqn: str, _label: str = label) -> Any:
                return clients[fqn].call_async(ChangeState.Request(transition=Transition(label=_label)))

            futures = {fqn: request(fqn) for fqn in clients}
            sent = dict.fromkeys(clients, time.monotonic())
            reached: set[str] = set()  # answered by the node's state, the answer itself lost
            deadline = time.monotonic() + timeout
            while not all(f.done() or fqn in reached for fqn, f in futures.items()):
                if cancelled():
                    return ["cancelled"]
                if time.monotonic() > deadline:
                    return [f"{fqn}: no answer to {label} within {timeout:g} s"
                            for fqn, f in futures.items() if not f.done() and fqn not in reached]
                spin_once(0.05)
                for fqn, f in futures.items():
                    if f.done() or fqn in reached or time.monotonic() - sent[fqn] < recheck:
                        continue
                    # DDS can drop a request or its answer while one side of the service's discovery lags the
                    # other: ask the node where it is; re-send only from the state the transition starts from
                    state = get_state(node, spin_once, fqn, timeout=min(recheck, 5.0))
                    if state == GOAL.get(label):
                        reached.add(fqn)
                        node.get_logger().warning(f"{fqn}: no answer to {label}, but it is {state}: answer lost")
                    elif state in _STARTS:
                        futures[fqn] = request(fqn)
                        node.get_logger().warning(f"{fqn}: no answer to {label} after {recheck:g} s and still "
                                                  f"{state}: request sent again")
                    sent[fqn] = time.monotonic()
            failed = []
            for fqn, f in futures.items():
                if fqn in reached or f.result().success:
                    continue
                # a re-sent request refused because the first one did arrive after all
                if get_state(node, spin_once, fqn, timeout=5.0) != GOAL.get(label):
                    failed.append(f"{fqn}: {label} failed (its log says why)")
            if failed:
                return failed
        return []
    finally:
        for c in clients.values():
            node.destroy_client(c)


def get_state(node: Node, spin_once: SpinOnce, fqn: str, timeout: float = 10.0) -> str | None:
    """The lifecycle state label of node ``fqn`` (``None`` when it does not answer within ``timeout`` s)."""
    client = node.create_client(GetState, f"{fqn}/get_state")
    try:
        deadline = time.monotonic() + timeout
        while not client.service_is_ready():
            if time.monotonic() > deadline:
                return None
            spin_once(0.05)
        future = client.call_async(GetState.Request())
        while not future.done():
            if time.monotonic() > deadline:
                return None
            spin_once(0.05)
        return str(future.result().current_state.label)
    finally:
        node.destroy_client(client)
