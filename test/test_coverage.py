"""Seed-004 coverage-area positioning: two levels, minimum size, outlier removal, MIMO compensation."""
from __future__ import annotations

import numpy as np
import pytest

from indoor_loc.errors import ConfigError, InvalidInputError
from indoor_loc.params import params_from_dict
from indoor_loc.wifi.coverage import CoverageArea, CoverageParams, fuse, mimo_factors
from indoor_loc.wifi.types import RadioMap, WifiScan
from test_pathloss import score, synthetic_field

ALL_OFF = dict(two_level=False, min_size=False, outlier_removal=False, mimo=False)


def _scan(bssids, rssi, t=0):
    return WifiScan(t, tuple(bssids), np.asarray(rssi, float), np.full(len(bssids), 2437.0))


def _toy_map(ap_xy: dict[str, np.ndarray], rng, n=30, spread=3.0, rssi=-70.0):
    """A radio map where each AP is heard at n fingerprints scattered (std spread m) around ap_xy."""
    pos, rows = [], []
    bssids = list(ap_xy)
    for j, b in enumerate(bssids):
        p = ap_xy[b] + spread * rng.standard_normal((n, 2))
        r = np.full((n, len(bssids)), np.nan)
        r[:, j] = rssi
        pos.append(p)
        rows.append(r)
    return RadioMap(np.vstack(pos), bssids, np.vstack(rows), np.full(len(bssids), 2437.0))


def test_batch_ca_matches_equations_and_recursive_update():
    rng = np.random.default_rng(0)
    rm, _, scans, _ = synthetic_field(rng, n_test=1)
    ca = CoverageArea().fit(rm)
    mu_w, cov_w, mu_s, cov_s = ca.coverage_areas()
    j = 5
    z = rm.positions[np.isfinite(rm.rssi_dbm[:, j])]
    n = len(z)
    B = 100.0 ** 2 * np.eye(2)
    mu = z.mean(0)
    np.testing.assert_allclose(mu_w[j], mu)
    np.testing.assert_allclose(cov_w[j], (z.T @ z + B - n * np.outer(mu, mu)) / (n + 1), rtol=1e-9)
    # eqs. 28-29 written out, against add_fingerprint
    x_new = np.array([12.0, 7.0])
    mu1 = (n * mu + x_new) / (n + 1)
    cov1 = ((n + 1) * (cov_w[j] - np.outer(mu1, mu1)) + np.outer(x_new, x_new) + n * np.outer(mu, mu)) / (n + 2)
    ca.add_fingerprint(x_new, _scan([rm.bssids[j], "02:aa:00:00:00:01"], [-80.0, -50.0]))
    mu_w2, cov_w2, mu_s2, cov_s2 = ca.coverage_areas()
    np.testing.assert_allclose(mu_w2[j], mu1)
    np.testing.assert_allclose(cov_w2[j], cov1, rtol=1e-9)
    # a new AP gets mean = the fingerprint and covariance B / 2 on both levels (RSS -50 >= -60)
    np.testing.assert_allclose(mu_w2[-1], x_new)
    np.testing.assert_allclose(cov_w2[-1], B / 2)
    np.testing.assert_allclose(cov_s2[-1], 20.0 ** 2 * np.eye(2) / 2)
    assert ca.locate(_scan(["02:aa:00:00:00:01"], [-50.0])).ok


def test_positions_bounded_and_consistent_and_ablation_changes_behaviour():
    rng = np.random.default_rng(1)
    rm, txy, scans, _ = synthetic_field(rng)
    res = {}
    variants = {"all_on": {}, "all_off": ALL_OFF, **{f"{k}_off": {k: False} for k in ALL_OFF}}
    for name, over in variants.items():
        fixes = CoverageArea(CoverageParams(**over)).fit(rm).locate_many(scans)
        res[name] = (score(fixes, txy), np.array([f.xy if f.ok else [np.nan] * 2 for f in fixes]))
    (ok, e, c50, c95), _ = res["all_on"]
    assert ok >= 0.9 and e.mean() < 8.0 and c95 >= 0.8, (ok, e.mean(), c95)
    assert e.mean() < res["all_off"][0][1].mean()
    assert res["all_off"][0][3] < c95  # without the modifications the covariance is overconfident
    for name in variants:
        # this field has no moved APs; outlier removal is exercised by test_outlier_removal_*
        if name not in ("all_on", "outlier_removal_off"):
            assert not np.allclose(res[name][1], res["all_on"][1], equal_nan=True), name


def test_min_size_bounds_the_ca_axes():
    rng = np.random.default_rng(2)
    rm = _toy_map({"02:00:00:00:00:01": np.array([5.0, 5.0])}, rng, n=200, spread=1.0)
    for on in (True, False):
        ca = CoverageArea(CoverageParams(min_size=on)).fit(rm)
        f = ca.locate(_scan(["02:00:00:00:00:01"], [-70.0]))
        lam = np.linalg.eigvalsh(f.cov)
        assert (lam.min() >= 40.0 ** 2 - 1e-6) == on


def test_outlier_removal_drops_a_moved_ap():
    rng = np.random.default_rng(3)
    aps = {f"02:00:00:00:00:{i:02x}": np.array([10.0 + 3 * i, 10.0 + (i % 2)]) for i in range(4)}
    aps["02:00:00:00:00:99"] = np.array([300.0, 200.0])  # moved far away since the survey
    rm = _toy_map(aps, rng, rssi=-55.0)
    scan = _scan(list(aps), [-55.0] * 5)
    on = CoverageArea().fit(rm).locate(scan)
    off = CoverageArea(CoverageParams(outlier_removal=False)).fit(rm).locate(scan)
    assert on.ok and on.info["n_outliers"] == 1 and "02:00:00:00:00:99" not in on.info["bssids"]
    assert np.linalg.norm(on.xy - [14.5, 10.5]) < 3.0
    assert np.linalg.norm(off.xy - [14.5, 10.5]) > 10.0
    # two distant CAs only: the scan is dropped
    two = CoverageArea().fit(rm).locate(_scan(["02:00:00:00:00:00", "02:00:00:00:00:99"], [-55.0, -55.0]))
    assert not two.ok and two.reason == "outlier_conflict"


def test_mimo_identical_cas_count_once():
    """Seed 004 appendix property: k identical CAs far from the others act like one."""
    mu = np.array([[0.0, 0.0], [0.0, 0.0], [0.0, 0.0], [30.0, 0.0]])
    cov = np.tile(np.eye(2) * 25.0, (4, 1, 1))
    f = mimo_factors(mu, cov)
    np.testing.assert_allclose(f, [3.0, 3.0, 3.0, 1.0])
    xy, S = fuse(mu, cov * f[:, None, None])
    xy1, S1 = fuse(mu[2:], cov[2:])
    np.testing.assert_allclose(xy, xy1)
    np.testing.assert_allclose(S, S1)
    # and in the positioner
    rng = np.random.default_rng(4)
    aps = {"02:00:00:00:00:01": np.array([0.0, 0.0]), "02:00:00:00:00:02": np.array([0.0, 0.0]),
           "02:00:00:00:00:03": np.array([0.0, 0.0]), "02:00:00:00:00:04": np.array([12.0, 0.0])}
    rm = _toy_map(aps, rng, spread=2.0, rssi=-55.0)
    rm.positions[30:90] = rm.positions[:30].repeat(2, axis=0)[:60]  # identical fingerprints for the trio
    scan = _scan(list(aps), [-55.0] * 4)
    on = CoverageArea(CoverageParams(outlier_removal=False)).fit(rm).locate(scan)
    off = CoverageArea(CoverageParams(outlier_removal=False, mimo=False)).fit(rm).locate(scan)
    assert on.xy[0] > off.xy[0] + 2.0  # less pulled towards the trio
    assert np.trace(on.cov) > 1.8 * np.trace(off.cov)


def test_two_level_uses_strong_cas():
    rng = np.random.default_rng(5)
    rm, _, scans, _ = synthetic_field(rng, n_test=20)
    on = CoverageArea().fit(rm).locate_many(scans)
    off = CoverageArea(CoverageParams(two_level=False)).fit(rm).locate_many(scans)
    assert sum(f.info["n_strong"] for f in on if f.ok) > 0
    assert sum(f.info["n_strong"] for f in off if f.ok) == 0


def test_bad_input_gives_declined_fixes():
    rng = np.random.default_rng(6)
    rm, _, scans, _ = synthetic_field(rng, n_test=1)
    ca = CoverageArea().fit(rm)
    f = ca.locate(_scan([], []))
    assert not f.ok and f.reason == "empty_scan"
    f = ca.locate(_scan(["aa:bb:cc:dd:ee:ff"], [-50.0]))
    assert not f.ok and f.reason == "no_known_ap"
    assert CoverageArea().locate(scans[0]).reason == "no_map"
    with pytest.raises(ConfigError, match="prior_weak_m2"):
        params_from_dict(CoverageParams, {"prior_weak_m2": -1.0})
    with pytest.raises(ConfigError, match="bool"):
        params_from_dict(CoverageParams, {"mimo": "yes"})
    with pytest.raises(InvalidInputError, match="nan"):
        ca.add_fingerprint(np.array([np.nan, 0.0]), scans[0])
