"""Requesting lifecycle transitions of managed nodes through their ``lifecycle_msgs`` services (:func:`drive`).

Used by ``bringup`` (its monitor node configures and activates the learner and the MPC) and by the
``lifecycle_manager`` executable the launch files start. Every node of a step gets its request at once (the
learner's ``configure`` starts its training process, a few seconds), and the next step begins when all answered.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence

from lifecycle_msgs.msg import Transition
from lifecycle_msgs.srv import ChangeState, GetState
from rclpy.node import Node

#: ``spin_once(timeout_s)``: lets the caller's executor run while :func:`drive` waits
SpinOnce = Callable[[float], None]


def drive(node: Node, spin_once: SpinOnce, fqns: Sequence[str], transitions: Sequence[str], timeout: float,
          cancelled: Callable[[], bool] = lambda: False) -> list[str]:
    """Request ``transitions`` (labels, e.g. ``["configure", "activate"]``) of the nodes ``fqns`` in order.

    Returns what went wrong (empty when every node made every transition): a service that did not appear
    within ``timeout`` s, a refused or failed transition (the node logs why), no answer within ``timeout`` s,
    or ``cancelled()`` becoming true.
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
            futures = {fqn: c.call_async(ChangeState.Request(transition=Transition(label=label)))
                       for fqn, c in clients.items()}
            deadline = time.monotonic() + timeout
            while not all(f.done() for f in futures.values()):
                if cancelled():
                    return ["cancelled"]
                if time.monotonic() > deadline:
                    return [f"{fqn}: no answer to {label} within {timeout:g} s"
                            for fqn, f in futures.items() if not f.done()]
                spin_once(0.05)
            failed = [f"{fqn}: {label} failed (its log says why)" for fqn, f in futures.items()
                      if not f.result().success]
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
