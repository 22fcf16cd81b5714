"""Input QoS of the stage nodes: sensor inputs best effort by default (real drivers), reliable with
``sensor_reliability: reliable`` (replays) or per topic with the standard ``qos_overrides.`` parameters;
a QoS override naming no topic of the node and an unknown reliability stop start-up; a publisher
that cannot match is reported, not silently missed."""
from __future__ import annotations

import pytest
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import Imu

from helpers_dds import ros_node, spin_until
from indoor_loc.errors import ConfigError
from indoor_loc.nodes.base import StageNode, subscription_qos
from indoor_loc.params import params_for_node
from indoor_loc.pipeline.imu_stage import ImuStage
from indoor_loc.pipeline.wifi_scan_stage import WifiScanStage

# a bound for a hung test, above the sum of a test's condition deadlines (which a loaded machine may
# use up one after another), not an expected duration
pytestmark = pytest.mark.timeout(120)


def _sub_qos(node: StageNode, topic: str):
    subs = [s for s in node.subscriptions if s.topic_name == topic]
    assert len(subs) == 1, [s.topic_name for s in node.subscriptions]
    return subs[0].qos_profile


def _imu_node(probe, *params: str) -> StageNode:
    args = [a for p in params for a in ("-p", p)]
    return StageNode(ImuStage, context=probe.context, namespace="/alice", cli_args=["--ros-args", *args])


def test_sensor_inputs_best_effort_by_default_reliable_on_request(ros_domain):
    with ros_node("probe") as (probe, _):
        node = _imu_node(probe)
        try:
            assert _sub_qos(node, "/alice/imu/data_raw").reliability == ReliabilityPolicy.BEST_EFFORT
        finally:
            node.destroy_node()
        node = _imu_node(probe, "sensor_reliability:=reliable")
        try:
            for rel in ("imu/data_raw", "imu/mag", "imu/data"):
                qos = _sub_qos(node, f"/alice/{rel}")
                assert qos.reliability == ReliabilityPolicy.RELIABLE and qos.depth == 10000
            assert node.describe_parameter("sensor_reliability").read_only
        finally:
            node.destroy_node()
        # the standard ROS 2 way, per topic (fully qualified name)
        node = _imu_node(probe, "qos_overrides./alice/imu/data.subscription.reliability:=reliable",
                         "qos_overrides./alice/imu/data.subscription.depth:=5000")
        try:
            qos = _sub_qos(node, "/alice/imu/data")
            assert qos.reliability == ReliabilityPolicy.RELIABLE and qos.depth == 5000
            assert _sub_qos(node, "/alice/imu/data_raw").reliability == ReliabilityPolicy.BEST_EFFORT
        finally:
            node.destroy_node()


@pytest.mark.parametrize("param,match", [
    ("sensor_reliability:=sometimes", r"sensor_reliability: expected one of"),
    # the topic without the node's namespace: rclpy would ignore it without a word
    ("qos_overrides./imu/data.subscription.reliability:=reliable", r"name no topic of this node"),
    ("qos_overrides./alice/imu/data.subscription.reliability:=sometimes", r"QoS of subscription"),
])
def test_bad_qos_parameters_stop_start_up(ros_domain, param, match):
    with ros_node("probe") as (probe, _):
        with pytest.raises(ConfigError, match=match):
            _imu_node(probe, param)


def test_scan_raw_is_reliable():
    """Scans are few and large (a 10 000-AP scan is ~1 MB): the ingestion node takes them reliably."""
    stage = WifiScanStage(WifiScanStage.PARAMS(), namespace="/alice")
    ports = {p.topic: p for p in stage.inputs()}
    assert subscription_qos(ports["wifi/scan_raw"].qos).reliability == ReliabilityPolicy.RELIABLE


def test_incompatible_publisher_is_reported(ros_domain):
    """A best-effort driver on a reliable input does not match: the node says so and counts it."""
    with ros_node("probe") as (probe, ex):
        node = _imu_node(probe, "sensor_reliability:=reliable")
        ex.add_node(node)
        try:
            probe.create_publisher(Imu, "/alice/imu/data_raw",
                                   QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT))
            assert spin_until(ex, lambda: node.stage.diag.rejected.get("incompatible_qos", 0) > 0, 60)
            assert "imu/data_raw" in node.stage.diag.last_error
        finally:
            ex.remove_node(node)
            node.destroy_node()


def test_offline_runs_ignore_the_live_node_parameters():
    files = {"/**/imu_node": {"sensor_reliability": "reliable", "use_sim_time": True,
                              "qos_overrides": {"/a/imu/data": {"subscription": {"reliability": "reliable"}}},
                              "step_length_m": 0.7}}
    assert params_for_node(files, "imu_node", "/a") == {"step_length_m": 0.7}
