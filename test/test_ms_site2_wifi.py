"""Real data: one floor of ms_site2 (F8, held out from every method choice) through the importer's
reader, the documented split and the WiFi methods — a regression on the figures of
``indoor-loc bench wifi --dataset ms_site2``."""
from __future__ import annotations

import numpy as np

from conftest import dataset
from indoor_loc.bench.wifi_ms import PLAIN, errors
from indoor_loc.datasets.ms_indoor import read_trace, scans_with_truth, split_map_test
from indoor_loc.datasets.ms_indoor_site import site_floors
from indoor_loc.wifi.methods import make_positioner
from indoor_loc.wifi.radiomap import add_fingerprints, empty_radiomap


def test_f8_powed_locates_every_scan_and_beats_plain_wknn():
    floor = next(f for f in site_floors(dataset("ms_site2")) if f.name == "F8")
    ids = {p.name.split(".")[0]: p for p in floor.trace_files}
    survey, test = split_map_test(list(ids))
    assert (len(survey), len(test)) == (14, 10)
    rm = empty_radiomap()
    for tid in survey:
        sc, xy = scans_with_truth(read_trace(ids[tid], imu=False))
        rm = add_fingerprints(rm, xy, sc, tid)
    scans, truth = [], []
    for tid in test:
        sc, xy = scans_with_truth(read_trace(ids[tid], imu=False))
        scans += sc
        truth.append(xy)
    truth = np.vstack(truth)
    assert rm.n_scans == 265 and len(scans) == 159
    assert rm.age_ms is not None and np.nanmedian(rm.age_ms) > 1000          # cached results are common
    p_ok, p_e, _ = errors(make_positioner("wknn", PLAIN).fit(rm).locate_many(scans), truth)
    ok, e, m2 = errors(make_positioner("powed", {}).fit(rm).locate_many(scans), truth)
    assert ok.all() and p_ok.mean() < 0.95                                    # bench: 100 % vs 88.7 %
    assert e[p_ok].mean() < 0.8 * p_e[p_ok].mean()                            # bench: 11.49 vs 16.30 m
    assert 0.4 < np.mean(m2 <= 2 * np.log(2)) < 0.7 and np.mean(m2 <= 5.991) > 0.85   # bench: 55 / 89


def test_floor_detection_between_adjacent_floors_f7_f8():
    floors = {f.name: f for f in site_floors(dataset("ms_site2")) if f.name in ("F7", "F8")}
    rm = empty_radiomap()
    tests = []
    for name, f in floors.items():
        ids = {p.name.split(".")[0]: p for p in f.trace_files}
        survey, test = split_map_test(list(ids))
        z = f.z_m()
        for tid in survey:
            sc, xy = scans_with_truth(read_trace(ids[tid], imu=False))
            rm = add_fingerprints(rm, xy, sc, tid, z_m=z, floors={name: z})
        for tid in test[:4]:
            tests += [(s, z) for s in scans_with_truth(read_trace(ids[tid], imu=False))[0]]
    pos = make_positioner("powed", {"cov_calibration": False}).fit(rm)      # floors only: no covariance needed
    fixes = pos.locate_many([s for s, _ in tests])
    right = np.mean([f.ok and f.z == z for f, (_, z) in zip(fixes, tests)])
    assert len(tests) > 80 and right >= 0.98


def test_by_day_groups_test_scans_by_utc_date_on_the_scans_both_located():
    from indoor_loc.bench.wifi_ms import by_day
    from indoor_loc.wifi.types import WifiScan
    day_ns = 86400 * 10**9
    t0 = 18220 * day_ns                                                       # 2019-11-20 00:00 UTC
    stamps = [t0 + 3600 * 10**9, t0 + 7200 * 10**9, t0 + day_ns + 60 * 10**9, t0 + day_ns + 120 * 10**9]
    scans = [WifiScan(t, ("a",), np.array([-60.0]), np.array([2412.0]), source=w)
             for t, w in zip(stamps, ["w1", "w1", "w2", "w2"])]
    truth = np.array([[0.0, 0.0], [3600.0, 0.0], [0.0, 0.0], [0.0, 60.0]])     # 1 m/s on both dates
    rm = add_fingerprints(empty_radiomap(), np.zeros((3, 2)),
                          [WifiScan(t, ("a",), np.array([-60.0]), np.array([2412.0]))
                           for t in (t0, t0 + day_ns, t0 + day_ns + 1)], "s")
    ok = np.array([True, True, True, False])
    e = np.array([2.0, 4.0, 6.0, np.nan])
    ref_ok = np.array([True, True, True, True])
    ref_e = np.array([4.0, 4.0, 3.0, 9.0])
    days = by_day(scans, truth, rm, (ok, e, e, ref_ok, ref_e))
    assert [d["date"] for d in days] == ["2019-11-20", "2019-11-21"]
    assert [d["map_scans"] for d in days] == [1, 2]
    assert [d["scans"] for d in days] == [2, 1]                               # the 4th: ours gave no fix
    assert days[0]["mean"] == 3.0 and days[0]["ref_mean"] == 4.0 and days[0]["ratio"] == 0.75
    assert days[1]["ratio"] == 2.0
    assert [d["speed_m_s"] for d in days] == [1.0, 1.0]                       # not across the two walks
