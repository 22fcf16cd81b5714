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
