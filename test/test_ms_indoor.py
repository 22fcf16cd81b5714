"""Microsoft indoor-location traces: parser, bags, importer (hand-written traces in test/data/ms_site)."""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import pytest
import yaml

from indoor_loc.errors import ConfigError, DatasetError
from indoor_loc.datasets.ms_indoor import read_trace, scans_with_truth, split_map_test
from indoor_loc.datasets.ms_indoor_site import floor_level, site_floors

SITE = Path(__file__).parent / "data" / "ms_site"
F1 = SITE / "F1" / "path_data_files" / "5f0000000000000000000001.txt"
B1 = SITE / "B1" / "path_data_files" / "5f0000000000000000000002.txt.gz"
T0 = 1574240200000


def test_trace_every_row_type_unsorted_and_duplicates():
    tr = read_trace(F1)
    assert tr.floor == "F1" and tr.device == "ACME P1"
    assert len(tr.acc) == len(tr.gyro) == len(tr.mag) == len(tr.rotvec) == 50
    assert len(tr.acc_uncal) == len(tr.gyro_uncal) == len(tr.mag_uncal) == 50
    assert np.all(np.diff(tr.acc.t_ns) > 0) and tr.acc.t_ns[0] == T0 * 1_000_000
    assert tr.acc_uncal.values.shape == (50, 6)
    assert tr.beacons == 1
    assert tr.row_counts["TYPE_BLUE"] == 1 and tr.row_counts["TYPE_DIST1"] == 1
    # waypoints sorted, in metres
    assert tr.waypoint_t.tolist() == [(T0 + 5) * 1_000_000, (T0 + 905) * 1_000_000]
    # three scans, sorted; the malformed BSSID row is dropped and counted
    assert [s.stamp_ns // 1_000_000 - T0 for s in tr.scans] == [400, 800, 950]
    assert tr.dropped["bad_bssid"] == 1
    s1 = tr.scans[0]
    assert len(s1) == 3 and len(set(s1.bssid)) == 3
    d = dict(zip(s1.bssid, s1.rssi_dbm))
    assert d["aa:bb:cc:00:00:01"] == -50                      # upper-case BSSID normalised
    assert d["aa:bb:cc:00:00:03"] == -78                      # duplicate: the most recently seen
    ages = dict(zip(s1.bssid, s1.age_ms))
    assert ages["aa:bb:cc:00:00:02"] == 4000 and ages["aa:bb:cc:00:00:03"] == 100
    assert any("duplicate BSSID" in o for o in tr.oddities)
    # rotation vector -> unit quaternion (45° about z)
    q = tr.quaternions_xyzw()[0]
    assert np.isclose(np.linalg.norm(q), 1.0) and np.isclose(q[3], np.cos(np.pi / 8), atol=1e-6)


def test_gz_trace_and_missing_sensor():
    tr = read_trace(B1)
    assert len(tr.mag) == 0 and len(tr.acc) == 50
    assert any("no mag rows" in o for o in tr.oddities)


def test_scans_with_truth_interpolates_inside_the_waypoint_span():
    tr = read_trace(F1)
    scans, xy = scans_with_truth(tr)
    assert len(scans) == 2                                       # the scan at +950 ms is outside
    np.testing.assert_allclose(xy[0], [10.0 + 9.0 * 395 / 900, 20.0])


def test_floor_levels_split_and_bad_input(tmp_path):
    assert [floor_level(n) for n in ("B2", "B1", "F1", "F3", "1F", "L8")] == [-2, -1, 0, 2, 0, 7]
    assert floor_level("roof") is None                       # no convention: a site-level fallback
    m, t = split_map_test([f"{i:02d}" for i in range(10)][::-1])
    assert m == ["00", "02", "04", "05", "07", "09"] and t == ["01", "03", "06", "08"]
    (tmp_path / "x.txt").write_text("# header only\n")
    with pytest.raises(DatasetError, match="no data rows"):
        read_trace(tmp_path / "x.txt")
    with pytest.raises(DatasetError, match="does not exist"):
        site_floors(tmp_path / "nope")


def _args(out: Path, **kw) -> argparse.Namespace:
    base = dict(dataset_dir=SITE, out_dir=out, floors="", walks="", survey_walks="", storey_height_m=5.0,
                overwrite=False)
    base.update(kw)
    return argparse.Namespace(**base)


def test_import_writes_bags_map_plans_params_and_round_trips(tmp_path):
    from indoor_loc.bag import read_bag
    from indoor_loc.commands.import_ms_indoor import import_ms_indoor
    from msg_adapters.imu import imu_from_msg, mag_from_msg
    from msg_adapters.path import path_from_msg
    from msg_adapters.wifi_scan import scan_from_msg
    from indoor_loc.wifi.radiomap import load_radiomap

    out = tmp_path / "out"
    # one walk per floor: mark both as survey walks so the map spans two floors
    assert import_ms_indoor(_args(out, survey_walks="5f0000000000000000000001,5f0000000000000000000002")) == 0
    bag = out / "F1" / "5f0000000000000000000001.mcap"
    msgs = list(read_bag(bag))
    ns = "/f1_5f0000000000000000000001"
    by = {}
    for m in msgs:
        by.setdefault(m.topic, []).append(m)
    assert {t: len(v) for t, v in by.items()} == {
        f"{ns}/ground_truth": 1, f"{ns}/imu/data_raw": 50, f"{ns}/imu/mag": 50, f"{ns}/imu/data": 50,
        f"{ns}/wifi/scan": 3, f"{ns}/ble/scan": 1}
    stamps = [m.stamp_ns for m in msgs]
    assert stamps == sorted(stamps)
    tr = read_trace(F1)
    raw = [imu_from_msg(m.msg) for m in by[f"{ns}/imu/data_raw"]]
    np.testing.assert_allclose([r.acc for r in raw], tr.acc.values[:, :3])
    np.testing.assert_allclose([r.gyro for r in raw], tr.gyro.values[:, :3])
    _, field = mag_from_msg(by[f"{ns}/imu/mag"][0].msg)
    np.testing.assert_allclose(field, tr.mag.values[0, :3] * 1e-6)
    ori = imu_from_msg(by[f"{ns}/imu/data"][0].msg)
    np.testing.assert_allclose(ori.quat_xyzw, tr.quaternions_xyzw()[0])
    scans = [scan_from_msg(m.msg) for m in by[f"{ns}/wifi/scan"]]
    for a, b in zip(scans, tr.scans):
        assert a.stamp_ns == b.stamp_ns and a.bssid == b.bssid
        np.testing.assert_allclose(a.rssi_dbm, b.rssi_dbm)
        np.testing.assert_allclose(a.age_ms, b.age_ms)
    t, xy, _ = path_from_msg(by[f"{ns}/ground_truth"][0].msg)
    np.testing.assert_array_equal(t, tr.waypoint_t)
    np.testing.assert_allclose(xy, tr.waypoint_xy)
    assert by[f"{ns}/ground_truth"][0].msg.poses[0].pose.position.z == 0.0      # F1 = ground floor
    # the B1 walk has no magnetometer: no imu/mag topic, the rest is there
    topics_b1 = {m.topic for m in read_bag(out / "B1" / "5f0000000000000000000002.mcap")}
    assert "/b1_5f0000000000000000000002/imu/mag" not in topics_b1
    assert "/b1_5f0000000000000000000002/imu/data_raw" in topics_b1
    # radio map: both floors, the in-span scans only, with z and ages
    rm = load_radiomap(out / "radiomap")
    assert rm.n_scans == 4 and rm.floors == {"B1": -5.0, "F1": 0.0}
    assert sorted(set(rm.z_m.tolist())) == [-5.0, 0.0]
    assert rm.age_ms is not None and np.nanmax(rm.age_ms) == 4000
    from indoor_loc.commands.radiomap import info_lines
    info = "\n".join(info_lines(out / "radiomap"))
    assert "floors: B1 z=-5 m (2 scans), F1 z=0 m (2 scans)" in info and "reading ages: median" in info
    params = yaml.safe_load((out / "params.yaml").read_text())
    wifi = params["/**/wifi_fix_node"]["ros__parameters"]
    assert Path(wifi["radiomap"]) == out / "radiomap" and wifi["method"] == "powed"    # ages, two floors
    assert Path(wifi["floor_plans"]) == out / "floors" and wifi["powed"] == {"field_weight": 0.05}   # plans: field on
    # phone yaw 45°, walking east: the heading offset that maps the phone's yaw onto the walk
    assert params["/**/imu_node"]["ros__parameters"]["heading_offset_rad"] == pytest.approx(-np.pi / 4, abs=1e-3)
    plan = yaml.safe_load((out / "floors" / "B1" / "map.yaml").read_text())
    assert plan["z_m"] == -5.0 and plan["width_m"] == 60.0
    assert (out / "floors" / "B1" / "geojson_map.json").exists()
    report = (out / "import_report.md").read_text()
    assert "duplicate BSSID" in report and "no mag rows" in report
    assert "## Heading check" in report and "- F1: 1 waypoint pairs, mean -45.0°, R = 1.00" in report
    split = yaml.safe_load((out / "split.yaml").read_text())
    assert split["F1"]["survey"] == ["5f0000000000000000000001"]
    # a second import onto the same bags is refused unless asked
    with pytest.raises(ConfigError, match="refusing to overwrite"):
        import_ms_indoor(_args(out, floors="F1"))


def test_import_selection_errors(tmp_path):
    from indoor_loc.commands.import_ms_indoor import import_ms_indoor
    with pytest.raises(ConfigError, match="no floor"):
        import_ms_indoor(_args(tmp_path / "o", floors="F9"))
    with pytest.raises(ConfigError, match="matches 2"):
        import_ms_indoor(_args(tmp_path / "o", walks="5f"))
    # a survey walk that is not among the selected floors' walks is named, not ignored
    with pytest.raises(ConfigError, match="--survey-walks: '5f0000000000000000000001' matches 0"):
        import_ms_indoor(_args(tmp_path / "o2", survey_walks="5f0000000000000000000001", floors="B1"))
    with pytest.raises(ConfigError, match="inside the dataset"):
        import_ms_indoor(_args(SITE / "out"))


def test_cli_entry(tmp_path):
    from indoor_loc.cli import main
    assert main(["import", "ms-indoor", str(SITE), str(tmp_path / "o"), "--floors", "F1"]) == 0
    assert (tmp_path / "o" / "F1" / "5f0000000000000000000001.mcap").exists()
    assert main(["import", "ms-indoor", str(SITE), str(tmp_path / "o"), "--floors", "F1"]) == 2


def test_an_unreadable_walk_is_skipped_and_reported_not_fatal(tmp_path, capsys):
    import shutil
    from indoor_loc.commands.import_ms_indoor import import_ms_indoor
    site = tmp_path / "site"
    shutil.copytree(SITE, site)
    (site / "F1" / "path_data_files" / "5f0000000000000000000009.txt.gz").write_bytes(b"not gzip at all")
    args = _args(tmp_path / "out", floors="F1")
    args.dataset_dir = site
    assert import_ms_indoor(args) == 0
    assert (tmp_path / "out" / "F1" / "5f0000000000000000000001.mcap").exists()
    assert "SKIPPED 1 unreadable walk(s): 5f0000000000000000000009" in capsys.readouterr().out
    assert "5f0000000000000000000009: SKIPPED, unreadable" in (tmp_path / "out" / "import_report.md").read_text()


def test_imported_bags_replayed_through_wifi_give_the_core_fixes(tmp_path):
    """indoor-loc run --nodes wifi with the importer's params.yaml = the powed positioner on the same
    map and scans (the live/offline stage adds nothing and loses nothing)."""
    from indoor_loc.bag import read_bag
    from indoor_loc.commands.import_ms_indoor import import_ms_indoor
    from indoor_loc.pipeline.offline import run_offline
    from indoor_loc.wifi.powed_knn import PowedKnn
    from indoor_loc.wifi.powed_knn_params import PowedKnnParams
    from indoor_loc.wifi.radiomap import load_radiomap
    from indoor_loc.wifi.walkable import load_floor_plans
    out = tmp_path / "out"
    assert import_ms_indoor(_args(out, survey_walks="5f0000000000000000000001,5f0000000000000000000002")) == 0
    bag = out / "B1" / "5f0000000000000000000002.mcap"
    run_offline([bag], tmp_path / "run.mcap", nodes=["wifi"], params=out / "params.yaml", progress=False)
    fixes = [m.msg for m in read_bag(tmp_path / "run.mcap") if m.topic.endswith("/wifi/fix")]
    walkable, _ = load_floor_plans(out / "floors")              # the params turn the plan-bounded field on
    pos = PowedKnn(PowedKnnParams(field_weight=0.05), walkable=walkable).fit(load_radiomap(out / "radiomap"))
    assert pos._prior is not None
    expect = [pos.locate(s) for s in read_trace(B1).scans]
    assert len(fixes) == len(expect) == 3 and all(f.ok for f in expect)
    for msg, f in zip(fixes, expect):
        p = msg.pose.pose.position
        np.testing.assert_allclose([p.x, p.y], f.xy, atol=1e-9)
        assert p.z == f.z == -5.0
        np.testing.assert_allclose(np.reshape(msg.pose.covariance, (6, 6))[:2, :2], f.cov, atol=1e-9)
