"""Hostile messages per input port, as hypothesis strategies: the property tests
(``test/test_ports_property.py``) and the fault benchmark (:mod:`indoor_loc.bench.chaos`) draw from the
same ones.

From a valid message of a port (``base``): numeric fields set to NaN, inf, +-1e308, negatives, huge or
tiny values, or values just inside the contract's bounds; covariance arrays at random; strings at
random; empty and huge scans; JSON with absurd numbers (:func:`hostile_for`). The benchmark adds what
only a live input has (:func:`wire_case`): stamps zero, far in the future, backwards or duplicated,
wrong frames, and serialised samples that are empty or garbage.

``hypothesis`` is a test dependency; this module is imported only by tests and benchmarks.
"""
from __future__ import annotations

import copy
import json
import math
import struct
from typing import Any

import numpy as np
from hypothesis import strategies as st

from msg_adapters.time import MAX_STAMP_NS, stamp_from_ns

SEC = 1_000_000_000

#: absurd values, and extreme ones just inside the contract's bounds (they reach the estimators)
HOSTILE_FLOATS = [math.nan, math.inf, -math.inf, 1e308, -1e308, -1.0, 0.0, 1e6, -1e6, 1e-300, -1e-300, 5e4,
                  1e12, 3.0, -0.5, 9.9e4, -9.9e4, 1e10, 1e-6, 1e-9, 199.0, -99.0, 4.9e-3, 9.99e6]
hostile_float = st.one_of(st.sampled_from(HOSTILE_FLOATS), st.sampled_from(HOSTILE_FLOATS),
                          st.floats(allow_nan=True, allow_infinity=True))


def stamp_ns_of(msg: Any) -> int:
    """``header.stamp`` of a message, ns."""
    return msg.header.stamp.sec * SEC + msg.header.stamp.nanosec


def numeric_leaves(msg: Any, prefix: tuple = ()) -> list[tuple]:
    """Paths to every float field and float-array element of a message (not the stamp's integers)."""
    out = []
    for name, typ in msg.get_fields_and_field_types().items():
        v = getattr(msg, name)
        if typ in ("double", "float"):
            out.append(prefix + (name,))
        elif typ.startswith("double[") or typ.startswith("float["):
            out += [prefix + (name, i) for i in range(len(v))]
        elif hasattr(v, "get_fields_and_field_types"):
            out += numeric_leaves(v, prefix + (name,))
    return out


def set_path(msg: Any, path: tuple, value: Any) -> None:
    """Set the field (or array element) at ``path`` of ``msg`` (a path of :func:`numeric_leaves`)."""
    *head, last = path
    obj = msg
    for p in head:
        obj = getattr(obj, p)
    if isinstance(last, int):
        obj[last] = value
    else:
        setattr(obj, last, value)


def array_fields(msg: Any, prefix: tuple = ()) -> list[tuple[tuple, int]]:
    """``(path, length)`` of every fixed-size double array of a message (covariances)."""
    out = []
    for name, typ in msg.get_fields_and_field_types().items():
        v = getattr(msg, name)
        if typ.startswith("double["):
            out.append((prefix + (name,), len(v)))
        elif hasattr(v, "get_fields_and_field_types"):
            out += array_fields(v, prefix + (name,))
    return out


def leaf_groups(msg: Any) -> list[list[tuple]]:
    """The numeric leaves grouped by the field holding them (a vector, a quaternion, a covariance), so
    each field is as likely to be picked as any other however many numbers it holds."""
    groups: dict[tuple, list[tuple]] = {}
    for path in numeric_leaves(msg):
        groups.setdefault(path[:-1], []).append(path)
    return list(groups.values())


@st.composite
def numeric_mutation(draw, base):
    """A copy of ``base`` with one field (a vector, quaternion or covariance) hostile, wholly or in one or
    two of its numbers, or a covariance array at random."""
    msg = copy.deepcopy(base)
    arrays = array_fields(msg)
    if arrays and draw(st.integers(0, 3)) == 0:           # (a FluidPressure has no array)
        path, n = draw(st.sampled_from(arrays))
        values = draw(st.lists(st.one_of(hostile_float, st.floats(-10, 10)), min_size=n, max_size=n))
        obj = msg
        for p in path[:-1]:
            obj = getattr(obj, p)
        setattr(obj, path[-1], np.array(values, dtype=np.float64))
        return msg
    group = draw(st.sampled_from(leaf_groups(msg)))
    if draw(st.booleans()):                 # the whole vector / quaternion / covariance
        value = draw(hostile_float)
        for path in group:
            set_path(msg, path, value)
    else:
        for path in draw(st.lists(st.sampled_from(group), min_size=1, max_size=2)):
            set_path(msg, path, draw(hostile_float))
    return msg


_HUGE: dict[int, Any] = {}


def huge_scan(n: int = 10_000) -> Any:
    """A valid ``n``-AP scan stamped 0 (made once per size and shared: :func:`restamp` a copy, or its
    serialised bytes, where it goes)."""
    if n not in _HUGE:
        from indoor_loc.wifi.types import WifiScan
        from msg_adapters.wifi_scan import scan_to_msg
        rng = np.random.default_rng(5)
        bssid = tuple(f"{i >> 24 & 255:02x}:{i >> 16 & 255:02x}:{i >> 8 & 255:02x}:{i & 255:02x}:00:01"
                      for i in range(n))
        _HUGE[n] = scan_to_msg(WifiScan(stamp_ns=0, bssid=bssid, rssi_dbm=rng.uniform(-100, -30, n),
                                        freq_mhz=np.full(n, 2412.0), ssid=("big",) * n))
    return _HUGE[n]


@st.composite
def scan_mutation(draw, base, huge_n: int = 10_000):
    """A hostile ``wifi_scan.v1`` DiagnosticArray from a valid one (a ``huge`` one is :func:`huge_scan`
    itself, stamped 0)."""
    kind = draw(st.sampled_from(["value"] * 4 + ["name", "summary", "empty", "huge"]))
    if kind == "huge":
        return huge_scan(huge_n)
    msg = copy.deepcopy(base)
    if kind == "empty":
        msg.status = msg.status[:draw(st.integers(0, 1))]
        return msg
    if kind == "summary":
        kv = draw(st.sampled_from(msg.status[0].values))
        kv.value = draw(st.text(max_size=12))
        return msg
    ap = draw(st.sampled_from(msg.status[1:]))
    if kind == "name":
        ap.name = draw(st.text(max_size=20))
        return msg
    from diagnostic_msgs.msg import KeyValue
    key = draw(st.sampled_from(["rssi_dbm", "frequency_mhz", "age_ms"]))
    value = draw(st.one_of(hostile_float.map(repr), st.text(max_size=8)))
    ap.values = [kv for kv in ap.values if kv.key != key] + [KeyValue(key=key, value=value)]
    return msg


@st.composite
def json_mutation(draw, base):
    """Hostile JSON text from a valid scan document: random text, or absurd numbers in it."""
    from std_msgs.msg import String
    if draw(st.booleans()):
        return String(data=draw(st.text(max_size=40)))
    doc = json.loads(base.data)
    entry = draw(st.sampled_from(doc["data"]))
    key = draw(st.sampled_from(["rssi", "frequency_mhz", "frequency_GHz", "last_seen_ms", "mac"]))
    entry[key] = draw(st.one_of(hostile_float, st.text(max_size=8)))
    return String(data=json.dumps(doc))


def hostile_for(topic: str, base: Any, *, huge_n: int = 10_000):
    """The strategy of hostile messages of ``topic``'s type made from its valid message ``base``."""
    if topic in ("wifi/scan", "wifi/scan_raw"):
        return scan_mutation(base, huge_n)
    if topic == "wifi/scan_json":
        return json_mutation(base)
    return numeric_mutation(base)


def restamp(msg: Any, stamp_ns: int) -> Any:
    """``msg`` with ``header.stamp`` set (a message without a header unchanged)."""
    if hasattr(msg, "header"):
        msg.header.stamp = stamp_from_ns(stamp_ns)
    return msg


# -- what only a live input has: stamps, frames, the serialised bytes ---------------------------------
#: Kinds of :func:`wire_case`, each drawn as often as the others.
#: Empty samples are not drawn (DDS refuses them and a reliable subscription waits for them: a few go
#: on each port as explicit cases, see :mod:`indoor_loc.bench.chaos_faults`).
WIRE_KINDS = ("fields", "fields", "fields", "stamp", "frame", "garbage_bytes", "truncated")
#: Stamps of the ``stamp`` kind, relative to the valid message's stamp ``s`` (None: absolute zero).
STAMP_KINDS = ("zero", "future", "far_future", "backwards", "far_backwards", "duplicate", "max")


class WireCase:
    """One hostile message as it goes on the wire: ``data`` (CDR bytes) on ``topic``; ``kind`` says
    what is wrong with it (``fields``, ``stamp:<how>``, ``frame``, ``empty_bytes``, ...)."""
    __slots__ = ("topic", "kind", "data")

    def __init__(self, topic: str, kind: str, data: bytes) -> None:
        self.topic, self.kind, self.data = topic, kind, data


@st.composite
def wire_case(draw, topic: str, base: Any, *, huge_n: int = 100_000):
    """A hostile message of ``topic`` (see :data:`WIRE_KINDS`) made from its valid message ``base``,
    serialised. Field-level cases keep ``base``'s stamp (the message is judged by its contents);
    ``stamp`` cases keep its contents."""
    from rclpy.serialization import serialize_message
    kind = draw(st.sampled_from(WIRE_KINDS))
    if kind == "garbage_bytes":
        n = draw(st.integers(1, 256))
        head = draw(st.sampled_from([b"", b"\x00\x01\x00\x00"]))        # with a valid CDR header, or none
        return WireCase(topic, kind, head + draw(st.binary(min_size=n, max_size=n)))
    if kind == "truncated":
        data = serialize_message(base)
        return WireCase(topic, kind, data[:draw(st.integers(1, max(1, len(data) - 1)))])
    msg = copy.deepcopy(base)
    if kind == "fields":
        msg = draw(hostile_for(topic, base, huge_n=huge_n))
        if msg is _HUGE.get(huge_n):           # shared: its bytes restamped
            data = serialize_message(msg)
            s = stamp_ns_of(base)
            return WireCase(topic, "huge_scan", data[:4] + struct.pack("<iI", s // SEC, s % SEC) + data[12:])
        if hasattr(msg, "header") and hasattr(base, "header"):
            msg.header.stamp = copy.deepcopy(base.header.stamp)
    elif kind == "frame":
        if not hasattr(msg, "header"):
            kind = "fields"
            msg = draw(hostile_for(topic, base, huge_n=huge_n))
        else:
            msg.header.frame_id = draw(st.sampled_from(["", "wrong_frame", "/map", "odom", "x" * 300]))
    else:
        how = draw(st.sampled_from(STAMP_KINDS))
        kind = f"stamp:{how}"
        if hasattr(msg, "header"):
            s = stamp_ns_of(base)
            new = {"zero": 0, "future": s + 3600 * SEC, "far_future": s + 10 * 365 * 86400 * SEC,
                   "backwards": max(0, s - 30 * SEC), "far_backwards": max(0, s - 10 * 365 * 86400 * SEC),
                   "duplicate": s, "max": MAX_STAMP_NS}[how]
            restamp(msg, new)
    return WireCase(topic, kind, serialize_message(msg))
