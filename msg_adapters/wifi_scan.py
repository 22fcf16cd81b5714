"""WiFi scan (schema ``wifi_scan.v1``) <-> diagnostic_msgs/DiagnosticArray.

Layout: ``header.stamp`` = scan time, ``header.frame_id`` = receiver frame; ``status[0]`` is the
scan summary (name ``"scan"``, values ``schema``, ``ap_count``, ``source``); then one
DiagnosticStatus per access point: name = BSSID (lower-case, colon-separated), message = SSID,
values ``rssi_dbm``, ``frequency_mhz`` and optionally ``age_ms``. Floats are written with
``repr`` so a scan built from core values round-trips bit-exactly. SSIDs lose any NUL character
(hidden networks are sometimes reported as ``"\\x00\\x00..."``): a CDR string ends at the first NUL.
"""
from __future__ import annotations

import math
import re

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

from indoor_loc.contract import BOUNDS, SCHEMA_WIFI_SCAN
from indoor_loc.errors import InvalidMessageError
from msg_adapters.time import stamp_from_ns, stamp_to_ns
from indoor_loc.wifi.types import WifiScan

RSSI_MIN_DBM = BOUNDS["rssi"].lo
RSSI_MAX_DBM = BOUNDS["rssi"].hi
SUMMARY_NAME = "scan"
_BSSID_RE = re.compile(r"^[0-9a-f]{2}(:[0-9a-f]{2}){5}$")


def normalize_bssid(bssid: str) -> str:
    """``"AA-BB-CC-DD-EE-FF"`` / ``"AA:BB:..."`` -> ``"aa:bb:cc:dd:ee:ff"`` (``"bad_bssid"`` otherwise)."""
    b = str(bssid).strip().lower().replace("-", ":")
    if not _BSSID_RE.match(b):
        raise InvalidMessageError("bad_bssid", f"BSSID {bssid!r} is not six colon-separated hex bytes")
    return b


def _number(bssid: str, key: str, text: str | None) -> float:
    if text is None or text.strip() == "":
        raise InvalidMessageError("missing_field", f"AP {bssid}: no value for {key!r}")
    try:
        v = float(text)
    except ValueError as err:
        raise InvalidMessageError("bad_value", f"AP {bssid}: {key}={text!r} is not a number") from err
    if not math.isfinite(v):
        raise InvalidMessageError("nan", f"AP {bssid}: {key}={text!r}")
    return v


def _check_arrays(bssid: tuple[str, ...], rssi: np.ndarray, freq: np.ndarray, age: np.ndarray | None) -> None:
    """The checks shared by both directions (values are already finite floats)."""
    if len(bssid) == 0:
        raise InvalidMessageError("empty_scan", "scan has no access points")
    seen: set[str] = set()
    for b in bssid:
        if b in seen:
            raise InvalidMessageError("duplicate_bssid", f"BSSID {b} appears more than once")
        seen.add(b)
    bad = np.flatnonzero((rssi < RSSI_MIN_DBM) | (rssi > RSSI_MAX_DBM))
    if bad.size:
        i = int(bad[0])
        raise InvalidMessageError("rssi_range", f"AP {bssid[i]}: rssi {rssi[i]} dBm outside "
                                                f"[{RSSI_MIN_DBM:g}, {RSSI_MAX_DBM:g}]")
    f_b = BOUNDS["frequency"]
    bad = np.flatnonzero((freq != 0.0) & ((freq < f_b.lo) | (freq > f_b.hi)))
    if bad.size:
        i = int(bad[0])
        raise InvalidMessageError(f_b.reason, f"AP {bssid[i]}: frequency_mhz = {freq[i]:.6g} outside [{f_b.lo:g}, "
                                              f"{f_b.hi:g}] MHz and not 0 (unknown) ({f_b.name}: {f_b.why})")
    if age is not None:
        a_b = BOUNDS["age"]
        bad = np.flatnonzero((age < a_b.lo) | (age > a_b.hi))
        if bad.size:
            i = int(bad[0])
            raise InvalidMessageError(a_b.reason, f"AP {bssid[i]}: age_ms = {age[i]:.6g} outside [{a_b.lo:g}, "
                                                  f"{a_b.hi:g}] ms ({a_b.name}: {a_b.why})")


def scan_from_msg(msg: DiagnosticArray) -> WifiScan:
    """Validate and unpack a ``wifi_scan.v1`` DiagnosticArray into a :class:`WifiScan`.

    Reasons: ``schema_version``, ``empty_scan``, ``bad_bssid``, ``duplicate_bssid``, ``nan``,
    ``rssi_range``, ``out_of_range`` (a frequency or age beyond :data:`indoor_loc.contract.BOUNDS`;
    frequency 0 = unknown passes), ``too_many_aps``, ``missing_field``, ``bad_value``, ``ap_count``,
    ``negative_stamp``.
    ``age_ms`` is None when no AP carries one, NaN for the APs without one otherwise.
    """
    stamp = stamp_to_ns(msg.header.stamp)
    if not msg.status or msg.status[0].name != SUMMARY_NAME:
        raise InvalidMessageError("schema_version", f"status[0] must be the {SUMMARY_NAME!r} summary "
                                                    f"of schema {SCHEMA_WIFI_SCAN}")
    summary = {kv.key: kv.value for kv in msg.status[0].values}
    if summary.get("schema") != SCHEMA_WIFI_SCAN:
        raise InvalidMessageError("schema_version", f"schema {summary.get('schema')!r}, expected {SCHEMA_WIFI_SCAN!r}")
    aps = msg.status[1:]
    if not aps:
        raise InvalidMessageError("empty_scan", "scan has no access points")
    if len(aps) > BOUNDS["scan_aps"].hi:
        raise InvalidMessageError("too_many_aps", f"{len(aps)} access points in one scan, more than "
                                                  f"{BOUNDS['scan_aps'].hi:g} (contract bound scan_aps)")
    if "ap_count" in summary:
        try:
            declared = int(summary["ap_count"])
        except ValueError as err:
            raise InvalidMessageError("bad_value", f"ap_count={summary['ap_count']!r}") from err
        if declared != len(aps):
            raise InvalidMessageError("ap_count", f"ap_count={declared} but {len(aps)} AP entries")
    bssid, ssid = [], []
    rssi = np.empty(len(aps))
    freq = np.empty(len(aps))
    age = np.full(len(aps), np.nan)
    any_age = False
    for i, st in enumerate(aps):
        b = normalize_bssid(st.name)
        kv = {k.key: k.value for k in st.values}
        rssi[i] = _number(b, "rssi_dbm", kv.get("rssi_dbm"))
        freq[i] = _number(b, "frequency_mhz", kv.get("frequency_mhz"))
        if "age_ms" in kv:
            age[i] = _number(b, "age_ms", kv["age_ms"])
            any_age = True
        bssid.append(b)
        ssid.append(st.message)
    bssid_t = tuple(bssid)
    age_arr = age if any_age else None
    _check_arrays(bssid_t, rssi, freq, None if age_arr is None else age_arr[np.isfinite(age_arr)])
    return WifiScan(stamp_ns=stamp, bssid=bssid_t, rssi_dbm=rssi, freq_mhz=freq, ssid=tuple(ssid),
                    age_ms=age_arr, frame_id=msg.header.frame_id, source=summary.get("source", ""))


def scan_to_msg(scan: WifiScan) -> DiagnosticArray:
    """Build the ``wifi_scan.v1`` DiagnosticArray of a scan (validated the same way as on input;
    an ``age_ms`` of NaN means unknown for that AP and is left out)."""
    n = len(scan.bssid)
    bssid = tuple(normalize_bssid(b) for b in scan.bssid)
    rssi = np.asarray(scan.rssi_dbm, dtype=np.float64)
    freq = np.asarray(scan.freq_mhz, dtype=np.float64)
    age = None if scan.age_ms is None else np.asarray(scan.age_ms, dtype=np.float64)
    ssid = tuple(scan.ssid) if scan.ssid else ("",) * n
    for name, arr in (("rssi_dbm", rssi), ("freq_mhz", freq), ("age_ms", age), ("ssid", ssid)):
        if arr is not None and len(arr) != n:
            raise InvalidMessageError("shape", f"{name} has {len(arr)} entries for {n} BSSIDs")
    if not (np.all(np.isfinite(rssi)) and np.all(np.isfinite(freq))):
        raise InvalidMessageError("nan", "rssi_dbm / freq_mhz must be finite")
    if age is not None and np.any(np.isinf(age)):
        raise InvalidMessageError("nan", "age_ms must be finite (NaN = unknown)")
    _check_arrays(bssid, rssi, freq, None if age is None else age[np.isfinite(age)])
    for i, name in enumerate(ssid):
        try:
            str(name).encode("utf-8")
        except UnicodeEncodeError as err:     # lone surrogates cannot go into a ROS string
            raise InvalidMessageError("bad_ssid", f"AP {bssid[i]}: SSID {name!r} is not valid UTF-8 text") from err

    arr = DiagnosticArray()
    arr.header.stamp = stamp_from_ns(scan.stamp_ns)
    arr.header.frame_id = scan.frame_id
    summary = DiagnosticStatus(level=DiagnosticStatus.OK, name=SUMMARY_NAME, message="",
                               hardware_id=scan.frame_id)
    summary.values = [KeyValue(key="schema", value=SCHEMA_WIFI_SCAN), KeyValue(key="ap_count", value=str(n)),
                      KeyValue(key="source", value=scan.source)]
    statuses = [summary]
    for i in range(n):
        values = [KeyValue(key="rssi_dbm", value=repr(float(rssi[i]))),
                  KeyValue(key="frequency_mhz", value=repr(float(freq[i])))]
        if age is not None and np.isfinite(age[i]):
            values.append(KeyValue(key="age_ms", value=repr(float(age[i]))))
        statuses.append(DiagnosticStatus(level=DiagnosticStatus.OK, name=bssid[i],
                                         message=str(ssid[i]).replace("\0", ""),
                                         hardware_id=scan.frame_id, values=values))
    arr.status = statuses
    return arr
