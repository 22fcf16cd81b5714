"""``TYPE_BEACON`` rows of the Microsoft indoor-location traces -> BLE scans (pure Python/numpy).

A row is ``unix_ms TYPE_BEACON uuid major minor tx_power rssi distance mac [unix_ms]`` (iBeacon; the
competition's own parsing code reads the same fields). The beacon id is ``<uuid>-<major>-<minor>`` in lower
case (:func:`indoor_loc.datasets.getsensordata.beacon_id_of`, the same id as a GetSensorData ``BLE4``
line), the tx power the advertised power at 1 m (dBm; 0 = not given), the MAC the scan entry's name. The
rows sharing one first-column time form one scan; a beacon twice in it keeps the later row.
"""
from __future__ import annotations

import math

import numpy as np

from indoor_loc.contract import BOUNDS
from indoor_loc.wifi.ble import BleScan


def beacon_row(t_ms: int, f: list[str]) -> tuple[int, str, str, float, float] | str:
    """(t_ms, beacon id, mac, rssi dBm, tx power dBm or NaN) of a ``TYPE_BEACON`` row split at tabs, or
    the reason it is dropped."""
    from indoor_loc.datasets.getsensordata import beacon_id_of
    if len(f) < 7:
        return "malformed_beacon"
    try:
        tx, rssi = float(f[5]), float(f[6])
    except ValueError:
        return "malformed_beacon"
    if not (math.isfinite(rssi) and -120.0 <= rssi <= 0.0):
        return "beacon_rssi_range"
    mac = f[8].strip().lower() if len(f) > 8 else ""
    bid = beacon_id_of("ibeacon", mac, f[2], f[3], f[4])
    if not bid:
        return "malformed_beacon"
    # a tx power outside the contract's bound (some ms_site2 beacons advertise +68 dBm) is as unknown as 0:
    # the scan keeps the beacon's RSSI, and ble/scan's validation does not reject the whole scan for it
    b = BOUNDS["tx_power_dbm"]
    return t_ms, bid, mac, rssi, (tx if math.isfinite(tx) and tx != 0 and b.lo <= tx <= b.hi else math.nan)


def beacon_scans(rows: list[tuple[int, str, str, float, float]], source: str = "") -> list[BleScan]:
    """Rows of :func:`beacon_row` -> BLE scans sorted by stamp (ns)."""
    by_t: dict[int, dict[str, tuple[str, float, float]]] = {}
    for t, bid, mac, rssi, tx in rows:
        by_t.setdefault(t, {})[bid] = (mac, rssi, tx)
    out = []
    for t in sorted(by_t):
        b = by_t[t]
        ids = tuple(b)
        out.append(BleScan(stamp_ns=t * 1_000_000, beacon_id=ids, rssi_dbm=np.array([b[i][1] for i in ids], float),
                           tx_power_dbm=np.array([b[i][2] for i in ids], float), name=tuple(b[i][0] for i in ids),
                           source=source))
    return out
