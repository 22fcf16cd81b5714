"""``json`` — the CMU cabot ``wireless_scanner_ros`` string (``std_msgs/String`` on
``/wireless/wifi``): ``{"type": "rssi", "phoneID": ..., "timestamp": <s>, "data": [{"type": "WiFi",
"id": "<ssid>-<mac>", "ssid", "mac", "rssi", "frequency_GHz" | "channel", "last_seen_ms"}]}``, and the
common variants: a bare list of entries, the list under ``data``/``aps``/``results``/``networks``/
``scan``/``wifi``/``access_points``; per entry the BSSID under ``bssid``/``BSSID``/``mac``/
``address`` (or the MAC at the end of cabot's ``id``), the SSID under ``ssid``/``SSID``/``essid``,
the RSSI in dBm under ``rssi``/``rssi_dbm``/``level`` (Android ``ScanResult``)/``signal``/
``signal_dbm``/``dbm``, or a 0–100 ``quality``; the frequency under ``frequency_mhz``/``freq_mhz``/
``frequency``/``freq`` (MHz; values below 100 are taken as GHz), ``frequency_GHz``, or ``channel``
(+ optional ``band``); the age under ``age_ms``/``last_seen_ms``. Entries whose ``type`` is not
WiFi (cabot's BLE beacons) are ignored. Scan time: ``stamp_ns`` (int ns) or ``timestamp`` (s, ms,
µs or ns, told apart by magnitude). Numbers may be given as strings.
"""
from __future__ import annotations

import json
import math
import re
from typing import Any

from indoor_loc.errors import ParseError
from indoor_loc.wifi.parsers.common import (ParseResult, build_scan, leading_number, channel_to_freq_mhz,
                                            quality_to_dbm)
from indoor_loc.wifi.types import WifiScan

_JSON_LISTS = ("data", "aps", "results", "networks", "scan", "wifi", "access_points")
_JSON_BSSID = ("bssid", "BSSID", "mac", "MAC", "address", "hwaddr")
_JSON_SSID = ("ssid", "SSID", "essid", "name")
_JSON_RSSI = ("rssi", "RSSI", "rssi_dbm", "level", "signal", "signal_dbm", "dbm")
_JSON_FREQ_MHZ = ("frequency_mhz", "freq_mhz", "frequency", "freq")
_JSON_FREQ_GHZ = ("frequency_GHz", "frequency_ghz", "freq_ghz")
_JSON_AGE = ("age_ms", "last_seen_ms")
_MAC_AT_END = re.compile(r"([0-9A-Fa-f]{2}(?:[:-][0-9A-Fa-f]{2}){5})$")


def _first(d: dict[str, Any], keys: tuple[str, ...]) -> Any:
    for k in keys:
        if k in d and d[k] is not None and d[k] != "":
            return d[k]
    return None


def _num(value: Any, what: str) -> float:
    if isinstance(value, bool):
        raise ValueError(f"{what} is a bool")
    if isinstance(value, (int, float)):
        return float(value)
    if isinstance(value, str):
        v = leading_number(value)
        if v is not None:
            return v
    raise ValueError(f"{what} {value!r} is not a number")


def stamp_from_seconds_like(value: float) -> int:
    """A timestamp in s, ms, µs or ns (told apart by magnitude around the present era) -> int ns."""
    v = float(value)
    if not math.isfinite(v) or v < 0:
        raise ValueError(f"timestamp {value!r} is not a finite non-negative number")
    if v < 1e11:
        return int(round(v * 1e6)) * 1000        # a float of seconds holds about µs resolution
    if v < 1e14:
        return int(round(v * 1e6))
    if v < 1e17:
        return int(round(v * 1e3))
    return int(v)


def _json_entry(e: Any, signal_mapping: str) -> tuple[str, str, float, float, float] | None:
    """One JSON entry -> row; None for a non-WiFi entry; ValueError when it cannot be read."""
    if not isinstance(e, dict):
        raise ValueError(f"entry is a {type(e).__name__}, not an object")
    kind = e.get("type")
    if isinstance(kind, str) and kind.strip().lower() not in ("wifi", "wlan", "ap", "wi-fi"):
        return None
    bssid = _first(e, _JSON_BSSID)
    if bssid is None and isinstance(e.get("id"), str) and (m := _MAC_AT_END.search(e["id"])):
        bssid = m.group(1)
    if not isinstance(bssid, str):
        raise ValueError("no bssid/mac")
    rssi_v = _first(e, _JSON_RSSI)
    if rssi_v is not None:
        rssi = _num(rssi_v, "rssi")
    elif (q := _first(e, ("quality", "signal_quality", "strength"))) is not None:
        rssi = quality_to_dbm(_num(q, "quality"), signal_mapping)
    else:
        raise ValueError(f"{bssid}: no rssi/level/signal")
    freq = 0.0
    if (f := _first(e, _JSON_FREQ_MHZ)) is not None:
        freq = _num(f, "frequency")
        freq = freq * 1000.0 if 0 < freq < 100 else freq     # "frequency": 2.412 (GHz)
    elif (f := _first(e, _JSON_FREQ_GHZ)) is not None:
        freq = round(_num(f, "frequency_GHz") * 1000.0, 3)
    elif (c := _first(e, ("channel", "chan"))) is not None:
        band = e.get("band")
        freq = channel_to_freq_mhz(int(_num(c, "channel")), str(band) if band is not None else "")
    age_v = _first(e, _JSON_AGE)
    age = _num(age_v, "age_ms") if age_v is not None else math.nan
    ssid = _first(e, _JSON_SSID)
    return (bssid, str(ssid) if ssid is not None else "", rssi, freq, age)


def parse_json(text: str | bytes, *, stamp_ns: int = 0, frame_id: str = "", source: str = "json",
               signal_mapping: str = "nm") -> ParseResult:
    """Parse a scan JSON document (see the module doc for the accepted shapes).

    ``stamp_ns``/``frame_id``/``source`` are used when the document does not carry its own
    (``stamp_ns``/``timestamp``, ``frame_id``, ``source``). Entries that cannot be read are
    skipped (with warnings); a document with entries none of which can be read raises ParseError.
    """
    try:
        doc = json.loads(text)
    except (json.JSONDecodeError, UnicodeDecodeError, TypeError) as err:
        n = len(text) if isinstance(text, (str, bytes)) else 0
        hint = " (truncated?)" if isinstance(err, json.JSONDecodeError) and err.pos >= n - 1 else ""
        raise ParseError(f"json: not valid JSON{hint}: {err}") from err
    meta: dict[str, Any] = {}
    if isinstance(doc, list):
        entries = doc
    elif isinstance(doc, dict):
        meta = doc
        key = next((k for k in _JSON_LISTS if isinstance(doc.get(k), list)), None)
        if key is None:
            raise ParseError(f"json: object has no list of access points under any of {list(_JSON_LISTS)}; "
                             f"keys are {sorted(doc)[:12]}")
        entries = doc[key]
    else:
        raise ParseError(f"json: expected an object or a list, got {type(doc).__name__}")
    warnings: list[str] = []
    try:
        if isinstance(meta.get("stamp_ns"), int) and not isinstance(meta.get("stamp_ns"), bool):
            stamp_ns = int(meta["stamp_ns"])
        elif meta.get("timestamp") is not None:
            stamp_ns = stamp_from_seconds_like(_num(meta["timestamp"], "timestamp"))
    except ValueError as err:
        warnings.append(f"json: {err}; using the receive time")
    frame_id = str(meta.get("frame_id") or frame_id)
    source = str(meta.get("source") or source)
    rows: list[tuple[str, str, float, float, float]] = []
    skipped = 0
    for i, e in enumerate(entries):
        try:
            row = _json_entry(e, signal_mapping)
        except (ValueError, TypeError, OverflowError) as err:
            skipped += 1
            warnings.append(f"json: entry {i}: {err}; skipped")
            continue
        if row is not None:
            rows.append(row)
    if skipped and not rows:
        raise ParseError(f"json: none of {len(entries)} entries could be read; first: {warnings[-skipped]}")
    return ParseResult(build_scan(rows, stamp_ns=stamp_ns, frame_id=frame_id, source=source),
                       False, skipped, tuple(warnings))


def format_json(scan: WifiScan) -> str:
    """WifiScan -> a cabot-compatible JSON string that :func:`parse_json` reads back exactly.

    Besides cabot's keys (``type``, ``phoneID``, ``timestamp`` in s, per entry ``type``, ``id``,
    ``ssid``, ``mac``, ``rssi``, ``frequency_GHz``, ``last_seen_ms``) it writes the lossless
    ``stamp_ns``, ``frame_id``, ``source`` and ``frequency_mhz``.
    """
    data = []
    for i, b in enumerate(scan.bssid):
        ssid = scan.ssid[i] if i < len(scan.ssid) else ""
        e: dict[str, Any] = {"type": "WiFi", "id": f"{ssid}-{b}", "ssid": ssid, "mac": b,
                             "rssi": float(scan.rssi_dbm[i]), "frequency_mhz": float(scan.freq_mhz[i]),
                             "frequency_GHz": float(scan.freq_mhz[i]) / 1000.0}
        if scan.age_ms is not None and math.isfinite(float(scan.age_ms[i])):
            e["last_seen_ms"] = float(scan.age_ms[i])
        data.append(e)
    doc = {"type": "rssi", "phoneID": scan.frame_id or "indoor_loc", "timestamp": scan.stamp_ns * 1e-9,
           "stamp_ns": int(scan.stamp_ns), "frame_id": scan.frame_id, "source": scan.source, "data": data}
    return json.dumps(doc, ensure_ascii=False)
