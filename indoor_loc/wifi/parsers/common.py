"""What every scan-text parser shares: :class:`ParseResult`, signal/channel unit conversions and
the line helpers (see :mod:`indoor_loc.wifi.parsers` for the contract)."""
from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np

from indoor_loc.errors import ParseError
from indoor_loc.wifi.types import WifiScan


@dataclass(frozen=True)
class ParseResult:
    """What a parser read. ``scan`` holds raw readings (see :mod:`indoor_loc.wifi.parsers`);
    ``truncated`` is True when the text ended inside an entry; ``skipped`` counts
    incomplete/unreadable entries."""
    scan: WifiScan
    truncated: bool = False
    skipped: int = 0
    warnings: tuple[str, ...] = ()

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


def leading_number(text: str) -> float | None:
    """The number a value starts with, accepting a decimal comma ("5180,0 MHz" -> 5180.0)."""
    m = _NUMBER.match(text)
    return float(m.group(1).replace(",", ".")) if m else None


def build_scan(rows: list[tuple[str, str, float, float, float]], *, stamp_ns: int, frame_id: str,
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


def split_cut_line(text: str) -> tuple[list[str], bool]:
    """Lines of ``text``; when it does not end with a newline the last line may be cut (a command
    killed mid-write) and is dropped. Returns (lines, cut)."""
    lines = text.splitlines()
    cut = bool(text) and not text.endswith(("\n", "\r")) and bool(lines)
    if cut:
        lines = lines[:-1]
    return lines, cut
