"""An estimate's ``geometry_msgs/PoseWithCovarianceStamped`` straight to CDR bytes, for the estimators'
per-hop poses (``pf/pose``, ``pdr_kf/pose``) in multi-user nodes.

Every ``pdr/odom`` hop of every user makes one pose: building it with :func:`msg_adapters.pose.pose_to_msg`
(a message of nested Python objects, 36 covariance floats) and having rclpy serialise it, then reading it
back for the ``map -> odom`` correction (:func:`msg_adapters.tf.pose_yaw_var`), costs more than the
filter's own arithmetic in ``pdr_kf_node``. :func:`pose_cdr` packs the bytes of
``serialize_message(pose_to_msg(...))`` (tested against it) and carries what ``pose_yaw_var`` would read
of it (:attr:`PoseCdr.estimate`), so nothing is built or decoded twice.

Layout (XCDR1, little endian, alignment counted after the 4-byte encapsulation header): header
(stamp sec int32, nanosec uint32, frame_id: uint32 length incl. NUL, bytes, NUL), padding to 8, then
position (3 doubles), orientation (x, y, z, w doubles) and the 6x6 covariance (36 doubles, row-major).
"""
from __future__ import annotations

import math
import struct
from typing import Any

import numpy as np

from msg_adapters.pose import YAW_VAR_UNKNOWN, pose_to_msg
from msg_adapters.time import MAX_STAMP_NS, NS_PER_S

_ENCAPSULATION = b"\x00\x01\x00\x00"
_HEAD = struct.Struct("<iII")
_BODY = struct.Struct("<43d")


class PoseCdr(bytes):
    """The CDR bytes of a pose (a publisher takes them as the message), with ``estimate``: what
    :func:`msg_adapters.tf.pose_yaw_var` reads of the message, ``(stamp_ns, frame_id, (x, y, yaw),
    yaw variance)``."""
    estimate: tuple[int, str, tuple[float, float, float], float]


def pose_cdr(stamp_ns: int, xy, yaw: float = 0.0, cov_xy=None, *, frame_id: str = "map",
             yaw_var: float = YAW_VAR_UNKNOWN, z: float = 0.0, z_var: float = 0.0) -> Any:
    """``pose_to_msg(...)`` (same arguments) as :class:`PoseCdr`; what the packer does not take (a
    covariance of another shape, a non-finite value, a stamp out of range) comes back as
    ``pose_to_msg``'s message, or its ``InvalidMessageError``."""
    try:
        x, y = float(xy[0]), float(xy[1])
        c = np.asarray(cov_xy, dtype=np.float64) if cov_xy is not None else None
        simple = ((c is None or c.shape == (2, 2)) and np.shape(xy) == (2,) and isinstance(stamp_ns, (int, np.integer))
                  and 0 <= int(stamp_ns) <= MAX_STAMP_NS)
        vals = (x, y, float(z), float(yaw), float(yaw_var), float(z_var))
    except (TypeError, ValueError, IndexError):
        simple = False
    if not simple or not math.isfinite(math.fsum(vals)) or (c is not None and not np.isfinite(c).all()):
        return pose_to_msg(stamp_ns, xy, yaw, cov_xy, frame_id=frame_id, yaw_var=yaw_var, z=z, z_var=z_var)
    half = 0.5 * float(yaw)
    qz, qw = math.sin(half), math.cos(half)             # yaw_to_quat
    cov = [0.0] * 36
    if c is not None:
        cov[0], cov[1], cov[6], cov[7] = float(c[0, 0]), float(c[0, 1]), float(c[1, 0]), float(c[1, 1])
    cov[14] = float(z_var)
    yv = min(float(yaw_var), YAW_VAR_UNKNOWN)
    cov[35] = yv
    name = frame_id.encode() + b"\x00"
    sec, nsec = divmod(int(stamp_ns), NS_PER_S)
    head = _HEAD.pack(sec, nsec, len(name)) + name
    out = PoseCdr(_ENCAPSULATION + head + b"\x00" * ((-len(head)) % 8)
                  + _BODY.pack(x, y, float(z), 0.0, 0.0, qz, qw, *cov))
    # quat_to_yaw of that orientation, as the correction reads it from the message
    qx = qy = 0.0
    out.estimate = (int(stamp_ns), frame_id, (x, y, math.atan2(2.0 * (qw * qz + qx * qy), 1.0 - 2.0 * (qy * qy + qz * qz))),
                    yv)
    return out
