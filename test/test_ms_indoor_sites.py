"""Microsoft indoor-location format on sites other than ms_site2: floor-name conventions, the quirks of
the competition's files, the importer and the bench on a synthetic site written in the test."""
from __future__ import annotations

import argparse
import gzip
import json
import math
from pathlib import Path

import numpy as np
import pytest
import yaml

from indoor_loc.datasets.ms_indoor import read_trace, scans_with_truth
from indoor_loc.datasets.ms_indoor_site import floor_levels, parse_floor_levels, read_site
from indoor_loc.errors import ConfigError

T0 = 1574240200000
SITE_HEADER = "#\tSiteID:5f00000000000000000000aa\tSiteName:Test mall\tFloorId:x\tFloorName:{floor}\n"


# ---------------------------------------------------------------------------------------------------
# floor names
# ---------------------------------------------------------------------------------------------------
def test_floor_levels_follow_the_sites_conventions():
    lv = {n: v for n, (v, _) in floor_levels(["B2", "B1", "F1", "F3", "1F2"]).items()}
    assert lv == {"B2": -2, "B1": -1, "F1": 0, "F3": 2, "1F2": 3}        # 1F2 matches no convention: above
    # G present: L1 is the first floor above ground (British); M sits between them
    got = floor_levels(["G", "L1", "L2", "M", "2M", "UG"])
    assert {n: v for n, (v, _) in got.items()} == {"G": 0, "L1": 1, "L2": 2, "M": 0.5, "2M": 2.5, "UG": 3}
    assert got["UG"][1].startswith("fallback: its level 0.5 is another floor's")   # UG and M collide
    # below ground: lower ground, then basements, then parking stack from the top
    got = floor_levels(["F1", "LG1", "LG2", "B1", "B2", "P1", "P2", "LM", "BM"])
    assert {n: v for n, (v, _) in got.items()} == {"F1": 0, "LG1": -1, "LG2": -2, "B1": -3, "B2": -4,
                                                   "P1": -5, "P2": -6, "LM": -0.5, "BM": -2.5}
    assert {n: v for n, (v, _) in floor_levels(["BF", "1F", "2F", "P1", "1M"]).items()} == {
        "BF": -1, "1F": 0, "2F": 1, "P1": -2, "1M": 0.5}
    # case, spaces and separators do not matter; unknown names go above the highest floor, in order
    got = floor_levels(["f 2", "b-1", "Roof", "Sky10", "Sky9"])
    assert {n: v for n, (v, _) in got.items()} == {"f 2": 1, "b-1": -1, "Roof": 2, "Sky10": 4, "Sky9": 3}
    assert got["Roof"][1].startswith("fallback: not a known floor name")
    # bare numbers and "Level n": 1 = ground unless a 0 is there
    assert {n: v for n, (v, _) in floor_levels(["-1", "1", "2", "Level 3"]).items()} == {
        "-1": -1, "1": 0, "2": 1, "Level 3": 2}
    assert {n: v for n, (v, _) in floor_levels(["Floor 0", "1", "2"]).items()} == {"Floor 0": 0, "1": 1, "2": 2}
    # overrides win; a derived level that an override holds falls back
    got = floor_levels(["G", "F1", "Roof"], {"Roof": 1, "G": 0})
    assert {n: v for n, (v, _) in got.items()} == {"G": 0, "F1": 2, "Roof": 1}
    assert got["Roof"][1] == "set by the user" and got["F1"][1].startswith("fallback")


def test_parse_floor_levels():
    assert parse_floor_levels(" G=0, M=0.5 ,P1=-2") == {"G": 0.0, "M": 0.5, "P1": -2.0}
    assert parse_floor_levels("") == {}
    for bad, msg in (("G", "NAME=LEVEL"), ("G=x", "NAME=LEVEL"), ("=1", "NAME=LEVEL"), ("G=nan", "NAME=LEVEL"),
                     ("G=0,G=1", "given twice"), ("G=0,M=0", "two floors at one level")):
        with pytest.raises(ConfigError, match=msg):
            parse_floor_levels(bad)


# ---------------------------------------------------------------------------------------------------
# quirks of the trace files
# ---------------------------------------------------------------------------------------------------
def test_trace_quirks_are_recovered_or_counted(tmp_path):
    t = T0
    lines = [
        "\ufeff#\tstartTime:1574240200000\n",
        "# SiteID:abc floorname:LG1 Brand:ACME Model:P 2\n",            # spaces, lower-case key
        f"{t}\tTYPE_WAYPOINT\t1.0\t2.0\n",
        f"{t + 10}\tTYPE_ACCELEROMETER\t0.1\t0.2\t9.8\t3{t + 10}\tTYPE_GYROSCOPE\t0.01\t0.02\t0.03\t3\r\n",   # run on
        f"{t + 20}\tTYPE_ACCELEROMETER\t0.1\t0.2\n",                    # short row
        f"{t + 30}\tTYPE_ACCELEROMETER\t0.1\tx\t9.8\t3\n",              # non-numeric field
        "1574240200O40\tTYPE_ACCELEROMETER\t0.1\t0.2\t9.8\t3\n",       # non-numeric stamp
        f"{t + 50}\tTYPE_ACCELEROMETER\t0.1\t0.2\t9.8\t3\n",
        f"{t + 100}\tTYPE_WIFI\tnet\taa:bb:cc:00:00:01\t-50\t2412\t{t + 90}\n",
        f"{t + 100}\tTYPE_WIFI\tno freq\taa:bb:cc:00:00:02\t-60\t{t + 80}\n",
        f"{t + 100}\tTYPE_WIFI\tno seen\taa:bb:cc:00:00:03\t-70\t5180\n",
        f"{t + 100}\tTYPE_WIFI\tbare\tAA-BB-CC-00-00-04\t-75\n",        # neither; dashes, upper case
        f"{t + 100}\tTYPE_WIFI\ttab\tin ssid\taa:bb:cc:00:00:05\t-80\t2437\t{t + 100}{t + 100}\tTYPE_WIFI\t"
        f"x\taa:bb:cc:00:00:06\t-81\t2437\t{t + 99}\n",                 # ssid with a tab, then a run-on
        f"{t + 100}\tTYPE_WIFI\tbad\taa:bb:cc:00:00:07\tstrong\t2412\t{t}\n",
        f"{t + 100}\tTYPE_WIFI\tshort\n",
        f"not a record{t + 100}\tTYPE_WIFI\tglued\taa:bb:cc:00:00:08\t-82\t2412\t{t + 98}\n",   # junk, then a run-on
        f"{t + 150}\tTYPE_BEACON\tuuid\t1\t2\t-60\t-70\t1.5\tdd:ee:ff:00:00:01\t{t + 150}\n",
        f"{t + 160}\tTYPE_WAYPOINT\t5.0\n",                              # short waypoint
        f"{t + 200}\tTYPE_WAYPOINT\t3.0\t2.0\n",
        f"{t + 210}\tTYPE_SOMETHING_NEW\t1\n",
        f"{'9' * 20}\tTYPE_ACCELEROMETER\t0.1\t0.2\t9.8\t3\n",         # a stamp no int64 ns can hold
        "#\tendTime:1574240200300\n",
    ]
    p = tmp_path / "5f0000000000000000000003.txt"
    p.write_text("".join(lines), encoding="utf-8")
    tr = read_trace(p)
    assert tr.floor == "LG1" and tr.device == "ACME P 2" and tr.header["startTime"] == "1574240200000"
    assert tr.header["endTime"] == "1574240200300"
    assert len(tr.acc) == 2 and len(tr.gyro) == 1 and tr.gyro.t_ns[0] == (T0 + 10) * 1_000_000
    assert tr.dropped["malformed_acc"] == 2 and tr.dropped["malformed"] == 2       # the stamp, the junk
    assert tr.dropped["malformed_wifi"] == 2 and tr.dropped["malformed_waypoint"] == 1
    assert tr.beacons == 1 and tr.row_counts["TYPE_SOMETHING_NEW"] == 1 and tr.dropped["stamp_range"] == 1
    assert len(tr.waypoint_t) == 2
    (scan,) = tr.scans
    got = {b: (r, f, a) for b, r, f, a in zip(scan.bssid, scan.rssi_dbm, scan.freq_mhz, scan.age_ms)}
    assert set(got) == {f"aa:bb:cc:00:00:0{i}" for i in (1, 2, 3, 4, 5, 6, 8)}
    assert got["aa:bb:cc:00:00:01"] == (-50, 2412, 10)
    assert got["aa:bb:cc:00:00:02"][1:] == (0, 20)                     # frequency unknown = 0
    assert got["aa:bb:cc:00:00:03"][1] == 5180 and math.isnan(got["aa:bb:cc:00:00:03"][2])
    assert got["aa:bb:cc:00:00:04"][0] == -75 and math.isnan(got["aa:bb:cc:00:00:04"][2])
    assert got["aa:bb:cc:00:00:06"] == (-81, 2437, 1)
    assert scan.ssid[scan.bssid.index("aa:bb:cc:00:00:05")] == "tab\tin ssid"
    odd = "\n".join(tr.oddities)
    for text in ("3 lines held records run together", "2 WiFi readings without a frequency",
                 "2 WiFi readings without a last-seen time", "2 rows dropped: malformed_acc",
                 "rows not used: TYPE_SOMETHING_NEW 1"):
        assert text in odd, (text, odd)


# ---------------------------------------------------------------------------------------------------
# a synthetic site
# ---------------------------------------------------------------------------------------------------
LON0, LAT0 = 120.0, 30.0
K_LAT = math.radians(1.0) * 6378137.0
K_LON = K_LAT * math.cos(math.radians(LAT0 + 20 / K_LAT))


def _lonlat(x, y):
    return [LON0 + x / K_LON, LAT0 + y / K_LAT]


def _plan(multi: bool) -> dict:
    """A 60 × 40 m outline with one shop, in lon/lat as the competition's plans; the shop as a
    MultiPolygon or a Polygon."""
    outline = [[_lonlat(0, 0), _lonlat(60, 0), _lonlat(60, 40), _lonlat(0, 40), _lonlat(0, 0)]]
    shop = [[_lonlat(40, 25), _lonlat(55, 25), _lonlat(55, 35), _lonlat(40, 35), _lonlat(40, 25)]]
    return {"type": "FeatureCollection", "features": [
        {"type": "Feature", "properties": {"floor": "x"}, "geometry": {"type": "Polygon", "coordinates": outline}},
        {"type": "Feature", "properties": {}, "geometry": {"type": "MultiPolygon", "coordinates": [shop]}
         if multi else {"type": "Polygon", "coordinates": shop}}]}


def _walk(path: Path, floor: str, floor_ix: int, k: int, rng, *, waypoints: int = 2, gz: bool = False,
          x_end: float = 55.0):
    """One walk across the floor (y = 5 + 6 k, x 5 -> 55 m in 25 s): IMU at 10 Hz, a WiFi scan every
    2.5 s from per-floor APs (path loss in distance, 6 dB per floor between floors), two waypoints (or
    ``waypoints`` = 1: the first, 0: none)."""
    t0 = T0 + 10_000_000 * floor_ix + 100_000 * k
    y = 5.0 + 6.0 * (k % 6)
    aps = [(f"aa:00:00:00:{f:02x}:{j:02x}", 10.0 + 20.0 * (j % 3), 8.0 + 24.0 * (j // 3), f)
           for f in range(4) for j in range(6)]
    out = [SITE_HEADER.format(floor=floor), "#\tBrand:ACME\tModel:P1\n"]
    for i in range(250):
        t = t0 + 100 * i
        out.append(f"{t}\tTYPE_ACCELEROMETER\t0.1\t0.2\t9.8\t3\n{t}\tTYPE_GYROSCOPE\t0.0\t0.0\t0.01\t3\n"
                   f"{t}\tTYPE_MAGNETIC_FIELD\t20\t-30\t-12\t3\n{t}\tTYPE_ROTATION_VECTOR\t0\t0\t0.38\t3\n")
    for i in range(10):
        t = t0 + 1000 + 2500 * i
        x = 5.0 + 50.0 * (t - t0) / 25_000
        for b, ax, ay, f in aps:
            d = math.hypot(x - ax, y - ay) + 1.0
            rss = -35.0 - 25.0 * math.log10(d) - 6.0 * abs(f - floor_ix) * 3 + rng.normal(0, 2)
            if rss > -95:
                out.append(f"{t}\tTYPE_WIFI\tmall\t{b}\t{rss:.0f}\t2412\t{t - 300}\n")
    out += [f"{t0}\tTYPE_WAYPOINT\t5.0\t{y}\n", f"{t0 + 25_000}\tTYPE_WAYPOINT\t{x_end}\t{y}\n"][:waypoints]
    text = "".join(out)
    if gz:
        path.with_name(path.name + ".gz").write_bytes(gzip.compress(text.encode()))
    else:
        path.write_text(text)


def test_geojson_extent_in_metres_and_malformed_plans(tmp_path):
    """A lon/lat plan's extent in metres (the 60 × 40 m outline); a plan of no usable coordinates,
    whatever its shape, is a MapError (read_site notes it), never another exception."""
    from indoor_loc.datasets.ms_indoor_site import geojson_extent_m
    from indoor_loc.errors import MapError
    p = tmp_path / "geojson_map.json"
    p.write_text(json.dumps(_plan(True)))
    assert np.allclose(geojson_extent_m(p), (60.0, 40.0), atol=1e-3)
    for text in ('{"features": null}', "[]", '{"features": [null, 5, {"geometry": 3}, {"geometry": {}}]}',
                 '{"features": [{"geometry": {"coordinates": [[1e400, 2], [3, "a"]]}}]}', "not json"):
        p.write_text(text)
        with pytest.raises(MapError):
            geojson_extent_m(p)


def test_a_damaged_gz_walk_is_a_dataset_error(tmp_path):
    """A .txt.gz whose deflate stream is damaged (zlib.error, no OSError) is an unreadable walk, which the
    importer skips and reports, not an exception that stops it."""
    from indoor_loc.datasets.ms_indoor import has_truth_span
    from indoor_loc.errors import DatasetError
    d = tmp_path / "F2" / "path_data_files"
    d.mkdir(parents=True)
    _walk(d / f"{wid(0, 0)}.txt", "F2", 0, 0, np.random.default_rng(5), gz=True)
    p = d / f"{wid(0, 0)}.txt.gz"
    raw = bytearray(p.read_bytes())
    raw[30:60] = bytes(range(200, 230))
    p.write_bytes(bytes(raw))
    with pytest.raises(DatasetError, match="cannot read trace"):
        read_trace(p)
    assert has_truth_span(p) is False


def wid(ix: int, k: int) -> str:
    """Walk id of the k-th walk of the ix-th floor written (ids sort by floor, then walk)."""
    return f"5f{ix}{k:021d}"


def make_site(root: Path) -> Path:
    """Floors: G (floor_info, plan with a MultiPolygon shop, 5 walks and one without waypoints), LG1
    (no floor_info.json: extent from the plan), M (no plan), Roof (a name of no convention), P1 (an
    empty path_data_files/); and a directory that is no floor."""
    rng = np.random.default_rng(7)
    for ix, (floor, info, plan) in enumerate((("LG1", False, "poly"), ("G", True, "multi"), ("M", True, None),
                                             ("Roof", True, "poly"))):
        d = root / floor / "path_data_files"
        d.mkdir(parents=True)
        if info:
            (root / floor / "floor_info.json").write_text(json.dumps({"map_info": {"width": 60.0, "height": 40.0}}))
        if plan:
            (root / floor / "geojson_map.json").write_text(json.dumps(_plan(plan == "multi")))
        for k in range(5):
            _walk(d / f"{wid(ix, k)}.txt", floor, ix, k, rng, gz=k == 1, x_end=61.0 if floor == "M" and k == 4 else 55.0)
        if floor == "G":
            _walk(d / f"{wid(ix, 9)}.txt", floor, ix, 9, rng, waypoints=0)
    (root / "P1" / "path_data_files").mkdir(parents=True)
    (root / "P1" / "floor_info.json").write_text(json.dumps({"map_info": {"width": 60.0, "height": 40.0}}))
    (root / "docs").mkdir()
    (root / "B3").mkdir()
    return root


def _args(site: Path, out: Path, **kw) -> argparse.Namespace:
    base = dict(dataset_dir=site, out_dir=out, floors="", walks="", survey_walks="", storey_height_m=5.0,
                overwrite=False, floor_levels="", metadata=None)
    base.update(kw)
    return argparse.Namespace(**base)


def test_read_site_finds_every_floor_and_says_what_is_odd(tmp_path):
    site = read_site(make_site(tmp_path / "site"))
    fl = {f.name: f for f in site.floors}
    assert [f.name for f in site.floors] == ["P1", "B3", "LG1", "G", "M", "Roof"]
    assert {n: f.level for n, f in fl.items()} == {"B3": -4, "P1": -5, "LG1": -1, "G": 0, "M": 0.5, "Roof": 1}
    assert fl["Roof"].level_rule.startswith("fallback") and site.ignored == ("docs",)
    assert fl["LG1"].width_m == pytest.approx(60.0, abs=1e-6) and fl["LG1"].height_m == pytest.approx(40.0, abs=1e-6)
    assert "no floor_info.json" in fl["LG1"].notes and any("from the GeoJSON" in n for n in fl["LG1"].notes)
    assert fl["P1"].notes == ("no walks (empty path_data_files/)",) and fl["P1"].trace_files == ()
    assert fl["B3"].notes[:2] == ("no walks (no path_data_files/)", "no floor_info.json")
    assert len(fl["G"].trace_files) == 6 and fl["G"].trace_files[1].name.endswith(".txt.gz")
    with pytest.raises(ConfigError, match="no floor"):
        read_site(tmp_path / "site", levels={"F9": 3})


def test_import_of_a_site_with_every_quirk(tmp_path, capsys):
    from indoor_loc.bag import read_bag
    from indoor_loc.commands.import_ms_indoor import import_ms_indoor
    from indoor_loc.wifi.methods import make_positioner
    from indoor_loc.wifi.radiomap import load_radiomap
    from indoor_loc.wifi.walkable import load_floor_plans
    site = make_site(tmp_path / "site")
    out = tmp_path / "out"
    assert import_ms_indoor(_args(site, out)) == 0
    printed = capsys.readouterr().out
    assert "floor Roof: level 1 by fallback" in printed
    assert "floors LG1 z=-5 m, G z=0 m, M z=2.5 m, Roof z=5 m)" in printed        # not P1, B3: no walks
    z = {"B3": -20.0, "P1": -25.0, "LG1": -5.0, "G": 0.0, "M": 2.5, "Roof": 5.0}
    rm = load_radiomap(out / "radiomap")
    assert rm.floors == {k: v for k, v in z.items() if k not in ("P1", "B3")}     # no walks there
    split = yaml.safe_load((out / "split.yaml").read_text())
    assert {k: v["z_m"] for k, v in split.items()} == z
    assert split["G"]["no_truth"] == [wid(1, 9)] and len(split["G"]["survey"]) == 3
    for floor in z:
        assert yaml.safe_load((out / "floors" / floor / "map.yaml").read_text())["z_m"] == z[floor]
    # plans: G (MultiPolygon shop), LG1 (placed by its lon/lat extent), Roof; none for M (no GeoJSON)
    assert sorted(p.parent.name for p in (out / "floors").glob("*/geojson_map.json")) == ["G", "LG1", "Roof"]
    walkable, used = load_floor_plans(out / "floors")
    assert sorted(used) == [-5.0, 0.0, 5.0]
    xy = np.array([[30.0, 10.0], [47.0, 30.0]])                        # free corridor, inside the shop
    assert walkable(xy, 0.0).tolist() == [True, False] and walkable(xy, -5.0).tolist() == [True, False]
    # ground truth and bags carry the chosen z; the walk without waypoints is written, unscored
    gt = [m.msg for m in read_bag(out / "M" / f"{wid(2, 0)}.mcap") if m.topic.endswith("ground_truth")]
    assert gt[0].poses[0].pose.position.z == 2.5
    topics = {m.topic for m in read_bag(out / "G" / f"{wid(1, 9)}.mcap")}
    assert f"/g_{wid(1, 9)}/wifi/scan" in topics and not any(t.endswith("ground_truth") for t in topics)
    report = (out / "import_report.md").read_text()
    assert f"| G | {wid(1, 9)} | no truth |" in report
    assert "| Roof | 1 | 5 | fallback: not a known floor name; placed above the highest floor | 5 | 0 |" in report
    assert "| M | 0.5 | 2.5 | mezzanine | 5 | 0 | no floor_info.json" not in report          # M has its info
    assert "| P1 | -5 | -25 | parking, below ground | 0 | 0 | no walks (empty path_data_files/) |" in report
    assert "GeoJSON plan not used" not in report and "Not floors (no path_data_files/, trace or plan file), ignored: docs" in report
    assert f"{wid(1, 9)}: no waypoints: nothing to score or map" in report
    assert f"{wid(2, 4)}: 1 of 2 waypoints outside the floor's extent [0, 60.0] × [0, 40.0] m" in report
    # floor detection and wifi/fix z follow the levels: a scan of M's test walk is placed at z = 2.5
    pos = make_positioner("powed", {}).fit(rm)
    tr = read_trace(site / "M" / "path_data_files" / f"{wid(2, 3)}.txt")
    fixes = [pos.locate(s) for s in scans_with_truth(tr)[0]]
    assert fixes and all(f.ok and f.z == 2.5 for f in fixes)
    # an override moves the floor, everywhere
    out2 = tmp_path / "out2"
    assert import_ms_indoor(_args(site, out2, floor_levels="Roof=3", floors="Roof,G")) == 0
    assert load_radiomap(out2 / "radiomap").floors == {"G": 0.0, "Roof": 15.0}
    assert "| Roof | 3 | 15 | set by the user |" in (out2 / "import_report.md").read_text()
    with pytest.raises(ConfigError, match="--floor-levels: no floor"):
        import_ms_indoor(_args(site, tmp_path / "out3", floor_levels="F9=3"))


def test_a_plan_that_cannot_be_placed_or_drawn_is_not_copied(tmp_path):
    from indoor_loc.commands.import_ms_indoor import import_ms_indoor
    site = make_site(tmp_path / "site")
    (site / "M" / "geojson_map.json").write_text('{"type": "FeatureCollection", "features": []}')
    (site / "LG1" / "geojson_map.json").write_text("not json")
    out = tmp_path / "out"
    assert import_ms_indoor(_args(site, out, floors="LG1,M,G")) == 0
    assert sorted(p.parent.name for p in (out / "floors").glob("*/geojson_map.json")) == ["G"]
    report = (out / "import_report.md").read_text()
    assert "GeoJSON plan not used: the floor's extent is unknown" in report          # LG1: no info, bad plan
    assert "extent unknown:" in report and "GeoJSON plan not used:" in report


def test_namespaces_are_valid_for_any_floor_name(tmp_path):
    from indoor_loc.datasets.ms_indoor_bags import walk_namespace
    p = tmp_path / "5F00AB.txt"
    _walk(p, "1F", 0, 0, np.random.default_rng(0))
    tr = read_trace(p)
    assert walk_namespace(tr) == "/floor_1f_5f00ab"
    assert walk_namespace(tr, "B1") == "/b1_5f00ab" and walk_namespace(tr, "L-2 East") == "/l_2_east_5f00ab"
    assert walk_namespace(tr, "一楼") == "/floor_5f00ab"


def test_bench_on_any_site(tmp_path, capsys):
    from indoor_loc.bench import wifi as bench_wifi
    site = make_site(tmp_path / "site")
    args = argparse.Namespace(data=tmp_path / "none", site=site, dataset="", floors="", floor_levels="",
                              json=tmp_path / "b.json", quick=False)
    assert bench_wifi.run(args) == 0
    text = capsys.readouterr().out
    assert "no floor of this site was used to choose methods (all held out)" in text
    assert "floor Roof: storey index 1 by fallback" in text
    assert "floor G: 1 of 6 walks have fewer than two waypoints (no truth): not used" in text
    assert "2. pooled over the four floors (floor known)" in text
    for floor in ("LG1", "G", "M", "Roof"):
        assert f"1. floor {floor} (held out): " in text
    rep = json.loads((tmp_path / "b.json").read_text())
    assert sorted(rep["floors"]) == ["G", "LG1", "M", "Roof"]
    assert rep["site"]["floors"]["M"]["z_m"] == 2.5 and rep["site"]["site_id"] == "5f00000000000000000000aa"
    det = rep["floor_detection"]
    assert sum(det[f]["right"] for f in ("G", "LG1", "M", "Roof")) == sum(det[f]["n"] for f in ("G", "LG1", "M", "Roof"))
    base = rep["floors"]["G"]["methods"]["plain WKNN (baseline)"]
    assert base["located"] == base["n"] == 20 and base["mean"] < 10
    # one floor, an override, errors
    args.floors, args.floor_levels, args.json = "Roof", "Roof=4", None
    assert bench_wifi.run(args) == 0
    assert "floors: Roof z=20 m" in capsys.readouterr().out
    args.floors = "F9"
    assert bench_wifi.run(args) == 2 and "--floors: no floor(s) ['F9']" in capsys.readouterr().out
    args.floors, args.dataset = "", "putmc"
    assert bench_wifi.run(args) == 2 and "--site is a site of the Microsoft format" in capsys.readouterr().out
    args.site, args.floors, args.floor_levels = None, "F1", ""      # no PUTMC option: said, not ignored
    assert bench_wifi.run(args) == 2 and "--floors select floors of --site" in capsys.readouterr().out


def test_bench_leaves_out_a_walk_it_cannot_read(tmp_path):
    """A walk whose file is damaged after its waypoints (a .gz's trailing checksum) still counts as having
    truth, but cannot be read: the bench leaves it out with a note, as the importer does, and goes on."""
    from indoor_loc.bench.wifi_ms import load_site
    site = make_site(tmp_path / "site")
    p = site / "G" / "path_data_files" / f"{wid(1, 1)}.txt.gz"
    raw = bytearray(p.read_bytes())
    raw[-8:-4] = bytes(4 - i for i in range(4))
    p.write_bytes(bytes(raw))
    whole = load_site(make_site(tmp_path / "whole"), only=["G"])["G"]
    notes: list[str] = []
    g = load_site(site, only=["G"], notes=notes)["G"]
    assert any(f"walk {wid(1, 1)} left out" in n and "cannot read" in n for n in notes)
    assert g["walks"] == whole["walks"]                              # the split is the same
    assert (g["map"].n_scans, len(g["scans"])) != (whole["map"].n_scans, len(whole["scans"]))


def test_bench_tags_the_floors_that_chose_the_methods_by_the_floor_recorded_on(tmp_path, capsys, monkeypatch):
    """On a copy of the site whose methods were chosen on some floors, with those floors renamed, the
    tags follow the walks' header FloorName, not the directory's name."""
    from indoor_loc.bench import wifi as bench_wifi
    from indoor_loc.bench import wifi_ms
    site = make_site(tmp_path / "site")
    (site / "G").rename(site / "GF")                       # recorded as G, stored under GF
    monkeypatch.setattr(wifi_ms, "MS_SITE2_ID", "5f00000000000000000000aa")
    monkeypatch.setattr(wifi_ms, "TUNED_ON", ("G",))
    args = argparse.Namespace(data=tmp_path / "none", site=site, dataset="", floors="GF,LG1", floor_levels="",
                              json=None, quick=False)
    assert bench_wifi.run(args) == 0
    text = capsys.readouterr().out
    assert "choices made on GF (ms_site2's G) (tuned), the rest held out." in text
    assert "1. floor GF (tuned): " in text and "1. floor LG1 (held out): " in text
    args.floors = "LG1"
    assert bench_wifi.run(args) == 0
    text = capsys.readouterr().out
    assert "choices made on ms_site2's G, none of them here (all held out)." in text


def test_a_site_without_any_waypoint_is_imported_without_a_map(tmp_path, capsys):
    from indoor_loc.commands.import_ms_indoor import import_ms_indoor
    d = tmp_path / "site" / "F2" / "path_data_files"
    d.mkdir(parents=True)
    rng = np.random.default_rng(1)
    for k in range(2):
        _walk(d / f"{wid(0, k)}.txt", "F2", 0, k, rng, waypoints=0)
    out = tmp_path / "out"
    assert import_ms_indoor(_args(tmp_path / "site", out)) == 0
    assert "radio map: NONE — no survey scan lies inside a waypoint span" in capsys.readouterr().out
    assert sorted(p.name for p in (out / "F2").glob("*.mcap")) == [f"{wid(0, 0)}.mcap", f"{wid(0, 1)}.mcap"]
    assert not (out / "radiomap").exists()
    params = yaml.safe_load((out / "params.yaml").read_text())
    assert sorted(params) == ["/**/imu_node", "/**/pdr_kf_node"]      # no radio map: no WiFi, pf or back-end
    split = yaml.safe_load((out / "split.yaml").read_text())
    assert split["F2"] == {"z_m": 5.0, "survey": [], "test": [], "no_truth": [wid(0, 0), wid(0, 1)]}
    assert "Radio map: **none**" in (out / "import_report.md").read_text()
    # re-imported over an import that had a map: that map goes with --overwrite
    (out / "radiomap").mkdir()
    (out / "radiomap" / "radiomap.yaml").write_text("stale")
    assert import_ms_indoor(_args(tmp_path / "site", out, overwrite=True)) == 0
    assert not (out / "radiomap").exists()


def test_a_walk_with_one_waypoint_has_no_truth(tmp_path):
    """One waypoint spans no time: the walk is imported as 'no truth', without a one-point ground_truth
    (which an evaluation cannot interpolate), and stays out of the split."""
    from indoor_loc.bag import read_bag
    from indoor_loc.commands.import_ms_indoor import import_ms_indoor
    from indoor_loc.datasets.ms_indoor import has_truth_span
    d = tmp_path / "site" / "F2" / "path_data_files"
    d.mkdir(parents=True)
    rng = np.random.default_rng(2)
    for k, n in enumerate((2, 1, 2, 2)):
        _walk(d / f"{wid(0, k)}.txt", "F2", 0, k, rng, waypoints=n)
    assert [has_truth_span(d / f"{wid(0, k)}.txt") for k in range(4)] == [True, False, True, True]
    out = tmp_path / "out"
    assert import_ms_indoor(_args(tmp_path / "site", out)) == 0
    split = yaml.safe_load((out / "split.yaml").read_text())["F2"]
    assert split["no_truth"] == [wid(0, 1)] and wid(0, 1) not in split["survey"] + split["test"]
    topics = {m.topic for m in read_bag(out / "F2" / f"{wid(0, 1)}.mcap")}
    assert f"/f2_{wid(0, 1)}/wifi/scan" in topics and not any(t.endswith("ground_truth") for t in topics)
    report = (out / "import_report.md").read_text()
    assert f"| F2 | {wid(0, 1)} | no truth |" in report
    assert f"{wid(0, 1)}: one waypoint: no span to interpolate the truth over" in report


def test_walk_ids_with_dots_stay_apart(tmp_path):
    """A walk's id is its file name without .txt[.gz], dots and all: two walks named alike up to a
    dot are two walks (not one, the other lost)."""
    from indoor_loc.commands.import_ms_indoor import import_ms_indoor
    d = tmp_path / "site" / "F2" / "path_data_files"
    d.mkdir(parents=True)
    rng = np.random.default_rng(3)
    ids = [f"{wid(0, 0)}.{v}" for v in ("a", "b", "c", "d", "e")]
    for k, i in enumerate(ids):
        _walk(d / f"{i}.txt", "F2", 0, k, rng)
    out = tmp_path / "out"
    assert import_ms_indoor(_args(tmp_path / "site", out)) == 0
    split = yaml.safe_load((out / "split.yaml").read_text())["F2"]
    assert sorted(split["survey"] + split["test"]) == ids
    assert sorted(p.name for p in (out / "F2").glob("*.mcap")) == [f"{i}.mcap" for i in ids]


def test_the_kaggle_layout_traces_in_train_plans_in_metadata(tmp_path):
    """``train/<site>/<floor>/*.txt`` with the plans in ``metadata/<site>/<floor>/``: found on their own."""
    from indoor_loc.commands.import_ms_indoor import import_ms_indoor
    site = tmp_path / "train" / "5f00aa"
    rng = np.random.default_rng(2)
    for ix, floor in enumerate(("1F", "2F")):
        (site / floor).mkdir(parents=True)
        for k in range(3):
            _walk(site / floor / f"{wid(ix, k)}.txt", floor, ix, k, rng)
        meta = tmp_path / "metadata" / "5f00aa" / floor
        meta.mkdir(parents=True)
        (meta / "floor_info.json").write_text(json.dumps({"map_info": {"width": 60.0, "height": 40.0}}))
        (meta / "geojson_map.json").write_text(json.dumps(_plan(False)))
    floors = read_site(site).floors
    assert [(f.name, f.level, f.plans, len(f.trace_files)) for f in floors] == [
        ("1F", 0, tmp_path / "metadata" / "5f00aa" / "1F", 3), ("2F", 1, tmp_path / "metadata" / "5f00aa" / "2F", 3)]
    out = tmp_path / "out"
    assert import_ms_indoor(_args(site, out)) == 0
    assert sorted(p.parent.name for p in (out / "floors").glob("*/geojson_map.json")) == ["1F", "2F"]
    assert (out / "1F" / f"{wid(0, 0)}.mcap").exists()
    assert "Plan files of floors that hold none: from" in (out / "import_report.md").read_text()
    # an explicit --metadata that does not exist is an error, not a silent plan-less import
    from indoor_loc.errors import DatasetError
    with pytest.raises(DatasetError, match="metadata directory"):
        import_ms_indoor(_args(site, tmp_path / "out2", metadata=tmp_path / "nope"))
    # the bench finds them too, or takes them from --metadata for another layout
    from indoor_loc.bench.wifi_ms import load_site
    floors = load_site(site, only=["1F"])
    assert floors["1F"]["walkable"] is not None and floors["1F"]["walks"] == (2, 1)
    moved = tmp_path / "plans"
    (tmp_path / "metadata" / "5f00aa").rename(moved)
    assert load_site(site, only=["1F"])["1F"]["walkable"] is None
    assert load_site(site, only=["1F"], metadata=moved)["1F"]["walkable"] is not None


def test_ms_site2_rewritten_with_the_quirks_reads_back_record_for_record(tmp_path):
    """F8 of ms_site2 with other sites' quirks (test/ms_quirks.py): every record reads back equal, but
    the WiFi frequencies removed; the floor is found under its new name with its plan's extent."""
    from collections import Counter

    from conftest import dataset
    from ms_quirks import JUNK, rewrite
    from indoor_loc.datasets.ms_indoor_site import list_traces
    src = dataset("ms_site2")
    joined = rewrite(src, tmp_path / "q", floors={"F8": "Roof top"}, stride=3)    # 8 walks, every quirk
    assert joined > 1000
    (roof,) = [f for f in read_site(tmp_path / "q").floors if f.name == "Roof top"]
    assert roof.level_rule.startswith("fallback") and "no floor_info.json" in roof.notes
    assert (roof.width_m, roof.height_m) == pytest.approx((236.7118, 219.7468), abs=1e-3)
    pairs = list(zip(list_traces(src / "F8" / "path_data_files")[::3], roof.trace_files))
    assert len(pairs) == 8
    for p, q in pairs:
        a, b = read_trace(p), read_trace(q)
        for k in ("acc", "gyro", "mag", "acc_uncal", "gyro_uncal", "mag_uncal", "rotvec"):
            np.testing.assert_array_equal(getattr(a, k).t_ns, getattr(b, k).t_ns)
            np.testing.assert_array_equal(getattr(a, k).values, getattr(b, k).values)
        np.testing.assert_array_equal(a.waypoint_t, b.waypoint_t)
        np.testing.assert_array_equal(a.waypoint_xy, b.waypoint_xy)
        assert a.header == b.header and a.beacons == b.beacons
        assert a.row_counts + Counter({"TYPE_WIFI": 1}) == b.row_counts       # the short WiFi row
        assert b.dropped == Counter({"malformed": 1, "malformed_wifi": 1}), (q, b.dropped, JUNK)
        assert len(a.scans) == len(b.scans)
        for x, y in zip(a.scans, b.scans):
            assert (x.stamp_ns, x.bssid, x.ssid) == (y.stamp_ns, y.bssid, y.ssid)
            np.testing.assert_array_equal(x.rssi_dbm, y.rssi_dbm)
            np.testing.assert_array_equal(x.age_ms, y.age_ms)


def test_wifi_fix_of_an_imported_mezzanine_walk_carries_its_level(tmp_path):
    """indoor-loc run --nodes wifi with the importer's params.yaml: the fixes of a walk on M (a
    mezzanine, storey index 0.5) are at z = 2.5 m, the floor's height in the map and the plans."""
    from indoor_loc.bag import read_bag
    from indoor_loc.commands.import_ms_indoor import import_ms_indoor
    from indoor_loc.pipeline.offline import run_offline
    site = make_site(tmp_path / "site")
    out = tmp_path / "out"
    assert import_ms_indoor(_args(site, out, floors="G,M,Roof")) == 0
    bag = out / "M" / f"{wid(2, 1)}.mcap"
    run_offline([bag], tmp_path / "run.mcap", nodes=["wifi"], params=out / "params.yaml", progress=False)
    fixes = [m.msg for m in read_bag(tmp_path / "run.mcap") if m.topic.endswith("/wifi/fix")]
    assert len(fixes) == 10 and {f.pose.pose.position.z for f in fixes} == {2.5}
