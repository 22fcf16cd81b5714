"""PUTMC walks -> MCAP bags (messages through ``msg_adapters``, files through ``indoor_loc.bag``).

One bag per walk, namespace ``/walkNN`` (NN = GT number, two digits), log time = header stamp =
the device-boot clock of the files (see :mod:`indoor_loc.datasets.putmc`):

- ``imu/data`` (sensor_msgs/Imu, frame ``walkNN/imu_link``): one message per accelerometer sample,
  carrying the latest orientation sample at or before it (causal, never interpolated forward).
  Orientation = Android rotation vector rotated into the map frame (:func:`putmc.to_map_quat`,
  yaw + ``map_yaw_rad``); orientation_covariance = diag(σ_rp², σ_rp², headingAcc²) with
  σ_rp = :data:`ROLL_PITCH_STD_RAD` (Android reports only a heading accuracy). Samples before
  the first orientation carry none (orientation_covariance[0] = -1). No gyroscope in the data:
  angular_velocity_covariance[0] = -1.
- ``wifi/scan`` (diagnostic_msgs/DiagnosticArray, schema wifi_scan.v1, frame
  ``walkNN/wifi_link``): one per scan, stamped with the scan header time; source "putmc".
- ``ground_truth`` (nav_msgs/Path, frame ``map``, ENU): the true positions of the walk's WiFi
  scans (``positions.map``), each pose stamped with its scan's time. Written once, at the walk's
  first stamp, with latched QoS (transient_local): the time-stamped ground truth a radio-map
  builder or an evaluator uses.
- ``ground_truth/route`` (visualization_msgs/MarkerArray, frame ``map``, latched, written once at
  the first stamp): the GT route graph of ``GT/N/nodes.map`` in ENU — a LINE_LIST marker
  (ns ``ground_truth/route/links``, two points per segment) and a SPHERE_LIST of its nodes
  (ns ``ground_truth/route/nodes``), after DELETEALL markers. It has no timing.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from indoor_loc.bag import BagWriter
from indoor_loc.bag.schemas import qos_dict
from indoor_loc.contract import join_ns
from indoor_loc.datasets.putmc import PUTMC_MAP_YAW_RAD, Route, Walk, causal_index, to_map_quat
from msg_adapters.imu import imu_to_msg
from msg_adapters.markers import graph_markers
from msg_adapters.path import path_to_msg
from msg_adapters.wifi_scan import scan_to_msg

#: Roll/pitch standard deviation written into imu/data, rad: the rotation vector's tilt comes from
#: gravity and is far better than its heading; Android gives no figure, 2° is assumed.
ROLL_PITCH_STD_RAD = math.radians(2.0)
ROUTE_TOPIC = "ground_truth/route"
LATCHED = [qos_dict(reliability="reliable", durability="transient_local", depth=1)]


def walk_bag_counts(walk: Walk) -> dict[str, int]:
    """Messages per relative topic that :func:`write_walk_bag` writes for ``walk``."""
    return {"imu/data": len(walk.acc_t), "wifi/scan": len(walk.scans), "ground_truth": 1, ROUTE_TOPIC: 1}


def write_walk_bag(walk: Walk, route: Route, path: str | Path, *, map_yaw_rad: float = PUTMC_MAP_YAW_RAD,
                   progress=None) -> dict[str, int]:
    """Write one walk's bag (see module doc). ``progress``: optional callable(n) per n IMU
    messages written (e.g. ``tqdm.update``). Returns messages per full topic name."""
    ns = f"/{walk.name}"
    imu_frame, t_imu = f"{walk.name}/imu_link", join_ns(ns, "imu/data")
    t_wifi, t_gt, t_route = join_ns(ns, "wifi/scan"), join_ns(ns, "ground_truth"), join_ns(ns, ROUTE_TOPIC)
    q_map = to_map_quat(walk.quat_xyzw, map_yaw_rad) if len(walk.quat_xyzw) else walk.quat_xyzw
    k = causal_index(walk.acc_t, walk.ori_t)
    rp_var = ROLL_PITCH_STD_RAD ** 2
    t0 = walk.start_ns
    with BagWriter(path) as bag:
        bag.add_topic(t_gt, "nav_msgs/msg/Path", qos_profiles=LATCHED)
        bag.add_topic(t_route, "visualization_msgs/msg/MarkerArray", qos_profiles=LATCHED)
        bag.write(t_gt, path_to_msg(walk.scan_t, walk.scan_xy, None, frame_id="map", stamp_ns=t0), t0)
        bag.write(t_route, graph_markers(route.node_xy, route.links, "map", t0, ns=ROUTE_TOPIC), t0)
        # merge IMU and scans in stamp order (scans after an IMU sample of the same stamp)
        scan_t = walk.scan_t
        j = 0
        n_since = 0
        for i, t in enumerate(walk.acc_t.tolist()):
            while j < len(scan_t) and scan_t[j] < t:
                bag.write(t_wifi, scan_to_msg(walk.scans[j]), int(scan_t[j]))
                j += 1
            if k[i] >= 0:
                cov = np.diag([rp_var, rp_var, float(walk.heading_acc[k[i]]) ** 2])
                msg = imu_to_msg(t, imu_frame, walk.acc[i], None, q_map[k[i]], cov)
            else:
                msg = imu_to_msg(t, imu_frame, walk.acc[i])
            bag.write(t_imu, msg, t)
            n_since += 1
            if progress is not None and n_since >= 2000:
                progress(n_since)
                n_since = 0
        for jj in range(j, len(scan_t)):
            bag.write(t_wifi, scan_to_msg(walk.scans[jj]), int(scan_t[jj]))
        if progress is not None and n_since:
            progress(n_since)
        return dict(bag.topic_counts())
