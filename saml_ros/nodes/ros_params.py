"""A node's :class:`~saml_ros.core.params.Param` table through rclpy: declaring it, the start-up checks, the
checks of every later change (:class:`ParamGuard`), and reading ``system`` first.

Every parameter gets a ``ParameterDescriptor`` with its description and when a change applies
(:func:`~saml_ros.core.params.change_note`), so ``ros2 param describe`` and ``--params-file`` work as usual.
Float parameters and lists of floats are dynamically typed, so a YAML ``10`` is accepted for ``10.0`` (the checks
of the core refuse anything but numbers); another empty list default is declared with its ``item_type``'s array
type. rclpy refuses a value of another type for the others itself. The values come
back raw: the node's configuration class (``from_params``) converts and validates them, naming every bad
parameter.

rclpy itself ignores a command-line or parameter-file value of a name the node never declares, and accepts any
change of a dynamically typed parameter; :func:`check_startup` and :class:`ParamGuard` close both gaps with the
rules of the ROS-free core (:func:`saml_ros.core.params.review_change`). docs/nodes.md, "Parameter changes".
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from typing import Any

from rcl_interfaces.msg import ParameterDescriptor, SetParametersResult
from rclpy.exceptions import ParameterUninitializedException
from rclpy.lifecycle import LifecycleNode
from rclpy.node import Node
from rclpy.parameter import Parameter

from saml_ros.core.params import (
    ChangeReview,
    Param,
    ParamErrors,
    Problems,
    change_note,
    coerce_param,
    exclusive_problems,
    problems_of,
    review_change,
    unknown_problems,
)

#: rclpy type of an empty list parameter, by element type
_ARRAY_TYPES = {float: Parameter.Type.DOUBLE_ARRAY, int: Parameter.Type.INTEGER_ARRAY,
                str: Parameter.Type.STRING_ARRAY, bool: Parameter.Type.BOOL_ARRAY}
#: ``validate(values)``: the node's start-up / configure validation of ``{name: raw value}`` (raises ValueError)
Validate = Callable[[dict[str, Any]], object]


def is_managed(node: Node) -> bool:
    """True for a lifecycle node (its :data:`~saml_ros.core.params.CONFIGURE` parameters are read at configure)."""
    return isinstance(node, LifecycleNode)


def declare_params(node: Node, params: Iterable[Param], dynamic_typing: bool = False) -> dict[str, Any]:
    """Declare ``params`` on ``node``; ``{name: value}`` (the default where rclpy has none). ``dynamic_typing``:
    every parameter, not only the floats and float lists, is dynamically typed (the simulators convert every value
    themselves).

    Raises:
        ParamErrors: rclpy refused values (e.g. an override of the wrong type), each named; every parameter is
            declared all the same (a refused one with its default).
    """
    out: dict[str, Any] = {}
    problems = Problems()
    managed = is_managed(node)
    for p in params:
        dynamic = dynamic_typing or isinstance(p.default, float) or (isinstance(p.default, list) and p.item_type is float)
        descriptor = ParameterDescriptor(description=f"{p.description}. {change_note(p, managed)}",
                                         dynamic_typing=dynamic)
        typed = isinstance(p.default, list) and not p.default and not dynamic
        value = _ARRAY_TYPES[p.item_type] if typed else p.default
        try:
            got = node.declare_parameter(p.name, value, descriptor).value
        except Exception as exc:  # noqa: BLE001 - rclpy raises several types for bad overrides
            problems.add(_refused_override(node, p, exc), p.name)
            got = node.declare_parameter(p.name, value, descriptor, ignore_override=True).value
        out[p.name] = p.default if got is None else got
    problems.raise_if_any()
    return out


def _refused_override(node: Node, param: Param, exc: Exception) -> str:
    """Why rclpy refused the value given for ``param``, in the words of the core's checks where they apply."""
    given = getattr(node, "_parameter_overrides", {}).get(param.name)
    try:
        if given is not None:
            coerce_param(param.name, given.value, param.default, param.item_type, param.finite)
    except ValueError as own:
        return str(own)
    return f"parameter {param.name!r}: {exc}"


def current_values(node: Node, params: Iterable[Param]) -> dict[str, Any]:
    """The current values of the declared ``params`` of ``node`` by name (the default where rclpy has none, as
    for an empty list); a managed node reads them at ``configure``, so values set meanwhile apply."""
    out: dict[str, Any] = {}
    for p in params:
        try:
            got = node.get_parameter(p.name).value
        except ParameterUninitializedException:  # an empty list declared by its type holds no value
            got = None
        out[p.name] = p.default if got is None else got
    return out


def given_names(node: Node) -> set[str]:
    """The parameter names the command line (``-p``) and parameter files give ``node``. rclpy keeps them as the
    node's overrides and has no public accessor for them (it ignores those the node never declares)."""
    return set(getattr(node, "_parameter_overrides", {}))


def check_startup(node: Node, params: Sequence[Param], validate: Validate | None = None,
                  exclusive: Iterable[tuple[str, str]] = (), earlier: Sequence[str] = ()) -> None:
    """The start-up checks of a node that has declared all its parameters (``params`` its own table): every
    parameter given that the node does not declare, and both parameters of an ``exclusive`` pair given. When there
    is a problem (or ``earlier`` ones, e.g. refused declarations), ``validate``'s problems on the current values
    are added, so that every bad parameter is reported at once.

    Raises:
        ParamErrors: the problems, each naming its parameter.
    """
    given = given_names(node)
    declared = {name for name in given if node.has_parameter(name)} | {p.name for p in params}
    messages = list(earlier)
    messages += unknown_problems(given, declared, node.get_fully_qualified_name())
    values = current_values(node, params)
    messages += exclusive_problems(values, given, exclusive)
    if messages and validate is not None:
        try:
            validate(values)
        except (ValueError, TypeError) as exc:
            messages += [m for m in problems_of(exc) if m not in messages]
    if messages:
        raise ParamErrors(messages)


def start_params(node: Node, params: Sequence[Param], validate: Validate | None = None,
                 exclusive: Iterable[tuple[str, str]] = (), dynamic_typing: bool = False,
                 earlier: Sequence[str] = ()) -> dict[str, Any]:
    """:func:`declare_params`, then :func:`check_startup` (with the declarations rclpy refused, after ``earlier``
    problems); the current values by name. A node that is not managed validates them at once (``validate``); a
    managed one at configure.

    Raises:
        ParamErrors: every problem, each naming its parameter.
    """
    earlier = list(earlier)
    try:
        declare_params(node, params, dynamic_typing)
    except ValueError as exc:
        earlier += problems_of(exc)
    check_startup(node, params, validate, exclusive, earlier)
    return current_values(node, params)


class ParamGuard:
    """Checks every change of ``params`` on a running ``node`` (an rclpy set-parameters callback) with
    :func:`~saml_ros.core.params.review_change`: a refused change answers the setter (``ros2 param set``) with
    the reason and leaves the old value; an accepted one is stored, logged, and its :data:`~saml_ros.core.params.LIVE`
    values handed to ``apply`` (after rclpy stored them, so ``current_values`` reads them).

    Args:
        node: the node, with ``params`` declared (create the guard after declaring: rclpy calls the callbacks for
            declarations too).
        params: the node's table; other parameters (rclpy's own, e.g. ``use_sim_time``) are left to rclpy.
        validate: the node's start-up / configure validation of ``{name: raw value}``.
        apply: ``apply(live)`` with ``{name: converted value}`` of the accepted :data:`~saml_ros.core.params.LIVE`
            changes.
        configured: for a managed node, whether it is configured (its CONFIGURE parameters are then refused);
            default: not unconfigured.
        exclusive: pairs of parameters that cannot both be given (e.g. ``system`` and ``system_file``).
        extra: parameters the node declared elsewhere (a managed node's ``autostart``): a change is judged by
            when it applies and its type only, ``validate`` never sees them.
    """

    def __init__(self, node: Node, params: Sequence[Param], validate: Validate | None = None,
                 apply: Callable[[dict[str, Any]], None] | None = None, *,
                 configured: Callable[[], bool] | None = None, exclusive: Iterable[tuple[str, str]] = (),
                 extra: Sequence[Param] = ()) -> None:
        self.node = node
        self.params = [*params, *extra]
        self.names = {p.name for p in self.params}
        own = {p.name for p in params}
        self.validate: Validate | None = None
        if validate is not None:
            check = validate
            self.validate = lambda values: check({k: v for k, v in values.items() if k in own})
        self.apply = apply
        self.managed = is_managed(node)
        self.configured = configured or self._default_configured
        self.exclusive = list(exclusive)
        self.given = given_names(node)
        #: changes refused so far
        self.refused = 0
        self._accepted: ChangeReview | None = None
        node.add_on_set_parameters_callback(self._on_set)
        node.add_post_set_parameters_callback(self._after_set)

    def _default_configured(self) -> bool:
        return not self.managed or getattr(self.node, "state_label", "") != "unconfigured"

    def review(self, parameters: Sequence[Parameter]) -> ChangeReview:
        """The decision about ``parameters`` (rclpy ``Parameter`` objects), without making the change."""
        fqn = self.node.get_fully_qualified_name()
        deleted = [p.name for p in parameters if p.name in self.names and p.type_ == Parameter.Type.NOT_SET]
        if deleted:
            return ChangeReview(False, "; ".join(f"parameter {n!r} of {fqn} cannot be deleted" for n in deleted))
        changes = {p.name: p.value for p in parameters if p.name in self.names}
        if not changes:
            return ChangeReview(True)
        return review_change(self.params, current_values(self.node, self.params), changes, self.validate,
                             configured=self.configured(), managed=self.managed, node=fqn, given=self.given,
                             exclusive=self.exclusive)

    def _on_set(self, parameters: list[Parameter]) -> SetParametersResult:
        try:
            decision = self.review(parameters)
        except Exception as exc:  # noqa: BLE001 - a bug in a check must refuse the change, not end the node
            decision = ChangeReview(False, f"the change could not be checked ({type(exc).__name__}: {exc})")
        if not decision.accepted:
            self.refused += 1
            self._accepted = None
            self.node.get_logger().warning(f"refused parameter change ({', '.join(p.name for p in parameters)}): "
                                           f"{decision.reason}")
            return SetParametersResult(successful=False, reason=decision.reason)
        self._accepted = decision
        return SetParametersResult(successful=True)

    def _after_set(self, parameters: list[Parameter]) -> None:
        decision, self._accepted = self._accepted, None
        if decision is None:
            return
        self.given |= {p.name for p in parameters}
        logger = self.node.get_logger()
        stored, live = decision.stored, decision.live
        if self.managed and not self.configured():  # nothing runs yet: configure reads them all
            stored, live = {**stored, **live}, {}
        for name, value in stored.items():
            logger.info(f"parameter {name} set to {value!r}: read at the next configure")
        if live:
            text = ", ".join(f"{n} = {v!r}" for n, v in live.items())
            if self.apply is None:
                logger.info(f"parameter change applied: {text}")
                return
            try:
                self.apply(dict(live))
            except Exception as exc:  # noqa: BLE001 - the value is stored; say it could not be applied
                logger.error(f"parameter change {text} stored but not applied: {type(exc).__name__}: {exc}")
                return
            logger.info(f"parameter change applied: {text}")


def probe_system(node_name: str, default: str = "friction", file_param: str | None = None) -> tuple[str, bool]:
    """``(system, remapped)``: the ``system`` parameter a node called ``node_name`` gets (from the command line or
    a parameter file) and whether ``__ns`` is remapped, read by a short-lived probe node: a node's namespace
    (``/<system>`` unless remapped) must be known when it is created. With ``file_param`` (e.g. ``system_file``)
    set to a system file, the system is the ``name`` in that file (the node reports a bad file when it loads it).
    :class:`~saml_ros.core.params.ParamErrors` naming ``system`` if rclpy refuses the value."""
    probe = Node(node_name)
    try:
        system = probe.declare_parameter("system", default).value
        path = probe.declare_parameter(file_param, "").value if file_param else ""
    except Exception as exc:  # noqa: BLE001 - rclpy raises several types for bad overrides
        raise ParamErrors([f"parameter 'system': {exc}"]) from None
    finally:
        remapped = probe.get_namespace() != "/"
        probe.destroy_node()
    if path:
        system = _file_system_name(str(path)) or system
    return system, remapped


def _file_system_name(path: str) -> str | None:
    """The ``name`` of a system file, or None when it cannot be read."""
    import yaml

    try:
        with open(path) as f:
            name = yaml.safe_load(f).get("name")
    except Exception:  # noqa: BLE001 - reported properly when the node loads the file
        return None
    return name if isinstance(name, str) and name.isidentifier() else None
