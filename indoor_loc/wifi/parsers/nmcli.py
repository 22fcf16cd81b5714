"""``nmcli`` — ``nmcli -t -f BSSID,SSID,FREQ,SIGNAL,CHAN dev wifi list`` (terse: ``:`` separated with
``\\:`` and ``\\\\`` escapes; pass ``fields=`` when another ``-f`` list was used), and
``nmcli [-t] -m multiline -f ... dev wifi list`` (``KEY:value`` lines, one record per repeated key;
auto-detected). ``FREQ`` is read as the leading number whatever the unit's translation
(``2437 MHz``, ``2437 МГц``, ``5180,0 MHz``); ``CHAN`` is used when ``FREQ`` is absent. ``SIGNAL`` is
NetworkManager's 0–100 quality, converted to dBm by :func:`quality_to_dbm`. Hidden SSIDs are
empty or ``--``. Required per record: BSSID and SIGNAL.
"""
from __future__ import annotations

import math
import re
from typing import Iterable

from indoor_loc.errors import ParseError
from indoor_loc.wifi.parsers.common import (SIGNAL_MAPPINGS, ParseResult, build_scan, leading_number, split_cut_line,
                                            channel_to_freq_mhz, quality_to_dbm)

NMCLI_FIELDS: tuple[str, ...] = ("BSSID", "SSID", "FREQ", "SIGNAL", "CHAN")
"""The ``-f`` list the package runs nmcli with (and the default field order of :func:`parse_nmcli`)."""

_NMCLI_KNOWN_KEYS = frozenset({
    "NAME", "SSID", "SSID-HEX", "BSSID", "MODE", "CHAN", "FREQ", "RATE", "BANDWIDTH", "SIGNAL", "BARS",
    "SECURITY", "WPA-FLAGS", "RSN-FLAGS", "DEVICE", "ACTIVE", "IN-USE", "DBUS-PATH"})


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
    lines, cut = split_cut_line(text)
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
            quality = leading_number(rec["SIGNAL"])
            if not bssid or quality is None:
                raise KeyError("SIGNAL" if bssid else "BSSID")
        except KeyError as err:
            skipped += 1
            warnings.append(f"nmcli: record {idx + 1} has no usable {err.args[0]}; skipped")
            continue
        freq = leading_number(rec.get("FREQ", "")) if rec.get("FREQ") else None
        if freq is None:
            chan = leading_number(rec.get("CHAN", "")) if rec.get("CHAN") else None
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
    return ParseResult(build_scan(rows, stamp_ns=stamp_ns, frame_id=frame_id, source=source),
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
