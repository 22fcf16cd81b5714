"""One message per contract topic, built from fixed core values with the msg_adapters, and the
check that a received message carries exactly those values (read back with the adapters).
Shared by the sending process (contract_sender.py) and the receiving test."""
from __future__ import annotations

import numpy as np
from rosgraph_msgs.msg import Clock

from indoor_loc.contract import TOPICS
from msg_adapters.diagnostics import diagnostics_from_msg
from msg_adapters.imu import imu_from_msg, imu_to_msg, mag_from_msg, mag_to_msg
from msg_adapters.markers import graph_markers, marker_points, points_markers
from msg_adapters.odom import odom_from_msg, odom_to_msg
from msg_adapters.path import path_from_msg, path_to_msg
from msg_adapters.pressure import pressure_from_msg, pressure_to_msg
from msg_adapters.pose import fix_to_msg, pose_array_from_msg, pose_array_to_msg, pose_from_msg, pose_to_msg
from msg_adapters.tf import tf_message, transform_from_msg, transform_to_msg
from msg_adapters.time import stamp_from_ns, stamp_to_ns
from msg_adapters.wifi_scan import scan_from_msg, scan_to_msg
from indoor_loc.measurements import Fix
from indoor_loc.wifi.ble import BleScan
from indoor_loc.wifi.types import WifiScan

NAMESPACE = "/alice"
T0 = 1_712_345_678_123_456_789

_rng = np.random.default_rng(20240607)
QUAT = _rng.normal(size=4)
QUAT /= np.linalg.norm(QUAT)
V = {
    "acc": _rng.normal(size=3) + [0, 0, 9.81], "gyro": _rng.normal(size=3) * 0.1,
    "mag": _rng.normal(size=3) * 40e-6, "ocov": np.diag([1e-4, 2e-4, 3e-2]),
    "scan": WifiScan(stamp_ns=T0 + 4, bssid=("00:11:22:33:44:55", "66:77:88:99:aa:bb", "cc:dd:ee:ff:00:01"),
                     rssi_dbm=np.array([-41.5, -77.0, -119.75]), freq_mhz=np.array([2412.0, 5180.0, 5955.0]),
                     ssid=("lab", "", "guest \u00e9"), age_ms=np.array([12.0, np.nan, 3400.5]),
                     frame_id="alice/wifi_link", source="iw"),
    "odom_cov": np.array([[0.2, 0.01, 0.0], [0.01, 0.3, 0.02], [0.0, 0.02, 0.05]]),
    "fix": Fix(stamp_ns=T0 + 6, xy=np.array([12.25, 30.5]), cov=np.array([[4.0, 0.5], [0.5, 2.0]])),
    "pf_xy": np.array([3.5, -1.25]), "pf_cov": np.array([[0.5, 0.1], [0.1, 0.25]]),
    "particles": _rng.normal(size=(200, 2)) * 5, "particle_yaw": _rng.uniform(-3, 3, size=200),
    "path_stamps": T0 + np.arange(50, dtype=np.int64) * 500_000_000, "path_xy": np.cumsum(_rng.normal(size=(50, 2)), 0),
    "path_yaw": _rng.uniform(-3, 3, size=50),
    "nodes": np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 8.0], [0.0, 8.0]]), "links": np.array([[0, 1], [1, 2], [2, 3]]),
    "wifi_map": _rng.uniform(0, 40, size=(30, 2)),
    "ble": BleScan(stamp_ns=T0 + 14, beacon_id=("00000000-0000-beac-2022-000000005938-1-2", "abcdef012345"),
                   rssi_dbm=np.array([-70.5, -88.0]), tx_power_dbm=np.array([-59.0, np.nan]),
                   name=("20:22:b0:00:51:42", "20:22:b0:00:51:43"), frame_id="alice/ble_link", source="test"),
}


#: For a contract topic without values of its own: the topic whose values its type reuses.
CANONICAL_BY_TYPE = {
    "sensor_msgs/msg/Imu": "imu/data_raw", "sensor_msgs/msg/MagneticField": "imu/mag",
    "nav_msgs/msg/Odometry": "pdr/odom", "geometry_msgs/msg/PoseWithCovarianceStamped": "pf/pose",
    "geometry_msgs/msg/PoseArray": "pf/particles", "nav_msgs/msg/Path": "ground_truth",
    "visualization_msgs/msg/MarkerArray": "backend/wifi_map", "diagnostic_msgs/msg/DiagnosticArray": "/diagnostics",
    "rosgraph_msgs/msg/Clock": "/clock", "geometry_msgs/msg/TransformStamped": "pf/map_odom",
    "sensor_msgs/msg/FluidPressure": "baro/pressure",
}
_OWN = {"imu/data_raw", "imu/mag", "imu/data", "wifi/scan", "pdr/odom", "wifi/fix", "pf/pose", "pf/particles",
        "ground_truth", "map/graph", "backend/wifi_map", "/diagnostics", "/clock", "wifi/scan_json",
        "pf/map_odom", "/tf", "baro/pressure", "ble/scan"}
SCAN_JSON = '{"bssid": "aa:bb:cc:dd:ee:01", "rssi": -61, "ssid": "café"}'


def values_topic(topic: str) -> str:
    """``topic`` itself when it has values of its own, else the canonical topic of its type."""
    if topic in _OWN:
        return topic
    return CANONICAL_BY_TYPE[TOPICS[topic].type]


def build(topic: str):
    """The message sent on contract topic ``topic``."""
    topic = values_topic(topic)
    if topic == "imu/data_raw":
        return imu_to_msg(T0 + 1, "alice/imu_link", V["acc"], V["gyro"])
    if topic == "imu/mag":
        return mag_to_msg(T0 + 2, "alice/imu_link", V["mag"])
    if topic == "baro/pressure":
        return pressure_to_msg(T0 + 9, "alice/imu_link", 98765.43, 6.25)
    if topic == "imu/data":
        return imu_to_msg(T0 + 3, "alice/imu_link", V["acc"], V["gyro"], QUAT, V["ocov"])
    if topic == "wifi/scan":
        return scan_to_msg(V["scan"])
    if topic == "pdr/odom":
        return odom_to_msg(T0 + 5, "alice/odom", "alice/base_link", 1.5, -2.0, 0.75, V["odom_cov"], 1.25, -0.1)
    if topic == "wifi/fix":
        return fix_to_msg(V["fix"])
    if topic == "pf/pose":
        return pose_to_msg(T0 + 7, V["pf_xy"], -1.0, V["pf_cov"], yaw_var=0.04)
    if topic == "pf/particles":
        return pose_array_to_msg(T0 + 8, V["particles"], V["particle_yaw"])
    if topic == "ground_truth":
        return path_to_msg(V["path_stamps"], V["path_xy"], V["path_yaw"])
    if topic == "map/graph":
        return graph_markers(V["nodes"], V["links"], stamp_ns=T0 + 9)
    if topic == "backend/wifi_map":
        return points_markers("wifi_map", V["wifi_map"], "map", T0 + 10, texts=[f"s{i}" for i in range(30)])
    if topic == "/diagnostics":
        from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
        arr = DiagnosticArray()
        arr.header.stamp = stamp_from_ns(T0 + 11)
        arr.status = [DiagnosticStatus(level=DiagnosticStatus.WARN, name="/alice/imu_node", message="2 rejected",
                                       hardware_id="/alice", values=[KeyValue(key="rejected.nan", value="2")])]
        return arr
    if topic == "/clock":
        return Clock(clock=stamp_from_ns(T0 + 12))
    if topic == "wifi/scan_json":
        from std_msgs.msg import String
        return String(data=SCAN_JSON)
    if topic == "pf/map_odom":
        return transform_to_msg(T0 + 13, "map", "alice/odom", 3.25, -7.5, 0.6)
    if topic == "/tf":
        return tf_message([transform_to_msg(T0 + 13, "map", "alice/odom", 3.25, -7.5, 0.6)], 500_000_000)
    if topic == "ble/scan":
        from msg_adapters.ble_scan import ble_to_msg
        return ble_to_msg(V["ble"])
    raise KeyError(f"no test message for contract topic {topic!r}")


def check(topic: str, msg) -> None:
    """Assert that ``msg`` (received on ``topic``) carries exactly the values :func:`build` used."""
    topic = values_topic(topic)
    if topic in ("imu/data_raw", "imu/data"):
        s = imu_from_msg(msg)
        assert s.frame_id == "alice/imu_link" and np.array_equal(s.acc, V["acc"]) and np.array_equal(s.gyro, V["gyro"])
        if topic == "imu/data":
            assert s.stamp_ns == T0 + 3 and np.array_equal(s.quat_xyzw, QUAT)
            assert np.array_equal(s.orientation_cov, V["ocov"])
        else:
            assert s.stamp_ns == T0 + 1 and s.quat_xyzw is None
    elif topic == "imu/mag":
        stamp, f = mag_from_msg(msg)
        assert stamp == T0 + 2 and np.array_equal(f, V["mag"])
    elif topic == "baro/pressure":
        assert pressure_from_msg(msg) == (T0 + 9, 98765.43, 6.25, "alice/imu_link")
    elif topic == "wifi/scan":
        s, e = scan_from_msg(msg), V["scan"]
        assert (s.stamp_ns, s.bssid, s.ssid) == (e.stamp_ns, e.bssid, e.ssid)
        assert (s.frame_id, s.source) == (e.frame_id, e.source)
        assert np.array_equal(s.rssi_dbm, e.rssi_dbm) and np.array_equal(s.freq_mhz, e.freq_mhz)
        assert np.array_equal(s.age_ms, e.age_ms, equal_nan=True)
    elif topic == "pdr/odom":
        o = odom_from_msg(msg)
        assert (o.stamp_ns, o.x, o.y, o.speed, o.yaw_rate) == (T0 + 5, 1.5, -2.0, 1.25, -0.1)
        assert abs(o.yaw - 0.75) < 1e-12 and np.array_equal(o.cov, V["odom_cov"])
        assert (o.frame_id, o.child_frame_id) == ("alice/odom", "alice/base_link")
    elif topic == "wifi/fix":
        p = pose_from_msg(msg)
        assert p.stamp_ns == T0 + 6 and p.frame_id == "map"
        assert np.array_equal(p.xy, V["fix"].xy) and np.array_equal(p.cov_xy, V["fix"].cov)
    elif topic == "pf/pose":
        p = pose_from_msg(msg)
        assert p.stamp_ns == T0 + 7 and np.array_equal(p.xy, V["pf_xy"]) and np.array_equal(p.cov_xy, V["pf_cov"])
        assert abs(p.yaw + 1.0) < 1e-12 and msg.pose.covariance[35] == 0.04
    elif topic == "pf/particles":
        stamp, xy, yaw = pose_array_from_msg(msg)
        assert stamp == T0 + 8 and np.array_equal(xy, V["particles"])
        assert np.allclose(yaw, V["particle_yaw"], atol=1e-12)
    elif topic == "ground_truth":
        stamps, xy, yaw = path_from_msg(msg)
        assert np.array_equal(stamps, V["path_stamps"]) and np.array_equal(xy, V["path_xy"])
        assert np.allclose(yaw, V["path_yaw"], atol=1e-12) and msg.header.frame_id == "map"
    elif topic == "map/graph":
        lines = [m for m in msg.markers if m.ns == "graph/links" and m.points]
        nodes = [m for m in msg.markers if m.ns == "graph/nodes" and m.points]
        assert len(lines) == 1 and len(nodes) == 1 and lines[0].header.frame_id == "map"
        assert np.array_equal(marker_points(lines[0])[:, :2], V["nodes"][V["links"].ravel()])
        assert np.array_equal(marker_points(nodes[0])[:, :2], V["nodes"])
    elif topic == "backend/wifi_map":
        pts = [m for m in msg.markers if m.ns == "wifi_map" and m.points]
        texts = [m.text for m in msg.markers if m.ns == "wifi_map/text" and m.text]
        assert len(pts) == 1 and np.array_equal(marker_points(pts[0])[:, :2], V["wifi_map"])
        assert texts == [f"s{i}" for i in range(30)]
    elif topic == "/diagnostics":
        d = diagnostics_from_msg(msg)["/alice/imu_node"]
        assert stamp_to_ns(msg.header.stamp) == T0 + 11
        assert (d.level, d.message, d.hardware_id, d.values) == (1, "2 rejected", "/alice", {"rejected.nan": "2"})
    elif topic == "/clock":
        assert stamp_to_ns(msg.clock) == T0 + 12
    elif topic == "wifi/scan_json":
        assert msg.data == SCAN_JSON
    elif topic in ("pf/map_odom", "/tf"):
        t = msg if topic == "pf/map_odom" else msg.transforms[0]
        stamp, parent, child, (x, y, yaw) = transform_from_msg(t)
        assert (stamp, parent, child, x, y) == (T0 + 13 + (500_000_000 if topic == "/tf" else 0), "map", "alice/odom",
                                                3.25, -7.5)
        assert abs(yaw - 0.6) < 1e-12
    elif topic == "ble/scan":
        from msg_adapters.ble_scan import ble_from_msg
        b, e = ble_from_msg(msg), V["ble"]
        assert (b.stamp_ns, b.beacon_id, b.name, b.frame_id) == (e.stamp_ns, e.beacon_id, e.name, e.frame_id)
        assert np.array_equal(b.rssi_dbm, e.rssi_dbm) and np.array_equal(b.tx_power_dbm, e.tx_power_dbm, equal_nan=True)
    else:
        raise KeyError(topic)


ALL_TOPICS = list(TOPICS)
