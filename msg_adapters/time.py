"""builtin_interfaces/Time <-> int nanoseconds, plus the small checks every adapter shares."""
from __future__ import annotations

import math
from typing import Iterable

import numpy as np
from builtin_interfaces.msg import Time

from indoor_loc.errors import InvalidMessageError

NS_PER_S = 1_000_000_000
#: builtin_interfaces/Time.sec is an int32: the last representable stamp (2038-01-19).
MAX_STAMP_NS = (2**31 - 1) * NS_PER_S + NS_PER_S - 1


def stamp_to_ns(stamp: Time) -> int:
    """``builtin_interfaces/Time`` -> int ns since the epoch.

    Raises InvalidMessageError ``"negative_stamp"`` for a stamp before the epoch and
    ``"bad_stamp"`` for ``nanosec`` outside [0, 1e9).
    """
    sec, nsec = int(stamp.sec), int(stamp.nanosec)
    if not 0 <= nsec < NS_PER_S:
        raise InvalidMessageError("bad_stamp", f"nanosec {nsec} outside [0, 1e9)")
    ns = sec * NS_PER_S + nsec
    if ns < 0:
        raise InvalidMessageError("negative_stamp", f"stamp {sec}.{nsec:09d} s is before the epoch")
    return ns


def stamp_from_ns(ns: int) -> Time:
    """int ns since the epoch -> ``builtin_interfaces/Time`` (exact; negative -> ``"negative_stamp"``,
    beyond the int32 seconds of the message -> ``"stamp_range"``)."""
    ns = int(ns)
    if ns < 0:
        raise InvalidMessageError("negative_stamp", f"stamp {ns} ns is before the epoch")
    if ns > MAX_STAMP_NS:
        raise InvalidMessageError("stamp_range", f"stamp {ns} ns does not fit builtin_interfaces/Time (int32 s)")
    sec, nsec = divmod(ns, NS_PER_S)
    return Time(sec=sec, nanosec=nsec)


def header_ns(msg) -> int | None:
    """The header stamp of a message in ns, or None when it has no header."""
    header = getattr(msg, "header", None)
    return None if header is None else stamp_to_ns(header.stamp)


def require_finite(what: str, values: Iterable[float] | float) -> None:
    """Raise InvalidMessageError ``"nan"`` when any value is NaN or +-inf (``what`` names the field)."""
    if isinstance(values, (int, float)):
        if not math.isfinite(values):
            raise InvalidMessageError("nan", f"{what} is {values}")
        return
    # Hot path (every IMU sample): a finite sum proves every element finite (NaN and inf propagate);
    # only a non-finite sum (or an overflow of huge finite values) needs the element-wise look.
    try:
        total = float(values.sum()) if isinstance(values, np.ndarray) else float(sum(values))
    except (TypeError, ValueError):
        total = math.nan
    if math.isfinite(total):
        return
    arr = np.asarray(values, dtype=float)
    if not np.all(np.isfinite(arr)):
        raise InvalidMessageError("nan", f"{what} has non-finite values {arr.ravel().tolist()}")


def require_len(what: str, values, n: int) -> None:
    """A fixed-size message array of ``n`` finite numbers (``"shape"`` / ``"nan"`` otherwise)."""
    if len(values) != n:
        raise InvalidMessageError("shape", f"{what}: expected {n} numbers, got {len(values)}")
    require_finite(what, values)


def as_vector(what: str, values, n: int) -> np.ndarray:
    """``values`` as a finite float64 array of shape (n,) (``"shape"`` / ``"nan"`` otherwise)."""
    try:
        arr = np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError) as err:
        raise InvalidMessageError("shape", f"{what}: expected {n} numbers, got {values!r}") from err
    if arr.shape != (n,):
        raise InvalidMessageError("shape", f"{what}: expected shape ({n},), got {arr.shape}")
    require_finite(what, arr)
    return arr


def as_matrix(what: str, values, n: int) -> np.ndarray:
    """``values`` as a finite float64 (n, n) array (a flat n*n sequence is reshaped row-major)."""
    try:
        arr = np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError) as err:
        raise InvalidMessageError("shape", f"{what}: expected a {n}x{n} matrix, got {values!r}") from err
    if arr.shape == (n * n,):
        arr = arr.reshape(n, n)
    if arr.shape != (n, n):
        raise InvalidMessageError("shape", f"{what}: expected shape ({n}, {n}), got {arr.shape}")
    require_finite(what, arr)
    return arr
