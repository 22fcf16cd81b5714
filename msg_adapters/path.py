"""Time-stamped planar trajectories <-> nav_msgs/Path (``ground_truth``, back-end paths)."""
from __future__ import annotations

import numpy as np
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Path

from indoor_loc.errors import InvalidMessageError
from msg_adapters.odom import quat_to_yaw, yaw_to_quat
from msg_adapters.time import require_finite, stamp_from_ns, stamp_to_ns


def path_to_msg(stamps_ns, xy, yaw=None, frame_id: str = "map", stamp_ns: int | None = None,
                z=0.0) -> Path:
    """Path of N poses: stamps_ns (N,) int ns, xy (N, 2) m, yaw (N,) rad or None (identity);
    ``z`` (m) for every pose, or one per pose (N,) (a floor's height on multi-storey maps).

    The Path header stamp is ``stamp_ns``, or the last pose stamp (0 for an empty path).
    """
    stamps = np.asarray(stamps_ns)
    pts = np.asarray(xy, dtype=np.float64)
    n = stamps.shape[0] if stamps.ndim == 1 else -1
    if stamps.ndim != 1 or (stamps.size and not np.issubdtype(stamps.dtype, np.integer)):
        raise InvalidMessageError("shape", f"stamps_ns: expected a 1-D int array, got {stamps.dtype} {stamps.shape}")
    if pts.size == 0 and n == 0:
        pts = pts.reshape(0, 2)
    if pts.shape != (n, 2):
        raise InvalidMessageError("shape", f"xy: expected shape ({n}, 2), got {pts.shape}")
    require_finite("xy", pts)
    yaws = None
    if yaw is not None:
        yaws = np.asarray(yaw, dtype=np.float64)
        if yaws.shape != (n,):
            raise InvalidMessageError("shape", f"yaw: expected shape ({n},), got {yaws.shape}")
        require_finite("yaw", yaws)
    zs = np.broadcast_to(np.asarray(z, dtype=np.float64), (n,)) if np.ndim(z) == 0 else np.asarray(z, dtype=np.float64)
    if zs.shape != (n,):
        raise InvalidMessageError("shape", f"z: expected a float or shape ({n},), got {zs.shape}")
    require_finite("z", zs)
    msg = Path()
    last = int(stamps[-1]) if n else 0
    msg.header.stamp = stamp_from_ns(last if stamp_ns is None else int(stamp_ns))
    msg.header.frame_id = frame_id
    poses = []
    for i in range(n):
        ps = PoseStamped()
        ps.header.stamp = stamp_from_ns(int(stamps[i]))
        ps.header.frame_id = frame_id
        ps.pose.position.x = float(pts[i, 0])
        ps.pose.position.y = float(pts[i, 1])
        ps.pose.position.z = float(zs[i])
        if yaws is not None:
            ps.pose.orientation = yaw_to_quat(float(yaws[i]))
        poses.append(ps)
    msg.poses = poses
    return msg


def path_from_msg(msg: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(stamps_ns (N,) int64, xy (N, 2) m, yaw (N,) rad) of a Path (validated)."""
    stamp_to_ns(msg.header.stamp)
    n = len(msg.poses)
    stamps = np.empty(n, dtype=np.int64)
    xy = np.empty((n, 2), dtype=np.float64)
    yaw = np.empty(n, dtype=np.float64)
    for i, ps in enumerate(msg.poses):
        stamps[i] = stamp_to_ns(ps.header.stamp)
        xy[i] = (ps.pose.position.x, ps.pose.position.y)
        yaw[i] = quat_to_yaw(ps.pose.orientation, f"poses[{i}].orientation")
    require_finite("poses", xy)
    return stamps, xy, yaw
