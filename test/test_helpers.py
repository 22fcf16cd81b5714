"""The one implementation of small helpers several modules share: topic namespaces, event rates."""
from __future__ import annotations

import pytest

from indoor_loc.contract import namespace_of_topic, split_ns
from indoor_loc.pipeline.stage import TopicStats, rate_hz


@pytest.mark.parametrize("full, rel, ns", [
    ("/walk07/imu/data", "imu/data", "/walk07"),
    ("/a/b/imu/data", "imu/data", "/a/b"),
    ("/imu/data", "imu/data", ""),
    ("imu/data", "/imu/data", ""),
    ("/walk07/imu/data_raw", "imu/data", None),
    ("/walk07/xim/data", "im/data", None),
])
def test_namespace_of_topic(full, rel, ns):
    assert namespace_of_topic(full, rel) == ns


def test_split_ns_prefers_the_longest_relative_name():
    assert split_ns("/u/wifi/scan_raw", {"wifi/scan", "wifi/scan_raw", "scan_raw"}) == ("/u", "wifi/scan_raw")
    assert split_ns("/u/other", {"wifi/scan"}) == ("", "/u/other")


def test_rate_hz():
    assert rate_hz(11, 0, 1_000_000_000) == pytest.approx(10.0)
    assert rate_hz(1, 0, 5) == 0.0 and rate_hz(5, None, 10) == 0.0 and rate_hz(5, 10, 10) == 0.0
    st = TopicStats(count=3, first_ns=0, last_ns=500_000_000)
    assert st.rate_hz() == pytest.approx(4.0)


def test_ap_readings_gather_matches_the_dense_matrix(rng):
    """The inverted index returns exactly the masked readings of the asked columns, column by column."""
    import numpy as np

    from scipy import sparse

    from indoor_loc.wifi.types import ApReadings
    for m in (40, 400):                      # short runs (indexed element by element) and long ones (copied whole)
        vals = rng.normal(-70, 10, (m, 12))
        mask = rng.random((m, 12)) < 0.3
        cols = np.array([3, 0, 11, 3])
        assert (mask[:, cols].sum() >= ApReadings.RUN_COPY * len(cols)) == (m == 400)
        for idx in (ApReadings(mask, vals), ApReadings.from_sparse(sparse.csr_matrix(np.where(mask, vals, 0.0)))):
            rows, got, lens = idx.gather(cols)
            assert lens.tolist() == [int(mask[:, c].sum()) for c in cols]
            start = 0
            for c, n in zip(cols, lens):
                r = np.flatnonzero(mask[:, c])
                assert rows[start:start + n].tolist() == r.tolist()
                np.testing.assert_array_equal(got[start:start + n], vals[r, c])
                start += n
    empty = ApReadings(np.zeros((0, 0), bool), np.zeros((0, 0)))
    assert [len(a) for a in empty.gather(np.zeros(0, np.int64))] == [0, 0, 0]
