"""WifiFixStage / wifi_fix_node: fixes, bad scans counted, declined fixes, no map, parameters."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from indoor_loc.errors import ConfigError, MapError
from msg_adapters.pose import pose_from_msg
from msg_adapters.wifi_scan import scan_to_msg
from indoor_loc.params import load_params_file, params_for_node, params_from_dict
from indoor_loc.pipeline.wifi_fix_stage import WifiFixParams, WifiFixStage
from indoor_loc.wifi.radiomap import save_radiomap
from indoor_loc.wifi.types import RadioMap, WifiScan

ROOT = Path(__file__).resolve().parents[1]
B = [f"02:00:00:00:00:{i:02x}" for i in range(6)]


def grid_map() -> RadioMap:
    """6 APs on a 10 x 10 m square, fingerprints every 2 m, noiseless log-distance RSS."""
    ap = np.array([[0, 0], [10, 0], [0, 10], [10, 10], [5, 0], [5, 10]], float)
    pts = np.array([[x, y] for x in range(0, 11, 2) for y in range(0, 11, 2)], float)
    d = np.sqrt(((pts[:, None] - ap[None]) ** 2).sum(-1) + 1.0)
    return RadioMap(positions=pts, bssids=B, rssi_dbm=-35 - 30 * np.log10(d), freq_mhz=np.full(6, 2412.0))


def scan_at(xy, stamp_ns=5 * 10**9) -> WifiScan:
    ap = np.array([[0, 0], [10, 0], [0, 10], [10, 10], [5, 0], [5, 10]], float)
    d = np.sqrt(((np.asarray(xy, float)[None] - ap) ** 2).sum(-1) + 1.0)
    return WifiScan(stamp_ns, tuple(B), -35 - 30 * np.log10(d), np.full(6, 2412.0), frame_id="alice/wifi_link")


@pytest.fixture
def map_dir(tmp_path) -> Path:
    return save_radiomap(grid_map(), tmp_path / "rm")


def make(values: dict) -> WifiFixStage:
    return WifiFixStage(params_from_dict(WifiFixParams, values), namespace="/alice")


def test_scan_to_fix(map_dir):
    st = make({"radiomap": str(map_dir), "wknn": {"k": 4}})
    outs = st.process("wifi/scan", scan_to_msg(scan_at([4.2, 6.1])), 1)
    assert [t for t, _ in outs] == ["wifi/fix"]
    msg = outs[0][1]
    p = pose_from_msg(msg)
    assert msg.header.frame_id == "map" and p.stamp_ns == 5 * 10**9
    assert np.linalg.norm(p.xy - [4.2, 6.1]) < 1.5
    assert np.linalg.eigvalsh(p.cov_xy).min() >= 1.0 - 1e-9       # cov_floor_m = 1 m
    assert msg.pose.covariance[35] == 1e6                           # yaw unknown
    assert st.diag.published["wifi/fix"] == 1 and st.extra_diagnostics()["fixes"] == "1"
    assert st.extra_diagnostics()["map.scans"] == "36"


def test_bad_scans_are_counted_and_dropped(map_dir):
    st = make({"radiomap": str(map_dir)})
    nan = scan_to_msg(scan_at([1, 1]))
    nan.status[1].values[0].value = "nan"
    schema = scan_to_msg(scan_at([1, 1]))
    schema.status[0].values[0].value = "wifi_scan.v0"
    loud = scan_to_msg(scan_at([1, 1]))
    loud.status[2].values[0].value = "12.0"
    for m in (nan, schema, loud):
        assert st.process("wifi/scan", m, 1) == []
    assert dict(st.diag.rejected) == {"nan": 1, "schema_version": 1, "rssi_range": 1}
    # still works afterwards
    assert len(st.process("wifi/scan", scan_to_msg(scan_at([8, 8])), 2)) == 1


def test_declined_fixes_counted_by_reason(map_dir):
    st = make({"radiomap": str(map_dir), "wknn": {"shared_threshold": 0.9}})
    foreign = WifiScan(1, ("aa:bb:cc:dd:ee:01", "aa:bb:cc:dd:ee:02"), np.array([-50.0, -60.0]),
                       np.array([2412.0, 2412.0]))
    assert st.process("wifi/scan", scan_to_msg(foreign), 1) == []
    half = WifiScan(2, (B[0], "aa:bb:cc:dd:ee:02"), np.array([-50.0, -60.0]), np.array([2412.0, 2412.0]))
    assert st.process("wifi/scan", scan_to_msg(half), 2) == []
    diag = st.extra_diagnostics()
    assert diag["declined.no_candidates"] == "2" and diag["declined.total"] == "2"
    assert sum(st.diag.rejected.values()) == 0


def test_no_map_drops_scans_with_reason(map_dir):
    st = make({})
    assert st.process("wifi/scan", scan_to_msg(scan_at([1, 1])), 1) == []
    assert st.diag.rejected["no_map"] == 1
    assert "no radio map" in st.extra_diagnostics()["error"]
    from msg_adapters.diagnostics import stage_diagnostics
    status = stage_diagnostics("/alice/wifi_fix_node", st, 10).status[0]
    level = status.level if isinstance(status.level, int) else status.level[0]   # byte field
    assert level >= 1 and any(kv.key == "error" for kv in status.values)


def test_bad_parameters(map_dir, tmp_path):
    with pytest.raises(ConfigError, match="method"):
        make({"method": "magic"})
    with pytest.raises(ConfigError, match="WifiFixParams.wknn"):
        make({"wknn": {"k": 0}})
    with pytest.raises(ConfigError, match="unknown"):
        make({"wknn": {"kk": 3}})
    with pytest.raises(MapError, match="does not exist"):
        make({"radiomap": str(tmp_path / "nope")})


@pytest.mark.parametrize("method", ["pathloss", "coverage"])
def test_other_methods(map_dir, method):
    from indoor_loc.wifi.methods import available_methods
    if method not in available_methods():
        pytest.skip(f"{method} not available")
    st = make({"radiomap": str(map_dir), "method": method})
    outs = st.process("wifi/scan", scan_to_msg(scan_at([3, 7])), 1)
    assert len(outs) + sum(st.declined.values()) == 1


def test_config_file_parses_and_matches_defaults():
    files = load_params_file(ROOT / "config" / "wifi_fix_node.yaml")
    values = params_for_node(files, "wifi_fix_node", "/alice")
    p = params_from_dict(WifiFixParams, values)
    from indoor_loc.wifi.wknn import WknnParams
    assert params_from_dict(WknnParams, p.wknn) == WknnParams()     # the file documents the defaults
    assert p.radiomap == "" and p.method == "wknn"


def test_node_declares_dotted_method_parameters(map_dir, ros_domain):
    rclpy = pytest.importorskip("rclpy")
    from rclpy.parameter import Parameter

    from indoor_loc.nodes.base import StageNode
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    try:
        node = StageNode(WifiFixStage, context=ctx, parameter_overrides=[
            Parameter("radiomap", value=str(map_dir)), Parameter("wknn.k", value=2),
            Parameter("wknn.error_type", value="l1"), Parameter("coverage.mimo", value=False)])
        try:
            assert node.stage.positioner.params.k == 2 and node.stage.positioner.params.error_type == "l1"
            assert node.get_parameter("wknn.shared_threshold").value == 0.6
            assert node.stage.params.coverage.mimo is False
            res = node._on_set_params([Parameter("wknn.k", value=3)])
            assert not res.successful
        finally:
            node.destroy_node()
        with pytest.raises(ConfigError, match="wknn.kk"):
            StageNode(WifiFixStage, context=ctx, parameter_overrides=[Parameter("wknn.kk", value=2)])
    finally:
        rclpy.shutdown(context=ctx)


def test_two_floors_fix_carries_the_floor_and_fallback_is_counted(tmp_path):
    """A two-floor map (format v2): wifi/fix z = the detected floor's height, covariance[14] its
    variance, diagnostics name the floor; WKNN declines are positioned by the fallback and counted."""
    from indoor_loc.wifi.radiomap import add_fingerprints, empty_radiomap, map_scans
    lower, upper = grid_map(), grid_map()
    lower.rssi_dbm[:, 3:] -= 15.0                     # APs 3-5 hang upstairs: heard through the slab below
    upper.rssi_dbm[:, :3] -= 15.0                     # APs 0-2 downstairs
    rm = add_fingerprints(empty_radiomap(), lower.positions, map_scans(lower), "g", z_m=0.0, floors={"F1": 0.0})
    rm = add_fingerprints(rm, upper.positions, map_scans(upper), "u", z_m=5.0, floors={"F2": 5.0})
    d = save_radiomap(rm, tmp_path / "rm2")
    st = make({"radiomap": str(d), "method": "powed"})
    s = scan_at([4.0, 6.0])
    down = WifiScan(s.stamp_ns, s.bssid, s.rssi_dbm - np.r_[0, 0, 0, 15, 15, 15], s.freq_mhz, frame_id=s.frame_id)
    msg = st.process("wifi/scan", scan_to_msg(down), 1)[0][1]
    assert msg.pose.pose.position.z == 0.0 and msg.pose.covariance[14] >= 0.0
    assert st.extra_diagnostics()["last_floor"] == "F1"
    s = scan_at([4.0, 6.0], stamp_ns=6 * 10**9)
    up = WifiScan(s.stamp_ns, s.bssid, s.rssi_dbm - np.r_[15, 15, 15, 0, 0, 0], s.freq_mhz, frame_id=s.frame_id)
    msg = st.process("wifi/scan", scan_to_msg(up), 2)[0][1]
    assert msg.pose.pose.position.z == 5.0
    assert st.extra_diagnostics()["floor.F2"] == "1"
    # fallback: WKNN requiring all 36 map scans as candidates declines; powed positions the scan
    st = make({"radiomap": str(d), "method": "wknn", "wknn": {"k": 80}, "fallback": "powed"})
    assert len(st.process("wifi/scan", scan_to_msg(scan_at([4.0, 6.0])), 1)) == 1
    diag = st.extra_diagnostics()
    assert diag["fallback.few_candidates"] == "1" and diag["declined.total"] == "0"
    with pytest.raises(ConfigError, match="fallback"):
        make({"method": "wknn", "fallback": "wknn"})


def test_scan_stamps_going_backwards_are_rejected(map_dir):
    """A scan older than the last one accepted is rejected and counted (``stamp_backwards``), as
    the message contract in docs/nodes.md says; equal and later stamps go on."""
    st = make({"radiomap": str(map_dir)})
    now = 12 * 10**9      # the node's clock at reception
    assert len(st.process("wifi/scan", scan_to_msg(scan_at([4, 4], 10 * 10**9)), now)) == 1
    assert st.process("wifi/scan", scan_to_msg(scan_at([4, 4], 9 * 10**9)), now) == []
    assert dict(st.diag.rejected) == {"stamp_backwards": 1}
    assert len(st.process("wifi/scan", scan_to_msg(scan_at([4, 4], 10 * 10**9)), now)) == 1
    assert len(st.process("wifi/scan", scan_to_msg(scan_at([5, 5], 11 * 10**9)), now)) == 1
    assert st.fixes == 3
