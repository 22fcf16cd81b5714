"""A Foxglove WebSocket protocol (v1) server: channels, client publishing, services, parameters, time.

Spec: https://github.com/foxglove/ws-protocol/blob/main/docs/spec.md. Both subprotocol names are
accepted: ``foxglove.websocket.v1`` (the published spec; ``@foxglove/ws-protocol``, Lichtblick,
Foxglove before the SDK) and ``foxglove.sdk.v1`` (the same protocol under the name the Foxglove SDK
and foxglove_bridge >= 3 use). The foxglove-sdk Python server refuses the former (HTTP 400), which is
why the view serves the protocol itself over ``websockets``.

No rclpy here: the server knows channels, services and parameters as plain data; a ``Listener``
(the view node) turns client publishing, service calls and parameter requests into ROS calls.

Threading: the WebSocket server runs an asyncio loop in its own thread. ``add_channel``, ``log``,
``broadcast_time``, ``add_service`` and ``publish_parameter_values`` may be called from any thread.
A channel is registered *before* its advertisement is queued, and channels are never re-numbered,
so a client that subscribes right after an advertisement always finds the channel (no "unknown
channel" answer for a channel the client was just told about). Listener callbacks run on the
server's thread and must not block; they answer through the ``reply`` callable they are given,
from any thread.
"""
from __future__ import annotations

import asyncio
import json
import struct
import threading
import time
from collections import Counter
from dataclasses import dataclass, field
from typing import Any, Callable, Protocol

SUBPROTOCOLS = ("foxglove.websocket.v1", "foxglove.sdk.v1")

# binary opcodes (spec "Binary messages")
OP_MESSAGE_DATA = 0x01
OP_TIME = 0x02
OP_SERVICE_CALL_RESPONSE = 0x03
OP_CLIENT_MESSAGE_DATA = 0x01
OP_SERVICE_CALL_REQUEST = 0x02

STATUS_INFO, STATUS_WARNING, STATUS_ERROR = 0, 1, 2

#: frames queued per client before the oldest message data is dropped (a slow client never stalls ROS)
CLIENT_QUEUE = 4096


@dataclass(frozen=True)
class Channel:
    """A server channel (one ROS topic)."""
    id: int
    topic: str
    encoding: str
    schema_name: str
    schema: str
    schema_encoding: str

    def advertisement(self) -> dict[str, Any]:
        return {"id": self.id, "topic": self.topic, "encoding": self.encoding, "schemaName": self.schema_name,
                "schema": self.schema, "schemaEncoding": self.schema_encoding}


@dataclass(frozen=True)
class ClientChannel:
    """A channel a client advertised to publish on (``clientPublish``)."""
    client_id: int
    id: int
    topic: str
    encoding: str
    schema_name: str


@dataclass(frozen=True)
class Service:
    """A service clients may call; request/response schemas in ``schema_encoding``."""
    id: int
    name: str
    type: str
    encoding: str
    request_schema_name: str
    request_schema: str
    response_schema_name: str
    response_schema: str
    schema_encoding: str

    def advertisement(self) -> dict[str, Any]:
        def part(name: str, schema: str) -> dict[str, str]:
            return {"encoding": self.encoding, "schemaName": name, "schemaEncoding": self.schema_encoding,
                    "schema": schema}
        # request/response objects (current spec) and the older requestSchema/responseSchema strings
        return {"id": self.id, "name": self.name, "type": self.type,
                "request": part(self.request_schema_name, self.request_schema),
                "response": part(self.response_schema_name, self.response_schema),
                "requestSchema": self.request_schema, "responseSchema": self.response_schema}


class Listener(Protocol):
    """What the server asks of its owner; every method runs on the server thread and must not block."""

    def on_client_advertise(self, channel: ClientChannel) -> str | None:
        """Return an error text to refuse the channel, or None."""

    def on_client_unadvertise(self, channel: ClientChannel) -> None: ...

    def on_client_message(self, channel: ClientChannel, payload: bytes) -> str | None:
        """Return an error text when the payload could not be published, or None."""

    def on_service_call(self, service: Service, encoding: str, payload: bytes,
                        reply: Callable[[bytes | None, str], None]) -> None:
        """Call ``reply(response_payload, "")`` or ``reply(None, error_text)`` once, from any thread."""

    def on_get_parameters(self, names: list[str], reply: Callable[[list[dict[str, Any]]], None]) -> None: ...

    def on_set_parameters(self, params: list[dict[str, Any]], reply: Callable[[list[dict[str, Any]]], None]) -> None:
        ...


@dataclass
class _Client:
    id: int
    ws: Any
    queue: asyncio.Queue = field(default_factory=lambda: asyncio.Queue(CLIENT_QUEUE))
    subs: dict[int, int] = field(default_factory=dict)          # subscription id -> channel id
    by_channel: dict[int, int] = field(default_factory=dict)    # channel id -> subscription id
    channels: dict[int, ClientChannel] = field(default_factory=dict)
    param_subs: set[str] = field(default_factory=set)
    param_subs_all: bool = False


def message_data_frame(sub_id: int, log_time_ns: int, payload: bytes) -> bytes:
    return struct.pack("<BIQ", OP_MESSAGE_DATA, sub_id, log_time_ns & 0xFFFFFFFFFFFFFFFF) + payload


def time_frame(ns: int) -> bytes:
    return struct.pack("<BQ", OP_TIME, ns & 0xFFFFFFFFFFFFFFFF)


def service_response_frame(service_id: int, call_id: int, encoding: str, payload: bytes) -> bytes:
    enc = encoding.encode()
    return struct.pack("<BIII", OP_SERVICE_CALL_RESPONSE, service_id, call_id, len(enc)) + enc + payload


class FoxgloveServer:
    """``FoxgloveServer(name, host=..., port=0).start()`` then ``add_channel`` / ``log``; ``stop()``.

    ``counts`` (a Counter) tallies what clients did wrong or lost, by reason (``unknown_channel``,
    ``bad_request``, ``dropped_slow_client``, ...), and ``sent`` the message frames queued."""

    def __init__(self, name: str, *, host: str = "127.0.0.1", port: int = 8765, listener: Listener | None = None,
                 capabilities: tuple[str, ...] = ("time",), supported_encodings: tuple[str, ...] = ("cdr",)) -> None:
        self.name = name
        self.host = host
        self.port = port
        self.listener = listener
        self.capabilities = list(capabilities)
        self.supported_encodings = list(supported_encodings)
        self.session_id = str(time.time_ns())
        self.counts: Counter[str] = Counter()
        self.sent = 0
        self._lock = threading.Lock()
        self._channels: dict[int, Channel] = {}
        self._services: dict[int, Service] = {}
        self._clients: dict[int, _Client] = {}
        self._next_channel = 1
        self._next_service = 1
        self._next_client = 1
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self._stop: asyncio.Future | None = None
        self._ready = threading.Event()
        self._error: BaseException | None = None

    # -- lifecycle ---------------------------------------------------------------------------------
    def start(self, timeout_s: float = 10.0) -> int:
        """Bind and serve in a background thread; return the bound port."""
        self._thread = threading.Thread(target=self._run, name="foxglove-ws", daemon=True)
        self._thread.start()
        if not self._ready.wait(timeout_s):
            raise OSError(f"Foxglove WebSocket server did not start within {timeout_s} s")
        if self._error is not None:
            raise self._error
        return self.port

    def stop(self) -> None:
        loop, stop = self._loop, self._stop
        if loop is not None and stop is not None and not loop.is_closed():
            loop.call_soon_threadsafe(lambda: stop.done() or stop.set_result(None))
        if self._thread is not None:
            self._thread.join(timeout=5.0)

    def _run(self) -> None:
        try:
            asyncio.run(self._main())
        except BaseException as err:      # noqa: BLE001 - reported to start()
            self._error = err
            self._ready.set()

    async def _main(self) -> None:
        from websockets.asyncio.server import serve
        self._loop = asyncio.get_running_loop()
        self._stop = self._loop.create_future()
        async with serve(self._session, self.host, self.port, subprotocols=list(SUBPROTOCOLS),  # type: ignore[arg-type]
                         compression=None, max_size=64 * 2**20, ping_interval=None) as server:
            self.port = next(iter(server.sockets)).getsockname()[1]
            self._ready.set()
            await self._stop

    # -- what the owner offers ----------------------------------------------------------------------
    def add_channel(self, topic: str, *, encoding: str, schema_name: str, schema: str, schema_encoding: str) -> int:
        with self._lock:
            ch = Channel(self._next_channel, topic, encoding, schema_name, schema, schema_encoding)
            self._next_channel += 1
            self._channels[ch.id] = ch
            clients = list(self._clients.values())
        text = json.dumps({"op": "advertise", "channels": [ch.advertisement()]})
        for c in clients:
            self._push(c, text)
        return ch.id

    def remove_channel(self, channel_id: int) -> None:
        with self._lock:
            if self._channels.pop(channel_id, None) is None:
                return
            clients = list(self._clients.values())
            for c in clients:
                sub = c.by_channel.pop(channel_id, None)
                if sub is not None:
                    c.subs.pop(sub, None)
        text = json.dumps({"op": "unadvertise", "channelIds": [channel_id]})
        for c in clients:
            self._push(c, text)

    def add_service(self, name: str, type_name: str, *, encoding: str, request: tuple[str, str],
                    response: tuple[str, str], schema_encoding: str) -> int:
        """``request``/``response``: (schema name, schema text)."""
        with self._lock:
            svc = Service(self._next_service, name, type_name, encoding, request[0], request[1], response[0],
                          response[1], schema_encoding)
            self._next_service += 1
            self._services[svc.id] = svc
            clients = list(self._clients.values())
        text = json.dumps({"op": "advertiseServices", "services": [svc.advertisement()]})
        for c in clients:
            self._push(c, text)
        return svc.id

    def remove_service(self, service_id: int) -> None:
        with self._lock:
            if self._services.pop(service_id, None) is None:
                return
            clients = list(self._clients.values())
        text = json.dumps({"op": "unadvertiseServices", "serviceIds": [service_id]})
        for c in clients:
            self._push(c, text)

    def channels(self) -> list[Channel]:
        with self._lock:
            return list(self._channels.values())

    def client_count(self) -> int:
        with self._lock:
            return len(self._clients)

    def log(self, channel_id: int, payload: bytes, log_time_ns: int) -> None:
        """Send a message to every client subscribed to the channel."""
        with self._lock:
            targets = [(c, c.by_channel[channel_id]) for c in self._clients.values() if channel_id in c.by_channel]
        for c, sub in targets:
            self._push(c, message_data_frame(sub, log_time_ns, payload), droppable=True)
            self.sent += 1

    def broadcast_time(self, ns: int) -> None:
        if "time" not in self.capabilities:
            return
        with self._lock:
            clients = list(self._clients.values())
        frame = time_frame(ns)
        for c in clients:
            self._push(c, frame, droppable=True)

    def publish_parameter_values(self, params: list[dict[str, Any]]) -> None:
        """Tell clients subscribed to these parameters (``parametersSubscribe``) their new values."""
        with self._lock:
            clients = list(self._clients.values())
        for c in clients:
            mine = [p for p in params if c.param_subs_all or p["name"] in c.param_subs]
            if mine:
                self._push(c, json.dumps({"op": "parameterValues", "parameters": mine}))

    # -- per client ---------------------------------------------------------------------------------
    def _push(self, client: _Client, frame: str | bytes, *, droppable: bool = False) -> None:
        loop = self._loop
        if loop is None or loop.is_closed():
            return

        def put() -> None:
            try:
                client.queue.put_nowait(frame)
            except asyncio.QueueFull:
                if not droppable:              # control messages must arrive: make room for them
                    client.queue.get_nowait()
                    client.queue.put_nowait(frame)
                self.counts["dropped_slow_client"] += 1
        try:
            loop.call_soon_threadsafe(put)
        except RuntimeError:                   # loop closed while stopping
            pass

    def _status(self, client: _Client, level: int, message: str, reason: str) -> None:
        self.counts[reason] += 1
        self._push(client, json.dumps({"op": "status", "level": level, "message": message}))

    async def _writer(self, client: _Client) -> None:
        while True:
            frame = await client.queue.get()
            await client.ws.send(frame)

    async def _session(self, ws: Any) -> None:
        from websockets.exceptions import ConnectionClosed
        with self._lock:
            client = _Client(self._next_client, ws)
            self._next_client += 1
            # the greeting and the current channels go out under the lock, so no add_channel is
            # advertised to this client twice or missed
            info: dict[str, Any] = {"op": "serverInfo", "name": self.name, "capabilities": self.capabilities,
                                    "metadata": {}, "sessionId": self.session_id}
            if {"clientPublish", "services"} & set(self.capabilities):
                info["supportedEncodings"] = self.supported_encodings
            client.queue.put_nowait(json.dumps(info))
            client.queue.put_nowait(json.dumps({"op": "advertise",
                                                "channels": [c.advertisement() for c in self._channels.values()]}))
            if "services" in self.capabilities:
                client.queue.put_nowait(json.dumps({"op": "advertiseServices",
                                                    "services": [s.advertisement() for s in self._services.values()]}))
            self._clients[client.id] = client
        writer = asyncio.ensure_future(self._writer(client))
        try:
            async for frame in ws:
                try:
                    if isinstance(frame, str):
                        self._on_text(client, frame)
                    else:
                        self._on_binary(client, bytes(frame))
                except (ValueError, KeyError, TypeError, struct.error) as err:
                    self._status(client, STATUS_ERROR, f"bad request: {type(err).__name__}: {err}", "bad_request")
        except ConnectionClosed:
            pass
        finally:
            writer.cancel()
            with self._lock:
                self._clients.pop(client.id, None)
            if self.listener is not None:
                for ch in client.channels.values():
                    self.listener.on_client_unadvertise(ch)

    def _on_text(self, client: _Client, text: str) -> None:
        doc = json.loads(text)
        if not isinstance(doc, dict):
            raise ValueError("a JSON message must be an object")
        op = doc.get("op")
        if op == "subscribe":
            for sub in doc["subscriptions"]:
                sub_id, ch_id = int(sub["id"]), int(sub["channelId"])
                with self._lock:
                    known = ch_id in self._channels
                    reused = sub_id in client.subs
                    twice = ch_id in client.by_channel
                    if known and not reused and not twice:
                        client.subs[sub_id] = ch_id
                        client.by_channel[ch_id] = sub_id
                if not known:
                    self._status(client, STATUS_WARNING, f"Unknown channel ID {ch_id}", "unknown_channel")
                elif reused:
                    self._status(client, STATUS_ERROR, f"subscription ID {sub_id} is already in use", "bad_request")
                elif twice:
                    self._status(client, STATUS_WARNING, f"already subscribed to channel {ch_id}", "bad_request")
        elif op == "unsubscribe":
            with self._lock:
                for sub_id in doc["subscriptionIds"]:
                    ch_id = client.subs.pop(int(sub_id), None)
                    if ch_id is not None:
                        client.by_channel.pop(ch_id, None)
        elif op == "advertise":
            self._client_advertise(client, doc["channels"])
        elif op == "unadvertise":
            for ch_id in doc["channelIds"]:
                ch = client.channels.pop(int(ch_id), None)
                if ch is not None and self.listener is not None:
                    self.listener.on_client_unadvertise(ch)
        elif op in ("getParameters", "setParameters"):
            self._parameters(client, op, doc)
        elif op == "subscribeParameterUpdates":
            self._require(client, "parametersSubscribe")
            names = [str(n) for n in doc.get("parameterNames", [])]
            if names:
                client.param_subs.update(names)
            else:
                client.param_subs_all = True
        elif op == "unsubscribeParameterUpdates":
            names = [str(n) for n in doc.get("parameterNames", [])]
            if names:
                client.param_subs.difference_update(names)
            else:
                client.param_subs.clear()
                client.param_subs_all = False
        else:
            self._status(client, STATUS_ERROR, f"unsupported operation {op!r}", "unsupported_op")

    def _require(self, client: _Client, capability: str) -> None:
        if capability not in self.capabilities:
            raise ValueError(f"the server does not offer {capability!r}")

    def _client_advertise(self, client: _Client, channels: list[dict[str, Any]]) -> None:
        self._require(client, "clientPublish")
        for spec in channels:
            ch = ClientChannel(client.id, int(spec["id"]), str(spec["topic"]), str(spec["encoding"]),
                               str(spec["schemaName"]))
            if ch.encoding not in self.supported_encodings:
                self._status(client, STATUS_ERROR, f"client channel {ch.topic}: encoding {ch.encoding!r} is not "
                             f"supported (supported: {self.supported_encodings})", "unsupported_encoding")
                continue
            error = self.listener.on_client_advertise(ch) if self.listener is not None else "no listener"
            if error:
                self._status(client, STATUS_ERROR, f"client channel {ch.topic}: {error}", "client_channel_refused")
                continue
            client.channels[ch.id] = ch

    def _on_binary(self, client: _Client, frame: bytes) -> None:
        if not frame:
            raise ValueError("empty binary message")
        op = frame[0]
        if op == OP_CLIENT_MESSAGE_DATA:
            ch_id, = struct.unpack_from("<I", frame, 1)
            ch = client.channels.get(ch_id)
            if ch is None:
                self._status(client, STATUS_ERROR, f"client channel {ch_id} was not advertised", "unknown_client_channel")
                return
            error = self.listener.on_client_message(ch, frame[5:]) if self.listener is not None else "no listener"
            if error:
                self._status(client, STATUS_ERROR, f"{ch.topic}: {error}", "client_message_refused")
        elif op == OP_SERVICE_CALL_REQUEST:
            self._require(client, "services")
            service_id, call_id, enc_len = struct.unpack_from("<III", frame, 1)
            encoding = frame[13:13 + enc_len].decode()
            payload = frame[13 + enc_len:]
            with self._lock:
                svc = self._services.get(service_id)
            if svc is None or self.listener is None:
                self._call_failed(client, service_id, call_id, f"unknown service {service_id}")
                return
            if encoding not in self.supported_encodings:
                self._call_failed(client, service_id, call_id, f"encoding {encoding!r} is not supported")
                return

            def reply(response: bytes | None, error: str) -> None:
                if response is None:
                    self._call_failed(client, service_id, call_id, error or "service call failed")
                else:
                    self._push(client, service_response_frame(service_id, call_id, encoding, response))
            self.listener.on_service_call(svc, encoding, payload, reply)
        else:
            self._status(client, STATUS_ERROR, f"unsupported binary opcode {op}", "unsupported_op")

    def _call_failed(self, client: _Client, service_id: int, call_id: int, message: str) -> None:
        self.counts["service_call_failed"] += 1
        self._push(client, json.dumps({"op": "serviceCallFailure", "serviceId": service_id, "callId": call_id,
                                       "message": message}))

    def _parameters(self, client: _Client, op: str, doc: dict[str, Any]) -> None:
        self._require(client, "parameters")
        request_id = doc.get("id")

        def reply(params: list[dict[str, Any]]) -> None:
            out: dict[str, Any] = {"op": "parameterValues", "parameters": params}
            if request_id is not None:
                out["id"] = request_id
            self._push(client, json.dumps(out))
        if self.listener is None:
            reply([])
        elif op == "getParameters":
            self.listener.on_get_parameters([str(n) for n in doc.get("parameterNames", [])], reply)
        else:
            self.listener.on_set_parameters(list(doc["parameters"]), reply)
