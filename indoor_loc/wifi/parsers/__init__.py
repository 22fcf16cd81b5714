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

Formats accepted, one module each: :mod:`.iw` (``iw dev IF scan``), :mod:`.nmcli` (``nmcli`` terse
and multiline), :mod:`.json_scan` (CMU cabot JSON and common variants); :func:`parse` dispatches.
"""
from __future__ import annotations

from typing import Any

from indoor_loc.errors import ParseError
from indoor_loc.wifi.parsers.common import SIGNAL_MAPPINGS, ParseResult, channel_to_freq_mhz, quality_to_dbm
from indoor_loc.wifi.parsers.iw import iw_unescape_ssid, parse_iw
from indoor_loc.wifi.parsers.json_scan import format_json, parse_json, stamp_from_seconds_like
from indoor_loc.wifi.parsers.nmcli import NMCLI_FIELDS, nmcli_split, parse_nmcli

FORMATS = ("iw", "nmcli", "json")

__all__ = ["FORMATS", "NMCLI_FIELDS", "SIGNAL_MAPPINGS", "ParseResult", "channel_to_freq_mhz", "format_json",
           "iw_unescape_ssid", "nmcli_split", "parse", "parse_iw", "parse_json", "parse_nmcli", "quality_to_dbm",
           "stamp_from_seconds_like"]


def parse(text: str, fmt: str, **kw: Any) -> ParseResult:
    """Dispatch on ``fmt`` ("iw", "nmcli" or "json")."""
    if fmt == "iw":
        return parse_iw(text, **kw)
    if fmt == "nmcli":
        return parse_nmcli(text, **kw)
    if fmt == "json":
        return parse_json(text, **kw)
    raise ParseError(f"unknown scan format {fmt!r}; expected one of {FORMATS}")
