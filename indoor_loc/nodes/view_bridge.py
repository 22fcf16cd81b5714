"""The view's ROS side of what a Foxglove client asks: publishing, service calls, parameters.

- **Client publishing** (``clientPublish``): a client channel (``cdr`` encoding, a ROS 2 type as
  ``pkg/msg/Name`` or ``pkg/Name``) becomes a reliable publisher on the same topic; its payloads are
  published as they are (serialised CDR). Foxglove's 3D panel *2D pose estimate* publishes
  ``geometry_msgs/PoseWithCovarianceStamped`` on the topic set in the panel: ``/<user>/initialpose``
  re-initialises that user's ``tll_pf``.
- **Services** (``services``): every service of the graph (parameter services excepted) is offered;
  a call is deserialised into the service's request type, called, and the response sent back
  serialised, or a ``serviceCallFailure`` after ``SERVICE_TIMEOUT_S``.
- **Parameters** (``parameters``, ``parametersSubscribe``): named ``/<ns>/<node>.<parameter>`` (as
  foxglove_bridge names them), read and set through each node's parameter services, updates from
  ``/parameter_events``.

Each request runs on its own short-lived thread that waits for the ROS futures (completed by the
node's executor), so the WebSocket server thread never blocks.
"""
from __future__ import annotations

import base64
import re
import threading
from typing import Any, Callable

from rclpy.node import Node
from rclpy.parameter import Parameter, parameter_value_to_python
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rclpy.serialization import deserialize_message, serialize_message

from indoor_loc.bag.schemas import service_definitions
from indoor_loc.errors import BagError
from indoor_loc.fgws.server import ClientChannel, FoxgloveServer, Service

SERVICE_TIMEOUT_S = 10.0
PARAM_TIMEOUT_S = 3.0
_PARAM_SERVICES = ("describe_parameters", "get_parameter_types", "get_parameters", "get_type_description",
                   "list_parameters", "set_parameters", "set_parameters_atomically")
_TYPE_RE = re.compile(r"^([A-Za-z][A-Za-z0-9_]*)/(?:msg/)?([A-Za-z][A-Za-z0-9_]*)$")


def ros_type(schema_name: str) -> str:
    """``pkg/Name`` or ``pkg/msg/Name`` -> ``pkg/msg/Name``; ValueError otherwise."""
    m = _TYPE_RE.match(schema_name)
    if m is None:
        raise ValueError(f"schema name {schema_name!r} is not a ROS 2 message type (pkg/msg/Name)")
    return f"{m.group(1)}/msg/{m.group(2)}"


def to_foxglove_parameter(name: str, value_msg: Any) -> dict[str, Any]:
    """A ``rcl_interfaces/ParameterValue`` as a Foxglove parameter (spec "Parameter Values")."""
    value = parameter_value_to_python(value_msg)
    if isinstance(value, (bytes, bytearray)) or (isinstance(value, list) and value and isinstance(value[0], bytes)):
        raw = bytes(value) if isinstance(value, (bytes, bytearray)) else b"".join(value)
        return {"name": name, "value": base64.b64encode(raw).decode(), "type": "byte_array"}
    if isinstance(value, float):
        return {"name": name, "value": value, "type": "float64"}
    if not isinstance(value, (str, bool, int)) and value is not None:
        value = list(value)
        if value and all(isinstance(v, float) for v in value):
            return {"name": name, "value": value, "type": "float64_array"}
    return {"name": name, "value": value}


def from_foxglove_parameter(param: dict[str, Any]) -> Parameter:
    """A Foxglove ``setParameters`` entry as an rclpy Parameter (its node prefix removed by the caller)."""
    value, kind = param.get("value"), param.get("type")
    if kind == "byte_array":
        value = [bytes([b]) for b in base64.b64decode(str(value))]
    elif kind == "float64":
        value = float(value)
    elif kind == "float64_array":
        value = [float(v) for v in value]
    if value is None:
        raise ValueError("unsetting a parameter is not supported")
    return Parameter(str(param["name"]), value=value)


def split_parameter_name(name: str) -> tuple[str, str]:
    """``/alice/tll_pf.n_particles`` -> (``/alice/tll_pf``, ``n_particles``)."""
    node, sep, param = name.partition(".")
    if not sep or not node.startswith("/") or not param:
        raise ValueError(f"parameter {name!r}: expected /<namespace>/<node>.<parameter>")
    return node, param


def _wait(future: Any, timeout_s: float) -> Any:
    done = threading.Event()
    future.add_done_callback(lambda _f: done.set())
    if not done.wait(timeout_s):
        future.cancel()
        raise TimeoutError(f"no answer within {timeout_s} s")
    return future.result()


class ViewBridge:
    """The server's Listener: client channels, service calls and parameters on a ROS node."""

    def __init__(self, node: Node, server: FoxgloveServer, msg_class: Callable[[str], Any],
                 srv_class: Callable[[str], Any]) -> None:
        self.node = node
        self.server = server
        self._msg_class = msg_class
        self._srv_class = srv_class
        self._lock = threading.Lock()
        self._publishers: dict[str, tuple[Any, int]] = {}      # topic -> (publisher, client channels on it)
        self._services: dict[str, int] = {}                    # ROS service name -> server service id
        self._service_types: dict[str, str] = {}
        self._clients: dict[tuple[str, str], Any] = {}
        self.published = 0

    # -- client publishing ----------------------------------------------------------------------------
    def on_client_advertise(self, channel: ClientChannel) -> str | None:
        try:
            type_name = ros_type(channel.schema_name)
            cls = self._msg_class(type_name)
        except (ImportError, AttributeError, ValueError) as err:
            return f"cannot publish {channel.schema_name!r}: {err}"
        with self._lock:
            pub, n = self._publishers.get(channel.topic, (None, 0))
            if pub is None:
                qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
                pub = self.node.create_publisher(cls, channel.topic, qos)
            elif pub.msg_type is not cls:
                return f"{channel.topic} is already published here as another type"
            self._publishers[channel.topic] = (pub, n + 1)
        self.node.get_logger().info(f"client publishes {channel.topic} [{type_name}]")
        return None

    def on_client_unadvertise(self, channel: ClientChannel) -> None:
        with self._lock:
            pub, n = self._publishers.get(channel.topic, (None, 0))
            if pub is None:
                return
            if n > 1:
                self._publishers[channel.topic] = (pub, n - 1)
                return
            del self._publishers[channel.topic]
        self.node.destroy_publisher(pub)

    def on_client_message(self, channel: ClientChannel, payload: bytes) -> str | None:
        with self._lock:
            pub, _ = self._publishers.get(channel.topic, (None, 0))
        if pub is None:
            return "not advertised"
        try:
            deserialize_message(payload, pub.msg_type)       # refuse what no subscriber could read
        except Exception as err:                            # noqa: BLE001 - rclpy raises plain errors on bad CDR
            return f"undecodable {pub.msg_type.__name__} payload: {err}"
        pub.publish(payload)
        self.published += 1
        return None

    # -- services -------------------------------------------------------------------------------------
    def poll_services(self, *, exclude: Callable[[str], bool]) -> None:
        """Offer every new service of the graph; withdraw the ones that went away."""
        seen = set()
        for name, types in self.node.get_service_names_and_types():
            if name.rsplit("/", 1)[-1] in _PARAM_SERVICES or exclude(name) or len(types) != 1:
                continue
            seen.add(name)
            if name in self._services:
                continue
            try:
                request, response = service_definitions(types[0])
                self._srv_class(types[0])
            except (BagError, ImportError, AttributeError, ValueError) as err:
                self.node.get_logger().warning(f"service {name} [{types[0]}] not offered: {err}", once=True)
                continue
            self._service_types[name] = types[0]
            self._services[name] = self.server.add_service(
                name, types[0], encoding="cdr", schema_encoding="ros2msg",
                request=(f"{types[0]}_Request", request), response=(f"{types[0]}_Response", response))
        for name in set(self._services) - seen:
            self.server.remove_service(self._services.pop(name))

    def on_service_call(self, service: Service, encoding: str, payload: bytes,
                        reply: Callable[[bytes | None, str], None]) -> None:
        threading.Thread(target=self._call, args=(service, payload, reply), daemon=True,
                         name="view-service-call").start()

    def _client(self, kind: str, name: str, srv_type: Any) -> Any:
        with self._lock:
            client = self._clients.get((kind, name))
            if client is None:
                client = self._clients[(kind, name)] = self.node.create_client(srv_type, name)
        return client

    def _call(self, service: Service, payload: bytes, reply: Callable[[bytes | None, str], None]) -> None:
        try:
            srv = self._srv_class(service.type)
            request = deserialize_message(payload, srv.Request)
            client = self._client("service", service.name, srv)
            if not client.wait_for_service(timeout_sec=SERVICE_TIMEOUT_S):
                raise TimeoutError(f"{service.name} is not available")
            response = _wait(client.call_async(request), SERVICE_TIMEOUT_S)
            reply(serialize_message(response), "")
        except Exception as err:                            # noqa: BLE001 - every failure goes back to the client
            reply(None, f"{service.name}: {type(err).__name__}: {err}")

    # -- parameters -------------------------------------------------------------------------------------
    def on_get_parameters(self, names: list[str], reply: Callable[[list[dict[str, Any]]], None]) -> None:
        threading.Thread(target=lambda: reply(self._get(names)), daemon=True, name="view-get-params").start()

    def on_set_parameters(self, params: list[dict[str, Any]], reply: Callable[[list[dict[str, Any]]], None]) -> None:
        threading.Thread(target=lambda: reply(self._set(params)), daemon=True, name="view-set-params").start()

    def _nodes(self) -> list[str]:
        me = self.node.get_fully_qualified_name()
        out = []
        for name, ns in self.node.get_node_names_and_namespaces():
            fqn = f"{ns.rstrip('/')}/{name}"
            if fqn != me and not name.startswith("_"):
                out.append(fqn)
        return sorted(set(out))

    def _get(self, names: list[str]) -> list[dict[str, Any]]:
        from rcl_interfaces.srv import GetParameters, ListParameters
        wanted: dict[str, list[str]] = {}
        if names:
            for n in names:
                try:
                    node, param = split_parameter_name(n)
                except ValueError:
                    continue
                wanted.setdefault(node, []).append(param)
        else:
            wanted = {node: [] for node in self._nodes()}
        out: list[dict[str, Any]] = []
        for node, params in wanted.items():
            try:
                if not params:
                    lister = self._client("list", f"{node}/list_parameters", ListParameters)
                    if not lister.wait_for_service(timeout_sec=PARAM_TIMEOUT_S):
                        continue
                    params = list(_wait(lister.call_async(ListParameters.Request()), PARAM_TIMEOUT_S).result.names)
                getter = self._client("get", f"{node}/get_parameters", GetParameters)
                if not params or not getter.wait_for_service(timeout_sec=PARAM_TIMEOUT_S):
                    continue
                values = _wait(getter.call_async(GetParameters.Request(names=params)), PARAM_TIMEOUT_S).values
            except TimeoutError:
                continue
            out += [to_foxglove_parameter(f"{node}.{p}", v) for p, v in zip(params, values)]
        return out

    def _set(self, params: list[dict[str, Any]]) -> list[dict[str, Any]]:
        from rcl_interfaces.srv import SetParameters
        by_node: dict[str, list[Any]] = {}
        for p in params:
            try:
                node, name = split_parameter_name(str(p["name"]))
                by_node.setdefault(node, []).append(from_foxglove_parameter({**p, "name": name}).to_parameter_msg())
            except (KeyError, ValueError, TypeError) as err:
                self.node.get_logger().warning(f"setParameters: {p!r} refused: {err}")
        for node, msgs in by_node.items():
            setter = self._client("set", f"{node}/set_parameters", SetParameters)
            try:
                if setter.wait_for_service(timeout_sec=PARAM_TIMEOUT_S):
                    results = _wait(setter.call_async(SetParameters.Request(parameters=msgs)), PARAM_TIMEOUT_S).results
                    for m, r in zip(msgs, results):
                        if not r.successful:
                            self.node.get_logger().warning(f"setParameters {node}.{m.name}: {r.reason}")
            except TimeoutError:
                self.node.get_logger().warning(f"setParameters: {node} did not answer")
        return self._get([str(p["name"]) for p in params])

    def on_parameter_event(self, event: Any) -> None:
        """``/parameter_events`` -> ``parameterValues`` to the clients subscribed to those names."""
        node = event.node
        changed = [to_foxglove_parameter(f"{node}.{p.name}", p.value)
                   for p in list(event.new_parameters) + list(event.changed_parameters)]
        if changed:
            self.server.publish_parameter_values(changed)
