"""ROS names of the topics: namespaces and absolute topic names (the one copy every node and bag tool uses)."""

from __future__ import annotations


def normalize_namespace(namespace: str) -> str:
    """``"friction"``, ``" /friction/ "`` -> ``"/friction"``; ``""`` / ``"/"`` -> ``"/"``."""
    return "/" + namespace.strip().strip("/")


def join_topic(namespace: str, name: str) -> str:
    """Absolute topic name: ``join_topic("/friction", "state") == "/friction/state"``, ``join_topic("/", "state")
    == "/state"``; absolute names pass unchanged."""
    if name.startswith("/"):
        return name
    return f"{normalize_namespace(namespace).rstrip('/')}/{name}"
