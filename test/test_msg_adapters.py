"""msg_adapters: exact round trips from core values, and every documented rejection reason."""
from __future__ import annotations

import math

import numpy as np
import pytest
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from hypothesis import given, settings
from hypothesis import strategies as st
from rclpy.serialization import deserialize_message, serialize_message
from nav_msgs.msg import Path
from visualization_msgs.msg import Marker

from indoor_loc.errors import InvalidMessageError
from msg_adapters.diagnostics import diagnostics_from_msg, stage_diagnostics
from msg_adapters.imu import imu_from_msg, imu_to_msg, mag_from_msg, mag_to_msg
from msg_adapters.markers import graph_markers, marker_points, points_markers
from msg_adapters.odom import odom_from_msg, odom_to_msg
from msg_adapters.path import path_from_msg, path_to_msg
from msg_adapters.pose import (YAW_VAR_UNKNOWN, fix_from_msg, fix_to_msg, pose_array_from_msg,
                                          pose_array_to_msg, pose_from_msg, pose_to_msg)
from msg_adapters.time import MAX_STAMP_NS, header_ns, stamp_from_ns, stamp_to_ns
from msg_adapters.wifi_scan import scan_from_msg, scan_to_msg
from indoor_loc.measurements import Fix
from indoor_loc.wifi.types import WifiScan

STAMP = 1_700_000_123_456_789_012


def reason(exc_info) -> str:
    return exc_info.value.reason


def wrap(a: float) -> float:
    return (a + math.pi) % (2 * math.pi) - math.pi


# ---------------------------------------------------------------------------------------- time
@given(st.integers(min_value=0, max_value=MAX_STAMP_NS))
def test_stamp_round_trip(ns):
    assert stamp_to_ns(stamp_from_ns(ns)) == ns
    assert stamp_to_ns(deserialize_message(serialize_message(stamp_from_ns(ns)), Time)) == ns


def test_negative_and_bad_stamps():
    with pytest.raises(InvalidMessageError) as e:
        stamp_from_ns(-1)
    assert reason(e) == "negative_stamp"
    with pytest.raises(InvalidMessageError) as e:
        stamp_to_ns(Time(sec=-5, nanosec=0))
    assert reason(e) == "negative_stamp"
    with pytest.raises(InvalidMessageError) as e:
        stamp_to_ns(Time(sec=1, nanosec=1_000_000_000))
    assert reason(e) == "bad_stamp"
    assert header_ns(Time()) is None
    with pytest.raises(InvalidMessageError) as e:
        stamp_from_ns(MAX_STAMP_NS + 1)
    assert reason(e) == "stamp_range"


# ----------------------------------------------------------------------------------------- imu
def test_imu_raw_round_trip(rng):
    acc, gyro = rng.normal(size=3), rng.normal(size=3)
    msg = imu_to_msg(STAMP, "alice/imu_link", acc, gyro)
    assert msg.orientation_covariance[0] == -1.0
    s = imu_from_msg(msg)
    assert s.stamp_ns == STAMP and s.frame_id == "alice/imu_link"
    assert np.array_equal(s.acc, acc) and np.array_equal(s.gyro, gyro)
    assert s.quat_xyzw is None and s.orientation_cov is None


def test_imu_orientation_round_trip(rng):
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    cov = np.diag([1e-3, 2e-3, 0.05])
    s = imu_from_msg(imu_to_msg(STAMP, "f", [0.1, 0.2, 9.8], [0.0, 0.0, 0.1], q, cov))
    assert np.array_equal(s.quat_xyzw, q) and np.array_equal(s.orientation_cov, cov)


def test_imu_accelerometer_only_has_no_gyro():
    msg = imu_to_msg(STAMP, "f", [0, 0, 9.81])
    assert msg.angular_velocity_covariance[0] == -1.0
    assert imu_from_msg(msg).gyro is None


@pytest.mark.parametrize("field", ["acc", "gyro", "quat", "cov"])
@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_imu_rejects_non_finite(field, bad):
    msg = imu_to_msg(STAMP, "f", [0, 0, 9.8], [0, 0, 0], [0, 0, 0, 1], np.eye(3))
    if field == "acc":
        msg.linear_acceleration.y = bad
    elif field == "gyro":
        msg.angular_velocity.z = bad
    elif field == "quat":
        msg.orientation.x = bad
    else:
        msg.orientation_covariance[4] = bad
    with pytest.raises(InvalidMessageError) as e:
        imu_from_msg(msg)
    assert reason(e) == "nan"
    with pytest.raises(InvalidMessageError) as e:
        imu_to_msg(STAMP, "f", [bad, 0, 0])
    assert reason(e) == "nan"


def test_imu_absent_fields_are_not_checked():
    msg = imu_to_msg(STAMP, "f", [0, 0, 9.8])
    msg.orientation.x = math.nan          # orientation absent (cov[0] = -1): not read
    msg.angular_velocity.x = math.nan     # gyro absent: not read
    s = imu_from_msg(msg)
    assert s.gyro is None and s.quat_xyzw is None


def test_imu_bad_quaternion_and_shape():
    msg = imu_to_msg(STAMP, "f", [0, 0, 9.8], None, [0, 0, 0, 1])
    msg.orientation.w = 2.0
    with pytest.raises(InvalidMessageError) as e:
        imu_from_msg(msg)
    assert reason(e) == "bad_quaternion"
    with pytest.raises(InvalidMessageError) as e:
        imu_to_msg(STAMP, "f", [0, 9.8])
    assert reason(e) == "shape"


def test_mag_round_trip_and_nan(rng):
    field = rng.normal(size=3) * 50e-6
    msg = mag_to_msg(STAMP, "imu", field)
    stamp, f = mag_from_msg(msg)
    assert stamp == STAMP and np.array_equal(f, field)
    msg.magnetic_field.x = math.nan
    with pytest.raises(InvalidMessageError) as e:
        mag_from_msg(msg)
    assert reason(e) == "nan"


# --------------------------------------------------------------------------------------- wifi
def make_scan(n=3, **kw) -> WifiScan:
    base = dict(stamp_ns=STAMP, bssid=tuple(f"aa:bb:cc:00:00:{i:02x}" for i in range(n)),
                rssi_dbm=np.linspace(-40.5, -90.25, n),
                freq_mhz=np.array([2412.0, 5180.0, 5955.0][:n] + [2437.0] * max(0, n - 3)),
                ssid=tuple(f"net{i}" for i in range(n)), age_ms=None, frame_id="alice/wifi_link", source="iw")
    base.update(kw)
    return WifiScan(**base)


def assert_scans_equal(a: WifiScan, b: WifiScan) -> None:
    assert (a.stamp_ns, a.bssid, a.ssid, a.frame_id, a.source) == (b.stamp_ns, b.bssid, b.ssid, b.frame_id, b.source)
    assert np.array_equal(a.rssi_dbm, b.rssi_dbm) and np.array_equal(a.freq_mhz, b.freq_mhz)
    if a.age_ms is None:
        assert b.age_ms is None
    else:
        assert np.array_equal(a.age_ms, b.age_ms, equal_nan=True)


def test_scan_layout():
    msg = scan_to_msg(make_scan())
    assert msg.status[0].name == "scan"
    summary = {kv.key: kv.value for kv in msg.status[0].values}
    assert summary == {"schema": "wifi_scan.v1", "ap_count": "3", "source": "iw"}
    assert [s.name for s in msg.status[1:]] == ["aa:bb:cc:00:00:00", "aa:bb:cc:00:00:01", "aa:bb:cc:00:00:02"]
    assert msg.status[1].message == "net0" and msg.header.frame_id == "alice/wifi_link"
    assert {kv.key for kv in msg.status[1].values} == {"rssi_dbm", "frequency_mhz"}


def test_scan_round_trip_with_partial_age():
    scan = make_scan(age_ms=np.array([0.0, np.nan, 1234.5]))
    back = scan_from_msg(scan_to_msg(scan))
    assert_scans_equal(scan, back)
    assert "age_ms" not in {kv.key for kv in scan_to_msg(scan).status[2].values}


bssids = st.lists(st.integers(min_value=0, max_value=2**48 - 1), min_size=1, max_size=40, unique=True).map(
    lambda xs: tuple(":".join(f"{(x >> s) & 0xFF:02x}" for s in range(40, -8, -8)) for x in xs))


@st.composite
def scans(draw) -> WifiScan:
    b = draw(bssids)
    n = len(b)
    fl = st.floats(min_value=-120.0, max_value=0.0, allow_nan=False)
    rssi = np.array(draw(st.lists(fl, min_size=n, max_size=n)))
    # the contract's bounds (indoor_loc.contract.BOUNDS): 0 = unknown, else 700-75 000 MHz; ages up to an hour
    freq = np.array(draw(st.lists(st.one_of(st.just(0.0), st.floats(min_value=700.0, max_value=7200.0)),
                                  min_size=n, max_size=n)))
    ssid_chars = st.characters(blacklist_characters="\0", blacklist_categories=("Cs",))
    ssid = tuple(draw(st.lists(st.text(ssid_chars, max_size=32), min_size=n, max_size=n)))
    age = draw(st.one_of(st.none(), st.lists(st.one_of(st.just(math.nan), st.floats(min_value=0, max_value=3.6e6)),
                                             min_size=n, max_size=n)))
    if age is not None and all(math.isnan(a) for a in age):
        age = None   # "all unknown" is written as no age at all -> reads back as None
    return WifiScan(stamp_ns=draw(st.integers(min_value=0, max_value=MAX_STAMP_NS)), bssid=b, rssi_dbm=rssi,
                    freq_mhz=freq, ssid=ssid, age_ms=None if age is None else np.array(age),
                    frame_id=draw(st.sampled_from(["", "wifi_link", "bob/wifi_link"])),
                    source=draw(st.sampled_from(["", "iw", "nmcli", "esp32"])))


@settings(max_examples=60, deadline=None)
@given(scans())
def test_scan_round_trip_property(scan):
    msg = scan_to_msg(scan)
    assert_scans_equal(scan, scan_from_msg(msg))
    wire = deserialize_message(serialize_message(msg), DiagnosticArray)     # through CDR too
    assert_scans_equal(scan, scan_from_msg(wire))


def test_scan_ssid_that_is_not_utf8_text_is_rejected():
    with pytest.raises(InvalidMessageError, match="bad_ssid"):
        scan_to_msg(make_scan(ssid=("\ud800", "ok", "ok2")))


def test_scan_ssid_nul_removed():
    scan = make_scan(ssid=("\0\0\0", "a\0b", "ok"))
    wire = deserialize_message(serialize_message(scan_to_msg(scan)), DiagnosticArray)
    assert scan_from_msg(wire).ssid == ("", "ab", "ok")


def test_scan_normalises_bssid_case():
    msg = scan_to_msg(make_scan())
    msg.status[1].name = "AA:BB:CC:00:00:00"
    msg.status[2].name = "aa-bb-cc-00-00-01"
    assert scan_from_msg(msg).bssid[:2] == ("aa:bb:cc:00:00:00", "aa:bb:cc:00:00:01")


def _kv(status: DiagnosticStatus, key: str, value: str | None) -> None:
    vals = [kv for kv in status.values if kv.key != key]
    if value is not None:
        vals.append(KeyValue(key=key, value=value))
    status.values = vals


@pytest.mark.parametrize("mutate,expected", [
    (lambda m: _kv(m.status[0], "schema", "wifi_scan.v2"), "schema_version"),
    (lambda m: _kv(m.status[0], "schema", None), "schema_version"),
    (lambda m: setattr(m.status[0], "name", "ap"), "schema_version"),
    (lambda m: setattr(m, "status", []), "schema_version"),
    (lambda m: setattr(m, "status", m.status[:1]), "empty_scan"),
    (lambda m: _kv(m.status[1], "rssi_dbm", "nan"), "nan"),
    (lambda m: _kv(m.status[2], "frequency_mhz", "inf"), "nan"),
    (lambda m: _kv(m.status[1], "age_ms", "-inf"), "nan"),
    (lambda m: _kv(m.status[1], "rssi_dbm", "5"), "rssi_range"),
    (lambda m: _kv(m.status[1], "rssi_dbm", "-120.5"), "rssi_range"),
    (lambda m: setattr(m.status[2], "name", "AA:BB:CC:00:00:00"), "duplicate_bssid"),
    (lambda m: setattr(m.status[1], "name", "aa:bb:cc:00:00"), "bad_bssid"),
    (lambda m: setattr(m.status[1], "name", "zz:bb:cc:00:00:00"), "bad_bssid"),
    (lambda m: _kv(m.status[1], "rssi_dbm", None), "missing_field"),
    (lambda m: _kv(m.status[1], "frequency_mhz", ""), "missing_field"),
    (lambda m: _kv(m.status[1], "rssi_dbm", "strong"), "bad_value"),
    (lambda m: _kv(m.status[0], "ap_count", "7"), "ap_count"),
    (lambda m: setattr(m.header.stamp, "sec", -3), "negative_stamp"),
])
def test_scan_rejections(mutate, expected):
    msg = scan_to_msg(make_scan())
    mutate(msg)
    with pytest.raises(InvalidMessageError) as e:
        scan_from_msg(msg)
    assert reason(e) == expected


def test_scan_rejects_bad_core_values():
    with pytest.raises(InvalidMessageError) as e:
        scan_to_msg(make_scan(rssi_dbm=np.array([-40.0, 3.0, -50.0])))
    assert reason(e) == "rssi_range"
    with pytest.raises(InvalidMessageError) as e:
        scan_to_msg(make_scan(n=0, bssid=(), rssi_dbm=np.array([]), freq_mhz=np.array([]), ssid=()))
    assert reason(e) == "empty_scan"
    with pytest.raises(InvalidMessageError) as e:
        scan_to_msg(make_scan(bssid=("aa:bb:cc:00:00:01",) * 3))
    assert reason(e) == "duplicate_bssid"
    with pytest.raises(InvalidMessageError) as e:
        scan_to_msg(make_scan(rssi_dbm=np.array([-40.0, np.nan, -50.0])))
    assert reason(e) == "nan"
    with pytest.raises(InvalidMessageError) as e:
        scan_to_msg(make_scan(stamp_ns=-1))
    assert reason(e) == "negative_stamp"


# -------------------------------------------------------------------------------- odom / pose
def test_odom_round_trip(rng):
    a = rng.normal(size=(3, 3))
    cov = a @ a.T
    for yaw in (0.0, 1.0, -2.5, math.pi - 1e-9, 3.0):
        o = odom_from_msg(odom_to_msg(STAMP, "alice/odom", "alice/base_link", 1.5, -2.25, yaw, cov, 1.3, -0.2))
        assert (o.stamp_ns, o.x, o.y, o.speed, o.yaw_rate) == (STAMP, 1.5, -2.25, 1.3, -0.2)
        assert (o.frame_id, o.child_frame_id) == ("alice/odom", "alice/base_link")
        assert np.array_equal(o.cov, cov)
        assert abs(wrap(o.yaw - yaw)) < 1e-12


def test_odom_covariance_layout():
    cov = np.arange(9.0).reshape(3, 3)
    full = np.array(odom_to_msg(0, "o", "b", 0, 0, 0, cov, 0, 0).pose.covariance).reshape(6, 6)
    assert full[0, 0] == 0 and full[0, 1] == 1 and full[0, 5] == 2 and full[5, 5] == 8 and full[5, 0] == 6
    assert full[2, 2] == 0 and full[3, 3] == 0


def test_odom_rejects_nan():
    msg = odom_to_msg(STAMP, "o", "b", 0, 0, 0, np.eye(3), 1, 0)
    msg.twist.twist.linear.x = math.inf
    with pytest.raises(InvalidMessageError) as e:
        odom_from_msg(msg)
    assert reason(e) == "nan"
    with pytest.raises(InvalidMessageError) as e:
        odom_to_msg(STAMP, "o", "b", math.nan, 0, 0, np.eye(3), 1, 0)
    assert reason(e) == "nan"


def test_fix_round_trip():
    cov = np.array([[4.0, 0.5], [0.5, 2.25]])
    fix = Fix(stamp_ns=STAMP, xy=np.array([12.5, 30.125]), cov=cov)
    msg = fix_to_msg(fix)
    assert msg.header.frame_id == "map"
    full = np.array(msg.pose.covariance).reshape(6, 6)
    assert full[5, 5] == YAW_VAR_UNKNOWN
    p = pose_from_msg(msg)
    assert p.stamp_ns == STAMP and np.array_equal(p.xy, fix.xy) and np.array_equal(p.cov_xy, cov) and p.yaw == 0.0
    back = fix_from_msg(msg)
    assert back.ok and np.array_equal(back.xy, fix.xy) and np.array_equal(back.cov, cov)
    msg.pose.covariance[1] += 1e-15                 # asymmetric by rounding: taken, returned symmetric
    back = fix_from_msg(msg)
    assert back.cov[0, 1] == back.cov[1, 0] and abs(back.cov[0, 1] - 0.5) < 1e-14
    with pytest.raises(InvalidMessageError) as e:
        fix_to_msg(Fix(stamp_ns=1, xy=np.zeros(2), cov=np.eye(2), ok=False, reason="too few APs"))
    assert reason(e) == "fix_not_ok"


def test_pose_with_yaw_and_nan():
    msg = pose_to_msg(STAMP, [1.0, 2.0], 0.7, np.eye(2), yaw_var=0.01)
    assert abs(pose_from_msg(msg).yaw - 0.7) < 1e-12
    msg.pose.covariance[7] = math.nan
    with pytest.raises(InvalidMessageError) as e:
        pose_from_msg(msg)
    assert reason(e) == "nan"


def test_pose_array_round_trip(rng):
    xy, yaw = rng.normal(size=(50, 2)) * 10, rng.uniform(-3, 3, size=50)
    stamp, xy2, yaw2 = pose_array_from_msg(pose_array_to_msg(STAMP, xy, yaw))
    assert stamp == STAMP and np.array_equal(xy, xy2) and np.allclose(yaw, yaw2, atol=1e-12)


# --------------------------------------------------------------------------------------- path
@settings(max_examples=40, deadline=None)
@given(st.integers(min_value=0, max_value=60).flatmap(lambda n: st.tuples(
    st.lists(st.integers(min_value=0, max_value=MAX_STAMP_NS), min_size=n, max_size=n),
    st.lists(st.tuples(st.floats(-1e5, 1e5), st.floats(-1e5, 1e5)), min_size=n, max_size=n),
    st.lists(st.floats(-3.14159, 3.14159), min_size=n, max_size=n))))
def test_path_round_trip_property(data):
    stamps, xy, yaw = np.array(data[0], dtype=np.int64), np.array(data[1]).reshape(-1, 2), np.array(data[2])
    s2, xy2, yaw2 = path_from_msg(deserialize_message(serialize_message(path_to_msg(stamps, xy, yaw)), Path))
    assert np.array_equal(s2, stamps) and np.array_equal(xy2, xy)
    assert np.allclose(yaw2, yaw, atol=1e-12)


def test_path_without_yaw_and_header():
    msg = path_to_msg(np.array([1, 2, 3]), np.zeros((3, 2)))
    assert stamp_to_ns(msg.header.stamp) == 3 and msg.header.frame_id == "map"
    assert np.array_equal(path_from_msg(msg)[2], np.zeros(3))
    assert stamp_to_ns(path_to_msg(np.array([1]), np.zeros((1, 2)), stamp_ns=99).header.stamp) == 99
    with pytest.raises(InvalidMessageError) as e:
        path_to_msg(np.array([1, 2]), np.zeros((3, 2)))
    assert reason(e) == "shape"
    msg.poses[1].pose.position.y = math.nan
    with pytest.raises(InvalidMessageError) as e:
        path_from_msg(msg)
    assert reason(e) == "nan"


# ------------------------------------------------------------------------------------ markers
def test_points_markers(rng):
    xy = rng.normal(size=(7, 2))
    arr = points_markers("wifi_map", xy, "map", STAMP)
    assert arr.markers[0].action == Marker.DELETEALL
    m = arr.markers[1]
    assert m.type == Marker.SPHERE_LIST and m.header.frame_id == "map" and m.ns == "wifi_map"
    assert np.array_equal(marker_points(m)[:, :2], xy)
    arr = points_markers("wifi_map", xy, per_point=True, texts=[str(i) for i in range(7)], clear=False)
    spheres = [m for m in arr.markers if m.type == Marker.SPHERE]
    texts = [m for m in arr.markers if m.type == Marker.TEXT_VIEW_FACING]
    assert [m.id for m in spheres] == list(range(7)) and [t.text for t in texts] == [str(i) for i in range(7)]
    assert np.array_equal(np.vstack([marker_points(m)[:, :2] for m in spheres]), xy)
    with pytest.raises(InvalidMessageError):
        points_markers("x", xy, texts=["a"])
    with pytest.raises(InvalidMessageError) as e:
        points_markers("x", [[0.0, math.nan]])
    assert reason(e) == "nan"


def test_graph_markers():
    nodes = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 5.0]])
    links = np.array([[0, 1], [1, 2]])
    arr = graph_markers(nodes, links)
    line = next(m for m in arr.markers if m.type == Marker.LINE_LIST)
    assert line.header.frame_id == "map"
    assert np.array_equal(marker_points(line)[:, :2], nodes[[0, 1, 1, 2]])
    sph = next(m for m in arr.markers if m.type == Marker.SPHERE_LIST)
    assert np.array_equal(marker_points(sph)[:, :2], nodes)
    with pytest.raises(InvalidMessageError) as e:
        graph_markers(nodes, np.array([[0, 3]]))
    assert reason(e) == "bad_value"


# -------------------------------------------------------------------------------- diagnostics
def test_stage_diagnostics_round_trip():
    from indoor_loc.pipeline.stage import Stage

    class Dummy(Stage):
        NODE_NAME = "dummy"

        def __init__(self):
            super().__init__(None, namespace="/alice")
            self.on("in", lambda msg, now: [] if msg else (_ for _ in ()).throw(InvalidMessageError("nan", "x")))

    s = Dummy()
    s.process("in", True, 1)
    s.process("in", False, 2)
    arr = stage_diagnostics("/alice/dummy", s, 5)
    d = diagnostics_from_msg(arr)["/alice/dummy"]
    assert d.level == 1 and d.hardware_id == "/alice"
    assert d.values["rejected.nan"] == "1" and d.values["in.in.count"] == "2"
    assert isinstance(DiagnosticArray(), type(arr))


def test_standing_stage_error_makes_diagnostics_level_error():
    from diagnostic_msgs.msg import DiagnosticStatus

    from msg_adapters.diagnostics import stage_diagnostics
    from indoor_loc.params import params_from_dict
    from indoor_loc.pipeline.wifi_fix_stage import WifiFixParams, WifiFixStage

    stage = WifiFixStage(params_from_dict(WifiFixParams, {}), namespace="/alice")   # no radio map
    st = stage_diagnostics("/alice/wifi_fix_node", stage, 1_000_000_000).status[0]
    assert st.level == DiagnosticStatus.ERROR
    assert "no radio map" in st.message


def test_pdr_odom_twist_covariance_carries_speed_and_yaw_rate_variances():
    """pdr/odom's twist covariance is filled: [0] the walking-speed variance, [35] the yaw-rate
    variance (the two ends' heading variances over the hop; unknown heading -> 1e6)."""
    from indoor_loc.imu.pdr import Pdr, PdrParams

    pdr = Pdr(PdrParams(step_length_m=0.65))
    hop = 320_000_000
    poses = [pdr.update(i * hop, (i + 1) * hop, 0.6, 0.1 * i, 0.01) for i in range(3)]
    poses.append(pdr.update(3 * hop, 4 * hop, 0.6, None))                     # heading lost
    msgs = [odom_to_msg(p.stamp_ns, "u/odom", "u/base_link", p.x, p.y, p.yaw, p.cov, p.speed, p.yaw_rate,
                        p.speed_var, p.yaw_rate_var) for p in poses]
    dt = hop * 1e-9
    assert msgs[1].twist.covariance[35] == pytest.approx(0.02 / dt**2)
    assert msgs[1].twist.covariance[0] > 0
    assert msgs[3].twist.covariance[35] == 1e6
    assert odom_from_msg(msgs[1]).yaw_rate_var == pytest.approx(0.02 / dt**2)
    with pytest.raises(InvalidMessageError, match="bad_covariance|twist variances"):
        odom_to_msg(0, "a", "b", 0, 0, 0, np.eye(3), 0, 0, 0.0, -1.0)
