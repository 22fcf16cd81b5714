"""WiFi scan likelihood on the links (radio map interpolated along edges) on a synthetic RSS field."""
from __future__ import annotations

import numpy as np
import pytest

from indoor_loc.errors import ConfigError, MapError
from indoor_loc.graph import build_graph
from indoor_loc.graph.tll import TransitionParams, transition_table
from indoor_loc.pf.filter import PfParams
from indoor_loc.pf.tracker import GraphTracker
from indoor_loc.pf.wifi_field import EdgeFingerprintField, ScanFieldParams
from indoor_loc.wifi.radiomap import add_fingerprints, empty_radiomap
from indoor_loc.wifi.types import WifiScan

APS = np.array([[0.0, -3.0], [20.0, 3.0], [10.0, 14.0], [24.0, 12.0], [-2.0, 10.0]])
BSSIDS = tuple(f"02:00:00:00:00:{i:02x}" for i in range(len(APS)))


def field_dbm(xy: np.ndarray) -> np.ndarray:
    """Log-distance path loss of the five APs at points (N, 2) -> (N, 5) dBm."""
    d = np.hypot(*(np.asarray(xy)[:, None, :] - APS[None]).transpose(2, 0, 1))
    return -35.0 - 25.0 * np.log10(d + 1.0)


def rect_graph():
    xy = np.array([[0, 0], [20, 0], [20, 10], [0, 10]], float)
    return build_graph(range(4), xy, [(0, 1), (1, 2), (2, 3), (3, 0)])


def scan_at(xy, stamp_ns, rng, sigma_db=2.0) -> WifiScan:
    rss = field_dbm(np.asarray(xy, float)[None])[0] + rng.normal(0, sigma_db, len(APS))
    return WifiScan(stamp_ns, BSSIDS, rss, np.full(len(APS), 2412.0))


@pytest.fixture
def radio_map():
    rng = np.random.default_rng(11)
    g = rect_graph()
    # a survey every ~1.5 m along the corridors, 0.5 m off the centre line
    t = np.linspace(0, 1, 14, endpoint=False)
    pts = np.concatenate([g.point_at(np.full(len(t), k), t) for k in range(g.n_links)])
    pts = pts + rng.normal(0, 0.5, pts.shape)
    scans = [scan_at(p, 0, rng) for p in pts]
    return add_fingerprints(empty_radiomap(), pts, scans, "survey")


def test_interpolated_fingerprints_follow_the_field(radio_map):
    g = rect_graph()
    f = EdgeFingerprintField(g, radio_map)
    cols = f.aps.columns(BSSIDS)
    err = f.mu[:, cols] - field_dbm(f.points)
    assert np.median(np.abs(err)) < 2.0
    assert f.n_points == int(np.sum(np.ceil(g.link_len) + 1))


def test_scan_likelihood_peaks_at_the_scan_position(radio_map):
    g = rect_graph()
    f = EdgeFingerprintField(g, radio_map, ScanFieldParams(sigma_db=3.0, temper=1.0))   # the field's noise
    rng = np.random.default_rng(3)
    # particles every 0.1 m over the whole graph
    link = np.repeat(np.arange(g.n_links), 200).astype(np.int32)
    pos = np.tile(np.linspace(0, 1, 200), g.n_links) * g.link_len[link]
    xy = g.point_at(link, pos / g.link_len[link])
    for truth in ([5.0, 0.0], [20.0, 6.0], [13.0, 10.0], [0.0, 3.0]):
        ll = f.log_likelihood(link, pos, scan_at(truth, 0, rng))
        w = np.exp(ll - ll.max())
        w /= w.sum()
        near = np.hypot(*(xy - truth).T) < 3.0
        assert w[near].sum() > 4 * near.mean()                    # the mass concentrates near the scan
        assert np.hypot(*(xy[np.argmax(ll)] - truth)) < 2.5
    # an unknown AP set carries no information
    unk = WifiScan(0, ("02:ff:00:00:00:01",), np.array([-50.0]), np.array([2412.0]))
    assert f.known_aps(unk) == 0 and np.all(f.log_likelihood(link, pos, unk) == 0)


def test_tracker_locks_on_from_scans_alone_with_pdr(radio_map):
    g = rect_graph()
    f = EdgeFingerprintField(g, radio_map)
    tr = GraphTracker(g, transition_table(g, TransitionParams()), PfParams(n_particles=800, yaw_offset_sigma_rad=0.0),
                      rng=np.random.default_rng(5))
    rng = np.random.default_rng(6)
    t, s = 0, 2.0
    truth = lambda s: np.array([s, 0.0]) if s <= 20 else np.array([20.0, s - 20])   # noqa: E731
    tr.odom(t, 0.0, 0.0, 0.0)
    assert tr.scan(t, f, scan_at(truth(s), t, rng)) is not None                      # initialised from the scan
    ox = oy = 0.0
    for k in range(1, 80):
        t += 320_000_000
        h = 0.0 if s < 20 else np.pi / 2
        s += 0.35
        ox, oy = ox + 0.35 * np.cos(h), oy + 0.35 * np.sin(h)
        tr.odom(t, ox, oy, h)
        if k % 6 == 0:
            tr.scan(t, f, scan_at(truth(s), t, rng))
    assert np.hypot(*(tr.estimates[-1].xy - truth(s))) < 1.5


def test_bad_inputs(radio_map):
    g = rect_graph()
    with pytest.raises(MapError, match="no fingerprints"):
        EdgeFingerprintField(g, empty_radiomap())
    with pytest.raises(ConfigError, match="sigma_db"):
        ScanFieldParams(sigma_db=0.0).validate()
