"""WKNN (Nowicki & Skrzypczyński 2019): oracle, synthetic path-loss field, declines, scale, registry, PUTMC regression."""
from __future__ import annotations

import itertools
import time

import numpy as np
import pytest
from conftest import dataset

from indoor_loc.bench.wifi import rssi_at, scans_from_matrix, synthetic_field
from indoor_loc.errors import ConfigError, MapError
from indoor_loc.params import params_from_dict
from indoor_loc.wifi.methods import available_methods, make_positioner, params_class
from indoor_loc.wifi.types import RadioMap, WifiScan
from indoor_loc.wifi.wknn import Wknn, WknnParams


def _field(rng, spacing=2.0, size=(40.0, 20.0), n_aps=40):
    """Map on a regular grid of a log-distance field; returns (map, AP params for new queries)."""
    xs, ys = np.arange(0, size[0] + 1e-9, spacing), np.arange(0, size[1] + 1e-9, spacing)
    pts = np.array(list(itertools.product(xs, ys)), float)
    ap = rng.uniform([0, 0], size, size=(n_aps, 2))
    A, n = rng.uniform(-45, -30, n_aps), rng.uniform(3.5, 5.0, n_aps)
    rss = rssi_at(pts, ap, A, n, rng, sigma_db=3.0, floor_dbm=-90.0)
    bssids = [f"02:00:00:00:00:{i:02x}" for i in range(n_aps)]
    rm = RadioMap(positions=pts, bssids=bssids, rssi_dbm=rss, freq_mhz=np.full(n_aps, 2437.0))
    return rm, (ap, A, n, bssids)


def _queries(rng, field, n_q, size=(40.0, 20.0)):
    ap, A, n, bssids = field
    q = rng.uniform([2, 2], [size[0] - 2, size[1] - 2], size=(n_q, 2))
    return q, scans_from_matrix(rssi_at(q, ap, A, n, rng, sigma_db=3.0, floor_dbm=-90.0), bssids)


# ----------------------------------------------------------------------------------------------
# oracle: a slow, obviously correct WKNN on dicts
# ----------------------------------------------------------------------------------------------
def oracle(rm: RadioMap, scan: WifiScan, p: WknnParams):
    x = {b: r for b, r in zip(scan.bssid, scan.rssi_dbm) if r >= p.min_signal_dbm}
    cands = []
    for i in range(rm.n_scans):
        y = {b: r for b, r in zip(rm.bssids, rm.rssi_dbm[i]) if not np.isnan(r) and r >= p.min_signal_dbm}
        common = [b for b in x if b in y]
        if not x or not y or len(common) < p.min_shared_aps:
            continue
        fx, fy = len(common) / len(x), len(common) / len(y)
        thr = p.shared_threshold
        ok = (fx > thr and fy > thr) if p.shared_strict else (fx >= thr - 1e-12 and fy >= thr - 1e-12)
        if not ok:
            continue
        diff = np.array([x[b] - y[b] for b in common])
        d = {"l2": np.sqrt((diff ** 2).sum()), "l1": np.abs(diff).sum(), "rms": np.sqrt((diff ** 2).mean()),
             "mae": np.abs(diff).mean()}[p.error_type]
        cands.append((d, i))
    if len(cands) < (p.min_candidates or p.k):
        return None
    cands.sort()
    best = cands[:p.k]
    s = np.array([1.0 / (d + p.epsilon) for d, _ in best])
    return (s[:, None] * rm.positions[[i for _, i in best]]).sum(0) / s.sum(), [i for _, i in best]


@pytest.mark.parametrize("error_type,strict,thr", [("l2", False, 0.6), ("l1", False, 0.5), ("rms", True, 0.5),
                                                   ("mae", False, 0.7)])
def test_matches_oracle(rng, error_type, strict, thr):
    rm, field = _field(rng)
    _, scans = _queries(rng, field, 25)
    p = WknnParams(error_type=error_type, shared_strict=strict, shared_threshold=thr, k=4)
    fixes = Wknn(p).fit(rm).locate_many(scans)
    for scan, fix in zip(scans, fixes):
        ref = oracle(rm, scan, p)
        assert fix.ok == (ref is not None)
        if ref is not None:
            np.testing.assert_allclose(fix.xy, ref[0], atol=1e-9)
            assert sorted(fix.info["rows"].tolist()) == sorted(ref[1])
            np.testing.assert_allclose(fix.info["weights"].sum(), 1.0)


def test_locate_and_locate_many_agree(rng):
    rm, field = _field(rng)
    _, scans = _queries(rng, field, 20)
    w = Wknn().fit(rm)
    for a, b in zip(w.locate_many(scans), [w.locate(s) for s in scans]):
        assert a.ok == b.ok and a.reason == b.reason
        if a.ok:
            np.testing.assert_array_equal(a.xy, b.xy)
            np.testing.assert_array_equal(a.cov, b.cov)


def test_locate_rows_is_locate_with_less_info(rng):
    """The back-end's lighter call gives the same fix, rows, weights and reasons bit for bit."""
    rm, field = _field(rng)
    _, scans = _queries(rng, field, 30)
    scans += [WifiScan(1, ("aa:bb:cc:dd:ee:ff",), np.array([-50.0]), np.array([2412.0])),
              WifiScan(2, (rm.bssids[0],), np.array([-110.0]), np.array([2412.0])),
              WifiScan(3, (rm.bssids[0], rm.bssids[1]), np.array([np.nan, -60.0]), np.full(2, 2412.0))]
    seen = set()
    for p in (WknnParams(), WknnParams(error_type="rms", shared_strict=True, shared_threshold=0.5),
              WknnParams(error_type="mae", k=3, min_candidates=170)):
        w = Wknn(p).fit(rm)
        for s in scans:
            a, b = w.locate(s), w.locate_rows(s)
            seen.add(a.reason)
            assert (a.ok, a.reason, a.info["candidates"]) == (b.ok, b.reason, b.info["candidates"])
            assert a.xy.tobytes() == b.xy.tobytes() and a.cov.tobytes() == b.cov.tobytes()
            if a.ok:
                for key in ("rows", "weights", "similarity"):
                    assert a.info[key].tobytes() == b.info[key].tobytes()
                assert "sources" not in b.info
    assert seen == {"", "no_candidates", "no_usable_aps", "few_candidates"}


def test_recovers_positions_in_a_path_loss_field(rng):
    """2 m grid, 40 APs (n 3.5-5, 3 dB noise): WKNN mean error under 2 m (measured 0.9 m)."""
    rm, field = _field(rng)
    truth, scans = _queries(rng, field, 200)
    fixes = Wknn(WknnParams(k=4, shared_threshold=0.5)).fit(rm).locate_many(scans)
    ok = np.array([f.ok for f in fixes])
    assert ok.mean() > 0.95
    err = np.linalg.norm(np.array([f.xy for f in fixes])[ok] - truth[ok], axis=1)
    assert err.mean() < 2.0
    assert np.percentile(err, 95) < 4.5
    # covariances are symmetric positive definite, at least the floor
    for f in fixes:
        if f.ok:
            np.testing.assert_allclose(f.cov, f.cov.T)
            assert np.linalg.eigvalsh(f.cov).min() >= 1.0 - 1e-9


def test_exact_fingerprint_is_found(rng):
    rm, _ = _field(rng)
    scans = scans_from_matrix(rm.rssi_dbm[:10], rm.bssids)
    fixes = Wknn(WknnParams(k=1, min_candidates=1)).fit(rm).locate_many(scans)
    for i, f in enumerate(fixes):
        np.testing.assert_allclose(f.xy, rm.positions[i])


def test_declines_with_reasons(rng):
    rm, field = _field(rng)
    w = Wknn().fit(rm)
    unknown = WifiScan(1, ("aa:bb:cc:dd:ee:ff",), np.array([-50.0]), np.array([2412.0]))
    f = w.locate(unknown)
    assert not f.ok and f.reason == "no_candidates"
    weak = WifiScan(2, (rm.bssids[0],), np.array([-110.0]), np.array([2412.0]))
    assert w.locate(weak).reason == "no_usable_aps"
    # a single map scan can never give k = 4 candidates
    one = RadioMap(positions=rm.positions[:1], bssids=rm.bssids, rssi_dbm=rm.rssi_dbm[:1], freq_mhz=rm.freq_mhz)
    scan = scans_from_matrix(rm.rssi_dbm[:1], rm.bssids)[0]
    f = Wknn().fit(one).locate(scan)
    assert not f.ok and f.reason == "few_candidates" and f.info["candidates"] == 1
    assert Wknn(WknnParams(min_candidates=1)).fit(one).locate(scan).ok


def test_bad_params_and_maps():
    for kw, match in [({"k": 0}, "k"), ({"shared_threshold": 1.5}, "shared_threshold"),
                      ({"error_type": "l3"}, "error_type"), ({"cov_floor_m": 0.0}, "cov_floor_m"),
                      ({"epsilon": -1.0}, "epsilon"), ({"min_signal_dbm": 10.0}, "min_signal_dbm")]:
        with pytest.raises(ConfigError, match=match):
            params_from_dict(WknnParams, kw)
    with pytest.raises(ConfigError, match="unknown"):
        params_from_dict(WknnParams, {"kk": 3})
    with pytest.raises(MapError, match="fit"):
        Wknn().locate(WifiScan(0, ("aa:bb:cc:dd:ee:ff",), np.array([-50.0]), np.array([2412.0])))
    empty = RadioMap(positions=np.zeros((0, 2)), bssids=[], rssi_dbm=np.zeros((0, 0)), freq_mhz=np.zeros(0))
    with pytest.raises(MapError, match="no scans"):
        Wknn().fit(empty)


def test_ten_thousand_scan_map_is_fast():
    rng = np.random.default_rng(3)
    rm, _ = synthetic_field(rng, 10_000)
    queries = scans_from_matrix(rm.rssi_dbm[:100] + rng.normal(0, 3, (100, rm.n_aps)).clip(-20, 20), rm.bssids)
    t0 = time.perf_counter()
    w = Wknn().fit(rm)
    fixes = w.locate_many(queries)
    dt = time.perf_counter() - t0
    assert dt < 5.0, f"fit + 100 scans against 10 000 took {dt:.2f} s"
    ok = [f for f in fixes if f.ok]
    assert len(ok) > 90
    err = np.linalg.norm(np.array([f.xy for f in ok]) - rm.positions[[i for i, f in enumerate(fixes) if f.ok]], axis=1)
    assert np.median(err) < 3.0


def test_registry():
    w = make_positioner("wknn", {"k": 5, "error_type": "l1"})
    assert isinstance(w, Wknn) and w.params.k == 5 and w.params.error_type == "l1"
    assert params_class("wknn") is WknnParams
    with pytest.raises(ConfigError, match="unknown WiFi positioning method"):
        make_positioner("magic", {})
    with pytest.raises(ConfigError, match="unknown"):
        make_positioner("wknn", {"nope": 1})
    assert "wknn" in available_methods()
    for name in ("pathloss", "coverage"):
        if name in available_methods():
            assert make_positioner(name, {}).name == name


def test_putmc_regression():
    root = dataset("putmc")
    from indoor_loc.bench.wifi import AUTHORS, PAPER, load_putmc, run_method
    rm, scans, truth, _ = load_putmc(root)
    assert len(scans) == 347 and rm.n_scans == 114
    paper = run_method("wknn", PAPER, rm, scans, truth)
    # measured: mean 2.86 m (published 2.86), Q3 3.72 (3.66), 334/347 located
    assert abs(paper["mean"] - 2.86) <= 0.15 and paper["mean"] <= 3.0
    assert abs(paper["p75"] - 3.66) <= 0.2
    assert paper["located"] >= 330
    # the calibrated covariance: about half inside the 50 % ellipse, ~90 % inside the 95 % one
    assert 0.4 <= paper["cons50"] <= 0.65 and 0.85 <= paper["cons95"] <= 0.99
    authors = run_method("wknn", AUTHORS, rm, scans, truth)    # measured 2.91 m, Q3 3.65 m, 346 located
    assert abs(authors["mean"] - 2.91) <= 0.15 and authors["located"] >= 340
