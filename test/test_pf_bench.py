"""``indoor-loc bench pf`` scoring: the route is sampled where the reference has poses."""
from __future__ import annotations

import numpy as np

from indoor_loc.bench.pf import ROUTE_SAMPLE_S, paper_sampling


def test_route_sampling_spans_first_to_last_scan_and_holds_the_latest_estimate():
    s = 1_000_000_000
    t = np.arange(0, 20 * s + 1, s // 2, dtype=np.int64)           # estimates every 0.5 s over 20 s
    xy = np.column_stack([t * 1e-9, np.zeros(len(t))])
    scans = np.array([3 * s, 7 * s, 12 * s], np.int64)
    q, p = paper_sampling(t, xy, scans, scan_span=True)
    step = int(ROUTE_SAMPLE_S * 1e9)
    grid = np.arange(3 * s, 12 * s + 1, step)
    assert list(q) == sorted(set(grid.tolist()) | set(scans.tolist()))
    assert q[0] == 3 * s and q[-1] == 12 * s                       # nothing after the last scan
    np.testing.assert_allclose(p[:, 0], np.floor(q * 1e-9 * 2) / 2)  # latest estimate at or before
    # the whole trajectory without scan_span, as before
    q_all, _ = paper_sampling(t, xy, scans)
    assert q_all[0] == 0 and q_all[-1] > 18 * s
