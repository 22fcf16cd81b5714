"""``--consumers TOPIC=NODE[,NODE...]``: the nodes a player waits for on each topic, by name.

A subscriber count cannot tell a consuming node from an observer: the live view, a recorder or an
``ros2 topic echo`` subscribe to every topic, so "one subscriber" is met before ``imu_node`` has
matched and the node misses the first messages (271 IMU messages of a walker in the demo with the
view). Naming the consumers waits for them: a topic is ready when each named node has a
subscription on it in the ROS graph *and* the publisher has matched every subscription the graph
shows (so the named node's is matched too, not only discovered).

``TOPIC`` is a full name (``/alice/imu/data_raw``) or a name relative to any namespace
(``imu/data_raw``: every walker's); ``NODE`` is a node name (``imu_node``: in any namespace, which for
a namespaced topic is that user's node) or a fully qualified one (``/backend_node``).
"""
from __future__ import annotations

import re
from typing import Iterable

from indoor_loc.errors import ConfigError

_NAME = re.compile(r"^/?[A-Za-z_][A-Za-z0-9_/]*$")


class Consumers:
    def __init__(self, items: Iterable[str] = ()) -> None:
        self.per_topic: dict[str, tuple[str, ...]] = {}
        for item in items:
            topic, sep, nodes = str(item).partition("=")
            names = tuple(n for n in nodes.split(",") if n)
            if not sep or not topic.strip("/") or not names or not all(_NAME.match(n) for n in (topic, *names)):
                raise ConfigError(f"play.consumers: expected TOPIC=NODE[,NODE...], got {item!r}")
            key = topic if topic.startswith("/") else topic.strip("/")
            self.per_topic[key] = self.per_topic.get(key, ()) + names

    def __bool__(self) -> bool:
        return bool(self.per_topic)

    def __call__(self, topic: str) -> tuple[str, ...]:
        """The consumers named for a played topic (its full name)."""
        out: tuple[str, ...] = ()
        for name, nodes in self.per_topic.items():
            if name == topic or (not name.startswith("/") and topic.endswith("/" + name)):
                out += nodes
        return out

    def unused(self, topics: list[str]) -> list[str]:
        return [name for name in self.per_topic if not any(
            name == t or (not name.startswith("/") and t.endswith("/" + name)) for t in topics)]


def missing_consumers(wanted: tuple[str, ...], subscribers: list[tuple[str, str]]) -> list[str]:
    """Which of ``wanted`` have no subscription among ``subscribers`` ((node name, namespace) pairs)."""
    full = {f"{ns.rstrip('/')}/{name}" for name, ns in subscribers}
    bare = {name for name, _ in subscribers}
    return [w for w in wanted if (w not in full if w.startswith("/") else w not in bare)]


#: nodes that subscribe to every topic and consume none (the live view, the recorder)
OBSERVERS = frozenset({"view", "recorder"})


def met_by_observers(want: int, subscribers: list[tuple[str, str]]) -> bool:
    """Whether a subscriber count of ``want`` is reached only thanks to observers: the wait would
    end before any consuming node has subscribed."""
    consuming = [n for n, _ in subscribers if n not in OBSERVERS]
    return 0 < want <= len(subscribers) and len(consuming) < want
