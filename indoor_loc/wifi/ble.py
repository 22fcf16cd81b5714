"""BLE beacons as a second RF source beside WiFi (pure numpy).

A BLE scan (:class:`BleScan`, topic ``ble/scan``, schema ``ble_scan.v1``: the ``wifi/scan`` layout with one
entry per beacon) holds the advertisements heard at one instant. Phones hear a beacon every few hundred
milliseconds to seconds, out of step with the WiFi scans, so BLE is fused by **fingerprint**: the
readings of the last ``window_s`` seconds before a WiFi scan join that scan as extra entries, keyed
``ble:<beacon id>`` (:data:`BLE_PREFIX`, so a beacon never collides with a BSSID), and the radio map
holds the same keys, built from the survey the same way (:func:`merge_scans`). Every positioning method
then uses BLE like any other transmitter: its readings enter the match with their own age (``age_ms``
= how long before the WiFi scan the newest reading of that beacon came), and the fix's covariance is the
method's own on the joint fingerprint. A beacon heard several times in the window counts once, with the
mean of its readings in dBm (BLE RSSI scatters by several dB from one advertisement to the next).

:class:`BleWindow` is the online form (``wifi_fix_node`` with ``ble.enabled``), :func:`merge_scans` the
batch one over whole recordings; both give the same scans (tested).
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass, replace
from typing import Iterable, Sequence

import numpy as np

from indoor_loc.params import field, require
from indoor_loc.wifi.types import WifiScan

#: radio-map key prefix of a beacon: ``ble:<beacon id>`` (BSSIDs hold no letters beyond a-f and no 'l')
BLE_PREFIX = "ble:"


@dataclass(frozen=True)
class BleScan:
    """BLE advertisements heard at one instant: ``beacon_id`` unique (lower case; iBeacon
    ``<uuid>-<major>-<minor>``, Eddystone ``<namespace>-<instance>`` or its instance, else the MAC),
    ``rssi_dbm`` (n,), ``tx_power_dbm`` (n,) the advertised power at 1 m (NaN = unknown), ``age_ms``
    (n,) or None (unknown), ``name`` the MAC or a label per beacon."""
    stamp_ns: int
    beacon_id: tuple[str, ...]
    rssi_dbm: np.ndarray
    tx_power_dbm: np.ndarray
    name: tuple[str, ...] = ()
    age_ms: np.ndarray | None = None
    frame_id: str = ""
    source: str = ""

    def __len__(self) -> int:
        return len(self.beacon_id)


@dataclass(frozen=True)
class BleParams:
    """How ``wifi_fix_node`` takes ``ble/scan`` (group ``ble``)."""
    enabled: bool = field(False, "also subscribe to ble/scan and add the beacons heard in the last window_s "
                                 "to each WiFi scan as entries 'ble:<beacon id>' (the radio map must hold them: "
                                 "the importers build it so)")
    window_s: float = field(5.0, "BLE readings at most this old at a WiFi scan's stamp join it, s")

    def validate(self) -> None:
        require(0 < self.window_s <= 600, type(self).__name__, "window_s", "in (0, 600] s", self.window_s)


def ble_key(beacon_id: str) -> str:
    """The radio-map key of a beacon."""
    return BLE_PREFIX + beacon_id


def is_ble_key(key: str) -> bool:
    return key.startswith(BLE_PREFIX)


class BleWindow:
    """The BLE readings of the last ``window_s`` seconds, per beacon (the online merge)."""

    def __init__(self, window_s: float) -> None:
        self.window_ns = int(round(window_s * 1e9))
        #: beacon id -> readings (stamp_ns, rssi_dbm) in arrival order
        self.readings: dict[str, deque[tuple[int, float]]] = {}

    def clear(self) -> None:
        self.readings.clear()

    def add(self, scan: BleScan) -> None:
        ages = scan.age_ms if scan.age_ms is not None else np.zeros(len(scan))
        for b, r, a in zip(scan.beacon_id, np.asarray(scan.rssi_dbm, float).tolist(), np.asarray(ages).tolist()):
            t = scan.stamp_ns - int(round((a if a == a else 0.0) * 1e6))      # NaN age: at the stamp
            self.readings.setdefault(b, deque()).append((t, float(r)))

    def _prune(self, now_ns: int) -> None:
        lo = now_ns - self.window_ns
        for b in list(self.readings):
            q = self.readings[b]
            while q and q[0][0] < lo:
                q.popleft()
            if not q:
                del self.readings[b]

    def merge(self, scan: WifiScan) -> WifiScan:
        """``scan`` plus one entry per beacon heard in ``[stamp - window_s, stamp]`` (see module doc);
        readings older than the window are forgotten. The scan itself is returned when none was heard."""
        self._prune(scan.stamp_ns)
        keys, rssi, age = [], [], []
        for b, q in sorted(self.readings.items()):
            got = [(t, r) for t, r in q if t <= scan.stamp_ns]
            if not got:
                continue
            keys.append(ble_key(b))
            rssi.append(float(np.mean([r for _, r in got])))
            age.append((scan.stamp_ns - max(t for t, _ in got)) * 1e-6)
        if not keys:
            return scan
        have = set(scan.bssid)
        keep = [i for i, k in enumerate(keys) if k not in have]
        n = len(scan)
        old_age = scan.age_ms if scan.age_ms is not None else np.full(n, np.nan)
        return replace(scan, bssid=tuple(scan.bssid) + tuple(keys[i] for i in keep),
                       rssi_dbm=np.concatenate([np.asarray(scan.rssi_dbm, float), [rssi[i] for i in keep]]),
                       freq_mhz=np.concatenate([np.asarray(scan.freq_mhz, float), np.zeros(len(keep))]),
                       ssid=(tuple(scan.ssid) if scan.ssid else ("",) * n) + ("",) * len(keep),
                       age_ms=np.concatenate([np.asarray(old_age, float), [age[i] for i in keep]]))


def merge_scans(wifi: Sequence[WifiScan], ble: Iterable[BleScan], window_s: float) -> list[WifiScan]:
    """Each WiFi scan with the beacons of the ``window_s`` seconds before it (batch form of
    :class:`BleWindow`; both lists in any order, the output in the WiFi scans' order)."""
    order = sorted(range(len(wifi)), key=lambda i: wifi[i].stamp_ns)
    bles = sorted(ble, key=lambda s: s.stamp_ns)
    win = BleWindow(window_s)
    out: list[WifiScan | None] = [None] * len(wifi)
    j = 0
    for i in order:
        while j < len(bles) and bles[j].stamp_ns <= wifi[i].stamp_ns:
            win.add(bles[j])
            j += 1
        out[i] = win.merge(wifi[i])
    return [s for s in out if s is not None]


def without_ble(scan: WifiScan) -> WifiScan:
    """The scan's WiFi entries only."""
    keep = [i for i, b in enumerate(scan.bssid) if not is_ble_key(b)]
    if len(keep) == len(scan):
        return scan
    return replace(scan, bssid=tuple(scan.bssid[i] for i in keep), rssi_dbm=np.asarray(scan.rssi_dbm)[keep],
                   freq_mhz=np.asarray(scan.freq_mhz)[keep], ssid=tuple(scan.ssid[i] for i in keep) if scan.ssid else (),
                   age_ms=None if scan.age_ms is None else np.asarray(scan.age_ms)[keep])
