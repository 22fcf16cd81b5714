"""The Foxglove WebSocket server alone (no ROS): both subprotocol names, what a client gets wrong is
answered with a status and counted, never a crash; a subprotocol it does not speak is refused."""
from __future__ import annotations

import json
import struct

import pytest

from fgws_client import FoxgloveClient
from indoor_loc.fgws.server import FoxgloveServer

websockets = pytest.importorskip("websockets")


class Listener:
    def __init__(self) -> None:
        self.published: list[tuple[str, bytes]] = []

    def on_client_advertise(self, channel):
        return None if channel.schema_name.endswith("Imu") else "no such type here"

    def on_client_unadvertise(self, channel):
        pass

    def on_client_message(self, channel, payload):
        self.published.append((channel.topic, payload))
        return None

    def on_service_call(self, service, encoding, payload, reply):
        reply(payload[::-1], "")

    def on_get_parameters(self, names, reply):
        reply([{"name": n, "value": 1} for n in names])

    def on_set_parameters(self, params, reply):
        reply(params)


@pytest.fixture()
def server():
    srv = FoxgloveServer("t", port=0, listener=Listener(),
                         capabilities=("time", "clientPublish", "services", "parameters", "parametersSubscribe"))
    srv.start()
    yield srv
    srv.stop()


@pytest.mark.parametrize("subprotocol", ["foxglove.websocket.v1", "foxglove.sdk.v1"])
def test_channels_messages_services_and_parameters(server, subprotocol):
    ch = server.add_channel("/a", encoding="cdr", schema_name="pkg/msg/A", schema="int32 x", schema_encoding="ros2msg")
    svc = server.add_service("/s", "pkg/srv/S", encoding="cdr", request=("pkg/srv/S_Request", ""),
                             response=("pkg/srv/S_Response", ""), schema_encoding="ros2msg")
    c = FoxgloveClient(f"ws://127.0.0.1:{server.port}", subprotocol)
    try:
        assert c.pump_until(lambda: ch in c.channels and svc in c.services, 5)
        assert c.subprotocol == subprotocol and c.server_info["supportedEncodings"] == ["cdr"]
        c.subscribe([ch])
        c.pump_until(lambda: server.client_count() == 1, 2)
        c.pump(0.3)
        server.log(ch, b"\x00\x01\x00\x00\x07\x00\x00\x00", 123)
        assert c.pump_until(lambda: c.messages.get(ch), 5)
        assert c.messages[ch] == [b"\x00\x01\x00\x00\x07\x00\x00\x00"]
        c.advertise(5, "/imu", "sensor_msgs/msg/Imu")
        c.publish(5, b"abc")
        c.call(svc, 9, b"xyz")
        c.send_json({"op": "getParameters", "parameterNames": ["/n.p"], "id": "q"})
        assert c.pump_until(lambda: 9 in c.responses and "q" in c.parameters, 5)
        assert c.responses[9] == (svc, "cdr", b"zyx") and c.parameters["q"] == [{"name": "/n.p", "value": 1}]
        assert server.listener.published == [("/imu", b"abc")]
        assert c.statuses == []
    finally:
        c.close()


def test_what_a_client_gets_wrong_is_answered_and_counted(server):
    c = FoxgloveClient(f"ws://127.0.0.1:{server.port}", "foxglove.websocket.v1")
    try:
        c.pump_until(lambda: bool(c.server_info), 5)
        c.subscribe([77])                                            # a channel never advertised
        c.ws.send("not json")
        c.send_json({"op": "subscribe", "subscriptions": [{"id": "x"}]})
        c.send_json({"op": "frobnicate"})
        c.advertise(1, "/t", "pkg/msg/Unknown")                     # the listener refuses the type
        c.advertise(2, "/u", "sensor_msgs/msg/Imu", encoding="json")  # not a supported encoding
        c.ws.send(struct.pack("<BI", 0x01, 3) + b"payload")         # a client channel never advertised
        c.call(999, 4, b"")                                         # an unknown service
        c.ws.send(b"")
        assert c.pump_until(lambda: len(c.statuses) >= 8 and 4 in c.failures, 5), c.statuses
        text = json.dumps(c.statuses)
        for words in ("Unknown channel ID 77", "bad request", "unsupported operation", "no such type here",
                      "'json' is not supported", "client channel 3 was not advertised"):
            assert words in text, words
        assert "unknown service" in c.failures[4]
        for reason in ("unknown_channel", "bad_request", "unsupported_op", "client_channel_refused",
                       "unsupported_encoding", "unknown_client_channel", "service_call_failed"):
            assert server.counts[reason] >= 1, reason
        ch = server.add_channel("/late", encoding="cdr", schema_name="pkg/msg/A", schema="", schema_encoding="ros2msg")
        assert c.pump_until(lambda: ch in c.channels, 5)              # the session goes on
    finally:
        c.close()


def test_a_client_without_a_protocol_we_speak_is_refused(server):
    from websockets.exceptions import InvalidHandshake
    from websockets.sync.client import connect
    with pytest.raises(InvalidHandshake):
        connect(f"ws://127.0.0.1:{server.port}", subprotocols=["some.other.v1"], open_timeout=5)  # type: ignore[list-item]
