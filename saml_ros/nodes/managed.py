"""The managed-node base of the learner and the MPC (:class:`ManagedNode`, an ``rclpy.lifecycle.LifecycleNode``).

A subclass fills in four steps, each raising :class:`~saml_ros.core.runtime.lifecycle.TransitionRefused` when it cannot be
done as configured: :meth:`ManagedNode.configure_node` (read and validate the parameters, build what the node
needs, create its publishers and timers), :meth:`~ManagedNode.activate_node` (subscribe and start working),
:meth:`~ManagedNode.deactivate_node` (stop working, keep the configuration) and
:meth:`~ManagedNode.cleanup_node` (release everything; also called after an error, so it must cope with a
half-configured node). ``shutdown`` from any primary state runs :meth:`~ManagedNode.shutdown_node` (by default
deactivate, then cleanup). What this class adds to rclpy's:

* the ``autostart`` parameter (:data:`saml_ros.core.runtime.lifecycle.AUTOSTART`) and :func:`run_managed`, the spin
  loop of the executables: configure + activate at start-up unless ``autostart`` is false, spin until a stop
  signal or the ``finalized`` state, then shut down from wherever the node is;
* a ``change_state`` request for a transition the current state does not have (e.g. ``activate`` while
  unconfigured) is answered ``success: false`` and logged: rclpy (Jazzy) raises inside the executor instead,
  which would end the process and leave the caller waiting for an answer;
* every failed or raising step is logged with its reason (rclpy turns an exception into ``ERROR`` silently).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from rclpy.lifecycle import LifecycleNode, LifecycleState, TransitionCallbackReturn

from saml_ros.core.params import problems_of
from saml_ros.core.runtime.lifecycle import AUTOSTART, LIFECYCLE_PARAMS, Outcome, run_transition
from saml_ros.nodes.ros_params import declare_params
from saml_ros.nodes.runtime import StopFlag, spin_until_stopped

_RETURN: dict[Outcome, TransitionCallbackReturn] = {
    "success": TransitionCallbackReturn.SUCCESS,
    "failure": TransitionCallbackReturn.FAILURE,
    "error": TransitionCallbackReturn.ERROR,
}
#: primary states a shutdown transition leaves from
PRIMARY = ("unconfigured", "inactive", "active")


class ManagedNode(LifecycleNode):
    """A lifecycle node named ``node_name`` in ``namespace`` with the ``autostart`` parameter (module docstring)."""

    def __init__(self, node_name: str, namespace: str | None) -> None:
        super().__init__(node_name, namespace=namespace)
        #: problems of the parameters declared here (``autostart``), reported with the subclass's at start-up
        self.param_problems: list[str] = []
        try:
            self.autostart = bool(declare_params(self, LIFECYCLE_PARAMS)["autostart"])
        except ValueError as exc:
            self.autostart, self.param_problems = bool(AUTOSTART.default), problems_of(exc)
        #: ``change_state`` requests refused because the current state has no such transition
        self.invalid_transitions = 0
        #: the log line of the newest failed or raising step
        self.last_failure = ""
        #: True once a stop signal arrived (set by :func:`run_managed`): long start-up steps give up on it
        self.stop_requested: Callable[[], bool] = lambda: False
        service = self._service_change_state
        service.callback = self._guarded(service.callback)

    @property
    def state_label(self) -> str:
        """The current lifecycle state: ``unconfigured``, ``inactive``, ``active``, ``finalized`` (or a
        transition state while a step runs)."""
        return str(self._state_machine.current_state[1])

    # ---------------------------------------------------------------------------------- the subclass's steps
    def configure_node(self) -> None:
        """Read and validate the parameters; build what the node needs (raise TransitionRefused to fail)."""

    def activate_node(self) -> None:
        """Start working (subscribe, train or control)."""

    def deactivate_node(self) -> None:
        """Stop working; keep the configuration."""

    def cleanup_node(self) -> None:
        """Release everything configure made (idempotent: also run after an error)."""

    def shutdown_node(self, state: str) -> None:
        """Leave for good from primary ``state``: by default deactivate (if active), then clean up."""
        if state == "active":
            self.deactivate_node()
        if state in ("active", "inactive"):
            self.cleanup_node()

    # ---------------------------------------------------------------------------------- rclpy's callbacks
    def _step(self, name: str, step: Any) -> TransitionCallbackReturn:
        def log_error(text: str) -> None:
            self.last_failure = text
            self.get_logger().error(text)

        return _RETURN[run_transition(name, step, log_error)]

    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        return self._step("configure", self.configure_node)

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        ret = self._step("activate", self.activate_node)
        return super().on_activate(state) if ret == TransitionCallbackReturn.SUCCESS else ret  # lifecycle publishers

    def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
        ret = self._step("deactivate", self.deactivate_node)
        super().on_deactivate(state)
        return ret

    def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        return self._step("cleanup", self.cleanup_node)

    def on_shutdown(self, state: LifecycleState) -> TransitionCallbackReturn:
        return self._step("shutdown", lambda: self.shutdown_node(state.label))

    def on_error(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._step("cleanup after an error", self.cleanup_node)
        return TransitionCallbackReturn.SUCCESS  # -> unconfigured: a corrected configure can follow

    def _guarded(self, callback: Any) -> Any:
        def change_state(request: Any, response: Any) -> Any:
            try:
                return callback(request, response)
            except Exception as exc:  # noqa: BLE001 - rcl refuses a transition the current state does not have
                self.invalid_transitions += 1
                valid = sorted({t[1] for t in self._state_machine.available_transitions})
                why = str(exc).split(", at ")[0]  # rcl's message without its source location
                self.get_logger().warning(
                    f"refused transition {request.transition.label or request.transition.id!r} in state "
                    f"{self.state_label!r} ({why}); available: {valid}")
                response.success = False
                return response

        return change_state

    # ---------------------------------------------------------------------------------- start and end
    def start_up(self) -> bool:
        """``autostart``: configure and activate now; True when the node is active (or not asked to start)."""
        if not self.autostart:
            self.get_logger().info("autostart is false: unconfigured, waiting for lifecycle transitions")
            return True
        for trigger in (self.trigger_configure, self.trigger_activate):
            if trigger() != TransitionCallbackReturn.SUCCESS:
                if self.stop_requested():  # a stop signal cut the start-up short: not a configuration error
                    self.get_logger().info("stopped during start-up")
                    return True
                self.get_logger().fatal(f"configuration error: {self.last_failure}")
                return False
        return True

    def finish(self) -> None:
        """The shutdown transition from the current primary state (nothing once finalized)."""
        if self.state_label in PRIMARY:
            self.trigger_shutdown()


def run_managed(node: ManagedNode, stop: StopFlag, start_failed: int, executor: str = "single") -> int:
    """Start ``node`` (:meth:`ManagedNode.start_up`), spin it on ``executor``
    (:func:`~saml_ros.nodes.runtime.make_executor`) until a stop signal or ``finalized``, then
    :meth:`ManagedNode.finish`. Returns 0, or ``start_failed`` when autostart could not activate the node."""
    node.stop_requested = lambda: bool(stop["signal"])
    try:
        if not node.start_up():
            return start_failed
        spin_until_stopped(node, stop, keep_going=lambda: node.state_label != "finalized", executor=executor)
        return 0
    finally:
        node.finish()
