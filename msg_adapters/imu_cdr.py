"""``sensor_msgs/Imu`` straight to CDR bytes, for nodes that publish one per IMU sample.

Building an ``Imu`` message in Python and having rclpy serialise it costs about 0.4 ms (mostly
the message class's setters and the conversion of its three covariance arrays); a multi-user
``imu_node`` publishes ``imu/data`` for every sample of every user, so it packs the bytes
itself: :func:`imu_cdr` gives exactly what ``rclpy.serialization.serialize_message(imu_to_msg(...))``
gives (tested against it), with the same checks, in a few microseconds. rclpy publishes ``bytes``
as they are (``Publisher.publish``).

Layout (XCDR1, little endian; alignment counted after the 4-byte encapsulation header): header
(stamp sec int32, nanosec uint32, frame_id: uint32 length incl. NUL, bytes, NUL), padding to 8,
then 37 doubles: orientation (4), orientation_covariance (9), angular_velocity (3), its covariance
(9), linear_acceleration (3), its covariance (9).
"""
from __future__ import annotations

import math
import struct

import numpy as np

from indoor_loc.errors import InvalidMessageError
from msg_adapters.imu import QUAT_NORM_TOL, _check_quat
from msg_adapters.time import MAX_STAMP_NS, NS_PER_S

_HEAD = struct.Struct("<4siiI")
_DOUBLES = struct.Struct("<37d")
_ENCAPSULATION = b"\x00\x01\x00\x00"
_ABSENT = (-1.0,) + (0.0,) * 8
_ZEROS9 = (0.0,) * 9


def _floats(v) -> list[float]:
    return np.asarray(v, float).ravel().tolist() if not isinstance(v, list) else [float(x) for x in v]


def imu_cdr(stamp_ns: int, frame_id: str, acc, gyro=None, quat_xyzw=None, orientation_cov=None) -> bytes:
    """The CDR bytes of :func:`msg_adapters.imu.imu_to_msg` with the same arguments (and the same
    ``InvalidMessageError`` for a stamp out of range, a non-finite value or a non-unit quaternion)."""
    ns = int(stamp_ns)
    if ns < 0:
        raise InvalidMessageError("negative_stamp", f"stamp {ns} ns is before the epoch")
    if ns > MAX_STAMP_NS:
        raise InvalidMessageError("stamp_range", f"stamp {ns} ns does not fit builtin_interfaces/Time (int32 s)")
    sec, nsec = divmod(ns, NS_PER_S)
    values: list[float] = []
    if quat_xyzw is None:
        values += (0.0, 0.0, 0.0, 1.0)
        values += _ABSENT
    else:
        q = _floats(quat_xyzw)
        norm = math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]) if len(q) == 4 else math.nan
        if not abs(norm - 1.0) <= QUAT_NORM_TOL:
            _check_quat("quat_xyzw", np.asarray(q, float))      # its error, as imu_to_msg says it
        values += q
        if orientation_cov is None:
            values += _ZEROS9
        else:
            c = _floats(orientation_cov)
            if c[0] == -1.0:
                raise InvalidMessageError("bad_covariance", "orientation_cov[0, 0] = -1 would mark the orientation absent")
            values += c
    if gyro is None:
        values += (0.0, 0.0, 0.0)
        values += _ABSENT
    else:
        values += _floats(gyro)
        values += _ZEROS9
    values += _floats(acc)
    values += _ZEROS9
    if len(values) != 37 or not all(map(math.isfinite, values)):
        raise InvalidMessageError("nan", "imu/data: a non-finite value or a wrong shape in the filter's output")
    name = frame_id.encode() + b"\x00"
    head = _HEAD.pack(_ENCAPSULATION, sec, nsec, len(name)) + name
    pad = (-(len(head) - 4)) % 8
    return head + b"\x00" * pad + _DOUBLES.pack(*values)


def imu_cdr_run(stamps_ns: list[int], frame_id: str, acc: np.ndarray, gyro: np.ndarray, quat_xyzw: np.ndarray,
                orientation_cov: np.ndarray) -> list[bytes] | None:
    """:func:`imu_cdr` of N samples that all carry a gyroscope and an orientation with one covariance:
    ``acc``, ``gyro`` (N, 3), ``quat_xyzw`` (N, 4), ``orientation_cov`` (3, 3) for every sample. The
    same bytes as ``imu_cdr`` per sample; None when any sample would be refused by it (the caller
    then takes them one by one and gets its error)."""
    c = _floats(orientation_cov)
    if len(c) != 9 or c[0] == -1.0:
        return None
    name = frame_id.encode() + b"\x00"
    pad = b"\x00" * ((-(_HEAD.size + len(name) - 4)) % 8)
    head, pack, isfinite, tol = _HEAD.pack, _DOUBLES.pack, math.isfinite, QUAT_NORM_TOL
    out = []
    for ns, q, g, a in zip(stamps_ns, quat_xyzw.tolist(), gyro.tolist(), acc.tolist()):
        values = q + c + g + list(_ZEROS9) + a + list(_ZEROS9)
        if (not 0 <= ns <= MAX_STAMP_NS or len(values) != 37 or not all(map(isfinite, values))
                or not abs(math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]) - 1.0) <= tol):
            return None
        sec, nsec = divmod(ns, NS_PER_S)
        out.append(head(_ENCAPSULATION, sec, nsec, len(name)) + name + pad + pack(*values))
    return out


def imu_cdr_run_covs(stamps_ns: list[int], frame_id: str, acc: np.ndarray, gyro: np.ndarray,
                     quat_xyzw: np.ndarray, orientation_covs: list) -> list[bytes] | None:
    """:func:`imu_cdr_run` with a covariance per sample (the AEKF's grows between updates):
    ``orientation_covs`` N rows of the 9 row-major entries. The same bytes as :func:`imu_cdr` per
    sample; None when any sample would be refused by it."""
    name = frame_id.encode() + b"\x00"
    pad = b"\x00" * ((-(_HEAD.size + len(name) - 4)) % 8)
    head, pack, isfinite, tol = _HEAD.pack, _DOUBLES.pack, math.isfinite, QUAT_NORM_TOL
    out = []
    for ns, q, c, g, a in zip(stamps_ns, quat_xyzw.tolist(), orientation_covs, gyro.tolist(), acc.tolist()):
        values = q + list(c) + g + list(_ZEROS9) + a + list(_ZEROS9)
        if (not 0 <= ns <= MAX_STAMP_NS or len(values) != 37 or c[0] == -1.0 or not all(map(isfinite, values))
                or not abs(math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]) - 1.0) <= tol):
            return None
        sec, nsec = divmod(ns, NS_PER_S)
        out.append(head(_ENCAPSULATION, sec, nsec, len(name)) + name + pad + pack(*values))
    return out
