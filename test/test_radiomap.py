"""Radio map files: round trip, version/format checks, truncation, growth, building from bags."""
from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
import yaml

from indoor_loc.backend.wifi_map import survey_positions
from indoor_loc.errors import MapError
from indoor_loc.wifi.radiomap import (FINGERPRINTS_FILE, MANIFEST, add_fingerprints, empty_radiomap,
                                      interpolate_positions, load_radiomap, map_scans, save_radiomap)
from indoor_loc.wifi.types import RadioMap, WifiScan

B = [f"02:00:00:00:00:{i:02x}" for i in range(5)]


def small_map() -> RadioMap:
    rss = np.array([[-40.0, -71.5, np.nan, np.nan, np.nan],
                    [np.nan, -60.25, -88.0, np.nan, np.nan],
                    [np.nan, np.nan, np.nan, np.nan, np.nan],          # a scan that heard nothing
                    [-99.0, np.nan, -30.0, -55.0, np.nan]])            # B[4]: never heard
    return RadioMap(positions=np.array([[0.0, 0.0], [1.5, 2.25], [3.0, -1.0], [10.123456789, 7.0]]), bssids=B,
                    rssi_dbm=rss, freq_mhz=np.array([2412.0, 5180.0, 2437.0, 0.0, 2462.0]),
                    ssids=["corp", 'odd, "quoted"', "", "ünïcode", "x"], scan_ids=np.array([10, 11, 12, 20]),
                    stamps_ns=np.array([0, 5, 1_700_000_000_123_456_789, 0]),
                    source=["survey", "survey", "walk01", "walk,02"])


def assert_same(a: RadioMap, b: RadioMap) -> None:
    np.testing.assert_array_equal(a.positions, b.positions)
    np.testing.assert_array_equal(a.rssi_dbm, b.rssi_dbm)     # NaN positions equal too
    np.testing.assert_array_equal(a.freq_mhz, b.freq_mhz)
    assert a.bssids == b.bssids and a.ssids == b.ssids and a.source == b.source and a.frame_id == b.frame_id
    np.testing.assert_array_equal(a.scan_ids, b.scan_ids)
    np.testing.assert_array_equal(a.stamps_ns, b.stamps_ns)


def test_round_trip(tmp_path):
    rm = small_map()
    save_radiomap(rm, tmp_path / "m")
    back = load_radiomap(tmp_path / "m")
    assert_same(rm, back)
    man = yaml.safe_load((tmp_path / "m" / MANIFEST).read_text())
    assert man["format"] == "indoor_loc.radiomap" and man["version"] == 1
    assert man["counts"] == {"scans": 4, "aps": 5, "readings": 7}
    assert man["units"]["position"] == "m" and man["frame_id"] == "map"


def test_round_trip_keeps_source_labels_holding_a_nul(tmp_path):
    """A source label may hold any character the CSV file holds, a NUL too: labels stay with their scans."""
    rm = small_map()
    rm.source[2] = "walk\x0001"
    save_radiomap(rm, tmp_path / "m")
    assert load_radiomap(tmp_path / "m").source == ["survey", "survey", "walk\x0001", "walk,02"]


def test_version_and_format_checks(tmp_path):
    d = save_radiomap(small_map(), tmp_path / "m")
    man = yaml.safe_load((d / MANIFEST).read_text())
    man["version"] = 3
    (d / MANIFEST).write_text(yaml.safe_dump(man))
    with pytest.raises(MapError, match="version 3 is not supported"):
        load_radiomap(d)
    man["version"], man["format"] = 1, "something.else"
    (d / MANIFEST).write_text(yaml.safe_dump(man))
    with pytest.raises(MapError, match="not a radio map manifest"):
        load_radiomap(d)
    with pytest.raises(MapError, match="does not exist"):
        load_radiomap(tmp_path / "missing")


def test_truncated_or_bad_files(tmp_path):
    d = save_radiomap(small_map(), tmp_path / "m")
    lines = (d / FINGERPRINTS_FILE).read_text().splitlines()
    (d / FINGERPRINTS_FILE).write_text("\n".join(lines[:-1]) + "\n")
    with pytest.raises(MapError, match="manifest says"):
        load_radiomap(d)
    (d / FINGERPRINTS_FILE).write_text("\n".join(lines[:2] + ["11,5,1.5,2.25,survey,02:00:00:00:00:01,,loud,5180"]))
    with pytest.raises(MapError, match="malformed"):
        load_radiomap(d)
    # a quote opening a field and never closed: the rest of the file becomes one field, over csv's limit
    (d / FINGERPRINTS_FILE).write_text("\n".join(lines[:2] + ['"11,' + "5,1.5,2.25\n" * 20_000]))
    for read in (load_radiomap, survey_positions):
        with pytest.raises(MapError, match="malformed"):
            read(d)


def test_save_rejects_inconsistent_maps(tmp_path):
    rm = small_map()
    rm.scan_ids = np.array([1, 1, 2, 3])
    with pytest.raises(MapError, match="unique"):
        save_radiomap(rm, tmp_path / "a")
    rm = small_map()
    rm.rssi_dbm[0, 0] = 5.0
    with pytest.raises(MapError, match="dBm"):
        save_radiomap(rm, tmp_path / "b")


def test_map_without_column_file_loads(tmp_path):
    """A map directory with only the manifest and the long CSV (columns derived from the readings)."""
    rm = small_map()
    d = save_radiomap(rm, tmp_path / "m")
    (d / "aps.csv").unlink()
    man = yaml.safe_load((d / MANIFEST).read_text())
    del man["counts"]["aps"]
    (d / MANIFEST).write_text(yaml.safe_dump(man))
    back = load_radiomap(d)
    assert back.bssids == B[:4]               # the never-heard AP has no reading to recover it from
    np.testing.assert_array_equal(back.rssi_dbm, rm.rssi_dbm[:, :4])


def test_add_fingerprints_grows_columns_and_keeps_original():
    rm = small_map()
    before = rm.rssi_dbm.copy()
    scans = [WifiScan(100, (B[1], "aa:aa:aa:aa:aa:01"), np.array([-50.0, -60.0]), np.array([5180.0, 2412.0]),
                      ssid=("odd", "new")),
             WifiScan(200, ("aa:aa:aa:aa:aa:02",), np.array([-70.0]), np.array([2437.0]))]
    out = add_fingerprints(rm, [[1, 1], [2, 2]], scans, source="walk07")
    assert out.n_scans == 6 and out.n_aps == 7
    assert out.bssids[:5] == B and out.bssids[5:] == ["aa:aa:aa:aa:aa:01", "aa:aa:aa:aa:aa:02"]
    np.testing.assert_array_equal(out.rssi_dbm[:4, :5], before)
    assert np.all(np.isnan(out.rssi_dbm[:4, 5:]))
    assert out.rssi_dbm[4, 1] == -50.0 and out.rssi_dbm[4, 5] == -60.0 and out.rssi_dbm[5, 6] == -70.0
    np.testing.assert_array_equal(out.scan_ids[4:], [21, 22])
    np.testing.assert_array_equal(out.stamps_ns[4:], [100, 200])
    assert out.source[4:] == ["walk07", "walk07"] and out.ssids[5] == "new"
    np.testing.assert_array_equal(rm.rssi_dbm, before)           # not modified
    assert rm.n_scans == 4
    grown = add_fingerprints(empty_radiomap(), [[0, 0]], scans[:1], source=["a"])
    assert grown.n_scans == 1 and grown.scan_ids.tolist() == [0]
    with pytest.raises(MapError, match="positions for"):
        add_fingerprints(rm, [[0, 0]], scans)
    with pytest.raises(MapError, match="NaN"):
        add_fingerprints(rm, [[0, np.nan], [1, 1]], scans)
    # map_scans is the inverse view
    back = map_scans(out)
    assert back[4].bssid == (B[1], "aa:aa:aa:aa:aa:01")


def test_survey_spacing_counts_a_repeated_position_once():
    from indoor_loc.wifi.radiomap import nominal_spacing_m
    bss = ("02:00:00:00:00:01",)

    def scan(i):
        return WifiScan(i, bss, np.array([-50.0]), np.array([2412.0]))
    pts = [[0.0, 0.0]] * 5 + [[2.0, 0.0]] * 5 + [[2.0, 3.0]] * 5       # three points, each scanned 5 times
    rm = add_fingerprints(empty_radiomap(), pts, [scan(i) for i in range(15)], "s")
    assert nominal_spacing_m(rm) == pytest.approx(2.0)                  # nearest: 2, 2, 3 m
    up = add_fingerprints(rm, [[0.0, 0.5]], [scan(15)], "t", z_m=5.0)   # alone on its floor: no pair there
    assert nominal_spacing_m(up) == pytest.approx(2.0)
    assert np.isnan(nominal_spacing_m(add_fingerprints(empty_radiomap(), [[1.0, 1.0]] * 2,
                                                       [scan(0), scan(1)], "s")))


def test_interpolate_positions():
    t = np.array([10, 20, 40], np.int64) * 10**9
    xy = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 20.0]])
    q = np.array([5, 10, 15, 30, 40, 41], np.int64) * 10**9
    pos, inside = interpolate_positions(q, t[::-1], xy[::-1])   # unsorted path input
    assert inside.tolist() == [False, True, True, True, True, False]
    np.testing.assert_allclose(pos[inside], [[0, 0], [5, 0], [10, 10], [10, 20]])
    assert np.all(np.isnan(pos[~inside]))


# ----------------------------------------------------------------------------------------------
# building from bags
# ----------------------------------------------------------------------------------------------
def _write_bag(path: Path) -> None:
    bag = pytest.importorskip("indoor_loc.bag")
    from msg_adapters.path import path_to_msg
    from msg_adapters.wifi_scan import scan_to_msg
    s = 10**9
    with bag.BagWriter(path) as w:
        # truth: (0,0) at 1 s, (10,0) at 3 s, (10,10) at 5 s
        w.write("/alice/ground_truth", path_to_msg(np.array([1, 3, 5]) * s, [[0, 0], [10, 0], [10, 10]]), 1 * s)
        for k, t in enumerate([0.5, 1.5, 2.0, 2.5, 3.0, 3.5, 4.0, 4.5, 6.0]):   # first, last outside the span
            scan = WifiScan(int(t * s), (B[0], B[1]), np.array([-40.0 - k, -60.0 + k]), np.array([2412.0, 5180.0]),
                            frame_id="alice/wifi_link", source="test")
            w.write("/alice/wifi/scan", scan_to_msg(scan), int(t * s))
        bad = scan_to_msg(WifiScan(int(2.5 * s), (B[2],), np.array([-50.0]), np.array([2412.0])))
        bad.status[1].values[0].value = "nan"
        w.write("/alice/wifi/scan", bad, int(2.5 * s))
        # a namespace with scans but no truth
        w.write("/bob/wifi/scan", scan_to_msg(WifiScan(2 * s, (B[3],), np.array([-45.0]), np.array([2412.0]))),
                2 * s)


def test_build_from_bag_and_run_with_its_params(tmp_path):
    from indoor_loc.commands.radiomap import build, info_lines
    bag_path = tmp_path / "walk.mcap"
    _write_bag(bag_path)
    out = tmp_path / "rm"
    rm, report = build([bag_path], out)
    alice, bob = report["bags"]["/alice"], report["bags"]["/bob"]
    assert alice == {"scans": 9, "used": 7, "outside_truth": 2, "no_truth": 0, "invalid": {"nan": 1}, "z_m": 0.0,
                     "label": "alice"}
    assert bob["no_truth"] == 1 and bob["used"] == 0
    back = load_radiomap(out)
    assert back.n_scans == 7
    np.testing.assert_allclose(back.positions[[0, 1, 5]], [[2.5, 0.0], [5.0, 0.0], [10.0, 5.0]])  # 1.5, 2, 4 s
    assert back.source == ["alice"] * 7
    np.testing.assert_array_equal(back.stamps_ns[:2], [1_500_000_000, 2 * 10**9])
    assert back.rssi_dbm[1, back.bssids.index(B[0])] == -42.0
    params = yaml.safe_load((out / "params.yaml").read_text())
    # no reading ages, one floor: the best measured WKNN, with powed k-NN for the scans it declines
    assert params == {"/**/wifi_fix_node": {"ros__parameters": {
        "radiomap": str(out.resolve()), "method": "wknn", "fallback": "powed",
        "wknn": {"k": 3, "shared_threshold": 0.6, "shared_strict": True, "error_type": "rms"}}}}
    assert any("scans 7" in ln for ln in info_lines(out))

    # the params file positions the same (or another) recording with no editing
    from indoor_loc.bag import bag_topics
    from indoor_loc.pipeline.offline import run_offline
    res = tmp_path / "out.mcap"
    moved = tmp_path / "elsewhere"
    moved.mkdir()
    shutil.copy(out / "params.yaml", moved / "params.yaml")
    summary = run_offline([bag_path], res, nodes=["wifi"], params=moved / "params.yaml", progress=False)
    topics = bag_topics(res)
    assert topics["/alice/wifi/fix"] == ("geometry_msgs/msg/PoseWithCovarianceStamped", 9)
    assert summary.per_stage["/alice/wifi_fix_node"]["rejected.nan"] == "1"
    assert "/bob/wifi/fix" not in topics        # its AP is not in the map: declined, not published


def test_build_with_floor_plans_configures_the_plan_bounded_field(tmp_path):
    """--floor-plans: params.yaml names the plans and turns on powed k-NN's path-loss field, as the
    ms-indoor importer's params do; a directory holding no plan is refused before anything is written."""
    import json

    from indoor_loc.commands.radiomap import build
    from indoor_loc.errors import ConfigError
    from indoor_loc.wifi.radio_field import PLAN_FIELD_WEIGHT
    bag_path = tmp_path / "walk.mcap"
    _write_bag(bag_path)
    plans = tmp_path / "floors" / "F1"
    plans.mkdir(parents=True)
    (plans / "map.yaml").write_text(yaml.safe_dump({"floor": "F1", "z_m": 0.0, "width_m": 20.0, "height_m": 10.0,
                                                    "frame_id": "map"}))
    ring = [[0, 0], [200, 0], [200, 100], [0, 100], [0, 0]]
    (plans / "geojson_map.json").write_text(json.dumps({"type": "FeatureCollection", "features": [
        {"type": "Feature", "properties": {}, "geometry": {"type": "Polygon", "coordinates": [ring]}}]}))
    out = tmp_path / "rm"
    build([bag_path], out, floor_plans=tmp_path / "floors")
    wifi = yaml.safe_load((out / "params.yaml").read_text())["/**/wifi_fix_node"]["ros__parameters"]
    assert wifi["floor_plans"] == str((tmp_path / "floors").resolve())
    assert wifi["powed"] == {"field_weight": PLAN_FIELD_WEIGHT}
    assert wifi["method"] == "wknn" and wifi["fallback"] == "powed"

    empty = tmp_path / "no_plans"
    empty.mkdir()
    with pytest.raises(ConfigError, match="floor_plans"):
        build([bag_path], tmp_path / "rm2", floor_plans=empty)
    assert not (tmp_path / "rm2").exists()


def test_build_from_putmc_survey(tmp_path):
    from conftest import dataset
    from indoor_loc.commands.radiomap import build
    root = dataset("putmc")
    rm, report = build([], tmp_path / "rm", putmc=root, method="coverage")
    assert rm.n_scans == 114 and rm.n_aps == 119
    back = load_radiomap(tmp_path / "rm")
    # ENU: y = 1049/28.50518 - y_img; location 0 of positions.map is in the image's upper half
    assert back.positions[:, 1].min() > 0 and back.positions[:, 1].max() < 1049 / 28.50518
    assert yaml.safe_load((tmp_path / "rm" / "params.yaml").read_text())["/**/wifi_fix_node"]["ros__parameters"][
        "method"] == "coverage"
