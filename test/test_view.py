"""Live view: a Foxglove WebSocket client connects to ``view`` and receives the advertised channels
and the messages published on DDS (decoded from the forwarded CDR bytes)."""
from __future__ import annotations

import json
import re
import struct
import sys
import time

import pytest

from helpers_dds import Peer, child_env, ros_node, spin_until

websockets_sync = pytest.importorskip("websockets.sync.client")

# the view accepts both names of the protocol; a client offering both gets the first
SUBPROTOCOLS = ["foxglove.sdk.v1", "foxglove.websocket.v1"]


def _recv_json_until(ws, cond, timeout: float) -> dict:
    """Collect advertised channels (topic -> channel) until cond(channels) or timeout."""
    channels: dict[str, dict] = {}
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline and not cond(channels):
        try:
            msg = ws.recv(timeout=max(0.05, deadline - time.monotonic()))
        except TimeoutError:
            break
        if isinstance(msg, str):
            doc = json.loads(msg)
            if doc.get("op") == "advertise":
                for ch in doc["channels"]:
                    channels[ch["topic"]] = ch
    return channels


def test_websocket_client_receives_advertised_channels_and_messages(ros_domain, tmp_path):
    from geometry_msgs.msg import PoseWithCovarianceStamped
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from rclpy.serialization import deserialize_message

    from indoor_loc.sim.building import sample_building_path

    view = Peer([sys.executable, "-m", "indoor_loc.nodes.view_node", "--port", "0", "--poll", "0.2",
                 "--latch-period", "0.5", "--building", str(sample_building_path())], env=child_env())
    try:
        line = view.wait_line(r"ws://[0-9.]+:\d+", timeout=60)
        assert line is not None, view.output()
        port = int(re.search(r":(\d+) ", line + " ").group(1))
        latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
        with ros_node("view_test_pub") as (node, ex):
            pub = node.create_publisher(PoseWithCovarianceStamped, "/alice/pf/pose", latched)
            msg = PoseWithCovarianceStamped()
            msg.header.frame_id = "map"
            msg.pose.pose.position.x, msg.pose.pose.position.y = 12.5, 10.0
            pub.publish(msg)
            with websockets_sync.connect(f"ws://127.0.0.1:{port}", subprotocols=SUBPROTOCOLS) as ws:
                assert ws.subprotocol in SUBPROTOCOLS
                want = {"/alice/pf/pose", "/view/building"}
                channels: dict[str, dict] = {}
                deadline = time.monotonic() + 60
                while not want <= set(channels) and time.monotonic() < deadline:
                    spin_until(ex, lambda: False, 0.2)          # keep the publisher alive on DDS
                    channels.update(_recv_json_until(ws, lambda c: want <= set(c) | set(channels), 0.5))
                assert want <= set(channels), f"advertised: {sorted(channels)}\n{view.output()}"
                ch = channels["/alice/pf/pose"]
                assert ch["encoding"] == "cdr" and ch["schemaName"] == "geometry_msgs/msg/PoseWithCovarianceStamped"
                assert ch["schemaEncoding"] == "ros2msg" and "PoseWithCovariance pose" in ch["schema"]
                assert channels["/view/building"]["schemaName"] == "visualization_msgs/msg/MarkerArray"
                # one subscription, sent once (test_view_protocol subscribes to every channel at once)
                got, sub_ids = None, {7}
                ws.send(json.dumps({"op": "subscribe", "subscriptions": [{"id": 7, "channelId": ch["id"]}]}))
                deadline = time.monotonic() + 30
                while got is None and time.monotonic() < deadline:
                    spin_until(ex, lambda: False, 0.1)
                    try:
                        frame = ws.recv(timeout=0.5)
                    except TimeoutError:
                        continue
                    if isinstance(frame, bytes) and frame[0] == 0x01:        # message data
                        sub_id, = struct.unpack_from("<I", frame, 1)
                        if sub_id in sub_ids:
                            got = deserialize_message(frame[13:], PoseWithCovarianceStamped)
                assert got is not None, view.output()
                assert (got.pose.pose.position.x, got.pose.pose.position.y) == (12.5, 10.0)
    finally:
        view.stop()
    assert view.proc.returncode is not None


def test_shipped_layout_names_contract_topics():
    from indoor_loc.contract import BACKEND_PATH, TOPICS, split_ns
    from indoor_loc.demo import layout_path

    layout = json.loads(layout_path().read_text())
    panel = layout["configById"]["3D!indoorloc"]
    assert panel["followTf"] == "map"
    known = set(TOPICS) | {"map/graph", "view/building", "map"}
    for topic in panel["topics"]:
        ns, rel = split_ns(topic, known)
        backend = re.fullmatch(BACKEND_PATH.replace("{user}", r"[a-z]+").replace("/", r"\/"), topic.lstrip("/"))
        assert rel in known or backend, f"layout topic {topic} is not in the message contract"


@pytest.mark.parametrize("argv, match", [(["--port", "70000"], "view.port"), (["--poll", "0"], "view.poll"),
                                         (["--exclude", "(("], "view.exclude"),
                                         (["--building", "/nonexistent.geojson"], "view.building")])
def test_view_refuses_bad_options_before_starting(argv, match, capsys):
    from indoor_loc.nodes.view_node import main
    assert main(["view", *argv]) == 2
    assert match in capsys.readouterr().err
