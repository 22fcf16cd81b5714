"""builtin_interfaces/Time <-> int nanoseconds."""
from __future__ import annotations

from builtin_interfaces.msg import Time

from indoor_loc.errors import InvalidMessageError


def stamp_to_ns(stamp: Time) -> int:
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def stamp_from_ns(ns: int) -> Time:
    if ns < 0:
        raise InvalidMessageError("negative_stamp", f"stamp {ns} ns is before the epoch")
    sec, nsec = divmod(int(ns), 1_000_000_000)
    return Time(sec=sec, nanosec=nsec)


def header_ns(msg) -> int | None:
    """The header stamp of a message in ns, or None when it has no header."""
    header = getattr(msg, "header", None)
    return None if header is None else stamp_to_ns(header.stamp)
