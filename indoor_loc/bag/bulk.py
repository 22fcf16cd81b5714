"""Bulk CDR decoding of runs of fixed-layout messages into arrays (``sensor_msgs/Imu``, ``MagneticField``).

A ROS 2 message on the wire (and in an MCAP bag) is XCDR1: a 4-byte encapsulation header
(``00 01 00 00`` = little-endian CDR) then the fields, each aligned to its size counted from the end
of that header. ``std_msgs/Header`` is ``int32 sec, uint32 nanosec, string frame_id`` (uint32 length
including the terminating NUL, then the bytes); what follows in ``Imu`` and ``MagneticField`` is only
float64 (aligned to 8): quaternion (4) + covariance (9) + angular velocity (3) + covariance (9) +
linear acceleration (3) + covariance (9) = 37 numbers, or field (3) + covariance (9) = 12.

Messages of one sensor differ only in stamp and numbers, so a run of them has one size and one
header prefix: it is decoded with one ``np.frombuffer`` over the joined bytes. A run that is not
like that (another frame id inside it, big-endian CDR, a truncated record) is not decoded here
(``None``): the caller deserialises those messages one by one, as before.
"""
from __future__ import annotations

import struct
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np

from msg_adapters.imu import QUAT_NORM_TOL, ImuSample
from msg_adapters.plausible import cov_rows_ok, rows_within
from msg_adapters.time import MAX_STAMP_NS, NS_PER_S

#: float64 fields after the header
IMU_DOUBLES = 37
MAG_DOUBLES = 12
_CDR_LE = b"\x00\x01"


class ImuArrays(NamedTuple):
    """A run of ``sensor_msgs/Imu`` messages as arrays (N rows; one frame id)."""
    sec: np.ndarray                 # (N,) int64, header.stamp.sec
    nanosec: np.ndarray             # (N,) int64, header.stamp.nanosec
    frame_id: str
    orientation_xyzw: np.ndarray    # (N, 4)
    orientation_cov: np.ndarray     # (N, 9)
    angular_velocity: np.ndarray    # (N, 3)
    angular_velocity_cov: np.ndarray  # (N, 9)
    linear_acceleration: np.ndarray  # (N, 3)
    linear_acceleration_cov: np.ndarray  # (N, 9)

    def __len__(self) -> int:       # type: ignore[override]
        return len(self.sec)


class MagArrays(NamedTuple):
    """A run of ``sensor_msgs/MagneticField`` messages as arrays (N rows; one frame id)."""
    sec: np.ndarray
    nanosec: np.ndarray
    frame_id: str
    magnetic_field: np.ndarray      # (N, 3), T
    magnetic_field_cov: np.ndarray  # (N, 9)

    def __len__(self) -> int:       # type: ignore[override]
        return len(self.sec)


def _decode_fixed(datas: Sequence[bytes] | np.ndarray, n_doubles: int
                  ) -> tuple[np.ndarray, np.ndarray, str, np.ndarray] | None:
    """(sec, nanosec, frame_id, doubles (N, n_doubles)) of CDR records ``header + n_doubles float64``
    that share size and header prefix; None if they do not (or are not little-endian CDR).
    ``datas``: the records, or an (N, size) uint8 array of them."""
    if isinstance(datas, np.ndarray):
        if datas.ndim != 2 or not len(datas):
            return None
        a = datas
        n, rec = a.shape
        first = a[0].tobytes()
    else:
        if not datas:
            return None
        first = datas[0]
        n, rec = len(datas), len(first)
        a = None
    if len(first) < 16 or first[:2] != _CDR_LE:
        return None
    (slen,) = struct.unpack_from("<I", first, 12)
    str_end = 16 + slen
    off = 4 + (str_end - 4 + 7) // 8 * 8
    size = off + 8 * n_doubles
    if slen < 1 or rec != size:
        return None
    if a is None:
        buf = b"".join(datas)
        if len(buf) != n * rec:
            return None                         # sizes differ within the run
        a = np.frombuffer(buf, np.uint8).reshape(n, rec)
    prefix = a[:, :4]
    name = a[:, 12:str_end]
    if n > 1 and (np.any(prefix != prefix[0]) or np.any(name != name[0])):
        return None
    if first[str_end - 1] != 0:
        return None
    try:
        frame_id = first[16:str_end - 1].decode("utf-8")
    except UnicodeDecodeError:
        return None
    sec = np.ascontiguousarray(a[:, 4:8]).view("<i4").reshape(n).astype(np.int64)
    nsec = np.ascontiguousarray(a[:, 8:12]).view("<u4").reshape(n).astype(np.int64)
    vals = np.ascontiguousarray(a[:, off:size]).view("<f8").reshape(n, n_doubles)
    return sec, nsec, frame_id, vals


def decode_imu(datas: Sequence[bytes] | np.ndarray) -> ImuArrays | None:
    """CDR ``sensor_msgs/msg/Imu`` records (or an (N, size) uint8 array of them) -> :class:`ImuArrays`
    (None: decode them one by one)."""
    r = _decode_fixed(datas, IMU_DOUBLES)
    if r is None:
        return None
    sec, nsec, frame, v = r
    return ImuArrays(sec, nsec, frame, v[:, 0:4], v[:, 4:13], v[:, 13:16], v[:, 16:25], v[:, 25:28], v[:, 28:37])


def decode_mag(datas: Sequence[bytes] | np.ndarray) -> MagArrays | None:
    """CDR ``sensor_msgs/msg/MagneticField`` records -> :class:`MagArrays` (None: one by one)."""
    r = _decode_fixed(datas, MAG_DOUBLES)
    if r is None:
        return None
    sec, nsec, frame, v = r
    return MagArrays(sec, nsec, frame, v[:, 0:3], v[:, 3:12])


def _stamps_ok(sec: np.ndarray, nsec: np.ndarray) -> np.ndarray:
    """Rows whose stamp ``msg_adapters.time.stamp_to_ns`` accepts (nanosec in [0, 1e9), not before 1970)."""
    return (nsec >= 0) & (nsec < NS_PER_S) & (sec * NS_PER_S + nsec >= 0)


def _finite(a: np.ndarray) -> np.ndarray:
    return np.isfinite(a).all(axis=1)


class SampleRun(Sequence):
    """The per-message items of a run, :class:`ImuSample` each, made when first read (a batch path
    that works on whole columns reads ``arrays`` and never makes them); ``all_oriented``: every
    message carries an orientation."""

    def __init__(self, arrays: ImuArrays, stamps: list[int], gyro_on: list[bool], orient_on: list[bool]) -> None:
        self.arrays = arrays
        self.stamps = stamps
        self._gyro_on = gyro_on
        self._orient_on = orient_on
        self.all_oriented = all(orient_on)
        self._cov = arrays.orientation_cov.reshape(-1, 3, 3)
        self._items: list[ImuSample] | None = None

    def _make(self) -> list[ImuSample]:
        if self._items is None:
            arr, frame, cov = self.arrays, self.arrays.frame_id, self._cov
            acc, gyro, q = arr.linear_acceleration, arr.angular_velocity, arr.orientation_xyzw
            g_on, o_on = self._gyro_on, self._orient_on
            self._items = [ImuSample(t, frame, acc[i], gyro[i] if g_on[i] else None, q[i] if o_on[i] else None,
                                     cov[i] if o_on[i] else None)
                           for i, t in enumerate(self.stamps)]
        return self._items

    def __len__(self) -> int:
        return len(self.stamps)

    def __getitem__(self, i):  # type: ignore[override]
        return self._make()[i]

    def __iter__(self):  # type: ignore[override]
        return iter(self._make())


def imu_samples(arr: ImuArrays) -> SampleRun | None:
    """Validated samples of a decoded run, one per message, equal to ``imu_from_msg`` of each; None
    when any message would be rejected — by the same tests, finiteness and the contract's bounds
    (:mod:`msg_adapters.plausible`) — so the caller takes them one by one and each is counted under
    its own reason."""
    gyro_on = arr.angular_velocity_cov[:, 0] != -1.0
    orient_on = arr.orientation_cov[:, 0] != -1.0
    q = arr.orientation_xyzw
    ok = (_stamps_ok(arr.sec, arr.nanosec) & _finite(arr.linear_acceleration) & _finite(arr.linear_acceleration_cov)
          & rows_within(arr.linear_acceleration, "acceleration")
          & (~gyro_on | (_finite(arr.angular_velocity) & _finite(arr.angular_velocity_cov)
                         & rows_within(arr.angular_velocity, "angular_rate")))
          & (~orient_on | (_finite(q) & _finite(arr.orientation_cov)
                           & (np.abs(np.sqrt((q * q).sum(axis=1)) - 1.0) <= QUAT_NORM_TOL))))
    if not ok.all():
        return None
    if orient_on.any() and not cov_rows_ok(arr.orientation_cov[orient_on].reshape(-1, 3, 3), "angle_variance").all():
        return None
    return SampleRun(arr, (arr.sec * NS_PER_S + arr.nanosec).tolist(), gyro_on.tolist(), orient_on.tolist())


def mag_samples(arr: MagArrays) -> list[tuple[int, np.ndarray]] | None:
    """``(stamp_ns, field T (3,))`` per message, as ``mag_from_msg``; None when any would be rejected."""
    ok = (_stamps_ok(arr.sec, arr.nanosec) & _finite(arr.magnetic_field) & _finite(arr.magnetic_field_cov)
          & rows_within(arr.magnetic_field, "magnetic_field"))
    if not ok.all():
        return None
    f = arr.magnetic_field
    return [(t, f[i]) for i, t in enumerate((arr.sec * NS_PER_S + arr.nanosec).tolist())]


def bulk_items(type_name: str, datas: Sequence[bytes] | np.ndarray) -> Sequence | None:
    """CDR records of one message type (or an (N, size) uint8 array of them) -> what that type's
    adapter returns for each (``Imu``: ``msg_adapters.imu.imu_from_msg``'s :class:`ImuSample`;
    ``MagneticField``: ``mag_from_msg``'s ``(stamp_ns, field)``), for :meth:`indoor_loc.pipeline.stage.Stage.process_batch`. None for
    another type, a run that does not decode in bulk, or one holding a message the adapter rejects."""
    if type_name == "sensor_msgs/msg/Imu":
        imu = decode_imu(datas)
        return None if imu is None else imu_samples(imu)
    if type_name == "sensor_msgs/msg/MagneticField":
        mag = decode_mag(datas)
        return None if mag is None else mag_samples(mag)
    return None


_STAMP = struct.Struct("<iI")


def with_header_stamp(data: bytes, stamp_ns: int) -> bytes | None:
    """A little-endian CDR message that starts with a ``std_msgs/Header`` (``DiagnosticArray``,
    ``Odometry``, ...) with its ``header.stamp`` set to ``stamp_ns``, everything else as it was;
    None if ``data`` is not little-endian CDR or the stamp does not fit ``builtin_interfaces/Time``."""
    if len(data) < 12 or data[:2] != _CDR_LE or not 0 <= stamp_ns <= MAX_STAMP_NS:
        return None
    out = bytearray(data)
    _STAMP.pack_into(out, 4, *divmod(stamp_ns, NS_PER_S))     # sec, nanosec after the 4-byte CDR header
    return bytes(out)


#: message types :func:`bulk_items` decodes
BULK_TYPES = frozenset({"sensor_msgs/msg/Imu", "sensor_msgs/msg/MagneticField"})
