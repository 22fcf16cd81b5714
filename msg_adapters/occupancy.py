"""Occupancy grids (nav2 map_server's values) -> nav_msgs/OccupancyGrid (``/map``)."""
from __future__ import annotations

import math

import numpy as np
from nav_msgs.msg import OccupancyGrid

from indoor_loc.errors import InvalidMessageError
from msg_adapters.time import stamp_from_ns


def occupancy_to_msg(cells, resolution_m: float, origin_xy_yaw, *, z: float = 0.0, frame_id: str = "map",
                     stamp_ns: int = 0) -> OccupancyGrid:
    """``cells`` (H, W) int8 (-1 unknown, 0 free .. 100 occupied), row 0 at the origin (bottom-up, the
    message's row-major layout); ``resolution_m`` m/cell; ``origin_xy_yaw`` (x, y, yaw) of cell (0, 0)'s
    corner in ``frame_id``; ``z`` the floor's height (m)."""
    a = np.asarray(cells)
    if a.ndim != 2 or a.size == 0:
        raise InvalidMessageError("shape", f"cells: expected a non-empty (H, W) array, got shape {a.shape}")
    if np.any((a < -1) | (a > 100)):
        raise InvalidMessageError("occupancy_range", "cells: expected values in -1..100")
    if not (resolution_m > 0 and math.isfinite(resolution_m)) or not all(math.isfinite(v) for v in origin_xy_yaw):
        raise InvalidMessageError("nan", "resolution_m > 0 and a finite origin expected")
    msg = OccupancyGrid()
    msg.header.frame_id = frame_id
    msg.header.stamp = stamp_from_ns(int(stamp_ns))
    msg.info.map_load_time = msg.header.stamp
    msg.info.resolution = float(resolution_m)
    msg.info.height, msg.info.width = (int(n) for n in a.shape)
    x, y, yaw = (float(v) for v in origin_xy_yaw)
    msg.info.origin.position.x, msg.info.origin.position.y, msg.info.origin.position.z = x, y, float(z)
    msg.info.origin.orientation.z, msg.info.origin.orientation.w = math.sin(yaw / 2), math.cos(yaw / 2)
    msg.data = a.astype(np.int8).ravel().tobytes()
    return msg
