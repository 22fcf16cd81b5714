"""The live view from the client side, over both subprotocol names of the Foxglove WebSocket protocol:
every advertised channel subscribed once, at once, and every payload decoded; a 2D pose estimate
published by the client re-initialises a real ``tll_pf``; its ``~/global_localization`` called and
its parameters read by the client."""
from __future__ import annotations

import re
import sys

import numpy as np
import pytest
from rclpy.serialization import deserialize_message, serialize_message

from fgws_client import FoxgloveClient
from helpers_dds import Peer, child_env, ros_node
from indoor_loc.contract import msg_class
from indoor_loc.graph import build_graph, save_graph

pytest.importorskip("websockets.sync.client")

SUBPROTOCOLS = ["foxglove.websocket.v1", "foxglove.sdk.v1"]
N_TOPICS = 30


def start_view_and_pf(tmp_path) -> tuple[Peer, Peer, str]:
    from indoor_loc.sim.building import sample_building_path
    g = build_graph([0, 1, 2], np.array([[0, 0], [20, 0], [20, 10]], float), [(0, 1), (1, 2)])
    gf = save_graph(g, tmp_path / "g.graph.yaml")
    pf = Peer([sys.executable, "-m", "indoor_loc.nodes.tll_pf_node", "--ros-args", "-r", "__ns:=/alice",
               "-p", f"graph_file:={gf}", "-p", "n_particles:=300"], env=child_env())
    view = Peer([sys.executable, "-m", "indoor_loc.nodes.view_node", "--port", "0", "--poll", "0.2",
                 "--latch-period", "0.5", "--building", str(sample_building_path())], env=child_env())
    line = view.wait_line(r"ws://[0-9.]+:\d+", timeout=60)
    assert line is not None, view.output()
    port = re.search(r"ws://[0-9.]+:(\d+)", line).group(1)
    return pf, view, f"ws://127.0.0.1:{port}"


@pytest.mark.timeout(120)
@pytest.mark.parametrize("subprotocol", SUBPROTOCOLS)
def test_every_channel_subscribed_at_once_delivers_decodable_messages(ros_domain, tmp_path, subprotocol):
    from geometry_msgs.msg import PoseWithCovarianceStamped
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    pf, view, url = start_view_and_pf(tmp_path)
    try:
        with ros_node("view_test_pub") as (node, _ex):
            latched_qos = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                                     durability=DurabilityPolicy.TRANSIENT_LOCAL)
            client = FoxgloveClient(url, subprotocol, auto_subscribe=True)
            try:
                assert client.subprotocol == subprotocol
                # topics appear while the client is connected: it subscribes to each the moment it is told
                pubs = []
                for i in range(N_TOPICS):
                    pubs.append(node.create_publisher(PoseWithCovarianceStamped, f"/bob{i}/pf/pose", latched_qos))
                    msg = PoseWithCovarianceStamped()
                    msg.header.frame_id = "map"
                    msg.pose.pose.position.x, msg.pose.pose.position.y = 12.5, float(i)
                    pubs[-1].publish(msg)
                want = {"/view/building", "/alice/pf/pose", "/alice/pf/particles", "/diagnostics"}
                want |= {f"/bob{i}/pf/pose" for i in range(N_TOPICS)}
                assert client.pump_until(lambda: want <= {c["topic"] for c in client.channels.values()}, 60), \
                    f"{sorted(c['topic'] for c in client.channels.values())}\n{view.output()}"
                latched = [client.by_topic(t)["id"] for t in ["/view/building"] +
                           [f"/bob{i}/pf/pose" for i in range(N_TOPICS)]]
                assert client.pump_until(lambda: all(client.messages.get(c) for c in latched), 30), \
                    (f"no message on {[client.channels[c]['topic'] for c in latched if not client.messages.get(c)]}; "
                     f"{client.statuses}")
                client.pump(1.0)
                assert not [s for s in client.statuses if "nknown channel" in s["message"]], client.statuses
                assert not [s for s in client.statuses if s["level"] >= 1], client.statuses
                decoded = 0
                for cid, payloads in client.messages.items():
                    ch = client.channels[cid]
                    assert ch["encoding"] == "cdr" and ch["schemaEncoding"] == "ros2msg" and ch["schema"] is not None
                    cls = msg_class(ch["schemaName"])
                    for data in payloads:
                        deserialize_message(data, cls)
                        decoded += 1
                assert decoded >= N_TOPICS + 1
                for i in range(N_TOPICS):
                    got = deserialize_message(client.messages[latched[1 + i]][-1], PoseWithCovarianceStamped)
                    assert (got.pose.pose.position.x, got.pose.pose.position.y) == (12.5, float(i))
                building = deserialize_message(client.messages[latched[0]][-1], msg_class("visualization_msgs/msg/MarkerArray"))
                assert building.markers
            finally:
                client.close()
    finally:
        view.stop()
        pf.stop()


@pytest.mark.timeout(150)
def test_client_publishes_initialpose_calls_global_localization_and_reads_parameters(ros_domain, tmp_path):
    from geometry_msgs.msg import PoseWithCovarianceStamped
    from std_srvs.srv import Empty
    pf, view, url = start_view_and_pf(tmp_path)
    try:
        client = FoxgloveClient(url, "foxglove.websocket.v1")
        try:
            client.pump_until(lambda: bool(client.server_info), 10)
            caps = set(client.server_info["capabilities"])
            assert {"clientPublish", "services", "parameters", "parametersSubscribe"} <= caps
            assert client.pump_until(lambda: client.by_topic("/alice/pf/pose") is not None and any(
                s["name"] == "/alice/tll_pf/global_localization" for s in client.services.values()), 60), view.output()
            pose_ch = client.by_topic("/alice/pf/pose")["id"]
            client.subscribe([pose_ch])
            # Foxglove's 2D pose estimate: geometry_msgs/PoseWithCovarianceStamped on /<user>/initialpose
            client.advertise(1, "/alice/initialpose", "geometry_msgs/msg/PoseWithCovarianceStamped")
            msg = PoseWithCovarianceStamped()
            msg.header.frame_id = "map"
            msg.pose.pose.position.x, msg.pose.pose.position.y = 15.0, 0.0
            msg.pose.pose.orientation.w = 1.0
            msg.pose.covariance[0] = msg.pose.covariance[7] = 0.25
            poses: list = []

            def pose_near() -> bool:
                poses[:] = [deserialize_message(d, PoseWithCovarianceStamped) for d in client.messages.get(pose_ch, [])]
                return any(abs(p.pose.pose.position.x - 15.0) < 2.0 and abs(p.pose.pose.position.y) < 2.0
                           for p in poses)
            sent = 0
            for _ in range(20):           # publish until tll_pf's subscription has matched the view's publisher
                client.publish(1, serialize_message(msg))
                sent += 1
                if client.pump_until(pose_near, 2.0):
                    break
            assert pose_near(), f"{[(p.pose.pose.position.x, p.pose.pose.position.y) for p in poses]}\n{pf.output()}"
            assert not client.statuses, client.statuses
            # the global localisation service, called with a CDR request, answered with a CDR response
            svc = next(s for s in client.services.values() if s["name"] == "/alice/tll_pf/global_localization")
            assert svc["type"] == "std_srvs/srv/Empty" and svc["request"]["encoding"] == "cdr"
            client.call(svc["id"], 42, serialize_message(Empty.Request()))
            assert client.pump_until(lambda: 42 in client.responses or 42 in client.failures, 30), view.output()
            assert 42 in client.responses, client.failures
            service_id, encoding, payload = client.responses[42]
            assert (service_id, encoding) == (svc["id"], "cdr")
            deserialize_message(payload, Empty.Response)
            assert pf.wait_seen("global localisation", 10), pf.output()
            # an unknown service gets a serviceCallFailure, not silence
            client.call(9999, 43, b"")
            assert client.pump_until(lambda: 43 in client.failures, 10)
            # parameters: by name, and all of them
            client.send_json({"op": "getParameters", "parameterNames": ["/alice/tll_pf.n_particles"], "id": "one"})
            assert client.pump_until(lambda: "one" in client.parameters, 20), view.output()
            assert client.parameters["one"] == [{"name": "/alice/tll_pf.n_particles", "value": 300}]
            client.send_json({"op": "getParameters", "parameterNames": [], "id": "all"})
            assert client.pump_until(lambda: "all" in client.parameters, 40), view.output()
            names = {p["name"] for p in client.parameters["all"]}
            assert {"/alice/tll_pf.n_particles", "/alice/tll_pf.use_sim_time"} <= names
        finally:
            client.close()
    finally:
        view.stop()
        pf.stop()
    assert re.search(r"forwarded \d+ messages", view.output())
