"""A small client of the Foxglove WebSocket protocol v1 (the spec, not the server's code), for tests."""
from __future__ import annotations

import json
import struct
import time
from typing import Any

from websockets.sync.client import connect


class FoxgloveClient:
    """Connects with one subprotocol; ``pump()`` reads frames into ``channels``, ``services``,
    ``statuses``, ``messages`` (channel id -> payloads), ``responses`` (call id -> (service id, payload)),
    ``failures``, ``parameters`` (request id -> list)."""

    def __init__(self, url: str, subprotocol: str, *, auto_subscribe: bool = False) -> None:
        self.auto_subscribe = auto_subscribe          # subscribe to each channel the moment it is advertised
        self.ws = connect(url, subprotocols=[subprotocol], open_timeout=20)   # type: ignore[list-item]
        self.subprotocol = self.ws.subprotocol
        self.server_info: dict[str, Any] = {}
        self.channels: dict[int, dict] = {}
        self.services: dict[int, dict] = {}
        self.statuses: list[dict] = []
        self.messages: dict[int, list[bytes]] = {}
        self.responses: dict[int, tuple[int, str, bytes]] = {}
        self.failures: dict[int, str] = {}
        self.parameters: dict[str, list[dict]] = {}
        self.param_updates: list[dict] = []
        self._subs: dict[int, int] = {}          # subscription id -> channel id
        self._next_sub = 100

    def close(self) -> None:
        self.ws.close()

    def by_topic(self, topic: str) -> dict | None:
        return next((c for c in self.channels.values() if c["topic"] == topic), None)

    def pump(self, seconds: float) -> None:
        deadline = time.monotonic() + seconds
        while (left := deadline - time.monotonic()) > 0:
            try:
                frame = self.ws.recv(timeout=left)
            except TimeoutError:
                return
            self._handle(frame)

    def pump_until(self, cond, timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        while not cond():
            if time.monotonic() >= deadline:
                return False
            self.pump(min(0.2, deadline - time.monotonic()))
        return True

    def _handle(self, frame: str | bytes) -> None:
        if isinstance(frame, str):
            doc = json.loads(frame)
            op = doc["op"]
            if op == "serverInfo":
                self.server_info = doc
            elif op == "advertise":
                for ch in doc["channels"]:
                    self.channels[ch["id"]] = ch
                if self.auto_subscribe and doc["channels"]:
                    self.subscribe([ch["id"] for ch in doc["channels"]])
            elif op == "unadvertise":
                for cid in doc["channelIds"]:
                    self.channels.pop(cid, None)
            elif op == "advertiseServices":
                for s in doc["services"]:
                    self.services[s["id"]] = s
            elif op == "status":
                self.statuses.append(doc)
            elif op == "serviceCallFailure":
                self.failures[doc["callId"]] = doc["message"]
            elif op == "parameterValues":
                if "id" in doc:
                    self.parameters[doc["id"]] = doc["parameters"]
                else:
                    self.param_updates += doc["parameters"]
            return
        op = frame[0]
        if op == 0x01:
            sub_id, _log_time = struct.unpack_from("<IQ", frame, 1)
            self.messages.setdefault(self._subs[sub_id], []).append(bytes(frame[13:]))
        elif op == 0x03:
            service_id, call_id, n = struct.unpack_from("<III", frame, 1)
            self.responses[call_id] = (service_id, frame[13:13 + n].decode(), bytes(frame[13 + n:]))

    def subscribe(self, channel_ids) -> None:
        subs = []
        for cid in channel_ids:
            self._subs[self._next_sub] = cid
            subs.append({"id": self._next_sub, "channelId": cid})
            self._next_sub += 1
        self.ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))

    def advertise(self, channel_id: int, topic: str, schema_name: str, encoding: str = "cdr") -> None:
        self.ws.send(json.dumps({"op": "advertise", "channels": [
            {"id": channel_id, "topic": topic, "encoding": encoding, "schemaName": schema_name}]}))

    def publish(self, channel_id: int, payload: bytes) -> None:
        self.ws.send(struct.pack("<BI", 0x01, channel_id) + payload)

    def call(self, service_id: int, call_id: int, payload: bytes, encoding: str = "cdr") -> None:
        enc = encoding.encode()
        self.ws.send(struct.pack("<BIII", 0x02, service_id, call_id, len(enc)) + enc + payload)

    def send_json(self, doc: dict) -> None:
        self.ws.send(json.dumps(doc))
