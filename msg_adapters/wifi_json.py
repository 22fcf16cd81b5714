"""std_msgs/String carrying scan JSON (CMU cabot ``/wireless/wifi`` style) <-> :class:`WifiScan`.

The accepted JSON shapes are documented in :mod:`indoor_loc.wifi.parsers`. Readings come back raw
(as written in the JSON, duplicates kept); :func:`indoor_loc.wifi.normalize.normalize` cleans them,
dropping each reading outside the contract's bounds (``rssi_range``, ``bad_frequency``, ``bad_age``;
``indoor_loc.contract.BOUNDS``) rather than the whole scan, as a driver's scan may hold one odd entry.
"""
from __future__ import annotations

from std_msgs.msg import String

from indoor_loc.contract import BOUNDS
from indoor_loc.errors import InvalidMessageError, ParseError
from indoor_loc.wifi.parsers import ParseResult, format_json, parse_json
from indoor_loc.wifi.types import WifiScan


def parse_json_msg(msg: String, *, stamp_ns: int = 0, frame_id: str = "", source: str = "json",
                   signal_mapping: str = "nm") -> ParseResult:
    """Parse ``msg.data``; ``stamp_ns``/``frame_id``/``source`` apply when the JSON has none.

    Raises InvalidMessageError("json", ...) when the text is not a scan document.
    """
    data = getattr(msg, "data", None)
    if not isinstance(data, str):
        raise InvalidMessageError("json", f"expected std_msgs/String, got {type(msg).__name__}")
    try:
        result = parse_json(data, stamp_ns=stamp_ns, frame_id=frame_id, source=source,
                            signal_mapping=signal_mapping)
    except ParseError as err:
        raise InvalidMessageError("json", str(err)) from err
    if len(result.scan) > BOUNDS["scan_aps"].hi:
        raise InvalidMessageError("too_many_aps", f"{len(result.scan)} access points in one scan, more than "
                                                  f"{BOUNDS['scan_aps'].hi:g} (contract bound scan_aps)")
    return result


def scan_from_json_msg(msg: String, *, stamp_ns: int = 0, frame_id: str = "", source: str = "json") -> WifiScan:
    """The raw scan of a JSON string message (see :func:`parse_json_msg`)."""
    return parse_json_msg(msg, stamp_ns=stamp_ns, frame_id=frame_id, source=source).scan


def scan_to_json_msg(scan: WifiScan) -> String:
    """A scan as a cabot-compatible JSON string message (lossless: read back by :func:`scan_from_json_msg`)."""
    return String(data=format_json(scan))
