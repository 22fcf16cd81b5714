"""``initialpose`` / ``set_pose`` (geometry_msgs/PoseWithCovarianceStamped) -> the pose an estimator
restarts at, with its x/y covariance honoured.

RViz's *2D Pose Estimate* sends x/y variances 0.25 m² (and yaw 0.07 rad²); a message whose x/y block is
not positive definite (all zeros: a script that left it unset) gets :data:`DEFAULT_COV` (0.5 m standard
deviation per axis, RViz's own), never a zero-width prior. Validation as every pose
(:func:`msg_adapters.pose.pose_from_msg`: ``nan``, ``bad_quaternion``, ``bad_covariance``, stamps).
A stamp of 0 (a command, not a measurement) is returned as 0: the stage puts it at its newest input.
"""
from __future__ import annotations

import numpy as np
from geometry_msgs.msg import PoseWithCovarianceStamped

from indoor_loc.errors import InvalidMessageError
from indoor_loc.measurements import Fix
from msg_adapters.pose import pose_from_msg

DEFAULT_COV = np.eye(2) * 0.25


def initial_pose_from_msg(msg: PoseWithCovarianceStamped, frame_id: str = "map") -> Fix:
    """The initial pose as a :class:`Fix` (``xy``, ``cov`` m², ``z`` m; ``info["yaw"]`` rad, and
    ``info["yaw_var"]`` rad²); ``"wrong_frame"`` when not in ``frame_id``."""
    ps = pose_from_msg(msg)
    if ps.frame_id and ps.frame_id != frame_id:
        raise InvalidMessageError("wrong_frame", f"initial pose in frame {ps.frame_id!r}, expected {frame_id!r}")
    cov = np.asarray(ps.cov_xy, float)
    cov = 0.5 * (cov + cov.T)
    if not np.all(np.linalg.eigvalsh(cov) > 1e-9):
        cov = DEFAULT_COV.copy()
    return Fix(ps.stamp_ns, np.asarray(ps.xy, float), cov, z=float(msg.pose.pose.position.z),
               info={"yaw": float(ps.yaw), "yaw_var": float(msg.pose.covariance[35])})
