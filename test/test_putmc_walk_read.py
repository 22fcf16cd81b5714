"""PUTMC walk reading without copies or per-AP loops gives what the plain code gives: the WiFi scans
of a walk built in one batch equal those built one block at a time (also the oddities and the errors
on malformed blocks), and the stale-sample cut and the stamp cleaning by slices equal the masks and
indices they stand for."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from indoor_loc.datasets import putmc as P
from indoor_loc.errors import DatasetError

AP = "{}\tnet\t{}\t2412\t1"


def _folder(tmp_path: Path, wifi: str) -> Path:
    """A walk folder: 3 s of acc/orient at 50 Hz from t = 1 s and the given wifi.map, scans at 0, 1."""
    d = tmp_path / "xperia_traj1"
    d.mkdir(exist_ok=True)
    t = 1_000_000_000 + np.arange(150) * 20_000_000
    (d / "acc.map").write_text("".join(f"{ti} 0.1 0.2 9.8\n" for ti in t))
    (d / "orient.map").write_text("".join(f"{ti} 0.0 0.0 0.0 1.0 0.5\n" for ti in t))
    (d / "positions.map").write_text("0 1.5 2.5\n1 3.5 4.5\n")
    (d / "wifi.map").write_text(wifi)
    return d


def _scan(stamp: int, idx: int, aps: list[tuple[str, str]]) -> str:
    return f"{stamp} {idx} {len(aps)}\n" + "".join(AP.format(b, r) + "\n" for b, r in aps)


GOOD = [("aa:bb:cc:dd:ee:01", "-50.0"), ("AA-BB-CC-DD-EE-02", "-61.5"), (" aa:bb:cc:dd:ee:03 ", "-70")]
CASES = {
    "clean": _scan(1_500_000_000, 0, GOOD) + _scan(2_500_000_000, 1, GOOD[:2]),
    "empty scan": _scan(1_500_000_000, 0, []) + _scan(2_500_000_000, 1, GOOD),
    "repeated bssid": _scan(1_500_000_000, 0, GOOD + [("aa:bb:cc:dd:ee:01", "-40.0")])
    + _scan(2_500_000_000, 1, GOOD[:1] + [("aa-bb-cc-dd-ee-01", "-80.0")]),
    "bad bssid": _scan(1_500_000_000, 0, GOOD) + _scan(2_500_000_000, 1, [("aa:bb:cc:dd:ee", "-50.0")]),
    "bad rssi": _scan(1_500_000_000, 0, [("aa:bb:cc:dd:ee:01", "strong")]) + _scan(2_500_000_000, 1, GOOD),
    "bad rssi after a repeat": _scan(1_500_000_000, 0, GOOD + GOOD[:1])
    + _scan(2_500_000_000, 1, [("aa:bb:cc:dd:ee:01", "-5O")]),
    "bad header": _scan(1_500_000_000, 0, GOOD) + _scan(2_500_000_000, 1, GOOD).replace(" 1 ", " one ", 1),
    "bad bssid before a bad header": _scan(1_500_000_000, 0, [("aa:bb:cc:dd:ee:0g", "-50.0")])
    + _scan(2_500_000_000, 1, GOOD).replace(" 1 ", " one ", 1),
}


def _outcome(fn):
    try:
        return fn()
    except (DatasetError, ValueError) as err:
        return f"{type(err).__name__}: {err}"


def _same_walk(a: P.Walk, b: P.Walk) -> None:
    assert a.oddities == b.oddities and a.raw_counts == b.raw_counts and a.dropped == b.dropped
    assert a.scan_idx.tobytes() == b.scan_idx.tobytes() and a.scan_xy.tobytes() == b.scan_xy.tobytes()
    assert len(a.scans) == len(b.scans)
    for x, y in zip(a.scans, b.scans):
        assert (x.stamp_ns, x.bssid, x.ssid, x.frame_id, x.source) == (y.stamp_ns, y.bssid, y.ssid, y.frame_id,
                                                                       y.source)
        assert x.rssi_dbm.dtype == y.rssi_dbm.dtype and x.rssi_dbm.tobytes() == y.rssi_dbm.tobytes()
        assert x.freq_mhz.dtype == y.freq_mhz.dtype and x.freq_mhz.tobytes() == y.freq_mhz.tobytes()


@pytest.mark.parametrize("case", list(CASES))
def test_batch_scans_equal_block_at_a_time(tmp_path, monkeypatch, case):
    folder = _folder(tmp_path, CASES[case])
    batch = _outcome(lambda: P.read_walk(folder, 1))
    monkeypatch.setattr(P, "_scans_from_blocks", lambda *a, **k: None)     # the one-block-at-a-time path
    single = _outcome(lambda: P.read_walk(folder, 1))
    if isinstance(single, str):
        assert batch == single
        assert case.startswith("bad")
        if case == "bad bssid before a bad header":        # the first fault in the file is the one raised
            assert batch.startswith("DatasetError") and "scan 0: bad BSSID 'aa:bb:cc:dd:ee:0g'" in batch
        return
    assert not isinstance(batch, str), batch
    _same_walk(batch, single)
    if case == "repeated bssid":
        assert [o.kind for o in batch.oddities].count("duplicate_bssid") == 2
        assert batch.scans[0].rssi_dbm.tolist() == [-40.0, -61.5, -70.0]
        assert batch.scans[1].bssid == ("aa:bb:cc:dd:ee:01",) and batch.scans[1].rssi_dbm.tolist() == [-50.0]
    if case == "clean":
        assert batch.scans[0].bssid == ("aa:bb:cc:dd:ee:01", "aa:bb:cc:dd:ee:02", "aa:bb:cc:dd:ee:03")


def test_kept_from_is_the_mask_it_stands_for():
    rng = np.random.default_rng(3)
    for _ in range(200):
        stamps = np.cumsum(rng.integers(-2, 6, int(rng.integers(1, 40))))
        cut = int(rng.choice(stamps))
        n_before = int(np.sum(stamps < cut))
        kept = P._kept_from(stamps, cut, n_before)
        assert stamps[kept].tolist() == stamps[stamps >= cut].tolist()
        if np.all(np.diff(stamps) > 0):
            assert isinstance(kept, slice) and kept == slice(n_before, None)


def test_clean_stamps_slice_only_when_strictly_increasing():
    rng = np.random.default_rng(4)
    for _ in range(200):
        stamps = np.cumsum(rng.integers(-1, 4, int(rng.integers(1, 30))))
        odd: list[P.Oddity] = []
        idx = P._clean_stamps("acc", stamps, 1, odd)
        order = np.argsort(stamps, kind="stable")
        keep = order[np.r_[True, np.diff(stamps[order]) != 0]]      # first of each repeated stamp
        assert stamps[idx].tolist() == stamps[keep].tolist()
        assert isinstance(idx, slice) == bool(np.all(np.diff(stamps) > 0)) == (not odd)


SURVEY = {
    "clean": _scan(0, 3, GOOD) + _scan(0, 5, GOOD[1:]),
    "repeated bssid": _scan(0, 3, GOOD + GOOD[:1]) + _scan(0, 5, GOOD),
    "bad bssid before an unknown location": _scan(0, 3, [("aa:bb:cc:dd:ee", "-50.0")]) + _scan(0, 9, GOOD),
    "bad unknown location before a bad bssid": _scan(0, 9, GOOD) + _scan(0, 3, [("aa:bb:cc:dd:ee", "-50.0")]),
}


@pytest.mark.parametrize("case", list(SURVEY))
def test_survey_batch_scans_equal_block_at_a_time(tmp_path, monkeypatch, case):
    (tmp_path / P.MAP_DIR).mkdir()
    (tmp_path / P.MAP_DIR / "positions.map").write_text("3 1.5 2.5\n5 3.5 4.5\n")
    (tmp_path / P.MAP_DIR / "wifi.map").write_text(SURVEY[case])
    odd_batch: list[P.Oddity] = []
    odd_single: list[P.Oddity] = []
    batch = _outcome(lambda: P.read_survey_map(tmp_path, odd_batch))
    monkeypatch.setattr(P, "_scans_from_blocks", lambda *a, **k: None)
    single = _outcome(lambda: P.read_survey_map(tmp_path, odd_single))
    assert odd_batch == odd_single
    if isinstance(single, str):
        assert batch == single and case.startswith("bad")
        first = "bad BSSID" if case.startswith("bad bssid") else "location 9 has no entry"
        assert first in batch
        return
    assert not isinstance(batch, str), batch
    for f in ("positions", "rssi_dbm", "freq_mhz", "scan_ids", "stamps_ns"):
        a, b = getattr(batch, f), getattr(single, f)
        assert a.dtype == b.dtype and a.tobytes() == b.tobytes(), f
    assert (batch.bssids, batch.ssids, batch.source) == (single.bssids, single.ssids, single.source)
    assert ("duplicate_bssid" in [o.kind for o in odd_batch]) == (case == "repeated bssid")


@pytest.mark.parametrize("map_yaw_rad", [0.0, P.PUTMC_MAP_YAW_RAD, 2.9, -1.7])
def test_map_yaw_is_the_yaw_of_the_map_quaternion(map_yaw_rad):
    """``map_yaw`` = ``quat_yaw(to_map_quat(...))`` bit for bit, unit and non-unit quaternions."""
    q = np.random.default_rng(7).normal(size=(4000, 4))
    q[:2000] /= np.linalg.norm(q[:2000], axis=1, keepdims=True)
    expected = P.quat_yaw(P.to_map_quat(q, map_yaw_rad))
    assert P.map_yaw(q, map_yaw_rad).tobytes() == expected.tobytes()
    assert P.map_yaw(q[:0], map_yaw_rad).shape == (0,)


@pytest.mark.parametrize("map_yaw_rad", [0.0, P.PUTMC_MAP_YAW_RAD, -1.7])
def test_to_map_quat_is_the_normalised_product(map_yaw_rad):
    """``to_map_quat`` = Rz(map_yaw) ⊗ q, normalised, bit for bit as written out here."""
    q = np.random.default_rng(8).normal(size=(3000, 4))
    c, s = np.cos(map_yaw_rad / 2), np.sin(map_yaw_rad / 2)
    x, y, z, w = q.T
    ref = np.stack([c * x - s * y, c * y + s * x, c * z + s * w, c * w - s * z], axis=1)
    ref = ref / np.linalg.norm(ref, axis=1, keepdims=True)
    got = P.to_map_quat(q, map_yaw_rad)
    assert got.shape == (3000, 4) and got.flags.c_contiguous and got.tobytes() == ref.tobytes()
    assert P.to_map_quat(q[:0], map_yaw_rad).shape == (0, 4)
