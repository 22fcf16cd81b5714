"""GetSensorData logfiles: parser (every line type, unsorted and duplicated lines, a missing sensor, a
POSI-less log, clock oddities), the importer, the real sample log and the round trip bag -> log -> bag."""
from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np
import pytest
import yaml

from indoor_loc.datasets.geodesy import enu_to_geodetic, geodetic_to_enu
from indoor_loc.datasets.getsensordata import ble_scans, parse_header_date, read_log, wifi_scans

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT.parent / "shared" / "formats" / "getsensordata_sample_ipin2022.txt.gz"
HEADER = ("% LogFile created by the 'GetSensorData' App for Android.\n"
          "% Date of creation: Wed May 25 12:42:42 GMT+02:00 2022\n"
          "% Magnetometer data:  \t'MAGN;AppTimestamp(s);SensorTimestamp(s);Mag_X(uT);;Mag_Y(uT);Mag_Z(uT);Accuracy(integer)'\n"
          "%\n")
T0 = 1653475362 * 10 ** 9          # 12:42:42 GMT+02:00


def _lines(boot: float = 1000.0, *, gyro: bool = True, posi: bool = True) -> list[str]:
    """Records of a 2 s log: ACCE/GYRO at 50 Hz (read 0-3 ms late), MAGN, PRES, AHRS, two WiFi scans (one
    BSSID twice, per-AP result times), BLE4 iBeacon + Eddystone, POSI on two floors, GNSS/LIGH, junk."""
    out = []
    for k in range(100):
        t = 0.02 * k
        d = 0.001 * (k % 4)                          # read delay of the app
        out.append(f"ACCE;{t + d:.4f};{boot + t:.4f};0.1;0.2;9.8;3")
        if gyro:
            out.append(f"GYRO;{t + d + 0.0005:.4f};{boot + 5 + t:.4f};0.01;0.02;0.03;0")
        if k % 2 == 0:
            out.append(f"MAGN;{t + d:.4f};{boot + t:.4f};10.0;-20.0;-40.0;3")
        if k % 10 == 0:
            out.append(f"PRES;{t + d:.4f};{boot + t:.4f};1013.25;3")
            out.append(f"AHRS;{t + d:.4f};{boot + t:.4f};1.0;2.0;90.0;0.0;0.0;{math.sin(math.pi / 4):.6f};3")
    out += [f"WIFI;0.5;{boot + 0.49:.4f};net;AA:BB:CC:00:00:01;2412;-50",
            f"WIFI;0.5;{boot + 0.45:.4f};net;aa:bb:cc:00:00:02;5180;-60",
            f"WIFI;0.5;{boot + 0.40:.4f};net;aa:bb:cc:00:00:02;5180;-70",       # older result of the same BSSID
            f"WIFI;0.5;{boot + 0.47:.4f};a;b;aa:bb:cc:00:00:03;2437;-80",       # an SSID holding ';'
            f"WIFI;1.5;{boot + 1.49:.4f};;aa:bb:cc:00:00:01;2412;-55;",
            "WIFI;1.5;1.49;net;not-a-mac;2412;-55",
            "BLE4;0.30;iBeacon;20:22:B0:00:51:42;-93;-59;33759;57359;00000000-0000-BEAC-2022-000000005938",
            "BLE4;0.30;Eddystone;20:22:B0:00:51:43;-80;ABCDEF012345",
            "BLE4;1.10;iBeacon;20:22:B0:00:31:81;-55;0;0;0;00000000-0000-BEAC-2022-000000003878",
            "GNSS;0.7;1653475365.5190;41.453148;-8.289153;0.000;0.000;22.2;0.0;41;1",
            "LIGH;0.2;1000.2;243.0;3",
            "XXXX;1;2;3",
            "ACCE;oops;1;2;3;4;5"]
    if posi:
        out += ["POSI;0.0;1;41.4530;-8.2893;1;90", "POSI;1.0;2;41.4531;-8.2893;1;90",
                "POSI;2.0;3;41.4531;-8.2892;2;90"]
    return out


def _write(path: Path, lines: list[str], seed: int = 3) -> Path:
    rng = np.random.default_rng(seed)
    order = rng.permutation(len(lines))               # unsorted
    body = [lines[i] for i in order] + [lines[order[0]], lines[order[1]]]     # two lines duplicated
    path.write_text(HEADER + "\n".join(body) + "\n")
    return path


def test_every_line_type_unsorted_and_duplicated(tmp_path):
    log = read_log(_write(tmp_path / "walk.txt", _lines()))
    assert log.t0_ns == T0
    assert {k: len(v) for k, v in log.sensors.items()} == {"ACCE": 100, "GYRO": 100, "MAGN": 50, "PRES": 10, "AHRS": 10}
    acc = log.sensors["ACCE"]
    # the sensor clock gives the intervals, shifted onto the app clock by the least read delay
    np.testing.assert_allclose(acc.stamp_s, 0.02 * np.arange(100), atol=1e-9)
    assert log.clock["ACCE"]["read_delay_p99_ms"] == pytest.approx(3.0, abs=1e-6)
    np.testing.assert_allclose(log.sensors["GYRO"].stamp_s, 0.02 * np.arange(100) + 0.0005, atol=1e-9)
    assert log.sensors["PRES"].values[0, 0] == 1013.25
    # two WiFi scans at their app times; the repeated BSSID keeps its newest result; ages vs the newest
    scans, dup = wifi_scans(log)
    assert dup == 1 and [s.stamp_ns - T0 for s in scans] == [500_000_000, 1_500_000_000]
    s = scans[0]
    d = dict(zip(s.bssid, zip(s.rssi_dbm, s.age_ms, s.ssid)))
    assert d["aa:bb:cc:00:00:02"][:2] == (-60, pytest.approx(40.0))
    assert d["aa:bb:cc:00:00:01"][1] == 0 and d["aa:bb:cc:00:00:03"][2] == "a;b"
    assert len(scans[1]) == 1 and log.dropped["wifi_bad_bssid"] == 1
    # BLE: iBeacon uuid-major-minor, Eddystone instance; tx power 0 = not given
    bl = ble_scans(log)
    assert [len(b) for b in bl] == [2, 1]
    tx = dict(zip(bl[0].beacon_id, bl[0].tx_power_dbm))
    assert sorted(tx) == ["00000000-0000-beac-2022-000000005938-33759-57359", "abcdef012345"]
    assert tx["00000000-0000-beac-2022-000000005938-33759-57359"] == -59 and math.isnan(bl[1].tx_power_dbm[0])
    assert log.posi.floor.tolist() == [1, 1, 2] and np.all(np.diff(log.posi.app_s) > 0)
    assert log.counts["GNSS"] == 1 and log.unknown == {"XXXX": 1} and log.dropped["malformed_acce"] == 1
    odd = " | ".join(log.oddities)
    for words in ("ACCE: ", "lines out of AppTimestamp order", "duplicated lines dropped", "unknown line types: XXXX",
                  "malformed_acce"):
        assert words in odd
    assert "sensors missing" not in odd


def test_missing_sensor_posi_less_log_and_its_import(tmp_path):
    from indoor_loc.bag.reader import bag_topics, read_bag
    from indoor_loc.commands.import_data import main

    logs = tmp_path / "logs"
    logs.mkdir()
    _write(logs / "nogyro.txt", _lines(gyro=False, posi=False))
    _write(logs / "2walk.txt", _lines())
    log = read_log(logs / "nogyro.txt")
    assert "GYRO" not in log.sensors and len(log.posi) == 0
    assert any("sensors missing: GYRO" in o for o in log.oddities)
    assert any("no POSI" in o for o in log.oddities)
    out = tmp_path / "out"
    args = argparse.Namespace(dataset="getsensordata", paths=[logs, out], origin="", storey_height_m=None,
                              survey="", ble_window_s=5.0, overwrite=False)
    from indoor_loc.commands.import_getsensordata import import_getsensordata
    args.func = import_getsensordata
    assert main(args) == 0
    topics = bag_topics(out / "nogyro.mcap")
    assert "/nogyro/ground_truth" not in topics and "/nogyro/baro/pressure" in topics
    imu = next(m.msg for m in read_bag(out / "nogyro.mcap", ["/nogyro/imu/data_raw"]))
    assert imu.angular_velocity_covariance[0] == -1.0
    # the other log (name starting with a digit: namespace log_2walk) builds the map; the origin is its first POSI
    gt = next(m.msg for m in read_bag(out / "log_2walk.mcap", ["/log_2walk/ground_truth"]))
    assert [p.pose.position.z for p in gt.poses] == [4.0, 4.0, 8.0]
    assert gt.poses[0].pose.position.x == 0 and gt.poses[1].pose.position.y == pytest.approx(11.1, abs=0.1)
    rm = yaml.safe_load((out / "radiomap" / "radiomap.yaml").read_text())
    assert rm["counts"]["scans"] == 1            # the scan at 0.5 s; the one at 1.5 s lies between two floors
    report = (out / "import_report.md").read_text()
    assert "between POSI points on different floors" in report and "nogyro.txt: no POSI" in report
    params = yaml.safe_load((out / "params.yaml").read_text())
    assert params["/**/wifi_fix_node"]["ros__parameters"]["ble"]["enabled"] is True
    with pytest.raises(Exception, match="exist"):                 # an earlier import is not overwritten
        main(args)


def test_values_outside_the_contract_are_counted_not_fatal(tmp_path):
    from indoor_loc.datasets.getsensordata_bags import write_log_bag
    lines = ["ACCE;0.1;1000.1;0;0;9.8;3", "PRES;0.1;1000.1;1013.0;3",
             "PRES;0.2;1000.2;1.013;3", "WIFI;0.5;1000.5;a;aa:bb:cc:00:00:01;2412;-50",
             "WIFI;0.5;99999999.0;a;aa:bb:cc:00:00:02;2412;-60"]
    log = read_log(_write(tmp_path / "odd.txt", lines))
    scans, _ = wifi_scans(log)
    assert math.isnan(scans[0].age_ms[list(scans[0].bssid).index("aa:bb:cc:00:00:01")])   # another clock: unknown
    counts = write_log_bag(log, tmp_path / "odd.mcap", origin=(41.45, -8.29), storey_height_m=4.0)
    assert counts == {"/odd/imu/data_raw": 1, "/odd/baro/pressure": 1, "/odd/wifi/scan": 1}
    assert "1 messages not written, outside the message contract (baro/pressure: out_of_range)" in log.oddities


def test_a_sensor_clock_that_jumps_is_stamped_on_the_app_clock(tmp_path):
    lines = [f"ACCE;{0.02 * k:.4f};{1000 + 0.02 * k + (5.0 if k >= 50 else 0.0):.4f};0;0;9.8;3" for k in range(100)]
    log = read_log(_write(tmp_path / "jump.txt", lines))
    assert log.clock["ACCE"]["app_clock"] == 1.0
    np.testing.assert_allclose(log.sensors["ACCE"].stamp_s, 0.02 * np.arange(100), atol=1e-9)
    assert any("stamped on AppTimestamp instead" in o for o in log.oddities)


def test_header_dates_and_geodesy():
    assert parse_header_date("Wed May 25 12:42:42 GMT+02:00 2022") == T0
    assert parse_header_date("Thu Jan 01 00:00:00 GMT+00:00 2026") == 1_767_225_600 * 10 ** 9
    assert parse_header_date("garbage") is None
    xy = geodetic_to_enu([41.4531, 41.4530], [-8.2893, -8.2892], 41.4530, -8.2893)
    assert xy[0, 0] == pytest.approx(0, abs=1e-6) and xy[0, 1] == pytest.approx(11.1, abs=0.05)
    assert xy[1, 0] == pytest.approx(8.35, abs=0.05)
    lat, lon = enu_to_geodetic(np.array([[500.0, -300.0]]), 41.0, -8.0)
    np.testing.assert_allclose(geodetic_to_enu(lat, lon, 41.0, -8.0), [[500.0, -300.0]], atol=1e-6)


def test_the_real_sample_log_imports(tmp_path):
    if not SAMPLE.exists():
        pytest.skip(f"{SAMPLE} not found (../shared/formats beside the repository)")
    from indoor_loc.datasets.getsensordata_bags import truth_of

    log = read_log(SAMPLE)
    assert len(log.sensors["ACCE"]) == 18654 and len(log.sensors["GYRO"]) == 18653
    assert log.clock["ACCE"]["rate_hz"] == pytest.approx(100.0, rel=1e-3)
    assert log.clock["ACCE"]["app_clock"] == 0.0
    scans, _ = wifi_scans(log)
    assert len(scans) == 46 and sum(len(s) for s in scans) == 2312
    assert len(ble_scans(log)) == 3802 and len(log.posi) == 14
    _, xy, _, floor = truth_of(log, (float(log.posi.lat[0]), float(log.posi.lon[0])), 4.0)
    # the walk returns to its first landmark (points 1, 7, 8, 14): the same place in the map frame
    np.testing.assert_allclose(xy[[0, 6, 7, 13]], 0.0, atol=1e-6)
    assert 10 < np.max(np.linalg.norm(xy, axis=1)) < 40 and set(floor.tolist()) == {1}


def _contract_bag(path: Path) -> dict:
    """A two-floor bag of every topic the log format carries (user /ann)."""
    from indoor_loc.bag import BagWriter
    from indoor_loc.wifi.ble import BleScan
    from indoor_loc.wifi.types import WifiScan
    from msg_adapters.ble_scan import ble_to_msg
    from msg_adapters.pressure import pressure_to_msg
    from msg_adapters.imu import imu_to_msg, mag_to_msg
    from msg_adapters.path import path_to_msg
    from msg_adapters.wifi_scan import scan_to_msg

    rng = np.random.default_rng(5)
    t0 = 1_767_225_600 * 10 ** 9
    n = 200
    t = t0 + np.arange(n) * 10_000_000 + 3_000_000
    acc = rng.normal([0, 0, 9.8], 0.5, (n, 3))
    gyr = rng.normal(0, 0.2, (n, 3))
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    with BagWriter(path) as bag:
        gt = path_to_msg(t[::50], np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 5.0], [0.0, 5.0]]), None, stamp_ns=int(t[0]))
        for ps, z in zip(gt.poses, [0.0, 0.0, 4.0, 4.0]):
            ps.pose.position.z = z
        bag.write("/ann/ground_truth", gt, int(t[0]))
        for i in range(n):
            bag.write("/ann/imu/data_raw", imu_to_msg(int(t[i]), "ann/imu_link", acc[i], gyr[i]), int(t[i]))
            if i % 2 == 0:
                bag.write("/ann/imu/mag", mag_to_msg(int(t[i]), "ann/imu_link", [2e-5, -1e-5, -4e-5]), int(t[i]))
            if i % 20 == 0:
                bag.write("/ann/imu/data", imu_to_msg(int(t[i]), "ann/imu_link", acc[i], gyr[i], q,
                                                      np.eye(3) * 0.01), int(t[i]))
                bag.write("/ann/baro/pressure", pressure_to_msg(int(t[i]), "ann/imu_link", 101325.0 - i * 0.37),
                          int(t[i]))
            if i % 50 == 10:
                bag.write("/ann/wifi/scan", scan_to_msg(WifiScan(int(t[i]), ("aa:bb:cc:00:00:01", "aa:bb:cc:00:00:02"),
                                                                 np.array([-50.0, -71.0]), np.array([2412.0, 5180.0]),
                                                                 ("x", "y"), np.array([0.0, 120.0]))), int(t[i]))
                bag.write("/ann/ble/scan", ble_to_msg(BleScan(int(t[i]), (
                    "00000000-0000-beac-2022-000000005938-1-2", "abcdef012345"), np.array([-70.0, -80.0]),
                    np.array([-59.0, np.nan]), ("20:22:b0:00:51:42", "20:22:b0:00:51:43"))), int(t[i]))
    return {"t": t, "acc": acc, "gyr": gyr, "q": q}


def test_round_trip_bag_to_log_to_bag_keeps_every_message(tmp_path):
    from indoor_loc.bag.reader import read_bag
    from indoor_loc.commands.import_getsensordata import import_getsensordata
    from indoor_loc.commands.to_getsensordata import convert
    from msg_adapters.ble_scan import ble_from_msg
    from msg_adapters.imu import imu_from_msg
    from msg_adapters.wifi_scan import scan_from_msg

    ref = _contract_bag(tmp_path / "in.mcap")
    res = convert(tmp_path / "in.mcap", tmp_path / "logs", origin=(40.3, -3.48), storey_height_m=4.0, posi_period_s=0,
                  quiet=True)
    assert res["ann"]["lines"] == {"ACCE": 200, "GYRO": 200, "MAGN": 100, "AHRS": 10, "PRES": 10, "WIFI": 8,
                                   "BLE4": 8, "POSI": 4}
    out = tmp_path / "out"
    import_getsensordata(argparse.Namespace(paths=[tmp_path / "logs", out], origin="", storey_height_m=None, survey="",
                                            ble_window_s=5.0, overwrite=False))
    got: dict[str, list] = {}
    for m in read_bag(out / "ann.mcap"):
        got.setdefault(m.topic.split("/ann/")[1], []).append(m.msg)
    imu = [imu_from_msg(m) for m in got["imu/data_raw"]]
    np.testing.assert_allclose([s.stamp_ns for s in imu], ref["t"], atol=1e5)          # 0.1 ms: 4 decimals of s
    np.testing.assert_allclose([s.acc for s in imu], ref["acc"], atol=5e-6)
    np.testing.assert_allclose([s.gyro for s in imu], ref["gyr"], atol=5e-6)
    ori = [imu_from_msg(m).quat_xyzw for m in got["imu/data"]]
    qq = ref["q"] * np.sign(ref["q"][3])
    np.testing.assert_allclose(ori, np.tile(qq, (10, 1)), atol=2e-6)
    np.testing.assert_allclose([m.fluid_pressure for m in got["baro/pressure"]],
                               101325.0 - np.arange(0, 200, 20) * 0.37, atol=0.005)
    np.testing.assert_allclose([m.magnetic_field.x for m in got["imu/mag"]], 2e-5, atol=1e-10)
    scans = [scan_from_msg(m) for m in got["wifi/scan"]]
    assert len(scans) == 4 and scans[0].bssid == ("aa:bb:cc:00:00:01", "aa:bb:cc:00:00:02")
    np.testing.assert_allclose(scans[0].rssi_dbm, [-50, -71])
    np.testing.assert_allclose(scans[0].age_ms, [0.0, 120.0], atol=0.1)
    ble = [ble_from_msg(m) for m in got["ble/scan"]]
    assert ble[0].beacon_id == ("00000000-0000-beac-2022-000000005938-1-2", "abcdef012345")
    assert ble[0].tx_power_dbm[0] == -59 and math.isnan(ble[0].tx_power_dbm[1])
    gt = got["ground_truth"][0]
    np.testing.assert_allclose([[p.pose.position.x, p.pose.position.y, p.pose.position.z] for p in gt.poses],
                               [[0, 0, 0], [10, 0, 0], [10, 5, 4], [0, 5, 4]], atol=1e-6)


def test_round_trip_from_the_simulator(tmp_path):
    """indoor-loc sim --format getsensordata -> logs -> import: the same IMU, scans and truth (floors too)."""
    from indoor_loc.bag.reader import read_bag
    from indoor_loc.commands.import_getsensordata import import_getsensordata
    from indoor_loc.commands.sim import main as sim_main

    sim = tmp_path / "sim"
    assert sim_main(argparse.Namespace(out_dir=sim, building=None, walkers=1, duration=12.0, seed=4, imu_hz=100.0,
                                       mag_hz=50.0, scan_period=4.0, format="getsensordata", overwrite=False)) == 0
    out = tmp_path / "out"
    import_getsensordata(argparse.Namespace(paths=[sim / "getsensordata", out], origin="", storey_height_m=None,
                                            survey="", ble_window_s=5.0, overwrite=False))

    def msgs(bag, topic):
        return [m for m in read_bag(bag, [topic])]
    a = msgs(sim / "sim.mcap", "/alice/imu/data_raw")
    b = msgs(out / "alice.mcap", "/alice/imu/data_raw")
    assert len(a) == len(b) > 1000
    assert max(abs(x.stamp_ns - y.stamp_ns) for x, y in zip(a, b)) <= 100_000
    assert max(abs(x.msg.linear_acceleration.z - y.msg.linear_acceleration.z) for x, y in zip(a, b)) <= 5e-6
    wa = msgs(sim / "sim.mcap", "/alice/wifi/scan")
    wb = msgs(out / "alice.mcap", "/alice/wifi/scan")
    assert [x.stamp_ns // 100_000 for x in wa] == [y.stamp_ns // 100_000 for y in wb]
    assert [[s.name for s in x.msg.status[1:]] for x in wa] == [[s.name for s in y.msg.status[1:]] for y in wb]
    truth = np.loadtxt(sim / "truth" / "alice.csv", delimiter=",", skiprows=1)
    gt = msgs(out / "alice.mcap", "/alice/ground_truth")[0].msg
    stamps = [p.header.stamp.sec * 10 ** 9 + p.header.stamp.nanosec for p in gt.poses]
    rows = truth[np.searchsorted(truth[:, 0], stamps)]
    np.testing.assert_allclose([[p.pose.position.x, p.pose.position.y] for p in gt.poses], rows[:, 1:3], atol=1e-3)
    assert yaml.safe_load((out / "map_origin.yaml").read_text())["from"].endswith("map_origin.yaml")


_JUNK = ["", "nan", "inf", "-inf", "1e308", "-1e308", "abc", "0", "-5", "1,5", "20:22:00:00:00:50", "99999999999"]


def test_any_corrupted_log_imports_without_a_crash(tmp_path):
    """Fields replaced by junk, lines cut short or run together: every record is parsed or dropped and
    counted, and the bag is written (no crash, never a value outside the contract)."""
    from hypothesis import given, settings
    from hypothesis import strategies as st

    from indoor_loc.datasets.getsensordata_bags import write_log_bag
    base = _lines()

    @settings(max_examples=15, deadline=None)
    @given(st.lists(st.tuples(st.integers(0, len(base) - 1), st.integers(0, 12), st.sampled_from(_JUNK),
                              st.sampled_from(["field", "cut", "join"])), min_size=1, max_size=25))
    def check(edits):
        lines = list(base)
        for i, k, junk, how in edits:
            f = lines[i].split(";")
            if how == "field":
                f[k % len(f)] = junk
                lines[i] = ";".join(f)
            elif how == "cut":
                lines[i] = ";".join(f[: k % len(f)])
            else:
                lines[i] = lines[i] + lines[(i + 1) % len(lines)]
        path = _write(tmp_path / "fuzz.txt", lines)
        log = read_log(path)
        n_lines = sum(1 for x in path.read_text().splitlines() if x.strip() and not x.startswith("%"))
        assert sum(log.counts.values()) == n_lines
        for s in log.sensors.values():
            assert np.all(np.isfinite(s.stamp_s)) and np.all(np.isfinite(s.values))
        write_log_bag(log, tmp_path / "fuzz.mcap", origin=(41.45, -8.29), storey_height_m=4.0)
    check()


def test_a_floor_plan_image_with_reference_points_lands_in_the_map_frame(tmp_path):
    """A plan drawn 20° off the map axes at 5 cm/px, given by three reference points: aligned with the map
    frame (its walls where the map says) and, as the only floor, the building graph for tll_pf."""
    from PIL import Image

    from indoor_loc.commands.import_getsensordata import import_getsensordata
    from indoor_loc.datasets.plan_georef import PlanRef
    from indoor_loc.graph.io import load_graph

    h, w = 520, 460
    true = PlanRef(0.05, math.radians(20.0), np.array([-2.0, -9.0]), h, 0.0)
    u, v = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    xy = true.to_map(np.column_stack([u.ravel(), v.ravel()]))
    inside = (np.abs(xy[:, 0]) < 3.0) & (xy[:, 1] > -3.0) & (xy[:, 1] < 14.0)     # a 6 m wide corridor
    wall = (np.abs(xy[:, 0]) < 3.3) & (xy[:, 1] > -3.3) & (xy[:, 1] < 14.3) & ~inside
    img = np.full(h * w, 255, np.uint8)
    img[wall] = 0
    plans = tmp_path / "plans"
    plans.mkdir()
    Image.fromarray(img.reshape(h, w)).save(plans / "f1.png")
    ref_px = np.array([[10.0, 20.0], [400.0, 60.0], [200.0, 500.0]])
    lat, lon = enu_to_geodetic(true.to_map(ref_px), 41.4530, -8.2893)
    (plans / "plans.yaml").write_text(yaml.safe_dump([{"floor": 1, "image": "f1.png", "points": [
        [float(a), float(b), float(c), float(d)] for (a, b), c, d in zip(ref_px, lat, lon)]}]))
    logs = tmp_path / "logs"
    logs.mkdir()
    _write(logs / "walk.txt", _lines())
    out = tmp_path / "out"
    import_getsensordata(argparse.Namespace(paths=[logs, out], origin="", storey_height_m=None, survey="",
                                            ble_window_s=5.0, floor_plans=plans / "plans.yaml", overwrite=False))
    meta = yaml.safe_load((out / "floors" / "floor1" / "map.yaml").read_text())
    assert meta["resolution"] == pytest.approx(0.05) and meta["z_m"] == 4.0
    al = np.asarray(Image.open(out / "floors" / "floor1" / meta["image"]))
    ox, oy = meta["origin"][:2]

    def grey_at(x, y):
        return al[int(al.shape[0] - (y - oy) / 0.05), int((x - ox) / 0.05)]
    assert grey_at(3.15, 5.0) == 0 and grey_at(-3.15, 10.0) == 0 and grey_at(0.0, 14.15) == 0   # the walls
    assert grey_at(0.0, 5.0) == 255 and grey_at(2.0, 0.0) == 255
    g = load_graph(out / "graph.yaml")
    assert np.all(np.abs(g.node_xyz[:, 0]) < 3.0) and np.all((g.node_xyz[:, 1] > -3.0) & (g.node_xyz[:, 1] < 14.0))
    assert g.node_xyz[:, 1].max() - g.node_xyz[:, 1].min() > 8.0          # the corridor's medial axis
    params = yaml.safe_load((out / "params.yaml").read_text())
    assert params["/**/tll_pf"]["ros__parameters"]["graph_file"] == str(out / "graph.yaml")
    assert "| 1 | f1.png | 3 | 0.0500 | 20.00 | 0.00 |" in (out / "import_report.md").read_text()
