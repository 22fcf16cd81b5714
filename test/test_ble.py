"""BLE beacons: the ble/scan adapter (the wifi/scan mechanism), the online window against the batch merge,
the Microsoft traces' TYPE_BEACON rows, wifi_fix_node taking ble/scan offline and live over DDS."""
from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticArray, KeyValue
from geometry_msgs.msg import PoseWithCovarianceStamped

from indoor_loc.errors import InvalidMessageError
from indoor_loc.params import params_from_dict
from indoor_loc.pipeline.wifi_fix_stage import WifiFixParams, WifiFixStage
from indoor_loc.wifi.ble import BleScan, BleWindow, ble_key, merge_scans, without_ble
from indoor_loc.wifi.radiomap import add_fingerprints, empty_radiomap, save_radiomap
from indoor_loc.wifi.types import WifiScan
from msg_adapters.ble_scan import ble_from_msg, ble_to_msg
from msg_adapters.wifi_scan import scan_to_msg

S = 1_000_000_000
IB = "00000000-0000-beac-2022-000000005938-1-2"


def _ble(t_ns: int, ids, rssi, tx=None) -> BleScan:
    n = len(ids)
    return BleScan(t_ns, tuple(ids), np.asarray(rssi, float), np.full(n, np.nan) if tx is None else np.asarray(tx, float),
                   tuple(f"20:22:b0:00:00:{i:02x}" for i in range(n)))


def test_adapter_round_trip_and_rejections():
    b = BleScan(5 * S, (IB, "abcdef012345"), np.array([-70.0, -81.5]), np.array([-59.0, np.nan]),
                ("20:22:b0:00:51:42", "20:22:b0:00:51:43"), np.array([0.0, 250.0]), "ann/ble_link", "test")
    msg = ble_to_msg(b)
    assert msg.status[0].values[0].value == "ble_scan.v1"
    got = ble_from_msg(msg)
    assert got.beacon_id == b.beacon_id and got.name == b.name and got.stamp_ns == b.stamp_ns
    np.testing.assert_array_equal(got.rssi_dbm, b.rssi_dbm)
    assert got.tx_power_dbm[0] == -59 and math.isnan(got.tx_power_dbm[1])
    np.testing.assert_array_equal(got.age_ms, [0.0, 250.0])
    # a wifi/scan is not a ble/scan (and the reverse): the schema is checked
    wifi = scan_to_msg(WifiScan(S, ("aa:bb:cc:00:00:01",), np.array([-50.0]), np.array([2412.0])))
    with pytest.raises(InvalidMessageError, match="schema"):
        ble_from_msg(wifi)

    def broken(edit) -> DiagnosticArray:
        m = ble_to_msg(b)
        edit(m)
        return m
    cases = [(lambda m: setattr(m.status[1], "name", "bad id!"), "bad_beacon_id"),
             (lambda m: setattr(m.status[2], "name", IB), "duplicate_beacon"),
             (lambda m: m.status[1].values.append(KeyValue(key="tx_power_dbm", value="300")), "out_of_range"),
             (lambda m: setattr(m.status[1].values[0], "value", "nan"), "nan"),
             (lambda m: setattr(m.status[1].values[0], "value", "-130"), "rssi_range")]
    for edit, reason in cases:
        with pytest.raises(InvalidMessageError) as err:
            ble_from_msg(broken(edit))
        assert err.value.reason == reason


def test_window_online_equals_the_batch_merge_and_keys_never_collide(rng):
    wifi = [WifiScan(int(t * S), ("aa:bb:cc:00:00:01", "aa:bb:cc:00:00:02"), rng.uniform(-90, -40, 2),
                     np.array([2412.0, 5180.0]), ("a", "b"), np.array([0.0, 10.0])) for t in np.arange(2.0, 60.0, 3.0)]
    ids = ["b1", "b2", "b3"]
    bles = [_ble(int(t * S), [ids[int(rng.integers(3))]], [rng.uniform(-95, -50)]) for t in np.sort(rng.uniform(0, 60, 80))]
    batch = merge_scans(wifi, bles, 5.0)
    win = BleWindow(5.0)
    events = sorted([(s.stamp_ns, 0, s) for s in bles] + [(s.stamp_ns, 1, s) for s in wifi], key=lambda e: (e[0], e[1]))
    online = [win.merge(s) for _, k, s in events if k == 1 or win.add(s)]
    assert len(online) == len(batch) == len(wifi)
    for a, b in zip(online, batch):
        assert a.bssid == b.bssid
        np.testing.assert_array_equal(a.rssi_dbm, b.rssi_dbm)
        np.testing.assert_array_equal(a.age_ms, b.age_ms)
    # the oracle: each beacon's mean over the readings of the 5 s up to the scan, its newest reading's age
    for s in batch:
        for k, key in enumerate(s.bssid[2:], start=2):
            mine = [(b.stamp_ns, b.rssi_dbm[0]) for b in bles if ble_key(b.beacon_id[0]) == key
                    and s.stamp_ns - 5 * S <= b.stamp_ns <= s.stamp_ns]
            assert mine and s.rssi_dbm[k] == pytest.approx(np.mean([r for _, r in mine]))
            assert s.age_ms[k] == pytest.approx((s.stamp_ns - max(t for t, _ in mine)) * 1e-6)
        assert without_ble(s).bssid == s.bssid[:2]
    assert any(len(s) > 2 for s in batch) and all(key.startswith("ble:") for s in batch for key in s.bssid[2:])


def test_ms_traces_beacon_rows_become_ble_scans():
    from indoor_loc.datasets.ms_indoor import read_trace
    tr = read_trace(Path(__file__).parent / "data" / "ms_site" / "F1" / "path_data_files" / "5f0000000000000000000001.txt")
    assert len(tr.ble) == 1
    b = tr.ble[0]
    assert b.beacon_id == ("fda50693-a4e2-4fb1-afcf-c6eb07647825-10073-61418",)
    assert b.rssi_dbm[0] == -89 and b.tx_power_dbm[0] == -65 and b.name == ("0c:25:76:2f:7d:51",)
    assert b.stamp_ns == 1574240200040 * 1_000_000


def _two_place_map():
    """Two places with the same WiFi, told apart by which beacon is heard."""
    wifi = ("aa:bb:cc:00:00:01", "aa:bb:cc:00:00:02")
    scans = [WifiScan(0, wifi + (ble_key("b1"),), np.array([-50.0, -60.0, -60.0]), np.zeros(3)),
             WifiScan(0, wifi + (ble_key("b2"),), np.array([-50.0, -60.0, -60.0]), np.zeros(3))]
    return add_fingerprints(empty_radiomap(), [[0.0, 0.0], [10.0, 0.0]], scans)


def _query(t_ns: int):
    return scan_to_msg(WifiScan(t_ns, ("aa:bb:cc:00:00:01", "aa:bb:cc:00:00:02"), np.array([-50.0, -60.0]),
                                np.array([2412.0, 2412.0])))


def test_wifi_fix_stage_takes_ble_scan_when_enabled(tmp_path):
    from msg_adapters.pose import pose_from_msg
    d = save_radiomap(_two_place_map(), tmp_path / "rm")
    p = {"radiomap": str(d), "method": "wknn", "wknn": {"k": 1, "shared_threshold": 0.9}, "map_check": {"enabled": False}}
    on = WifiFixStage(params_from_dict(WifiFixParams, {**p, "ble": {"enabled": True}}))
    off = WifiFixStage(params_from_dict(WifiFixParams, p))
    assert [x.topic for x in on.inputs()] == ["wifi/scan", "ble/scan"] and [x.topic for x in off.inputs()] == ["wifi/scan"]
    assert on.process("ble/scan", ble_to_msg(_ble(9 * S, ["b2"], [-58.0])), 9 * S) == []
    fix = pose_from_msg(on.process("wifi/scan", _query(10 * S), 10 * S)[0][1])
    assert fix.xy.tolist() == [10.0, 0.0]
    assert on.extra_diagnostics()["ble.scans_with_beacons"] == "1"
    # the other beacon: the other place; WiFi alone matches both places only in part (declined)
    assert on.process("ble/scan", ble_to_msg(_ble(11 * S, ["b1"], [-58.0])), 11 * S) == []
    fix = pose_from_msg(on.process("wifi/scan", _query(15 * S), 15 * S)[0][1])
    assert fix.xy.tolist() == [0.0, 0.0]
    assert off.process("wifi/scan", _query(15 * S), 15 * S) == [] and on.process("wifi/scan", _query(17 * S), 17 * S) == []
    assert sum(on.declined.values()) == 1                      # at 17 s the readings of 9 s and 11 s are too old
    # a bad ble/scan is counted and leaves the next scans alone; disabled: the topic is not handled
    assert on.process("ble/scan", _query(18 * S), 18 * S) == []         # a wifi/scan on ble/scan
    assert on.diag.rejected["schema_version"] == 1
    assert on.process("ble/scan", ble_to_msg(_ble(19 * S, ["b2"], [-58.0])), 19 * S) == []
    assert pose_from_msg(on.process("wifi/scan", _query(20 * S), 20 * S)[0][1]).xy.tolist() == [10.0, 0.0]
    assert off.process("ble/scan", ble_to_msg(_ble(9 * S, ["b2"], [-58.0])), 9 * S) == []
    assert off.diag.rejected["unknown_topic"] == 1


@pytest.mark.timeout(120)
def test_ble_scan_reaches_wifi_fix_node_live(tmp_path, ros_domain):
    """wifi_fix_node as its own process in /ann with ble.enabled: ble/scan then wifi/scan over DDS give the
    fix at the beacon's place."""
    from helpers_dds import Peer, child_env, ros_node, spin_until
    from indoor_loc.contract import Qos
    from indoor_loc.nodes.base import qos_profile
    from msg_adapters.diagnostics import diagnostics_from_msg
    from msg_adapters.pose import pose_from_msg

    d = save_radiomap(_two_place_map(), tmp_path / "rm")
    exe = str(Path(sys.executable).with_name("wifi_fix_node"))
    peer = Peer([exe, "--ros-args", "-r", "__ns:=/ann", "-p", f"radiomap:={d}", "-p", "method:=wknn",
                 "-p", "wknn.k:=1", "-p", "wknn.shared_threshold:=0.9", "-p", "ble.enabled:=true",
                 "-p", "map_check.enabled:=false"], env=child_env())
    try:
        with ros_node("probe") as (node, ex):
            fixes: list = []
            diags: list = []
            node.create_subscription(PoseWithCovarianceStamped, "/ann/wifi/fix", fixes.append, qos_profile(Qos.RELIABLE))
            node.create_subscription(DiagnosticArray, "/diagnostics",
                                     lambda m: diags.append(diagnostics_from_msg(m).get("/ann/wifi_fix_node")),
                                     qos_profile(Qos.RELIABLE))
            ble_pub = node.create_publisher(DiagnosticArray, "/ann/ble/scan", qos_profile(Qos.RELIABLE))
            wifi_pub = node.create_publisher(DiagnosticArray, "/ann/wifi/scan", qos_profile(Qos.RELIABLE))
            assert spin_until(ex, lambda: ble_pub.get_subscription_count() > 0 and
                              wifi_pub.get_subscription_count() > 0 and any(diags), 60), peer.output()
            now = node.get_clock().now().nanoseconds
            ble_pub.publish(ble_to_msg(_ble(now - 1 * S, ["b2"], [-58.0])))
            assert spin_until(ex, lambda: any(x is not None and x.values.get("in.ble/scan.count") == "1"
                                              for x in diags), 30), peer.output()
            wifi_pub.publish(_query(now))
            assert spin_until(ex, lambda: len(fixes) == 1, 30), peer.output()
            assert pose_from_msg(fixes[0]).xy.tolist() == [10.0, 0.0]
            assert spin_until(ex, lambda: any(x is not None and x.values.get("ble.scans_with_beacons") == "1"
                                              for x in diags), 30), peer.output()
    finally:
        peer.stop()


def test_ms_import_puts_beacons_in_the_map_only_when_asked(tmp_path):
    import yaml
    from indoor_loc.commands.import_ms_indoor import import_ms_indoor
    from indoor_loc.wifi.radiomap import load_radiomap
    from test_ms_indoor import _args
    walks = "5f0000000000000000000001,5f0000000000000000000002"
    assert import_ms_indoor(_args(tmp_path / "plain", survey_walks=walks)) == 0
    assert import_ms_indoor(_args(tmp_path / "ble", survey_walks=walks, ble_window_s=5.0)) == 0
    plain, ble = (load_radiomap(tmp_path / d / "radiomap") for d in ("plain", "ble"))
    assert not any(b.startswith("ble:") for b in plain.bssids)
    assert set(ble.bssids) - set(plain.bssids) == {"ble:fda50693-a4e2-4fb1-afcf-c6eb07647825-10073-61418"}
    params = yaml.safe_load((tmp_path / "ble" / "params.yaml").read_text())["/**/wifi_fix_node"]["ros__parameters"]
    assert params["ble"] == {"enabled": True, "window_s": 5.0}
    assert "ble" not in yaml.safe_load((tmp_path / "plain" / "params.yaml").read_text())["/**/wifi_fix_node"][
        "ros__parameters"]


def test_any_message_on_ble_scan_leaves_the_stage_sound(tmp_path):
    """Hostile ble/scan messages (the wifi/scan mutations: absurd values, random ids and summaries, empty
    and 10 000-entry scans; and tx_power_dbm) between valid ones: no internal error, finite fixes, and the
    valid stream's fixes exactly when every hostile message was refused."""
    from hypothesis import given, settings
    from hypothesis import strategies as st

    from indoor_loc.bench.hostile import hostile_float, restamp, scan_mutation
    from msg_adapters.pose import pose_from_msg
    d = save_radiomap(_two_place_map(), tmp_path / "rm")
    params = params_from_dict(WifiFixParams, {"radiomap": str(d), "method": "wknn", "ble": {"enabled": True},
                                              "wknn": {"k": 1, "shared_threshold": 0.9}, "map_check": {"enabled": False}})
    valid = [(9 * S, "ble/scan", ble_to_msg(_ble(9 * S, ["b2"], [-58.0], [-59.0]))), (10 * S, "wifi/scan", _query(10 * S)),
             (11 * S, "ble/scan", ble_to_msg(_ble(11 * S, ["b1"], [-58.0]))), (15 * S, "wifi/scan", _query(15 * S)),
             (19 * S, "ble/scan", ble_to_msg(_ble(19 * S, ["b2"], [-58.0]))), (20 * S, "wifi/scan", _query(20 * S))]
    base = valid[0][2]

    def run(stream):
        st_ = WifiFixStage(params)
        outs = [o for t, topic, m in stream for _, o in st_.process(topic, m, t)]
        return st_, [pose_from_msg(o).xy.tolist() for o in outs]
    clean_stage, clean = run(valid)
    assert clean == [[10.0, 0.0], [0.0, 0.0], [10.0, 0.0]] and not clean_stage.diag.rejected

    @st.composite
    def tx_power(draw):
        from diagnostic_msgs.msg import KeyValue
        import copy
        m = copy.deepcopy(base)
        m.status[1].values = [kv for kv in m.status[1].values if kv.key != "tx_power_dbm"] + [
            KeyValue(key="tx_power_dbm", value=draw(hostile_float.map(repr)))]
        return m

    @settings(max_examples=40, deadline=None)
    @given(st.lists(st.tuples(st.integers(0, len(valid) - 1), st.one_of(scan_mutation(base, 10_000), tx_power())),
                    min_size=1, max_size=4))
    def check(hostile):
        stream = list(valid)
        for at, msg in sorted(hostile, key=lambda h: -h[0]):
            t = valid[at][0] + 1
            stream.insert(at + 1, (t, "ble/scan", restamp(msg, t)))
        stage, got = run(stream)
        assert stage.diag.rejected["internal_error"] == 0, stage.diag.last_error
        assert all(math.isfinite(v) for xy in got for v in xy)
        if sum(stage.diag.rejected.values()) == len(hostile):
            assert got == clean
    check()


def test_ms_beacon_row_with_implausible_tx_power_keeps_the_beacon_tx_unknown():
    """ms_site2 has beacons advertising +68 dBm: the row keeps its RSSI, its tx power is unknown (NaN),
    so ble/scan's tx_power_dbm bound does not reject the whole scan at import."""
    from indoor_loc.datasets.ms_indoor_ble import beacon_row
    f = ["1574240200040", "TYPE_BEACON", "65d37bb4-8a7b-0bc4-5602-aae9e8ea68b2", "3902", "44406", "68", "-80",
         "1.0", "aa:bb:cc:dd:ee:ff"]
    t, bid, mac, rssi, tx = beacon_row(1574240200040, f)
    assert rssi == -80 and math.isnan(tx)
    f[5] = "-59"
    assert beacon_row(1574240200040, f)[4] == -59
