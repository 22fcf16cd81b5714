"""sensor_msgs/Imu and sensor_msgs/MagneticField <-> arrays (REP 145 conventions).

A covariance whose first element is -1 marks the field as absent (REP 145): ``imu/data_raw`` has
``orientation_covariance[0] = -1``; an accelerometer-only IMU has ``angular_velocity_covariance[0] = -1``.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np
from geometry_msgs.msg import Quaternion, Vector3
from sensor_msgs.msg import Imu, MagneticField

from indoor_loc.errors import InvalidMessageError
from msg_adapters.plausible import check_cov, check_xyz
from msg_adapters.time import as_matrix, as_vector, require_len, stamp_from_ns, stamp_to_ns

#: |‖q‖ - 1| above this rejects an orientation as ``"bad_quaternion"``.
QUAT_NORM_TOL = 1e-3


class ImuSample(NamedTuple):
    """One IMU reading.

    acc: specific force incl. gravity, m/s^2, (3,); gyro: angular rate, rad/s, (3,) or None;
    quat_xyzw: orientation sensor->frame, (4,) or None; orientation_cov: (3, 3) rad^2 (roll, pitch,
    yaw) or None when there is no orientation.
    """
    stamp_ns: int
    frame_id: str
    acc: np.ndarray
    gyro: np.ndarray | None
    quat_xyzw: np.ndarray | None
    orientation_cov: np.ndarray | None


def _check_quat(what: str, q: np.ndarray) -> None:
    norm = float(np.linalg.norm(q))
    if abs(norm - 1.0) > QUAT_NORM_TOL:
        raise InvalidMessageError("bad_quaternion", f"{what}: |q| = {norm:.6g}, expected 1")


def imu_from_msg(msg: Imu) -> ImuSample:
    """Validate and unpack an Imu message (``"nan"``, ``"negative_stamp"``, ``"bad_quaternion"``;
    ``"out_of_range"`` for an acceleration or rate beyond :data:`indoor_loc.contract.BOUNDS`,
    ``"bad_covariance"`` for an orientation covariance that is not symmetric PSD with variances in
    [0, 1e6] rad²). The acceleration and rate covariances are not used: only finite."""
    stamp = stamp_to_ns(msg.header.stamp)
    a = msg.linear_acceleration
    acc = as_vector("linear_acceleration", [a.x, a.y, a.z], 3)
    check_xyz("linear_acceleration", a.x, a.y, a.z, "acceleration")
    require_len("linear_acceleration_covariance", msg.linear_acceleration_covariance, 9)
    gyro = None
    if msg.angular_velocity_covariance[0] != -1.0:
        w = msg.angular_velocity
        gyro = as_vector("angular_velocity", [w.x, w.y, w.z], 3)
        check_xyz("angular_velocity", w.x, w.y, w.z, "angular_rate")
        require_len("angular_velocity_covariance", msg.angular_velocity_covariance, 9)
    quat = cov = None
    if msg.orientation_covariance[0] != -1.0:
        o = msg.orientation
        quat = as_vector("orientation", [o.x, o.y, o.z, o.w], 4)
        _check_quat("orientation", quat)
        cov = as_matrix("orientation_covariance", msg.orientation_covariance, 3)
        check_cov("orientation_covariance", cov, "angle_variance")
    return ImuSample(stamp, msg.header.frame_id, acc, gyro, quat, cov)


def imu_to_msg(stamp_ns: int, frame_id: str, acc, gyro=None, quat_xyzw=None, orientation_cov=None) -> Imu:
    """Build an Imu message; absent gyro/orientation get covariance[0] = -1 (REP 145).

    acc (3,) m/s^2; gyro (3,) rad/s; quat_xyzw (4,) unit; orientation_cov (3, 3) rad^2 (zeros =
    unknown, per sensor_msgs) — used only with an orientation.
    """
    msg = Imu()
    msg.header.stamp = stamp_from_ns(stamp_ns)
    msg.header.frame_id = frame_id
    a = as_vector("acc", acc, 3)
    msg.linear_acceleration = Vector3(x=float(a[0]), y=float(a[1]), z=float(a[2]))
    if gyro is None:
        msg.angular_velocity_covariance[0] = -1.0
    else:
        g = as_vector("gyro", gyro, 3)
        msg.angular_velocity = Vector3(x=float(g[0]), y=float(g[1]), z=float(g[2]))
    if quat_xyzw is None:
        msg.orientation_covariance[0] = -1.0
    else:
        q = as_vector("quat_xyzw", quat_xyzw, 4)
        _check_quat("quat_xyzw", q)
        msg.orientation = Quaternion(x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3]))
        if orientation_cov is not None:
            c = as_matrix("orientation_cov", orientation_cov, 3)
            if c[0, 0] == -1.0:
                raise InvalidMessageError("bad_covariance",
                                          "orientation_cov[0, 0] = -1 would mark the orientation absent")
            msg.orientation_covariance = c.ravel().tolist()
    return msg


def mag_from_msg(msg: MagneticField) -> tuple[int, np.ndarray]:
    """(stamp_ns, magnetic field in tesla (3,), sensor frame); ``"out_of_range"`` beyond 5 mT per axis."""
    stamp = stamp_to_ns(msg.header.stamp)
    f = msg.magnetic_field
    field_t = as_vector("magnetic_field", [f.x, f.y, f.z], 3)
    check_xyz("magnetic_field", f.x, f.y, f.z, "magnetic_field")
    require_len("magnetic_field_covariance", msg.magnetic_field_covariance, 9)
    return stamp, field_t


def mag_to_msg(stamp_ns: int, frame_id: str, field_T) -> MagneticField:  # noqa: N803 - unit in the name
    """MagneticField from a (3,) field in tesla (covariance zeros = unknown)."""
    msg = MagneticField()
    msg.header.stamp = stamp_from_ns(stamp_ns)
    msg.header.frame_id = frame_id
    f = as_vector("field_T", field_T, 3)
    msg.magnetic_field = Vector3(x=float(f[0]), y=float(f[1]), z=float(f[2]))
    return msg
