"""BLE scan (schema ``ble_scan.v1``) <-> diagnostic_msgs/DiagnosticArray.

The ``wifi/scan`` layout (:mod:`msg_adapters.wifi_scan`, the same mechanism): ``status[0]`` the summary
(name ``"scan"``, values ``schema`` = ``ble_scan.v1``, ``ap_count`` = the number of beacons, ``source``),
then one DiagnosticStatus per beacon: name = the beacon id (lower case; iBeacon ``<uuid>-<major>-<minor>``,
Eddystone ``<namespace>-<instance>`` or its instance id, else the MAC), message = the MAC or a label,
values ``rssi_dbm``, ``frequency_mhz`` (0 = unknown; advertising channels are 2402, 2426, 2480 MHz) and
optionally ``age_ms`` and ``tx_power_dbm`` (the advertised power at 1 m). Reasons: those of
:func:`msg_adapters.wifi_scan.scan_from_msg`, with ``bad_beacon_id`` / ``duplicate_beacon`` for the id.
"""
from __future__ import annotations

import re

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray

from indoor_loc.contract import SCHEMA_BLE_SCAN
from indoor_loc.errors import InvalidMessageError
from indoor_loc.wifi.ble import BleScan
from msg_adapters.wifi_scan import RfEntries, RfSchema, rf_from_msg, rf_to_msg

_ID_RE = re.compile(r"^[0-9a-z][0-9a-z:._-]{0,79}$")


def normalize_beacon_id(beacon_id: str) -> str:
    """Lower case, trimmed; 1-80 characters of ``0-9 a-z : . _ -`` (``bad_beacon_id`` otherwise)."""
    b = str(beacon_id).strip().lower()
    if not _ID_RE.match(b):
        raise InvalidMessageError("bad_beacon_id", f"beacon id {beacon_id!r} is not 1-80 characters of "
                                                   f"0-9 a-z : . _ -")
    return b


BLE_SCHEMA = RfSchema(SCHEMA_BLE_SCAN, normalize_beacon_id, entry="beacon", duplicate_reason="duplicate_beacon",
                      extra=("tx_power_dbm",))


def ble_from_msg(msg: DiagnosticArray) -> BleScan:
    """Validate and unpack a ``ble_scan.v1`` DiagnosticArray."""
    e = rf_from_msg(msg, BLE_SCHEMA)
    return BleScan(stamp_ns=e.stamp_ns, beacon_id=e.ids, rssi_dbm=e.rssi_dbm, tx_power_dbm=e.extra["tx_power_dbm"],
                   name=e.names, age_ms=e.age_ms, frame_id=e.frame_id, source=e.source)


def ble_to_msg(scan: BleScan, freq_mhz: np.ndarray | None = None) -> DiagnosticArray:
    """Build the ``ble_scan.v1`` DiagnosticArray of a BLE scan (frequencies 0 = unknown unless given)."""
    n = len(scan.beacon_id)
    return rf_to_msg(RfEntries(stamp_ns=scan.stamp_ns, ids=tuple(scan.beacon_id), names=tuple(scan.name),
                               rssi_dbm=scan.rssi_dbm, freq_mhz=np.zeros(n) if freq_mhz is None else freq_mhz,
                               age_ms=scan.age_ms, extra={"tx_power_dbm": np.asarray(scan.tx_power_dbm, float)},
                               frame_id=scan.frame_id, source=scan.source), BLE_SCHEMA)
