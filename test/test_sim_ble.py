"""The simulator's fixed BLE beacons (indoor_loc/sim/ble.py) and bench ble --dataset sim."""
from __future__ import annotations

import numpy as np

from indoor_loc.sim.ble import BeaconField, BleSimParams, place_beacons
from indoor_loc.sim.building import make_tower_building
from indoor_loc.sim.rf import RfParams
from indoor_loc.wifi.ble import is_ble_key, merge_scans
from indoor_loc.wifi.types import WifiScan

B = make_tower_building()


def test_beacons_are_placed_in_the_zone_apart_with_fixed_ids():
    bs = place_beacons(B, (0, 2), (20.0, -1e3, 1e3, 1e3))
    assert bs == place_beacons(B, (0, 2), (20.0, -1e3, 1e3, 1e3))            # deterministic
    assert {a.floor for a in bs} == {0, 2} and all(a.xyz[0] >= 20.0 for a in bs)
    for f in (0, 2):
        xy = np.array([a.xyz[:2] for a in bs if a.floor == f])
        d = np.hypot(*(xy[:, None] - xy[None]).transpose(2, 0, 1))
        assert len(xy) >= 2 and d[~np.eye(len(xy), dtype=bool)].min() >= BleSimParams().spacing_m
    assert len({a.bssids[0] for a in bs}) == len(bs)


def test_a_phone_hears_the_nearest_beacon_loudest_under_the_same_ids_all_along():
    bs = place_beacons(B, (0,), (20.0, -1e3, 1e3, 1e3))
    field = BeaconField(B, bs, RfParams(), BleSimParams(), np.random.default_rng(0))
    rng = np.random.default_rng(1)
    t = np.arange(0, 20_000_000_000, 100_000_000)
    a = np.array(bs[0].xyz)
    xyz = np.tile(a - [0.0, 0.0, 1.4], (len(t), 1))                           # standing under beacon 0
    heard = field.along(t, xyz, np.zeros(len(t), int), 20.0, rng, "alice")
    assert len(heard) >= 15
    ids = {i for s in heard for i in s.beacon_id}
    assert ids <= {x.bssids[0] for x in bs}                                     # no rotating addresses
    loud = [s.beacon_id[int(np.argmax(s.rssi_dbm))] for s in heard]
    assert np.mean([i == bs[0].bssids[0] for i in loud]) > 0.9
    wifi = [WifiScan(int(5e9), ("aa:bb:cc:dd:ee:ff",), np.array([-60.0]), np.array([2412.0]))]
    fused = merge_scans(wifi, heard, 5.0)[0]
    assert any(is_ble_key(b) for b in fused.bssid) and "aa:bb:cc:dd:ee:ff" in fused.bssid
