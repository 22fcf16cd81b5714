"""Live view: every ROS topic of a running system, served over the Foxglove WebSocket protocol.

Both subprotocol names are accepted (``foxglove.websocket.v1``: Lichtblick, ``@foxglove/ws-protocol``,
Foxglove before the SDK; ``foxglove.sdk.v1``: current Foxglove), see :mod:`indoor_loc.fgws.server`.

``indoor-loc view [--port 8765] [--building building.geojson]`` (or ``ros2 run indoor_loc indoor_loc_view``)
then, in Foxglove: *Open connection* -> *Foxglove WebSocket* -> ``ws://localhost:8765``, and
*Import layout* ``indoor_loc/data/foxglove_layout.json`` (the building, every user's estimates,
particles and ground truth in a 3D panel; errors and diagnostics beside it).

- Serialised messages are forwarded as they are (``raw=True`` subscriptions, ``cdr`` encoding with
  the ``ros2msg`` schema of the type), so Foxglove decodes them like a rosbridge or a bag: no
  conversion here, and any message type works.
- Topics are discovered by polling the ROS graph (``--poll`` s, on the wall clock so it also runs
  before a player starts ``/clock``); each is subscribed with a QoS that matches its publishers
  (best effort if any is, transient_local if all are) and advertised to clients as a channel.
- Latched topics (maps, ground truth, smoothed paths) are re-sent every ``--latch-period`` s, so a
  client that connects late still sees them.
- ``--building`` adds the building's walls, graph and rooms (``/view/building`` MarkerArray) from a
  GeoJSON file (``indoor-loc sim`` writes one; the sample building ships with the package).
- ``/clock`` (from a player) is broadcast as the server time, so Foxglove shows bag time.
- Two-way (:mod:`indoor_loc.nodes.view_bridge`): clients may publish (Foxglove's *2D pose estimate*
  on ``/<user>/initialpose``), call every service of the graph (``/<user>/tll_pf/global_localization``)
  and read / set / follow every node's parameters.
"""
from __future__ import annotations

import argparse
import re
import sys
import threading
from pathlib import Path
from typing import Any, Callable

import rclpy
from rclpy.clock import Clock, ClockType
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy

from indoor_loc.bag.schemas import message_definition
from indoor_loc.contract import msg_class
from indoor_loc.errors import BagError, ConfigError
from indoor_loc.fgws.server import SUBPROTOCOLS, FoxgloveServer
from indoor_loc.nodes.help import run_option_node
from indoor_loc.nodes.view_bridge import ViewBridge
from indoor_loc.nodes.recorder_node import is_hidden, subscription_qos

NODE_NAME = "view"
BUILDING_TOPIC = "/view/building"
DEFAULT_EXCLUDE = r"^/(rosout|parameter_events)$"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--port", type=int, default=8765, help="WebSocket port (default 8765; 0 = any free port)")
    parser.add_argument("--host", default="127.0.0.1", help="address to bind (default 127.0.0.1; 0.0.0.0 = all)")
    parser.add_argument("--building", type=Path, default=None,
                        help="building GeoJSON to show as /view/building (e.g. OUT/sim/building.geojson)")
    parser.add_argument("--poll", type=float, default=1.0, help="ROS graph polling period, s (default 1.0)")
    parser.add_argument("--latch-period", type=float, default=2.0,
                        help="re-send the last message of latched topics this often, s (default 2.0)")
    parser.add_argument("--exclude", default=DEFAULT_EXCLUDE, help=f"regex of topics not served (default {DEFAULT_EXCLUDE!r})")
    parser.add_argument("--write-layout", type=Path, metavar="FILE",
                        help="write a Foxglove/Lichtblick layout for --users to FILE and exit")
    parser.add_argument("--users", default="alice,bob,carol", help="users of --write-layout, comma-separated")


class ViewNode(Node):
    """Subscribes (raw) to every topic and logs each message on a Foxglove channel of the same name."""

    def __init__(self, server: FoxgloveServer, *, poll_s: float = 1.0, latch_period_s: float = 2.0, exclude: str = "",
                 building: Path | None = None, **node_kwargs: Any) -> None:
        super().__init__(NODE_NAME, **node_kwargs)
        self.server = server
        self._exclude = re.compile(exclude) if exclude else None
        self._subs: dict[str, Any] = {}
        self._channels: dict[str, int] = {}
        self._latched: dict[str, bytes] = {}
        self._lock = threading.Lock()
        self._reported: set[tuple[str, str]] = set()
        self.forwarded = 0
        self.bridge = ViewBridge(self, server, msg_class, msg_class)
        server.listener = self.bridge
        from rcl_interfaces.msg import ParameterEvent
        self.create_subscription(ParameterEvent, "/parameter_events", self.bridge.on_parameter_event, 100)
        steady = Clock(clock_type=ClockType.STEADY_TIME)
        if building is not None:
            self._add_building(building)
        self._poll()
        self.create_timer(poll_s, self._poll, clock=steady)
        self.create_timer(latch_period_s, self._resend_latched, clock=steady)

    def _report(self, topic: str, text: str, *, warn: bool = False) -> None:
        if (topic, text) not in self._reported:
            self._reported.add((topic, text))
            (self.get_logger().warning if warn else self.get_logger().info)(f"{topic}: {text}")

    def _channel(self, topic: str, type_name: str) -> int:
        ch = self.server.add_channel(topic, encoding="cdr", schema_name=type_name,
                                     schema=message_definition(type_name), schema_encoding="ros2msg")
        self._channels[topic] = ch
        return ch

    def _add_building(self, path: Path) -> None:
        from rclpy.serialization import serialize_message

        from indoor_loc.sim.building import load_building
        from indoor_loc.sim.write import building_markers
        arr = building_markers(load_building(path), self.get_clock().now().nanoseconds)
        self._channel(BUILDING_TOPIC, "visualization_msgs/msg/MarkerArray")
        self._latched[BUILDING_TOPIC] = serialize_message(arr)
        self._resend_latched()

    def _excluded(self, name: str) -> bool:
        return is_hidden(name) or (self._exclude is not None and self._exclude.search(name) is not None)

    def _poll(self) -> None:
        self.bridge.poll_services(exclude=self._excluded)
        for topic, names in sorted(self.get_topic_names_and_types()):
            if topic in self._subs or topic in self._channels:
                continue
            if self._excluded(topic):
                continue
            if len(names) != 1:
                self._report(topic, f"published with several types {names}; not served", warn=True)
                continue
            try:
                cls = msg_class(names[0])
            except (ImportError, AttributeError, ValueError):
                self._report(topic, f"type {names[0]} is not installed here; not served", warn=True)
                continue
            try:
                message_definition(names[0])
            except BagError as err:
                self._report(topic, f"{err}; not served", warn=True)
                continue
            profiles = [i.qos_profile for i in self.get_publishers_info_by_topic(topic)]
            if not profiles:
                continue
            qos = subscription_qos(profiles)
            latched = qos.durability == DurabilityPolicy.TRANSIENT_LOCAL
            ch = self._channel(topic, names[0])
            self._subs[topic] = self.create_subscription(cls, topic, self._callback(topic, ch, latched), qos,
                                                         raw=True)
            self._report(topic, f"serving [{names[0]}]{' (latched)' if latched else ''}")

    def _callback(self, topic: str, channel: int, latched: bool) -> Callable[[bytes], None]:
        clock_topic = topic == "/clock"

        def cb(data: bytes) -> None:
            now = self.get_clock().now().nanoseconds
            self.server.log(channel, data, now)
            self.forwarded += 1
            if latched:
                with self._lock:
                    self._latched[topic] = data
            if clock_topic:
                self.server.broadcast_time(now)
        return cb

    def _resend_latched(self) -> None:
        with self._lock:
            items = list(self._latched.items())
        now = self.get_clock().now().nanoseconds
        for topic, data in items:
            self.server.log(self._channels[topic], data, now)


CAPABILITIES = ("time", "clientPublish", "services", "parameters", "parametersSubscribe")


def run(options: argparse.Namespace, ros_args: list[str] | None = None) -> int:
    if not 0 <= options.port <= 65535:
        raise ConfigError(f"view.port: expected 0..65535, got {options.port}")
    for name in ("poll", "latch_period"):
        if not getattr(options, name) > 0:
            raise ConfigError(f"view.{name}: expected > 0 s, got {getattr(options, name)}")
    try:
        re.compile(options.exclude)
    except re.error as err:
        raise ConfigError(f"view.exclude: not a regular expression: {err}") from err
    if options.building is not None and not options.building.is_file():
        raise ConfigError(f"view.building: {options.building} does not exist")
    if options.write_layout is not None:
        from indoor_loc.foxglove_layout import write_layout
        users = [u for u in options.users.split(",") if u]
        if not users or not all(re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", u) for u in users):
            raise ConfigError(f"view.users: expected comma-separated ROS names, got {options.users!r}")
        print(f"[view] layout for {', '.join(users)}: {write_layout(options.write_layout, users)}")
        return 0
    rclpy.init(args=ros_args if ros_args is not None else sys.argv[:1])
    server = FoxgloveServer("indoor_loc", host=options.host, port=options.port, capabilities=CAPABILITIES)
    try:
        server.start()
    except OSError as err:
        rclpy.try_shutdown()
        raise ConfigError(f"view: cannot serve on {options.host}:{options.port}: {err}") from err
    except ImportError as err:           # websockets.asyncio is websockets >= 13 (Ubuntu 24.04's apt has 10.4)
        rclpy.try_shutdown()
        raise ConfigError(f"view: needs the websockets package >= 13 (pip install 'websockets>=13'): {err}") from err
    print(f"[view] Foxglove WebSocket server on ws://{options.host}:{server.port} "
          f"(subprotocols {' and '.join(SUBPROTOCOLS)}; Foxglove or Lichtblick: Open connection -> "
          f"Foxglove WebSocket)", flush=True)
    node = None
    try:
        node = ViewNode(server, poll_s=options.poll, latch_period_s=options.latch_period, exclude=options.exclude,
                        building=options.building)
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        forwarded = node.forwarded if node is not None else 0
        if node is not None:
            node.destroy_node()
        server.stop()
        rclpy.try_shutdown()
    lost = {k: v for k, v in server.counts.items() if v}
    print(f"[view] forwarded {forwarded} messages"
          + (f"; client requests refused or lost: {lost}" if lost else ""), file=sys.stderr)
    return 0


def main(args: list[str] | None = None) -> int:
    """``indoor_loc_view`` executable: same options as ``indoor-loc view``, plus ``--ros-args ...``."""
    return run_option_node("indoor_loc_view", __doc__.splitlines()[0], add_arguments, run, args)


if __name__ == "__main__":
    sys.exit(main())
