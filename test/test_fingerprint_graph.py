"""Seed-002 per-vertex fingerprint Gaussians with interpolation along graph edges."""
from __future__ import annotations

import time

import numpy as np
import pytest

from indoor_loc.errors import ConfigError, MapError
from indoor_loc.params import params_from_dict
from indoor_loc.wifi.fingerprint_graph import FingerprintGraph, FingerprintGraphParams
from indoor_loc.wifi.types import WifiScan
from test_pathloss import synthetic_field


def grid_graph(size=(40.0, 20.0), step=2.5):
    """A 4-connected grid graph over the floor: node_xy (V, 2), link_nodes (L, 2)."""
    xs, ys = np.arange(0, size[0] + 1e-9, step), np.arange(0, size[1] + 1e-9, step)
    nx, ny = len(xs), len(ys)
    gx, gy = np.meshgrid(xs, ys, indexing="ij")
    node_xy = np.c_[gx.ravel(), gy.ravel()]
    ids = np.arange(nx * ny).reshape(nx, ny)
    links = np.vstack([np.c_[ids[:-1, :].ravel(), ids[1:, :].ravel()], np.c_[ids[:, :-1].ravel(), ids[:, 1:].ravel()]])
    return node_xy, links


def slow_log_likelihood(fg: FingerprintGraph, link: int, pos: float, scan: WifiScan) -> float:
    """Kim et al. 2012's fingerprint model written out for one point: distance-weighted vertex values, product over APs."""
    p = fg.params
    i, j = fg.link_nodes[link]
    xi, xj = fg.node_xy[i], fg.node_xy[j]
    x = xi + pos * (xj - xi)
    L = np.linalg.norm(xi - xj)
    wi, wj = np.linalg.norm(x - xj) / L, np.linalg.norm(x - xi) / L
    ll = 0.0
    if p.use_non_detections:  # log(1 - pdet) interpolated, over the map's APs not heard
        for a, b in enumerate(fg.bssids):
            if b not in scan.bssid:
                ll += wi * np.log(1 - fg.pdet[i, a]) + wj * np.log(1 - fg.pdet[j, a])
    for b, z in zip(scan.bssid, scan.rssi_dbm):
        if b not in fg.bssids:
            continue
        a = fg.bssids.index(b)
        mu = wi * fg.mu[i, a] + wj * fg.mu[j, a]
        var = wi * fg.var[i, a] + wj * fg.var[j, a]
        pd = wi * fg.pdet[i, a] + wj * fg.pdet[j, a]
        g = np.exp(-0.5 * (z - mu) ** 2 / var) / np.sqrt(2 * np.pi * var)
        ll += np.log(pd * ((1 - p.outlier_prob) * g + p.outlier_prob / p.rssi_range_db))
    return ll


@pytest.fixture(scope="module")
def field():
    rng = np.random.default_rng(0)
    return synthetic_field(rng, n_test=40)


@pytest.mark.parametrize("non_det", [False, True])
def test_vectorised_matches_the_equation(field, non_det):
    rm, _, scans, _ = field
    node_xy, links = grid_graph()
    fg = FingerprintGraph(FingerprintGraphParams(use_non_detections=non_det)).fit(rm, node_xy, links)
    rng = np.random.default_rng(1)
    link = rng.integers(0, len(links), 50)
    pos = rng.uniform(0, 1, 50)
    s = scans[0]
    s = WifiScan(s.stamp_ns, s.bssid[2:], s.rssi_dbm[2:], s.freq_mhz[2:])  # two map APs not heard
    ll = fg.log_likelihood(link, pos, s)
    slow = [slow_log_likelihood(fg, l, t, s) for l, t in zip(link, pos)]
    np.testing.assert_allclose(ll, slow, rtol=1e-10)
    # at the ends of an edge the interpolation returns the vertex values
    mu, var, pd = fg.interpolate(np.array([3, 3]), np.array([0.0, 1.0]))
    np.testing.assert_allclose(mu[0], fg.mu[links[3, 0]])
    np.testing.assert_allclose(var[1], fg.var[links[3, 1]])


@pytest.mark.parametrize("assign", ["kernel", "nearest"])
def test_likelihood_peaks_near_the_truth(field, assign):
    """Dense candidates on every edge: the maximum-likelihood point is near the true position."""
    rm, txy, scans, _ = field
    node_xy, links = grid_graph()
    fg = FingerprintGraph(FingerprintGraphParams(assign=assign)).fit(rm, node_xy, links)
    link = np.repeat(np.arange(len(links)), 6)
    pos = np.tile(np.linspace(0, 1, 6), len(links))
    xy = fg.link_point(link, pos)
    err = []
    for s, t in zip(scans, txy):
        ll = fg.log_likelihood(link, pos, s)
        err.append(np.linalg.norm(xy[np.argmax(ll)] - t))
    # one scan, sigma = 4 dB, single-sample fingerprints on a 2 m grid
    assert np.mean(err) < 3.5 and np.median(err) < 3.0, (np.mean(err), np.median(err))


def test_vertices_without_data_and_missing_aps(field):
    rm, _, scans, _ = field
    node_xy, links = grid_graph()
    far = len(node_xy)
    node_xy = np.vstack([node_xy, [[80.0, 10.0]]])  # a vertex 40 m from every fingerprint
    links = np.vstack([links, [[far - 1, far]]])
    fg = FingerprintGraph(FingerprintGraphParams(use_non_detections=False)).fit(rm, node_xy, links)
    assert np.all(np.isfinite(fg.mu)) and np.all(fg.var > 0)
    assert np.all(fg.var[far] > 30.0 ** 2)  # extrapolated 40 m: very uncertain
    np.testing.assert_allclose(fg.pdet[far], 0.5, atol=1e-6)  # detection falls back to the prior
    ll = fg.log_likelihood(np.array([len(links) - 1] * 2), np.array([0.0, 1.0]), scans[0])
    assert np.all(np.isfinite(ll)) and ll[0] > ll[1]  # the far end explains the scan worse
    # hearing an AP where the map says it is hardly ever heard costs likelihood
    a = int(np.argmin(fg.pdet.max(axis=0)))
    v_lo, v_hi = int(np.argmin(fg.pdet[:, a])), int(np.argmax(fg.pdet[:, a]))
    assert fg.pdet[v_lo, a] < fg.pdet[v_hi, a]
    # non-detections change the value when enabled
    fg2 = FingerprintGraph(FingerprintGraphParams(use_non_detections=True)).fit(rm, node_xy, links)
    s = scans[1]
    part = WifiScan(s.stamp_ns, s.bssid[3:], s.rssi_dbm[3:], s.freq_mhz[3:])  # three map APs not heard
    l2 = fg2.log_likelihood(np.array([0, 5]), np.array([0.2, 0.7]), part)
    l1 = fg.log_likelihood(np.array([0, 5]), np.array([0.2, 0.7]), part)
    assert np.all(l2 < l1)


def test_unknown_and_empty_scans_are_uninformative_and_fast(field):
    rm, _, scans, _ = field
    node_xy, links = grid_graph()
    fg = FingerprintGraph().fit(rm, node_xy, links)
    n = 20_000
    link = np.arange(n) % len(links)
    pos = np.linspace(0, 1, n)
    assert np.array_equal(fg.log_likelihood(link, pos, WifiScan(0, (), np.zeros(0), np.zeros(0))), np.zeros(n))
    unk = WifiScan(0, ("aa:bb:cc:dd:ee:ff",), np.array([-40.0]), np.array([2412.0]))
    assert np.array_equal(fg.log_likelihood(link, pos, unk), np.zeros(n))
    t0 = time.perf_counter()
    ll = fg.log_likelihood(link, pos, scans[0])
    assert ll.shape == (n,) and time.perf_counter() - t0 < 0.5  # vectorised: no loop per particle


def test_bad_input(field):
    rm, _, scans, _ = field
    node_xy, links = grid_graph()
    with pytest.raises(MapError):
        FingerprintGraph().fit(rm, node_xy, np.array([[0, 10_000]]))
    with pytest.raises(MapError):
        FingerprintGraph().log_likelihood(np.array([0]), np.array([0.5]), scans[0])
    fg = FingerprintGraph().fit(rm, node_xy, links)
    with pytest.raises(ConfigError, match="out of range"):
        fg.log_likelihood(np.array([len(links)]), np.array([0.5]), scans[0])
    with pytest.raises(ConfigError, match="assign"):
        params_from_dict(FingerprintGraphParams, {"assign": "voronoi"})
