"""Several publishers on a topic that should have one (ROS-free): the decision and what ``/diagnostics`` says.

A robot's ``state`` and its command (``applied_cmd``, or a robot's own ``cmd_vel``) each come from one node. Two
robots publishing into one namespace (a copied launch file, a forgotten simulator, a second robot started without
its own namespace) interleave on the same topics: the learner would pair them as one robot, and nothing else in
the data shows it when their stamps do not collide (docs/learner.md, "Several publishers on one topic"). The node
reads the ROS graph (the publishers' node names) and the number of publishers each subscription matched; this
module decides:

* :func:`publisher_report`: the level (WARN when any channel has more than one publisher), the message part that
  names the topics and the publishers' nodes, and the diagnostic values: ``multiple_publishers`` (``"topic:
  node, node; ..."``, empty when none), ``<ns>/publisher_nodes/<kind>`` and, with the refusal on,
  ``<ns>/refused/<kind>``;
* :class:`PublisherGate`: with the refusal on (the learner's ``pairing.refuse_multiple_publishers``), every
  message of a namespace is refused (not handed to the pairing, counted per channel) while any of that
  namespace's channels has matched more than one publisher; pairing resumes when it is back to one.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

#: diagnostics level (``diagnostic_msgs/DiagnosticStatus``) of a topic with several publishers
WARN = 1
OK = 0

#: one subscribed channel: namespace, kind (``state``, ``applied_cmd``, ``target``), full topic name
ChannelTopic = tuple[str, str, str]
#: what the ROS graph names an endpoint whose node it has not discovered yet (rmw's placeholders)
UNKNOWN_NODE = "(node not yet discovered)"


def node_label(namespace: str, name: str) -> str:
    """A publisher's node as ``/namespace/name`` from the ROS graph's endpoint info, or :data:`UNKNOWN_NODE` while
    the graph knows the endpoint but not its node (rmw's ``_NODE_NAME_UNKNOWN_``; the next report names it)."""
    if "_UNKNOWN_" in name or "_UNKNOWN_" in namespace:
        return UNKNOWN_NODE
    return f"{namespace.rstrip('/')}/{name}"


class PublisherGate:
    """Which channels' messages may be paired, from the publishers each one matched.

    Args:
        namespaces: the namespace of each channel (channels of one namespace are paired together).
        refuse: refuse a namespace's messages while any of its channels has more than one publisher; False:
            count only (:meth:`admit` always says yes).
    """

    def __init__(self, namespaces: Sequence[str], refuse: bool) -> None:
        self.namespaces = list(namespaces)
        self.refuse = bool(refuse)
        #: publishers matched by each channel's subscription (its matched-status events)
        self.counts = [0] * len(self.namespaces)
        #: messages refused per channel (only with ``refuse``)
        self.refused = [0] * len(self.namespaces)
        self._blocked: set[str] = set()

    def set_count(self, channel: int, publishers: int) -> None:
        """Channel ``channel``'s subscription now matches ``publishers`` publishers."""
        self.counts[channel] = max(0, int(publishers))
        self._blocked = {ns for ns, n in zip(self.namespaces, self.counts, strict=True) if n > 1}

    def blocked(self, namespace: str) -> bool:
        """Whether ``namespace`` has a channel with several publishers now."""
        return namespace in self._blocked

    def admit(self, channel: int) -> bool:
        """Whether a message of ``channel`` may be paired now; a refused one is counted."""
        if not self.refuse or self.namespaces[channel] not in self._blocked:
            return True
        self.refused[channel] += 1
        return False


def publisher_report(channels: Sequence[ChannelTopic], nodes: Mapping[str, Sequence[str]],
                     matched: Sequence[int] = (), refuse: bool = False,
                     refused: Sequence[int] = ()) -> tuple[int, list[str], dict[str, Any]]:
    """``(level, message parts, values)`` for the publishers of each subscribed channel.

    Args:
        channels: the subscribed channels, in order.
        nodes: topic -> the full names of the nodes publishing it, from the ROS graph (a node with two
            publishers on one topic appears twice).
        matched: per channel, the publishers its subscription matched (a publisher may be in the graph and not
            matched, e.g. incompatible QoS; or matched before the graph shows it); the larger of the two counts.
        refuse: whether such a channel's messages are refused (the message says so).
        refused: per channel, messages refused so far (reported only with ``refuse``).
    """
    values: dict[str, Any] = {}
    shared: list[str] = []
    for ch, (ns, kind, topic) in enumerate(channels):
        names = sorted(nodes.get(topic, ()))
        count = max(len(names), matched[ch] if ch < len(matched) else 0)
        values[f"{ns}/publisher_nodes/{kind}"] = ", ".join(names)
        if refuse:
            values[f"{ns}/refused/{kind}"] = int(refused[ch]) if ch < len(refused) else 0
        if count > 1:
            shared.append(f"{topic}: {', '.join(names) if names else '?'}" + (
                f" ({count} publishers)" if count != len(names) else ""))
    values["multiple_publishers"] = "; ".join(shared)
    if not shared:
        return OK, [], values
    what = ("not paired while so" if refuse else
            "their messages are paired as one robot's (pairing.refuse_multiple_publishers refuses them)")
    return WARN, [f"several publishers on {'; '.join(shared)}: {what}"], values


def state_command_report(topics: Sequence[tuple[str, str]], nodes: Mapping[str, Sequence[str]],
                         ) -> tuple[int, list[str], dict[str, Any]]:
    """The MPC's check: ``topics`` are ``(kind, topic)`` (``state``, ``cmd``) and ``nodes`` their publishers' node
    names from the ROS graph (the MPC's own ``cmd`` publisher included: two on ``cmd`` mean a second
    controller). WARN naming them when a topic has more than one; values ``multiple_publishers`` and
    ``publisher_nodes/<kind>``."""
    values: dict[str, Any] = {}
    shared = []
    for kind, topic in topics:
        names = sorted(nodes.get(topic, ()))
        values[f"publisher_nodes/{kind}"] = ", ".join(names)
        if len(names) > 1:
            shared.append(f"{topic}: {', '.join(names)}")
    values["multiple_publishers"] = "; ".join(shared)
    if not shared:
        return OK, [], values
    return WARN, [f"several publishers on {'; '.join(shared)}"], values
