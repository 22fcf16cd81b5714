"""Scan text -> :class:`WifiScan`: ``iw dev IF scan``, ``nmcli -t ... dev wifi list`` and scan JSON.

Pure functions (no subprocess, no ROS). Each parser returns a :class:`ParseResult` holding the raw
readings in input order — BSSIDs as printed, duplicates kept, nothing filtered; :func:`normalize`
in :mod:`indoor_loc.wifi.normalize` turns that into a contract-clean scan. Parsers keep every
complete entry and *report* what they could not use:

- ``truncated``: the text ended inside an entry (a capture cut mid-block, a command killed by its
  timeout); the incomplete entry is dropped, the complete ones are kept.
- ``skipped``: entries that lacked a required field or held unreadable values (with ``warnings``).

Input that is not the expected format at all raises :class:`~indoor_loc.errors.ParseError` with a
message naming the format and what was wrong; nothing else is raised.

Formats accepted
----------------
``iw`` — ``iw dev wlan0 scan`` / ``iw dev wlan0 scan dump`` (iw 4.x–6.x). Blocks start with
``BSS aa:bb:cc:dd:ee:ff(on wlan0)`` (optionally `` -- associated``); per block ``freq: 2412`` or
``freq: 5180.0`` (MHz, 2.4/5/6 GHz), ``signal: -54.00 dBm`` (or ``signal: 70/100`` from drivers
without dBm, mapped like nmcli's quality), ``last seen: 120 ms ago`` (-> ``age_ms``) and ``SSID:``
with iw's ``\\xNN`` byte escapes (UTF-8 SSIDs are printed byte-wise; hidden SSIDs are empty or all
``\\x00``). Required per block: BSSID, freq, signal.

``nmcli`` — ``nmcli -t -f BSSID,SSID,FREQ,SIGNAL,CHAN dev wifi list`` (terse: ``:`` separated with
``\\:`` and ``\\\\`` escapes; pass ``fields=`` when another ``-f`` list was used), and
``nmcli [-t] -m multiline -f ... dev wifi list`` (``KEY:value`` lines, one record per repeated key;
auto-detected). ``FREQ`` is read as the leading number whatever the unit's translation
(``2437 MHz``, ``2437 МГц``, ``5180,0 MHz``); ``CHAN`` is used when ``FREQ`` is absent. ``SIGNAL`` is
NetworkManager's 0–100 quality, converted to dBm by :func:`quality_to_dbm`. Hidden SSIDs are
empty or ``--``. Required per record: BSSID and SIGNAL.

``json`` — the CMU cabot ``wireless_scanner_ros`` string (``std_msgs/String`` on
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
from dataclasses import dataclass
from typing import Any, Iterable

import numpy as np

from indoor_loc.errors import ParseError
from indoor_loc.wifi.types import WifiScan

FORMATS = ("iw", "nmcli", "json")

NMCLI_FIELDS: tuple[str, ...] = ("BSSID", "SSID", "FREQ", "SIGNAL", "CHAN")
"""The ``-f`` list the package runs nmcli with (and the default field order of :func:`parse_nmcli`)."""

_NMCLI_KNOWN_KEYS = frozenset({
    "NAME", "SSID", "SSID-HEX", "BSSID", "MODE", "CHAN", "FREQ", "RATE", "BANDWIDTH", "SIGNAL", "BARS",
    "SECURITY", "WPA-FLAGS", "RSN-FLAGS", "DEVICE", "ACTIVE", "IN-USE", "DBUS-PATH"})


@dataclass(frozen=True)
class ParseResult:
    """What a parser read. ``scan`` holds raw readings (see module doc); ``truncated`` is True when
    the text ended inside an entry; ``skipped`` counts incomplete/unreadable entries."""
    scan: WifiScan
    truncated: bool = False
    skipped: int = 0
    warnings: tuple[str, ...] = ()


# ----------------------------------------------------------------------------------------------
# Units
# ----------------------------------------------------------------------------------------------
SIGNAL_MAPPINGS = ("nm", "half")


def quality_to_dbm(quality: float, mapping: str = "nm") -> float:
    """A 0–100 signal quality (nmcli ``SIGNAL``, iw ``signal: N/100``) -> RSSI in dBm.

    ``"nm"`` inverts NetworkManager's own ``nm_wifi_utils_level_to_quality()``, which clamps the
    driver's dBm to [-100, -40] and scales it linearly: ``q = 100 - (-dBm - 40) * 100 / 60``, so
    ``dBm = -100 + 0.6 q`` (0 % -> -100 dBm, 100 % -> -40 dBm; the clamp makes 100 % mean "-40 dBm
    or stronger"). ``"half"`` is the other common convention ``dBm = q / 2 - 100`` (Windows
    ``WLAN_SIGNAL_QUALITY``: 0 % -> -100 dBm, 100 % -> -50 dBm). Quality is clamped to [0, 100].
    """
    q = min(max(float(quality), 0.0), 100.0)
    if mapping == "nm":
        return round(-100.0 + 0.6 * q, 3)
    if mapping == "half":
        return round(q / 2.0 - 100.0, 3)
    raise ParseError(f"unknown signal mapping {mapping!r}; expected one of {SIGNAL_MAPPINGS}")


def channel_to_freq_mhz(channel: int, band: str = "") -> float:
    """IEEE 802.11 channel number -> centre frequency in MHz (0.0 when unknown).

    ``band`` "2.4", "5" or "6" (GHz) disambiguates; without it 1–14 are 2.4 GHz and 32–177 are
    5 GHz (6 GHz channels reuse 1–233, so a 6 GHz channel needs ``band="6"``).
    """
    ch = int(channel)
    b = band.strip().lower().removesuffix("ghz").strip() if band else ""
    if b in ("6", "6e"):
        if ch == 2:
            return 5935.0
        return 5950.0 + 5.0 * ch if 1 <= ch <= 233 else 0.0
    if b in ("2.4", "2,4", "2") or (not b and 1 <= ch <= 14):
        if ch == 14:
            return 2484.0
        return 2407.0 + 5.0 * ch if 1 <= ch <= 13 else 0.0
    if b == "5" or (not b and 32 <= ch <= 177):
        return 5000.0 + 5.0 * ch if 1 <= ch <= 200 else 0.0
    return 0.0


_NUMBER = re.compile(r"^\s*([+-]?[0-9]+(?:[.,][0-9]+)?)")


def _leading_number(text: str) -> float | None:
    """The number a value starts with, accepting a decimal comma ("5180,0 MHz" -> 5180.0)."""
    m = _NUMBER.match(text)
    return float(m.group(1).replace(",", ".")) if m else None


def _build_scan(rows: list[tuple[str, str, float, float, float]], *, stamp_ns: int, frame_id: str,
                source: str) -> WifiScan:
    """rows of (bssid, ssid, rssi_dbm, freq_mhz, age_ms or NaN) -> WifiScan (age None if all NaN)."""
    age = np.array([r[4] for r in rows], dtype=float)
    return WifiScan(
        stamp_ns=int(stamp_ns),
        bssid=tuple(r[0] for r in rows),
        rssi_dbm=np.array([r[2] for r in rows], dtype=float),
        freq_mhz=np.array([r[3] for r in rows], dtype=float),
        ssid=tuple(r[1] for r in rows),
        age_ms=age if rows and not np.all(np.isnan(age)) else None,
        frame_id=frame_id,
        source=source,
    )


def _split_cut_line(text: str) -> tuple[list[str], bool]:
    """Lines of ``text``; when it does not end with a newline the last line may be cut (a command
    killed mid-write) and is dropped. Returns (lines, cut)."""
    lines = text.splitlines()
    cut = bool(text) and not text.endswith(("\n", "\r")) and bool(lines)
    if cut:
        lines = lines[:-1]
    return lines, cut


# ----------------------------------------------------------------------------------------------
# iw
# ----------------------------------------------------------------------------------------------
_IW_BSS = re.compile(r"^BSS\s+([0-9A-Fa-f]{2}(?::[0-9A-Fa-f]{2}){5})\s*(?:\(on\s+[^)]*\))?")
_IW_FREQ = re.compile(r"^freq:\s*([0-9]+(?:\.[0-9]+)?)\s*$")
_IW_SIGNAL_DBM = re.compile(r"^signal:\s*(-?[0-9]+(?:\.[0-9]+)?)\s*dBm\s*$")
_IW_SIGNAL_PCT = re.compile(r"^signal:\s*([0-9]+)/100\s*$")
_IW_LAST_SEEN = re.compile(r"^last seen:\s*([0-9]+)\s*ms ago\s*$")
_IW_ESCAPE = re.compile(r"\\x([0-9A-Fa-f]{2})")


def iw_unescape_ssid(text: str) -> str:
    """Undo iw's SSID escaping: every byte that is not printable ASCII (and ``\\``, leading and
    trailing spaces) is printed as ``\\xNN``. Bytes are decoded as UTF-8 (invalid sequences become
    U+FFFD); NUL bytes are removed, so a hidden SSID (``\\x00\\x00...``) becomes ""."""
    raw = bytearray()
    pos = 0
    for m in _IW_ESCAPE.finditer(text):
        raw += text[pos:m.start()].encode("utf-8")
        raw.append(int(m.group(1), 16))
        pos = m.end()
    raw += text[pos:].encode("utf-8")
    return raw.decode("utf-8", errors="replace").replace("\x00", "")


def parse_iw(text: str, *, stamp_ns: int = 0, frame_id: str = "", source: str = "iw",
             signal_mapping: str = "nm") -> ParseResult:
    """Parse ``iw dev IF scan`` (or ``scan dump``) output; see the module doc for what is read.

    ``stamp_ns`` is the scan time (when the command returned); ``age_ms`` comes from ``last seen:
    N ms ago`` (NaN when absent). A block without freq or signal is skipped; when it is the last
    block (or the text does not end with a newline, or the last block has no ``SSID:`` line yet)
    the output was cut and ``truncated`` is set.
    """
    if not isinstance(text, str):
        raise ParseError(f"iw: expected text, got {type(text).__name__}")
    lines, cut = _split_cut_line(text)
    blocks: list[dict[str, Any]] = []
    preamble = 0
    for line in lines:
        s = line.strip()
        if not s:
            continue
        m = _IW_BSS.match(s)
        if m:
            blocks.append({"bssid": m.group(1), "line": s})
            continue
        if not blocks:
            preamble += 1
            continue
        cur = blocks[-1]
        if "freq" not in cur and (m := _IW_FREQ.match(s)):
            cur["freq"] = float(m.group(1))
        elif "signal" not in cur and (m := _IW_SIGNAL_DBM.match(s)):
            cur["signal"] = float(m.group(1))
        elif "signal" not in cur and (m := _IW_SIGNAL_PCT.match(s)):
            cur["signal"] = quality_to_dbm(float(m.group(1)), signal_mapping)
        elif "age" not in cur and (m := _IW_LAST_SEEN.match(s)):
            cur["age"] = float(m.group(1))
        elif "ssid" not in cur and s.startswith("SSID:"):
            cur["ssid"] = iw_unescape_ssid(s[5:].strip())
    if not blocks:
        if preamble:
            raise ParseError("iw: no 'BSS aa:bb:cc:dd:ee:ff(on IF)' line found; expected the output of "
                             "`iw dev IF scan` (an error message, or another tool's output?)")
        return ParseResult(_build_scan([], stamp_ns=stamp_ns, frame_id=frame_id, source=source), cut)
    warnings: list[str] = []
    if preamble:
        warnings.append(f"iw: ignored {preamble} line(s) before the first BSS block")
    rows: list[tuple[str, str, float, float, float]] = []
    skipped = 0
    truncated = False
    for i, b in enumerate(blocks):
        last = i == len(blocks) - 1
        complete = "freq" in b and "signal" in b
        if last:
            # iw prints freq, signal and SSID in a block's first lines: a final block without its
            # SSID line was cut (by a timeout, `head`, a full pipe) before it was complete.
            complete = complete and "ssid" in b
        if not complete:
            if last:
                truncated = True
                warnings.append(f"iw: output ends inside the block of {b['bssid']}; dropped it")
            else:
                skipped += 1
                missing = [k for k in ("freq", "signal") if k not in b]
                warnings.append(f"iw: block {b['bssid']} has no {'/'.join(missing) or 'SSID'} line; skipped")
            continue
        rows.append((b["bssid"], b.get("ssid", ""), b["signal"], b["freq"], b.get("age", math.nan)))
    if cut and not truncated:
        truncated = True
        warnings.append("iw: output ends mid-line; dropped the cut line")
    return ParseResult(_build_scan(rows, stamp_ns=stamp_ns, frame_id=frame_id, source=source),
                       truncated, skipped, tuple(warnings))


# ----------------------------------------------------------------------------------------------
# nmcli
# ----------------------------------------------------------------------------------------------
def nmcli_split(line: str) -> list[str]:
    """Split one ``nmcli -t`` line on unescaped ``:``, undoing ``\\:`` and ``\\\\``."""
    out: list[str] = []
    cur: list[str] = []
    i = 0
    while i < len(line):
        c = line[i]
        if c == "\\" and i + 1 < len(line):
            cur.append(line[i + 1])
            i += 2
            continue
        if c == ":":
            out.append("".join(cur))
            cur = []
        else:
            cur.append(c)
        i += 1
    out.append("".join(cur))
    return out


def _nmcli_unescape(value: str) -> str:
    return re.sub(r"\\(.)", r"\1", value)


def _nmcli_multiline_key(line: str) -> str | None:
    key = line.split(":", 1)[0].strip()
    return key if ":" in line and key in _NMCLI_KNOWN_KEYS else None


def _is_nmcli_multiline(lines: list[str]) -> bool:
    keys = [_nmcli_multiline_key(s) for s in lines[:2]]
    return len(keys) == 2 and None not in keys and keys[0] != keys[1]


def parse_nmcli(text: str, *, fields: Iterable[str] = NMCLI_FIELDS, stamp_ns: int = 0,
                frame_id: str = "", source: str = "nmcli", signal_mapping: str = "nm") -> ParseResult:
    """Parse ``nmcli -t -f FIELDS dev wifi list`` (terse) or ``-m multiline`` output.

    ``fields``: the ``-f`` list used for terse tabular output (ignored for multiline, which names
    every value). ``SIGNAL`` (0–100) becomes dBm with :func:`quality_to_dbm` (``signal_mapping``).
    nmcli gives no per-AP age (``age_ms`` is None).
    """
    if not isinstance(text, str):
        raise ParseError(f"nmcli: expected text, got {type(text).__name__}")
    if signal_mapping not in SIGNAL_MAPPINGS:
        raise ParseError(f"unknown signal mapping {signal_mapping!r}; expected one of {SIGNAL_MAPPINGS}")
    fields = tuple(f.strip().upper() for f in fields)
    for need in ("BSSID", "SIGNAL"):
        if need not in fields:
            raise ParseError(f"nmcli: field list {','.join(fields)} lacks {need}; run nmcli with "
                             f"-f {','.join(NMCLI_FIELDS)}")
    lines, cut = _split_cut_line(text)
    lines = [s for s in lines if s.strip()]
    if _is_nmcli_multiline(lines):
        records, last_partial = _nmcli_multiline_records(lines, cut)
    else:
        records, last_partial = _nmcli_terse_records(lines, fields, cut)
    rows: list[tuple[str, str, float, float, float]] = []
    warnings: list[str] = []
    skipped = 0
    chan_guess = False
    for idx, rec in records:
        try:
            bssid = rec["BSSID"].strip()
            quality = _leading_number(rec["SIGNAL"])
            if not bssid or quality is None:
                raise KeyError("SIGNAL" if bssid else "BSSID")
        except KeyError as err:
            skipped += 1
            warnings.append(f"nmcli: record {idx + 1} has no usable {err.args[0]}; skipped")
            continue
        freq = _leading_number(rec.get("FREQ", "")) if rec.get("FREQ") else None
        if freq is None:
            chan = _leading_number(rec.get("CHAN", "")) if rec.get("CHAN") else None
            freq = channel_to_freq_mhz(int(chan)) if chan is not None else 0.0
            chan_guess = chan_guess or chan is not None
        ssid = rec.get("SSID", "")
        ssid = "" if ssid.strip() == "--" else ssid
        rows.append((bssid, ssid, quality_to_dbm(quality, signal_mapping), float(freq), math.nan))
    if chan_guess:
        warnings.append("nmcli: no FREQ field; frequency derived from CHAN assuming 2.4/5 GHz")
    if lines and not records and skipped == 0:
        raise ParseError(f"nmcli: no record could be read from {len(lines)} line(s); expected "
                         f"`nmcli -t -f {','.join(fields)} dev wifi list` output; first line: {lines[0][:80]!r}")
    if records and not rows:
        raise ParseError(f"nmcli: none of {len(records)} record(s) has a BSSID and a SIGNAL: {warnings[0]}")
    if last_partial or cut:
        warnings.append("nmcli: output ends inside a record; dropped it")
    return ParseResult(_build_scan(rows, stamp_ns=stamp_ns, frame_id=frame_id, source=source),
                       bool(last_partial or cut), skipped, tuple(warnings))


def _nmcli_terse_records(lines: list[str], fields: tuple[str, ...], cut: bool
                         ) -> tuple[list[tuple[int, dict[str, str]]], bool]:
    records: list[tuple[int, dict[str, str]]] = []
    bad_counts: list[int] = []
    partial = False
    for i, line in enumerate(lines):
        values = nmcli_split(line)
        if len(values) != len(fields):
            if i == len(lines) - 1 and len(values) < len(fields) and records:
                partial = True          # a line cut at a line boundary by `head`, or the last write
                continue
            bad_counts.append(len(values))
            continue
        records.append((i, dict(zip(fields, values))))
    if bad_counts and not records:
        raise ParseError(f"nmcli: lines have {sorted(set(bad_counts))} ':'-separated fields, expected "
                         f"{len(fields)} ({','.join(fields)}); pass the -f list nmcli ran with (and use -t)")
    return records, partial


def _nmcli_multiline_records(lines: list[str], cut: bool) -> tuple[list[tuple[int, dict[str, str]]], bool]:
    terse = any("\\:" in s for s in lines)
    records: list[dict[str, str]] = []
    for line in lines:
        key = _nmcli_multiline_key(line)
        if key is None:
            continue
        value = line.split(":", 1)[1]
        value = _nmcli_unescape(value) if terse else value.strip()
        if not records or key in records[-1]:
            records.append({})
        records[-1][key] = value
    partial = False
    if records and len(records) > 1 and set(records[-1]) < set(records[0]):
        partial = True               # the last record lacks keys every other record has
        records.pop()
    return list(enumerate(records)), partial


# ----------------------------------------------------------------------------------------------
# JSON (CMU cabot and common variants)
# ----------------------------------------------------------------------------------------------
_JSON_LISTS = ("data", "aps", "results", "networks", "scan", "wifi", "access_points")
_JSON_BSSID = ("bssid", "BSSID", "mac", "MAC", "address", "hwaddr")
_JSON_SSID = ("ssid", "SSID", "essid", "name")
_JSON_RSSI = ("rssi", "RSSI", "rssi_dbm", "level", "signal", "signal_dbm", "dbm")
_JSON_FREQ_MHZ = ("frequency_mhz", "freq_mhz", "frequency", "freq")
_JSON_FREQ_GHZ = ("frequency_GHz", "frequency_ghz", "freq_ghz")
_JSON_AGE = ("age_ms", "last_seen_ms")
_MAC_AT_END = re.compile(r"([0-9A-Fa-f]{2}(?:[:-][0-9A-Fa-f]{2}){5})$")


def _first(d: dict, keys: tuple[str, ...]) -> Any:
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
        v = _leading_number(value)
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
    return ParseResult(_build_scan(rows, stamp_ns=stamp_ns, frame_id=frame_id, source=source),
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


def parse(text: str, fmt: str, **kw: Any) -> ParseResult:
    """Dispatch on ``fmt`` ("iw", "nmcli" or "json")."""
    if fmt == "iw":
        return parse_iw(text, **kw)
    if fmt == "nmcli":
        return parse_nmcli(text, **kw)
    if fmt == "json":
        return parse_json(text, **kw)
    raise ParseError(f"unknown scan format {fmt!r}; expected one of {FORMATS}")
