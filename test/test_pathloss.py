"""Seed-000 log-distance path-loss model: Gauss–Newton AP fit and multi-start positioning."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import chi2

from indoor_loc.errors import ConfigError, MapError
from indoor_loc.params import params_from_dict
from indoor_loc.wifi.pathloss import PathLoss, PathLossParams, model
from indoor_loc.wifi.types import RadioMap, WifiScan


def synthetic_field(rng: np.random.Generator, n_aps: int = 16, size: tuple[float, float] = (40.0, 20.0),
                    grid_m: float = 2.0, sigma_db: float = 4.0, n_test: int = 100, floor_dbm: float = -90.0,
                    d0: float = 1.0):
    """A known path-loss field on a size[0] x size[1] m floor: APs at random positions with
    A ~ U(-45, -35) dBm, n ~ U(2.5, 3.5), d = sqrt(r^2 + d0^2), Gaussian noise sigma_db, readings
    below floor_dbm not heard. Map fingerprints on a grid_m grid; n_test scans at random points.
    Returns (radio map, test positions (n_test, 2), test scans, truth dict)."""
    ap = rng.uniform([0, 0], size, (n_aps, 2))
    A = rng.uniform(-45, -35, n_aps)
    n = rng.uniform(2.5, 3.5, n_aps)
    bssids = [f"02:00:00:00:{i // 256:02x}:{i % 256:02x}" for i in range(n_aps)]
    gx, gy = np.meshgrid(np.arange(0, size[0] + 1e-9, grid_m), np.arange(0, size[1] + 1e-9, grid_m))
    pos = np.c_[gx.ravel(), gy.ravel()]

    def rss(xy: np.ndarray) -> np.ndarray:
        d = np.sqrt(((xy[:, None] - ap[None]) ** 2).sum(-1) + d0 * d0)
        v = A - 10 * n * np.log10(d) + sigma_db * rng.standard_normal((len(xy), n_aps))
        return np.where(v >= floor_dbm, v, np.nan)

    rm = RadioMap(positions=pos, bssids=bssids, rssi_dbm=rss(pos), freq_mhz=np.full(n_aps, 2437.0))
    test_xy = rng.uniform([0, 0], size, (n_test, 2))
    scans = []
    for t, row in enumerate(rss(test_xy)):
        m = np.isfinite(row)
        scans.append(WifiScan(t, tuple(b for b, k in zip(bssids, m) if k), row[m], np.full(int(m.sum()), 2437.0)))
    return rm, test_xy, scans, {"ap": ap, "A": A, "n": n}


def score(fixes, truth_xy):
    """(ok fraction, errors (m) of ok fixes, fraction inside the 50 % / 95 % ellipses)."""
    ok = np.array([f.ok for f in fixes])
    xy = np.array([f.xy for f in fixes])[ok]
    e = np.linalg.norm(xy - truth_xy[ok], axis=1)
    d2 = np.array([(f.xy - p) @ np.linalg.solve(f.cov, f.xy - p) for f, p in zip(fixes, truth_xy) if f.ok])
    return ok.mean(), e, np.mean(d2 <= chi2.ppf(0.5, 2)), np.mean(d2 <= chi2.ppf(0.95, 2))


def test_jacobians_match_finite_differences():
    theta = np.array([-40.0, 2.7, 3.0, 4.0])
    r = np.array([7.0, -1.0])
    h, Jt, Jr = model(theta, r, 1.0)
    eps = 1e-6
    for i in range(4):
        d = np.zeros(4)
        d[i] = eps
        assert Jt[i] == pytest.approx((model(theta + d, r, 1.0)[0] - model(theta - d, r, 1.0)[0]) / (2 * eps), rel=1e-6)
    for i in range(2):
        d = np.zeros(2)
        d[i] = eps
        assert Jr[i] == pytest.approx((model(theta, r + d, 1.0)[0] - model(theta, r - d, 1.0)[0]) / (2 * eps), rel=1e-6)


def test_fit_recovers_the_field_parameters():
    rng = np.random.default_rng(0)
    rm, _, _, truth = synthetic_field(rng)
    pl = PathLoss().fit(rm)
    assert np.median(np.linalg.norm(pl.theta[:, 2:4] - truth["ap"], axis=1)) < 0.5
    assert np.median(np.abs(pl.theta[:, 1] - truth["n"])) < 0.2
    assert np.median(np.abs(np.sqrt(pl.sigma2) - 4.0)) < 0.4
    # the parameter covariance is symmetric positive definite
    assert np.all(np.linalg.eigvalsh(pl.theta_cov) > 0)


def test_positions_and_consistency_on_a_known_field():
    """40 x 20 m floor, 16 APs, sigma = 4 dB, the correct model: median < 2 m, mean < 2.5 m (the
    tail is geometric ambiguity: there the found minimum has a lower cost than the truth), and
    the covariance is honest (truth inside the 95 % ellipse 80-99 %, inside the 50 % one 35-70 %)."""
    rng = np.random.default_rng(1)
    rm, txy, scans, _ = synthetic_field(rng)
    ok, e, c50, c95 = score(PathLoss(PathLossParams(model_error_m=0.0)).fit(rm).locate_many(scans), txy)
    assert ok == 1.0
    assert np.median(e) < 2.0 and e.mean() < 2.5, (np.median(e), e.mean())
    assert 0.8 <= c95 <= 0.99 and 0.35 <= c50 <= 0.7, (c50, c95)
    # the model-error term only makes the covariance more conservative
    _, e2, c50b, c95b = score(PathLoss().fit(rm).locate_many(scans), txy)
    np.testing.assert_allclose(e2, e)
    assert c50b >= c50 and c95b >= c95


def test_few_observations_stay_bounded():
    """An AP heard in only two map scans keeps a finite, prior-bounded position and covariance."""
    rng = np.random.default_rng(2)
    rm, _, _, _ = synthetic_field(rng, n_test=1)
    col = np.full(rm.n_scans, np.nan)
    col[[3, 4]] = [-70.0, -72.0]
    rm = RadioMap(positions=rm.positions, bssids=rm.bssids + ["02:00:00:00:ff:ff"],
                  rssi_dbm=np.c_[rm.rssi_dbm, col], freq_mhz=np.r_[rm.freq_mhz, 2437.0])
    pl = PathLoss().fit(rm)
    th, C = pl.theta[-1], pl.theta_cov[-1]
    assert np.all(np.isfinite(th)) and np.linalg.norm(th[2:4] - rm.positions[3]) < 10.0
    assert 1.0 <= th[1] <= 6.0
    assert np.sqrt(C[2, 2]) < 16.0


def test_bad_input_gives_declined_fixes():
    rng = np.random.default_rng(3)
    rm, _, scans, _ = synthetic_field(rng, n_test=3)
    pl = PathLoss().fit(rm)
    f = pl.locate(WifiScan(5, (), np.zeros(0), np.zeros(0)))
    assert not f.ok and f.reason == "empty_scan"
    f = pl.locate(WifiScan(5, ("aa:bb:cc:dd:ee:ff",), np.array([-50.0]), np.array([2412.0])))
    assert not f.ok and f.reason == "no_known_ap"
    s = scans[0]
    f = pl.locate(WifiScan(5, s.bssid[:2], s.rssi_dbm[:2], s.freq_mhz[:2]))
    assert not f.ok and f.reason == "too_few_aps"
    assert not PathLoss().locate(s).ok  # not fitted
    with pytest.raises(MapError):
        PathLoss().fit(RadioMap(np.zeros((0, 2)), [], np.zeros((0, 0)), np.zeros(0)))
    with pytest.raises(ConfigError, match="min_aps"):
        params_from_dict(PathLossParams, {"min_aps": 1})
    with pytest.raises(ConfigError, match="n_bounds"):
        params_from_dict(PathLossParams, {"n_bounds": [3.0, 2.0]})
