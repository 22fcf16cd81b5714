"""``nav_msgs/Path`` straight to CDR bytes, for the estimators' periodic paths in multi-user nodes.

``pdr_kf_node`` and ``tll_pf`` publish their whole path (up to ``path_max_poses``) every
``smooth_period_s`` / ``path_period_s``: building one ``PoseStamped`` per pose in Python and having
rclpy serialise them costs ~15 µs per pose, so a user walking for 10 minutes costs milliseconds per
second in path messages alone, growing with the walk. :func:`path_cdr` packs the bytes of
``serialize_message(path_to_msg(...))`` (tested against it) with the same checks, column-wise.

Layout (XCDR1, little endian, alignment counted after the 4-byte encapsulation header): Path header
(stamp sec int32, nanosec uint32, frame_id string: uint32 length incl. NUL, bytes, NUL), uint32
pose count, then per pose its header (aligned to 4) and, aligned to 8, position (3 doubles) and
orientation (x, y, z, w).
"""
from __future__ import annotations

import math

import numpy as np
from nav_msgs.msg import Path

from msg_adapters.path import path_to_msg
from msg_adapters.time import MAX_STAMP_NS, NS_PER_S

_ENCAPSULATION = b"\x00\x01\x00\x00"


def path_cdr(stamps_ns, xy, yaw=None, frame_id: str = "map", stamp_ns: int | None = None, z=0.0) -> bytes | Path:
    """The CDR bytes of ``path_to_msg(stamps_ns, xy, yaw, frame_id, stamp_ns, z)`` (the same
    ``InvalidMessageError`` for the same bad input: it is left to :func:`path_to_msg` to say). What the
    packer does not take (stamps that are not integers, …) comes back as the ``Path`` message itself,
    which a publisher takes as well as bytes (adapters do not serialise through rclpy)."""
    stamps = np.asarray(stamps_ns)
    n = stamps.shape[0] if stamps.ndim == 1 else -1
    pts = np.asarray(xy, dtype=np.float64)
    if pts.size == 0 and n == 0:
        pts = pts.reshape(0, 2)
    zs = (np.broadcast_to(np.asarray(z, dtype=np.float64), (max(n, 0),)) if np.ndim(z) == 0
          else np.asarray(z, dtype=np.float64))
    yaws = None if yaw is None else np.asarray(yaw, dtype=np.float64)
    ok = (n >= 0 and (not stamps.size or np.issubdtype(stamps.dtype, np.integer)) and pts.shape == (n, 2)
          and zs.shape == (n,) and (yaws is None or yaws.shape == (n,)) and bool(np.isfinite(pts).all())
          and bool(np.isfinite(zs).all()) and (yaws is None or bool(np.isfinite(yaws).all())))
    t = stamps.astype(np.int64) if ok else stamps
    last = int(t[-1]) if ok and n else 0
    head_ns = last if stamp_ns is None else int(stamp_ns)
    if not ok or not 0 <= head_ns <= MAX_STAMP_NS or (n and not (0 <= int(t.min()) and int(t.max()) <= MAX_STAMP_NS)):
        # what this packer does not take: the message itself (or path_to_msg's error)
        return path_to_msg(stamps_ns, xy, yaw, frame_id, stamp_ns, z)
    name = frame_id.encode() + b"\x00"
    ln = len(name)
    out = bytearray(_ENCAPSULATION)
    sec, nsec = divmod(head_ns, NS_PER_S)
    out += np.array([sec], "<i4").tobytes() + np.array([nsec, ln], "<u4").tobytes() + name
    out += b"\x00" * ((-(len(out) - 4)) % 4)
    out += np.array([n], "<u4").tobytes()
    if n:
        # every pose: header (12 + ln bytes), padding to 8, 7 doubles; the first starts where the count
        # ends, every later one at a multiple of 8 (the doubles end on one), so two paddings
        pos0 = len(out) - 4
        pad0 = (-(pos0 + 12 + ln)) % 8
        pad = (-(12 + ln)) % 8
        size = 12 + ln + pad + 56
        rec = np.zeros((n, size), dtype=np.uint8)
        rec[:, 0:4] = (t // NS_PER_S).astype("<i4").view(np.uint8).reshape(n, 4)
        rec[:, 4:8] = (t % NS_PER_S).astype("<u4").view(np.uint8).reshape(n, 4)
        rec[:, 8:12] = np.frombuffer(np.array([ln], "<u4").tobytes(), np.uint8)
        rec[:, 12:12 + ln] = np.frombuffer(name, np.uint8)
        vals = np.zeros((n, 7))
        vals[:, 0:2] = pts
        vals[:, 2] = zs
        if yaws is None:
            vals[:, 6] = 1.0
        else:               # yaw_to_quat: math.sin / math.cos per pose (numpy's may differ in the last bit)
            half = (0.5 * yaws).tolist()
            vals[:, 5] = list(map(math.sin, half))
            vals[:, 6] = list(map(math.cos, half))
        rec[:, 12 + ln + pad:] = vals.astype("<f8").view(np.uint8).reshape(n, 56)
        flat = rec.tobytes()
        if pad0 == pad:
            out += flat
        else:               # the first pose's padding differs: its header, its own padding, its doubles
            out += flat[:12 + ln] + b"\x00" * pad0 + flat[12 + ln + pad:size] + flat[size:]
    return bytes(out)
