"""Planar odometry (x, y, yaw) <-> nav_msgs/Odometry (``pdr/odom``).

The 6x6 pose covariance is ordered (x, y, z, roll, pitch, yaw); the planar (x, y, yaw) block sits
at rows/columns (0, 1, 5). z/roll/pitch are fixed (walking on a floor) and get variance 0.
twist.linear.x is the walking speed (m/s, body frame) and twist.angular.z the yaw rate (rad/s);
twist.covariance[0] is the variance of twist.linear.x (m²/s², 0 = not given; for ``pdr/odom`` it
carries the hop's step-count confidence, see indoor_loc/imu/pdr.py), the rest of it 0.
"""
from __future__ import annotations

import math

import numpy as np
from geometry_msgs.msg import Quaternion
from nav_msgs.msg import Odometry

from indoor_loc.contract import BOUNDS
from indoor_loc.errors import InvalidMessageError
from indoor_loc.measurements import OdomPose, PdrInterval, PdrIntervalDecoder, PdrIntervals, pdr_intervals
from msg_adapters.plausible import check, check_cov, check_xyz
from msg_adapters.time import as_matrix, as_vector, require_finite, stamp_from_ns, stamp_to_ns

PLANAR_IDX = (0, 1, 5)          # x, y, yaw in a 6x6 ROS covariance
_PLANAR_FLAT = np.array([6 * i + j for i in PLANAR_IDX for j in PLANAR_IDX])     # their row-major places


def yaw_to_quat(yaw: float) -> Quaternion:
    """Rotation about z by ``yaw`` rad."""
    return Quaternion(x=0.0, y=0.0, z=math.sin(0.5 * yaw), w=math.cos(0.5 * yaw))


def quat_to_yaw(q: Quaternion, what: str = "orientation") -> float:
    """Yaw (rad, in [-pi, pi]) of a quaternion (ZYX convention); rejects a non-unit quaternion."""
    v = as_vector(what, [q.x, q.y, q.z, q.w], 4)
    norm = float(np.linalg.norm(v))
    if abs(norm - 1.0) > 1e-3:
        raise InvalidMessageError("bad_quaternion", f"{what}: |q| = {norm:.6g}, expected 1")
    x, y, z, w = v
    return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def planar_cov_to_6x6(cov3, what: str = "cov_xyyaw") -> list[float]:
    return _planar_cov_36(cov3, what).tolist()


def _planar_cov_36(cov3, what: str = "cov_xyyaw") -> np.ndarray:
    """The (36,) row-major 6x6 covariance holding the planar 3x3 ``cov3`` (validated), zeros elsewhere."""
    full = np.zeros(36)
    full[_PLANAR_FLAT] = as_matrix(what, cov3, 3).ravel()
    return full


def planar_cov_from_6x6(cov36, what: str = "pose.covariance") -> np.ndarray:
    full = as_matrix(what, cov36, 6)
    return full[np.ix_(PLANAR_IDX, PLANAR_IDX)].copy()


def odom_to_msg(stamp_ns: int, frame_id: str, child_frame_id: str, x: float, y: float, yaw: float,
                cov_xyyaw, speed_mps: float, yaw_rate: float, speed_var: float = 0.0,
                yaw_rate_var: float = 0.0) -> Odometry:
    """Build a planar Odometry message (see module doc for the covariance layout);
    ``speed_var`` (m²/s², >= 0) goes to ``twist.covariance[0]`` and ``yaw_rate_var`` (rad²/s², >= 0)
    to ``twist.covariance[35]`` (the rest of it stays 0)."""
    for name, v in (("x", x), ("y", y), ("yaw", yaw), ("speed_mps", speed_mps), ("yaw_rate", yaw_rate),
                    ("speed_var", speed_var), ("yaw_rate_var", yaw_rate_var)):
        require_finite(name, float(v))
    if speed_var < 0 or yaw_rate_var < 0:
        raise InvalidMessageError("bad_covariance", f"twist variances must be >= 0, got {speed_var}, {yaw_rate_var}")
    msg = Odometry()
    msg.header.stamp = stamp_from_ns(stamp_ns)
    msg.header.frame_id = frame_id
    msg.child_frame_id = child_frame_id
    msg.pose.pose.position.x = float(x)
    msg.pose.pose.position.y = float(y)
    msg.pose.pose.orientation = yaw_to_quat(float(yaw))
    msg.pose.covariance = _planar_cov_36(cov_xyyaw)
    msg.twist.twist.linear.x = float(speed_mps)
    msg.twist.twist.angular.z = float(yaw_rate)
    msg.twist.covariance[0] = float(speed_var)
    msg.twist.covariance[35] = float(yaw_rate_var)
    return msg


#: the variances of the planar (x, y, yaw) covariance, by their bounds in the contract
PLANAR_VAR_BOUNDS = ("position_variance", "position_variance", "angle_variance")


def odom_from_msg(msg: Odometry, *, unknown_cov: bool = False) -> OdomPose:
    """Validate and unpack a planar Odometry message (``"nan"``, ``"bad_quaternion"``, stamps;
    ``"out_of_range"``: a position, walking speed or yaw rate beyond :data:`indoor_loc.contract.BOUNDS`;
    ``"bad_covariance"``: a planar (x, y, yaw) covariance not symmetric PSD or with a variance out
    of bounds, or a negative or huge ``twist.covariance[0]`` / ``[35]``). ``unknown_cov``: a robot
    driver's convention that ``covariance[0] = -1`` means "not given" (REP 103 / sensor_msgs) is
    accepted for the pose and the twist covariance, and such a covariance comes back as zeros."""
    stamp = stamp_to_ns(msg.header.stamp)
    p = msg.pose.pose.position
    require_finite("pose.position", [p.x, p.y, p.z])
    check_xyz("pose.position", p.x, p.y, p.z, "odom_position")
    yaw = quat_to_yaw(msg.pose.pose.orientation, "pose.orientation")
    if unknown_cov and msg.pose.covariance[0] == -1.0:
        cov = np.zeros((3, 3))
    else:
        cov = planar_cov_from_6x6(msg.pose.covariance)
        check_cov("pose.covariance (x, y, yaw)", cov, PLANAR_VAR_BOUNDS)
    t = msg.twist.twist
    require_finite("twist", [t.linear.x, t.linear.y, t.linear.z, t.angular.x, t.angular.y, t.angular.z])
    check("twist.linear.x", t.linear.x, "odom_speed")
    check("twist.angular.z", t.angular.z, "odom_yaw_rate")
    require_finite("twist.covariance", msg.twist.covariance)
    if not (unknown_cov and msg.twist.covariance[0] == -1.0):
        check("twist.covariance[0]", msg.twist.covariance[0], "rate_variance")
        check("twist.covariance[35]", msg.twist.covariance[35], "rate_variance")
    tc0, tc35 = float(msg.twist.covariance[0]), float(msg.twist.covariance[35])
    return OdomPose(stamp, float(p.x), float(p.y), yaw, cov, float(t.linear.x), float(t.angular.z),
                    msg.header.frame_id, msg.child_frame_id, max(tc0, 0.0), max(tc35, 0.0))


class OdomJumpGuard:
    """Refuses an odometry pose implausibly far from the last one accepted on its stream
    (``"odom_jump"``): farther than ``BOUNDS["odom_jump"].hi`` m plus ``BOUNDS["odom_speed"].hi``
    m/s times the stamp difference. :meth:`check` changes nothing; the stage calls :meth:`accept`
    once it has taken the pose, so a refused pose never becomes the reference. An upstream known to
    have restarted (:meth:`restart`: a new publisher, its sequence numbers anew) starts a new
    odometry frame: its first pose is taken whatever the distance; a restart nobody saw (back at its
    origin) is taken once the stamps allow the distance."""

    def __init__(self) -> None:
        self.last: tuple[int, float, float] | None = None     # stamp_ns, x, y of the last accepted pose

    def check(self, od: OdomPose) -> None:
        if self.last is None:
            return
        t, x, y = self.last
        d = math.hypot(od.x - x, od.y - y)
        allowed = BOUNDS["odom_jump"].hi + BOUNDS["odom_speed"].hi * abs(od.stamp_ns - t) * 1e-9
        if d > allowed:
            raise InvalidMessageError("odom_jump", f"pose ({od.x:.6g}, {od.y:.6g}) m is {d:.6g} m from the previous "
                                                   f"accepted ({x:.6g}, {y:.6g}) m, {(od.stamp_ns - t) * 1e-9:.3g} s "
                                                   f"before: more than the {allowed:.6g} m a walker can cover")

    def accept(self, od: OdomPose) -> None:
        self.last = (od.stamp_ns, od.x, od.y)

    def restart(self) -> None:
        """The odometry's producer restarted: its next pose is the first of a new frame."""
        self.last = None


class PdrOdomReader:
    """The one ``pdr/odom`` decoder: messages -> :class:`~indoor_loc.measurements.PdrInterval`
    (validation here, the arithmetic in :class:`~indoor_loc.measurements.PdrIntervalDecoder`).

    ``step_length_m`` is the nominal step length the PDR producer used (steps = distance / it)."""

    def __init__(self, step_length_m: float) -> None:
        self.decoder = PdrIntervalDecoder(step_length_m)
        self.guard = OdomJumpGuard()

    @property
    def last_stamp_ns(self) -> int | None:
        return self.decoder.last_stamp_ns

    def restart(self) -> None:
        """The odometry's producer restarted (a new frame from its origin): the next pose closes no
        interval (the hop across the restart is unknown) and is taken whatever its distance."""
        self.guard.restart()
        self.decoder.reset()

    def read(self, msg: Odometry) -> tuple[OdomPose, PdrInterval | None]:
        """Validate one message; returns it unpacked and the interval it closes (None for the first).
        Raises :class:`InvalidMessageError` (the reader is then unchanged), also ``"odom_jump"``
        (:class:`OdomJumpGuard`)."""
        od = odom_from_msg(msg)
        last = self.decoder.last_stamp_ns
        if last is not None and od.stamp_ns <= last:
            raise InvalidMessageError("non_monotonic_stamp", f"pdr/odom stamp {od.stamp_ns} <= previous {last}")
        self.guard.check(od)
        interval = self.decoder.update(od.stamp_ns, od.x, od.y, od.yaw, od.cov)
        self.guard.accept(od)
        return od, interval


def pdr_intervals_from_msgs(msgs: list[Odometry], step_length_m: float) -> PdrIntervals:
    """A whole ``pdr/odom`` stream -> intervals as arrays (the batch path of :class:`PdrOdomReader`)."""
    ods = [odom_from_msg(m) for m in msgs]
    return pdr_intervals(np.array([o.stamp_ns for o in ods], np.int64),
                         np.array([(o.x, o.y) for o in ods], float).reshape(-1, 2),
                         np.array([o.yaw for o in ods], float),
                         np.array([o.cov for o in ods], float).reshape(-1, 3, 3), step_length_m=step_length_m)
