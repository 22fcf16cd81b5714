"""Planar poses <-> geometry_msgs (``wifi/fix``, ``pf/pose`` PoseWithCovarianceStamped; ``pf/particles``
PoseArray).

A WiFi fix has no heading: its orientation is the identity and its yaw variance ``YAW_VAR_UNKNOWN``
(1e6 rad^2), the usual "ignore this axis" value for robot_localization. z/roll/pitch variances are 0
(planar). The x/y block is the fix covariance in m^2.
"""
from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from geometry_msgs.msg import Pose, PoseArray, PoseWithCovarianceStamped

from indoor_loc.errors import InvalidMessageError
from msg_adapters.odom import quat_to_yaw, yaw_to_quat
from msg_adapters.plausible import check, check_cov, check_xyz
from msg_adapters.time import as_matrix, as_vector, require_finite, stamp_from_ns, stamp_to_ns
from indoor_loc.measurements import Fix

YAW_VAR_UNKNOWN = 1e6   # rad^2


class PoseSample(NamedTuple):
    """stamp_ns; xy (2,) metres in ``frame_id``; yaw rad; cov_xy (2, 2) m^2."""
    stamp_ns: int
    xy: np.ndarray
    yaw: float
    cov_xy: np.ndarray
    frame_id: str


def pose_to_msg(stamp_ns: int, xy, yaw: float = 0.0, cov_xy=None, *, frame_id: str = "map",
                yaw_var: float = YAW_VAR_UNKNOWN, z: float = 0.0, z_var: float = 0.0) -> PoseWithCovarianceStamped:
    """A planar PoseWithCovarianceStamped: xy (2,) m, yaw rad, cov_xy (2, 2) m^2 (zeros when None),
    yaw variance ``yaw_var`` rad^2 (1e6 = unknown; a larger one is written as 1e6, the largest the
    contract's ``angle_variance`` bound lets a reader take); ``z`` m (a floor's height) with variance
    ``z_var`` m^2."""
    p = as_vector("xy", xy, 2)
    c = np.zeros((2, 2)) if cov_xy is None else as_matrix("cov_xy", cov_xy, 2)
    require_finite("yaw", float(yaw))
    require_finite("yaw_var", float(yaw_var))
    msg = PoseWithCovarianceStamped()
    msg.header.stamp = stamp_from_ns(stamp_ns)
    msg.header.frame_id = frame_id
    msg.pose.pose.position.x = float(p[0])
    msg.pose.pose.position.y = float(p[1])
    require_finite("z", float(z))
    msg.pose.pose.position.z = float(z)
    msg.pose.pose.orientation = yaw_to_quat(float(yaw))
    full = np.zeros((6, 6))
    full[:2, :2] = c
    full[2, 2] = float(z_var)
    full[5, 5] = min(float(yaw_var), YAW_VAR_UNKNOWN)     # beyond 'unknown' is unknown (the contract's bound)
    msg.pose.covariance = full.ravel().tolist()
    return msg


def fix_to_msg(fix: Fix, frame_id: str = "map") -> PoseWithCovarianceStamped:
    """The PoseWithCovarianceStamped of a WiFi fix (yaw unknown; position.z = the floor's height,
    covariance[14] its variance). A declined fix (``ok=False``) has no position to publish and
    raises InvalidMessageError ``"fix_not_ok"``."""
    if not fix.ok:
        raise InvalidMessageError("fix_not_ok", f"fix declined: {fix.reason}")
    return pose_to_msg(fix.stamp_ns, fix.xy, 0.0, fix.cov, frame_id=frame_id, yaw_var=YAW_VAR_UNKNOWN,
                       z=fix.z, z_var=fix.z_var)


def pose_from_msg(msg: PoseWithCovarianceStamped) -> PoseSample:
    """Validate and unpack a planar pose (``"nan"``, ``"bad_quaternion"``, stamps; ``"out_of_range"``:
    a position beyond ``BOUNDS["map_position"]``; ``"bad_covariance"``: an x/y block not symmetric
    PSD, or an x/y/z variance or the yaw variance out of its bound in :data:`indoor_loc.contract.BOUNDS`)."""
    stamp = stamp_to_ns(msg.header.stamp)
    p = msg.pose.pose.position
    xy = as_vector("pose.position", [p.x, p.y], 2)
    require_finite("pose.position.z", float(p.z))
    check_xyz("pose.position", p.x, p.y, p.z, "map_position")
    yaw = quat_to_yaw(msg.pose.pose.orientation, "pose.orientation")
    full = as_matrix("pose.covariance", msg.pose.covariance, 6)
    cov_xy = full[:2, :2].copy()
    check_cov("pose.covariance (x, y)", cov_xy, "position_variance")
    check("pose.covariance[14] (z variance)", full[2, 2], "position_variance")
    check("pose.covariance[35] (yaw variance)", full[5, 5], "angle_variance")
    return PoseSample(stamp, xy, yaw, cov_xy, msg.header.frame_id)


def fix_from_msg(msg: PoseWithCovarianceStamped, *, frame_id: str | None = None) -> Fix:
    """A :class:`Fix` from a ``wifi/fix`` message (inverse of :func:`fix_to_msg`).

    The x/y covariance must be a symmetric positive-definite 2x2 block (a fix is a Gaussian
    measurement; a negative, singular or asymmetric one would corrupt any filter it reaches): its
    smallest eigenvalue at least ``BOUNDS["fix_variance_min"]`` (1e-6 m²), otherwise
    ``"bad_covariance"``. An asymmetry within float rounding (a covariance computed as
    ``R @ D @ R.T`` or by inversion) is accepted and the block returned symmetrised, as the consumers
    require it exactly. With ``frame_id`` given, a fix in another frame is ``"wrong_frame"`` (it
    cannot be fused in this frame without a transform)."""
    s = pose_from_msg(msg)
    if frame_id is not None and s.frame_id != frame_id:
        raise InvalidMessageError("wrong_frame", f"fix in frame {s.frame_id!r}, expected {frame_id!r}")
    c = s.cov_xy
    a, b, d = float(c[0, 0]), 0.5 * (float(c[0, 1]) + float(c[1, 0])), float(c[1, 1])
    lam_min = 0.5 * (a + d) - math.hypot(0.5 * (a - d), b)          # smallest eigenvalue of the 2x2 block
    check("fix covariance smallest eigenvalue", lam_min, "fix_variance_min")
    return Fix(stamp_ns=s.stamp_ns, xy=s.xy, cov=(c + c.T) / 2, z=float(msg.pose.pose.position.z),
               z_var=float(msg.pose.covariance[14]))


def pose_array_to_msg(stamp_ns: int, xy, yaw=None, *, frame_id: str = "map") -> PoseArray:
    """PoseArray (particle cloud): xy (N, 2) m, yaw (N,) rad or None (identity orientation)."""
    pts = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    require_finite("xy", pts)
    yaws = np.zeros(len(pts)) if yaw is None else np.asarray(yaw, dtype=np.float64)
    if yaws.shape != (len(pts),):
        raise InvalidMessageError("shape", f"yaw: expected shape ({len(pts)},), got {yaws.shape}")
    require_finite("yaw", yaws)
    msg = PoseArray()
    msg.header.stamp = stamp_from_ns(stamp_ns)
    msg.header.frame_id = frame_id
    poses = []
    for (x, y), a in zip(pts.tolist(), yaws.tolist()):
        pose = Pose()
        pose.position.x, pose.position.y = x, y
        pose.orientation = yaw_to_quat(a)
        poses.append(pose)
    msg.poses = poses
    return msg


def pose_array_from_msg(msg: PoseArray) -> tuple[int, np.ndarray, np.ndarray]:
    """(stamp_ns, xy (N, 2) m, yaw (N,) rad) of a PoseArray."""
    stamp = stamp_to_ns(msg.header.stamp)
    xy = np.array([[p.position.x, p.position.y] for p in msg.poses], dtype=np.float64).reshape(-1, 2)
    require_finite("poses", xy)
    yaw = np.array([quat_to_yaw(p.orientation, f"poses[{i}].orientation") for i, p in enumerate(msg.poses)],
                   dtype=np.float64)
    return stamp, xy, yaw
