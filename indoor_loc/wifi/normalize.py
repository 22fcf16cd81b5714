"""Scan normalisation: raw readings -> a contract-clean :class:`WifiScan` (pure).

:func:`normalize_report` applies, in this order, and counts every reading it drops by reason:

1. ``bad_bssid`` — not six hex octets (``:``, ``-`` or ``.``-grouped Cisco style are accepted and
   rewritten lower-case colon-separated);
2. ``nan`` / ``rssi_range`` — RSSI not finite or outside [-120, 0] dBm (the message contract);
3. ``bad_frequency`` — frequency not finite or outside the contract's bound (700-75 000 MHz, 0 =
   unknown is kept); ``bad_age`` — an age (when known) negative, infinite or over an hour
   (``indoor_loc.contract.BOUNDS``);
4. ``random_mac`` — locally administered address (bit 1 of the first octet set): randomised
   client MACs, phone hotspots and other moving or short-lived emitters are not landmarks
   (``keep_random_macs`` keeps them; many enterprise APs use locally administered BSSIDs for
   their second and later virtual SSIDs, which an operator may want to keep);
5. ``bssid_deny`` / ``bssid_not_allowed`` and ``ssid_deny`` / ``ssid_not_allowed`` — glob
   patterns (``fnmatch``; BSSID patterns case-insensitive, SSID patterns case-sensitive); an empty
   allow-list allows all; deny wins over allow;
6. ``band`` — frequency not in the ``bands`` list ("2.4", "5", "6"; empty = all; an unknown
   frequency is dropped only when a list is given);
7. ``weak`` — RSSI below ``min_rssi_dbm``;
8. ``stale`` — older than ``max_age_ms`` (when set and the age is known; ``iw scan dump`` returns
   cached results);
9. ``duplicate`` — several readings of one BSSID (the same AP listed twice, or one BSSID on two
   bands): the strongest is kept, at the position of the first occurrence.
"""
from __future__ import annotations

import fnmatch
import math
import re
from collections import Counter
from dataclasses import dataclass

import numpy as np

from indoor_loc import params
from indoor_loc.contract import BOUNDS
from indoor_loc.errors import InvalidInputError
from indoor_loc.params import require
from indoor_loc.wifi.types import WifiScan

RSSI_MIN_DBM = -120.0
RSSI_MAX_DBM = 0.0
BANDS = ("2.4", "5", "6")

DROP_REASONS = ("bad_bssid", "nan", "rssi_range", "bad_frequency", "bad_age", "random_mac", "bssid_deny",
                "bssid_not_allowed", "ssid_deny", "ssid_not_allowed", "band", "weak", "stale", "duplicate")


@dataclass(frozen=True)
class NormalizeParams:
    """How raw scan readings are cleaned (see the module doc for the order of the checks)."""
    min_rssi_dbm: float = params.field(-120.0, "drop readings weaker than this, dBm (-120 keeps every "
                                               "reading the contract allows)")
    keep_random_macs: bool = params.field(False, "keep locally administered (randomised / hotspot) BSSIDs")
    ssid_allow: list[str] = params.field([], "SSID glob patterns to keep (empty = all), case-sensitive")
    ssid_deny: list[str] = params.field([], "SSID glob patterns to drop, e.g. ['*iPhone*', 'AndroidAP*']")
    bssid_allow: list[str] = params.field([], "BSSID glob patterns to keep (empty = all), e.g. ['00:1a:2b:*']")
    bssid_deny: list[str] = params.field([], "BSSID glob patterns to drop")
    bands: list[str] = params.field([], "frequency bands to keep, from '2.4', '5', '6' GHz (empty = all)")
    max_age_ms: float = params.field(0.0, "drop readings older than this at scan time, ms (0 = no limit)")

    def validate(self) -> None:
        o = type(self).__name__
        require(math.isfinite(self.min_rssi_dbm) and RSSI_MIN_DBM <= self.min_rssi_dbm <= RSSI_MAX_DBM,
                o, "min_rssi_dbm", f"a number in [{RSSI_MIN_DBM}, {RSSI_MAX_DBM}] dBm", self.min_rssi_dbm)
        for name in ("ssid_allow", "ssid_deny", "bssid_allow", "bssid_deny", "bands"):
            value = getattr(self, name)
            require(isinstance(value, (list, tuple)) and all(isinstance(v, str) for v in value),
                    o, name, "a list of strings", value)
        bad = [b for b in self.bands if b not in BANDS]
        require(not bad, o, "bands", f"values from {list(BANDS)}", self.bands)
        require(math.isfinite(self.max_age_ms) and self.max_age_ms >= 0, o, "max_age_ms",
                "a number >= 0 ms", self.max_age_ms)


@dataclass(frozen=True)
class NormalizeReport:
    """The normalised scan and how many readings were dropped, by reason (only non-zero reasons)."""
    scan: WifiScan
    dropped: dict[str, int]
    n_in: int

    @property
    def n_dropped(self) -> int:
        return sum(self.dropped.values())


_HEX12 = re.compile(r"^[0-9a-f]{12}$")


def canonical_bssid(text: str) -> str | None:
    """``"AA-BB-CC-DD-EE-FF"``, ``"aabb.ccdd.eeff"``, ``"AA:BB:..."`` -> ``"aa:bb:cc:dd:ee:ff"``;
    None when the text is not a MAC address."""
    if not isinstance(text, str):
        return None
    s = text.strip().lower()
    parts = re.split(r"[:\-]", s) if (":" in s or "-" in s) else None
    if parts is not None:
        if len(parts) != 6 or any(len(p) != 2 for p in parts):
            return None
        hexs = "".join(parts)
    else:
        hexs = s.replace(".", "") if s.count(".") == 2 else s
    if not _HEX12.match(hexs):
        return None
    return ":".join(hexs[i:i + 2] for i in range(0, 12, 2))


def is_locally_administered(bssid: str) -> bool:
    """Bit 1 (0x02) of the first octet: the U/L bit of IEEE 802 addresses (set = local)."""
    return bool(int(bssid[:2], 16) & 0x02)


def band_of(freq_mhz: float) -> str:
    """"2.4", "5", "6" (GHz band of a channel centre frequency in MHz) or "" when outside them."""
    f = float(freq_mhz)
    if 2400.0 <= f <= 2500.0:
        return "2.4"
    if 4900.0 <= f < 5925.0:
        return "5"
    if 5925.0 <= f <= 7125.0:
        return "6"
    return ""


def _matches(value: str, patterns: list[str], *, fold: bool) -> bool:
    if fold:
        value = value.lower()
        return any(fnmatch.fnmatchcase(value, p.lower()) for p in patterns)
    return any(fnmatch.fnmatchcase(value, p) for p in patterns)


def _drop_reason(bssid: str | None, ssid: str, rssi: float, freq: float, age: float,
                 p: NormalizeParams) -> str | None:
    if bssid is None:
        return "bad_bssid"
    if not math.isfinite(rssi):
        return "nan"
    if not RSSI_MIN_DBM <= rssi <= RSSI_MAX_DBM:
        return "rssi_range"
    if not math.isfinite(freq) or (freq != 0.0 and not BOUNDS["frequency"].holds(freq)):
        return "bad_frequency"
    if not math.isnan(age) and not BOUNDS["age"].holds(age):
        return "bad_age"
    if not p.keep_random_macs and is_locally_administered(bssid):
        return "random_mac"
    if p.bssid_deny and _matches(bssid, p.bssid_deny, fold=True):
        return "bssid_deny"
    if p.bssid_allow and not _matches(bssid, p.bssid_allow, fold=True):
        return "bssid_not_allowed"
    if p.ssid_deny and _matches(ssid, p.ssid_deny, fold=False):
        return "ssid_deny"
    if p.ssid_allow and not _matches(ssid, p.ssid_allow, fold=False):
        return "ssid_not_allowed"
    if p.bands and band_of(freq) not in p.bands:
        return "band"
    if rssi < p.min_rssi_dbm:
        return "weak"
    if p.max_age_ms > 0 and math.isfinite(age) and age > p.max_age_ms:
        return "stale"
    return None


def normalize_report(scan: WifiScan, p: NormalizeParams | None = None) -> NormalizeReport:
    """Clean ``scan`` (see the module doc) and count the readings dropped, by reason.

    The result keeps ``stamp_ns``, ``frame_id`` and ``source``; its BSSIDs are unique, lower-case
    and colon-separated, SSIDs have NUL characters removed, ``age_ms`` is kept when known.
    """
    p = p or NormalizeParams()
    n = len(scan.bssid)
    ssids = tuple(scan.ssid) if len(scan.ssid) == n else ("",) * n
    ages = np.asarray(scan.age_ms, dtype=float) if scan.age_ms is not None else np.full(n, np.nan)
    rssi = np.asarray(scan.rssi_dbm, dtype=float).reshape(-1)
    freq = np.asarray(scan.freq_mhz, dtype=float).reshape(-1)
    if not len(rssi) == len(freq) == len(ages) == n:
        raise InvalidInputError("bad_shape", f"scan has {n} BSSIDs but {len(rssi)} RSSIs, {len(freq)} "
                                               f"frequencies and {len(ages)} ages")
    dropped: Counter[str] = Counter()
    kept: dict[str, int] = {}          # bssid -> index of the reading kept so far
    order: list[str] = []
    for i in range(n):
        bssid = canonical_bssid(scan.bssid[i])
        ssid = str(ssids[i]).replace("\x00", "")
        reason = _drop_reason(bssid, ssid, float(rssi[i]), float(freq[i]), float(ages[i]), p)
        if reason is not None:
            dropped[reason] += 1
            continue
        assert bssid is not None
        j = kept.get(bssid)
        if j is None:
            kept[bssid] = i
            order.append(bssid)
            continue
        dropped["duplicate"] += 1
        if rssi[i] > rssi[j]:
            kept[bssid] = i
    idx = np.array([kept[b] for b in order], dtype=int)
    age_out = ages[idx] if scan.age_ms is not None and len(idx) and not np.all(np.isnan(ages[idx])) else None
    out = WifiScan(stamp_ns=int(scan.stamp_ns), bssid=tuple(order), rssi_dbm=rssi[idx].copy(),
                   freq_mhz=freq[idx].copy(), ssid=tuple(str(ssids[k]).replace("\x00", "") for k in idx),
                   age_ms=age_out, frame_id=scan.frame_id, source=scan.source)
    return NormalizeReport(out, dict(dropped), n)


def normalize(scan: WifiScan, p: NormalizeParams | None = None) -> WifiScan:
    """The normalised scan alone (see :func:`normalize_report` for the drop counts)."""
    return normalize_report(scan, p).scan
