"""bench/fix_causes.py: a scan's measurement time from its strongest readings' ages, and a walk's true
device offset against the survey readings near the truth."""
from __future__ import annotations

import numpy as np

from indoor_loc.bench.fix_causes import measurement_stamp, true_offset_db
from indoor_loc.wifi.radiomap import add_fingerprints, empty_radiomap
from indoor_loc.wifi.types import WifiScan

APS = tuple(f"00:00:00:00:00:{i:02x}" for i in range(7))


def _scan(rssi, age=None, t=10_000_000_000):
    return WifiScan(stamp_ns=t, bssid=APS, rssi_dbm=np.asarray(rssi, float), freq_mhz=np.full(7, 2412.0),
                    age_ms=None if age is None else np.asarray(age, float))


def test_measurement_stamp_is_the_stamp_minus_the_strongest_readings_median_age():
    s = _scan([-40, -45, -50, -55, -60, -90, -95], [1000, 2000, 3000, 0, 500, 9000, 9000])
    assert measurement_stamp(s) == 10_000_000_000 - 1_000_000_000      # median of 1000, 2000, 3000, 0, 500
    assert measurement_stamp(_scan([-40] * 7)) == 10_000_000_000       # no ages: the stamp


def test_true_offset_is_the_median_difference_to_the_survey_near_the_truth():
    rng = np.random.default_rng(1)
    base = rng.uniform(-80, -40, 7)
    near, far = _scan(base), _scan(base + 20.0)
    rm = add_fingerprints(empty_radiomap(), np.array([[0.0, 0.0], [10.0, 0.0]]), [near, far])
    assert true_offset_db(_scan(base - 6.0), np.array([0.5, 0.0]), rm) == np.float64(-6.0)
    assert np.isnan(true_offset_db(_scan(base), np.array([50.0, 0.0]), rm))      # no survey scan within 3 m
