"""MagSync: the online stamp-order merge equals the batch order; late samples are counted, not used."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from heading_synth import arrival_order
from indoor_loc.imu.mag_sync import IMU, MAG, MagSync, merge_events


def _online(t, mt, order, max_delay_s):
    s = MagSync(max_delay_s)
    got = []
    for kind, i in order:
        evs = s.push_imu(int(t[i]), i) if kind == "imu" else s.push_mag(int(mt[i]), i)
        got += [(k, p) for k, _, p in evs]
    got += [(k, p) for k, _, p in s.flush()]
    return got, s


@given(st.integers(0, 2**31), st.floats(0.0, 0.09))
def test_online_order_equals_batch_when_magnetometer_is_late_within_the_bound(seed, delay_s):
    rng = np.random.default_rng(seed)
    t = np.cumsum(rng.integers(2_000_000, 8_000_000, 300))
    mt = np.cumsum(rng.integers(10_000_000, 30_000_000, 60)) + int(rng.integers(-20_000_000, 20_000_000))
    mt = mt[mt > 0]
    delays = rng.integers(0, int(delay_s * 1e9) + 1, len(mt))        # each message its own delay
    delays[0] = 0            # before the first magnetometer sample nothing waits (a 6-D IMU has no latency)
    got, s = _online(t, mt, arrival_order(t, mt, delays), 0.1)
    assert got == merge_events(t, mt)
    assert s.n_late == 0


def test_magnetometer_later_than_the_bound_is_dropped_and_counted():
    t = np.arange(1, 101) * 10_000_000                     # 100 Hz
    mt = np.arange(1, 21) * 50_000_000 + 1                  # 20 Hz
    delays = np.zeros(len(mt), dtype=np.int64)
    delays[5] = 300_000_000        # 0.3 s late (bound 0.1 s); the topic is FIFO, so 6, 7, 8 queue behind it
    got, s = _online(t, mt, arrival_order(t, mt, delays), 0.1)
    dropped = {(MAG, j) for j in (5, 6, 7, 8)}              # 9 arrives exactly 0.1 s after its stamp: used
    assert s.n_late == 4
    assert not dropped & set(got)
    expected = [e for e in merge_events(t, mt) if e not in dropped]
    assert got == expected                                  # everything else in stamp order


def test_no_magnetometer_means_no_wait_and_missing_magnetometer_bounds_the_wait():
    s = MagSync(0.1)
    assert s.push_imu(1_000, "a") == [(IMU, 1_000, "a")]           # never saw a magnetometer: at once
    s.push_mag(2_000, "m")
    assert s.push_imu(3_000, "b") == [(MAG, 2_000, "m")]            # waits for a magnetometer >= 3000
    assert s.push_imu(50_000_000, "c") == []
    out = s.push_imu(103_000_001, "d")                              # 0.1 s after b: stop waiting
    assert [e[2] for e in out] == ["b"]
    out = s.push_imu(150_000_000, "e")                              # 0.1 s after c
    assert [e[2] for e in out] == ["c"]


def test_bad_stamps_and_bad_bound():
    s = MagSync(0.1)
    s.push_imu(10, None)
    with pytest.raises(ValueError, match="IMU stamps must increase"):
        s.push_imu(10, None)
    s.push_mag(5, None)
    with pytest.raises(ValueError, match="magnetometer stamps must increase"):
        s.push_mag(5, None)
    with pytest.raises(ValueError, match="max_delay_s"):
        MagSync(-1.0)


def test_save_restore():
    t = np.arange(1, 201) * 5_000_000
    mt = np.arange(1, 41) * 20_000_000 + 7
    order = arrival_order(t, mt, 30_000_000)
    ref, _ = _online(t, mt, order, 0.1)
    s = MagSync(0.1)
    got = []
    for n, (kind, i) in enumerate(order):
        if n == len(order) // 2:
            saved = s.state()
            s = MagSync(0.1)
            s.set_state(saved)
        evs = s.push_imu(int(t[i]), i) if kind == "imu" else s.push_mag(int(mt[i]), i)
        got += [(k, p) for k, _, p in evs]
    got += [(k, p) for k, _, p in s.flush()]
    assert got == ref
