"""``iw`` — ``iw dev wlan0 scan`` / ``iw dev wlan0 scan dump`` (iw 4.x–6.x). Blocks start with
``BSS aa:bb:cc:dd:ee:ff(on wlan0)`` (optionally `` -- associated``); per block ``freq: 2412`` or
``freq: 5180.0`` (MHz, 2.4/5/6 GHz), ``signal: -54.00 dBm`` (or ``signal: 70/100`` from drivers
without dBm, mapped like nmcli's quality), ``last seen: 120 ms ago`` (-> ``age_ms``) and ``SSID:``
with iw's ``\\xNN`` byte escapes (UTF-8 SSIDs are printed byte-wise; hidden SSIDs are empty or all
``\\x00``). Required per block: BSSID, freq, signal.
"""
from __future__ import annotations

import math
import re
from typing import Any

from indoor_loc.errors import ParseError
from indoor_loc.wifi.parsers.common import ParseResult, build_scan, split_cut_line, quality_to_dbm

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
    lines, cut = split_cut_line(text)
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
        return ParseResult(build_scan([], stamp_ns=stamp_ns, frame_id=frame_id, source=source), cut)
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
    return ParseResult(build_scan(rows, stamp_ns=stamp_ns, frame_id=frame_id, source=source),
                       truncated, skipped, tuple(warnings))
