"""WiFi scan (schema ``wifi_scan.v1``) <-> diagnostic_msgs/DiagnosticArray.

Layout: ``header.stamp`` = scan time, ``header.frame_id`` = receiver frame; ``status[0]`` is the
scan summary (name ``"scan"``, values ``schema``, ``ap_count``, ``source``); then one
DiagnosticStatus per access point: name = BSSID (lower-case, colon-separated), message = SSID,
values ``rssi_dbm``, ``frequency_mhz`` and optionally ``age_ms``. Floats are written with
``repr`` so a scan built from core values round-trips bit-exactly. SSIDs lose any NUL character
(hidden networks are sometimes reported as ``"\\x00\\x00..."``): a CDR string ends at the first NUL.

The mechanism is shared by every RF scan schema of this layout (:class:`RfSchema`, :func:`rf_from_msg`,
:func:`rf_to_msg`): ``ble/scan`` (:mod:`msg_adapters.ble_scan`) is the same layout with beacon ids.
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass
from typing import Callable

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


def _number(entry: str, key: str, text: str | None) -> float:
    if text is None or text.strip() == "":
        raise InvalidMessageError("missing_field", f"entry {entry}: no value for {key!r}")
    try:
        v = float(text)
    except ValueError as err:
        raise InvalidMessageError("bad_value", f"entry {entry}: {key}={text!r} is not a number") from err
    if not math.isfinite(v):
        raise InvalidMessageError("nan", f"entry {entry}: {key}={text!r}")
    return v


@dataclass(frozen=True)
class RfSchema:
    """One RF scan schema in the ``wifi_scan.v1`` layout: its name, how an entry's id is normalised
    (raising ``InvalidMessageError``), what an entry is called in messages, the reason of a repeated id,
    and the optional per-entry float values it carries beside ``rssi_dbm``, ``frequency_mhz`` and
    ``age_ms`` (NaN where an entry has none)."""
    schema: str
    normalize: Callable[[str], str]
    entry: str = "AP"
    duplicate_reason: str = "duplicate_bssid"
    extra: tuple[str, ...] = ()


WIFI_SCHEMA = RfSchema(SCHEMA_WIFI_SCAN, normalize_bssid)


@dataclass(frozen=True)
class RfEntries:
    """A validated scan of any :class:`RfSchema`: ``ids`` unique, ``names`` (SSID / MAC) and the arrays
    one per entry; ``age_ms`` None when no entry has one; ``extra[key]`` NaN where an entry has none."""
    stamp_ns: int
    ids: tuple[str, ...]
    names: tuple[str, ...]
    rssi_dbm: np.ndarray
    freq_mhz: np.ndarray
    age_ms: np.ndarray | None
    extra: dict[str, np.ndarray]
    frame_id: str = ""
    source: str = ""


def _check_arrays(ids: tuple[str, ...], rssi: np.ndarray, freq: np.ndarray, age: np.ndarray | None,
                  rf: RfSchema = WIFI_SCHEMA) -> None:
    """The checks shared by both directions (values are already finite floats)."""
    if len(ids) == 0:
        raise InvalidMessageError("empty_scan", f"scan has no {rf.entry} entries")
    seen: set[str] = set()
    for b in ids:
        if b in seen:
            raise InvalidMessageError(rf.duplicate_reason, f"{rf.entry} {b} appears more than once")
        seen.add(b)
    bad = np.flatnonzero((rssi < RSSI_MIN_DBM) | (rssi > RSSI_MAX_DBM))
    if bad.size:
        i = int(bad[0])
        raise InvalidMessageError("rssi_range", f"{rf.entry} {ids[i]}: rssi {rssi[i]} dBm outside "
                                                f"[{RSSI_MIN_DBM:g}, {RSSI_MAX_DBM:g}]")
    f_b = BOUNDS["frequency"]
    bad = np.flatnonzero((freq != 0.0) & ((freq < f_b.lo) | (freq > f_b.hi)))
    if bad.size:
        i = int(bad[0])
        raise InvalidMessageError(f_b.reason, f"{rf.entry} {ids[i]}: frequency_mhz = {freq[i]:.6g} outside "
                                              f"[{f_b.lo:g}, {f_b.hi:g}] MHz and not 0 (unknown) ({f_b.name}: {f_b.why})")
    if age is not None:
        a_b = BOUNDS["age"]
        bad = np.flatnonzero((age < a_b.lo) | (age > a_b.hi))
        if bad.size:
            i = int(bad[0])
            raise InvalidMessageError(a_b.reason, f"{rf.entry} {ids[i]}: age_ms = {age[i]:.6g} outside [{a_b.lo:g}, "
                                                  f"{a_b.hi:g}] ms ({a_b.name}: {a_b.why})")


def _check_extra(rf: RfSchema, ids: tuple[str, ...], extra: dict[str, np.ndarray]) -> None:
    for key, vals in extra.items():
        b = BOUNDS.get(key)
        if b is None:
            continue
        bad = np.flatnonzero(np.isfinite(vals) & ((vals < b.lo) | (vals > b.hi)))
        if bad.size:
            i = int(bad[0])
            raise InvalidMessageError(b.reason, f"{rf.entry} {ids[i]}: {key} = {vals[i]:.6g} outside [{b.lo:g}, "
                                                f"{b.hi:g}] {b.unit} ({b.name}: {b.why})")


def rf_from_msg(msg: DiagnosticArray, rf: RfSchema = WIFI_SCHEMA) -> RfEntries:
    """Validate and unpack a DiagnosticArray of schema ``rf`` (reasons: see :func:`scan_from_msg`)."""
    stamp = stamp_to_ns(msg.header.stamp)
    if not msg.status or msg.status[0].name != SUMMARY_NAME:
        raise InvalidMessageError("schema_version", f"status[0] must be the {SUMMARY_NAME!r} summary "
                                                    f"of schema {rf.schema}")
    summary = {kv.key: kv.value for kv in msg.status[0].values}
    if summary.get("schema") != rf.schema:
        raise InvalidMessageError("schema_version", f"schema {summary.get('schema')!r}, expected {rf.schema!r}")
    aps = msg.status[1:]
    if not aps:
        raise InvalidMessageError("empty_scan", f"scan has no {rf.entry} entries")
    if len(aps) > BOUNDS["scan_aps"].hi:
        raise InvalidMessageError("too_many_aps", f"{len(aps)} entries in one scan, more than "
                                                  f"{BOUNDS['scan_aps'].hi:g} (contract bound scan_aps)")
    if "ap_count" in summary:
        try:
            declared = int(summary["ap_count"])
        except ValueError as err:
            raise InvalidMessageError("bad_value", f"ap_count={summary['ap_count']!r}") from err
        if declared != len(aps):
            raise InvalidMessageError("ap_count", f"ap_count={declared} but {len(aps)} entries")
    ids, names = [], []
    rssi = np.empty(len(aps))
    freq = np.empty(len(aps))
    age = np.full(len(aps), np.nan)
    extra = {k: np.full(len(aps), np.nan) for k in rf.extra}
    any_age = False
    for i, st in enumerate(aps):
        b = rf.normalize(st.name)
        kv = {k.key: k.value for k in st.values}
        rssi[i] = _number(b, "rssi_dbm", kv.get("rssi_dbm"))
        freq[i] = _number(b, "frequency_mhz", kv.get("frequency_mhz"))
        if "age_ms" in kv:
            age[i] = _number(b, "age_ms", kv["age_ms"])
            any_age = True
        for k in rf.extra:
            if k in kv:
                extra[k][i] = _number(b, k, kv[k])
        ids.append(b)
        names.append(st.message)
    ids_t = tuple(ids)
    age_arr = age if any_age else None
    _check_arrays(ids_t, rssi, freq, None if age_arr is None else age_arr[np.isfinite(age_arr)], rf)
    _check_extra(rf, ids_t, extra)
    return RfEntries(stamp_ns=stamp, ids=ids_t, names=tuple(names), rssi_dbm=rssi, freq_mhz=freq, age_ms=age_arr,
                     extra=extra, frame_id=msg.header.frame_id, source=summary.get("source", ""))


def rf_to_msg(e: RfEntries, rf: RfSchema = WIFI_SCHEMA) -> DiagnosticArray:
    """Build the DiagnosticArray of schema ``rf`` (validated the same way as on input; an ``age_ms`` or
    extra value of NaN means unknown for that entry and is left out)."""
    n = len(e.ids)
    ids = tuple(rf.normalize(b) for b in e.ids)
    rssi = np.asarray(e.rssi_dbm, dtype=np.float64)
    freq = np.asarray(e.freq_mhz, dtype=np.float64)
    age = None if e.age_ms is None else np.asarray(e.age_ms, dtype=np.float64)
    names = tuple(e.names) if e.names else ("",) * n
    extra = {k: np.asarray(v, dtype=np.float64) for k, v in e.extra.items() if v is not None}
    for name, arr in (("rssi_dbm", rssi), ("freq_mhz", freq), ("age_ms", age), ("ssid", names), *extra.items()):
        if arr is not None and len(arr) != n:
            raise InvalidMessageError("shape", f"{name} has {len(arr)} entries for {n} ids")
    if not (np.all(np.isfinite(rssi)) and np.all(np.isfinite(freq))):
        raise InvalidMessageError("nan", "rssi_dbm / freq_mhz must be finite")
    if age is not None and np.any(np.isinf(age)):
        raise InvalidMessageError("nan", "age_ms must be finite (NaN = unknown)")
    if any(np.any(np.isinf(v)) for v in extra.values()):
        raise InvalidMessageError("nan", f"{', '.join(extra)} must be finite (NaN = unknown)")
    _check_arrays(ids, rssi, freq, None if age is None else age[np.isfinite(age)], rf)
    _check_extra(rf, ids, extra)
    for i, name in enumerate(names):
        try:
            str(name).encode("utf-8")
        except UnicodeEncodeError as err:     # lone surrogates cannot go into a ROS string
            raise InvalidMessageError("bad_ssid", f"{rf.entry} {ids[i]}: name {name!r} is not valid UTF-8 text") from err

    arr = DiagnosticArray()
    arr.header.stamp = stamp_from_ns(e.stamp_ns)
    arr.header.frame_id = e.frame_id
    summary = DiagnosticStatus(level=DiagnosticStatus.OK, name=SUMMARY_NAME, message="",
                               hardware_id=e.frame_id)
    summary.values = [KeyValue(key="schema", value=rf.schema), KeyValue(key="ap_count", value=str(n)),
                      KeyValue(key="source", value=e.source)]
    statuses = [summary]
    for i in range(n):
        values = [KeyValue(key="rssi_dbm", value=repr(float(rssi[i]))),
                  KeyValue(key="frequency_mhz", value=repr(float(freq[i])))]
        if age is not None and np.isfinite(age[i]):
            values.append(KeyValue(key="age_ms", value=repr(float(age[i]))))
        for k, v in extra.items():
            if np.isfinite(v[i]):
                values.append(KeyValue(key=k, value=repr(float(v[i]))))
        statuses.append(DiagnosticStatus(level=DiagnosticStatus.OK, name=ids[i],
                                         message=str(names[i]).replace("\0", ""),
                                         hardware_id=e.frame_id, values=values))
    arr.status = statuses
    return arr


def scan_from_msg(msg: DiagnosticArray) -> WifiScan:
    """Validate and unpack a ``wifi_scan.v1`` DiagnosticArray into a :class:`WifiScan`.

    Reasons: ``schema_version``, ``empty_scan``, ``bad_bssid``, ``duplicate_bssid``, ``nan``,
    ``rssi_range``, ``out_of_range`` (a frequency or age beyond :data:`indoor_loc.contract.BOUNDS`;
    frequency 0 = unknown passes), ``too_many_aps``, ``missing_field``, ``bad_value``, ``ap_count``,
    ``negative_stamp``.
    ``age_ms`` is None when no AP carries one, NaN for the APs without one otherwise.
    """
    e = rf_from_msg(msg, WIFI_SCHEMA)
    return WifiScan(stamp_ns=e.stamp_ns, bssid=e.ids, rssi_dbm=e.rssi_dbm, freq_mhz=e.freq_mhz, ssid=e.names,
                    age_ms=e.age_ms, frame_id=e.frame_id, source=e.source)


def scan_to_msg(scan: WifiScan) -> DiagnosticArray:
    """Build the ``wifi_scan.v1`` DiagnosticArray of a scan (validated the same way as on input;
    an ``age_ms`` of NaN means unknown for that AP and is left out)."""
    return rf_to_msg(RfEntries(stamp_ns=scan.stamp_ns, ids=tuple(scan.bssid), names=tuple(scan.ssid),
                               rssi_dbm=scan.rssi_dbm, freq_mhz=scan.freq_mhz, age_ms=scan.age_ms, extra={},
                               frame_id=scan.frame_id, source=scan.source), WIFI_SCHEMA)
