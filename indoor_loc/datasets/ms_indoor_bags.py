"""Microsoft indoor-location traces -> MCAP bags (messages through ``msg_adapters``).

One bag per walk, namespace ``/<floor>_<trace id>`` lower-case (e.g. ``/b1_5dc8cea7659e181adb076a3f``;
a ROS name cannot start with a digit), log time = header stamp = the trace's Unix time in ns:

- ``imu/data_raw`` (sensor_msgs/Imu, frame ``<ns>/imu_link``): one per calibrated accelerometer
  sample, with the latest gyroscope sample at or before it (none yet: covariance[0] = -1);
  no orientation (orientation_covariance[0] = -1, REP 145).
- ``imu/mag`` (sensor_msgs/MagneticField): the calibrated magnetometer, µT -> T.
- ``imu/data`` (sensor_msgs/Imu): one per rotation-vector sample, orientation = Android's rotation
  vector (device -> ENU, magnetic north), with the latest accelerometer/gyroscope sample;
  orientation_covariance = diag(σ_rp², σ_rp², σ_yaw²) with σ_rp = 2°, σ_yaw = 10° (Android reports
  no figure in these files).
- ``wifi/scan`` (schema ``wifi_scan.v1``, frame ``<ns>/wifi_link``): one per scan with ``age_ms``.
- ``ble/scan`` (schema ``ble_scan.v1``, frame ``<ns>/ble_link``): one per ``TYPE_BEACON`` time
  (:mod:`indoor_loc.datasets.ms_indoor_ble`), ``tx_power_dbm`` the advertised power at 1 m.
- ``ground_truth`` (nav_msgs/Path, frame ``map``, latched, written once at the first stamp): the
  waypoints, stamped, z = the floor's height (positions between waypoints are linear in time); not
  written for a walk with fewer than two waypoints (no span to interpolate over).
"""
from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np

from indoor_loc.bag import BagWriter
from indoor_loc.bag.schemas import qos_dict
from indoor_loc.contract import join_ns
from indoor_loc.datasets.ms_indoor import Trace
from msg_adapters.imu import imu_to_msg, mag_to_msg
from msg_adapters.path import path_to_msg
from msg_adapters.ble_scan import ble_to_msg
from msg_adapters.wifi_scan import scan_to_msg

ROLL_PITCH_STD_RAD = math.radians(2.0)
YAW_STD_RAD = math.radians(10.0)
LATCHED = [qos_dict(reliability="reliable", durability="transient_local", depth=1)]


def walk_namespace(trace: Trace, floor: str | None = None) -> str:
    """``/<floor>_<id>`` lower-case, ``floor`` the site's name of the walk's floor (default: the trace
    header's ``FloorName``). Characters a ROS name cannot hold become ``_`` and a floor part not
    starting with a letter (``1F``) is prefixed ``floor_``, so every floor name gives a valid name."""
    part = re.sub(r"_+", "_", re.sub(r"[^a-z0-9_]", "_", (floor if floor is not None else trace.floor).lower()))
    part = part.strip("_")
    if not part[:1].isalpha():
        part = f"floor_{part}".rstrip("_")
    return f"/{part}_{re.sub(r'[^a-z0-9_]', '_', trace.trace_id.lower())}"


def _causal(t_query: np.ndarray, t_ref: np.ndarray) -> np.ndarray:
    return np.searchsorted(t_ref, t_query, side="right") - 1


def trace_bag_counts(trace: Trace) -> dict[str, int]:
    """Messages per relative topic that :func:`write_trace_bag` writes."""
    return {"imu/data_raw": len(trace.acc), "imu/mag": len(trace.mag), "imu/data": len(trace.rotvec),
            "wifi/scan": len(trace.scans), "ble/scan": len(trace.ble), "ground_truth": int(len(trace.waypoint_t) > 1)}


def write_trace_bag(trace: Trace, path: str | Path, *, z_m: float = 0.0, floor: str | None = None
                    ) -> dict[str, int]:
    """Write one walk's bag (see module doc; ``floor`` names the namespace, :func:`walk_namespace`);
    returns messages per full topic name."""
    ns = walk_namespace(trace, floor)
    name = ns.strip("/")
    imu_frame, wifi_frame = f"{name}/imu_link", f"{name}/wifi_link"
    t_raw, t_mag, t_imu = join_ns(ns, "imu/data_raw"), join_ns(ns, "imu/mag"), join_ns(ns, "imu/data")
    t_wifi, t_gt, t_ble = join_ns(ns, "wifi/scan"), join_ns(ns, "ground_truth"), join_ns(ns, "ble/scan")
    acc, gyro, mag, rv = trace.acc, trace.gyro, trace.mag, trace.rotvec
    g_of_a = _causal(acc.t_ns, gyro.t_ns)
    a_of_r = _causal(rv.t_ns, acc.t_ns)
    g_of_r = _causal(rv.t_ns, gyro.t_ns)
    quat = trace.quaternions_xyzw() if len(rv) else np.zeros((0, 4))
    ori_cov = np.diag([ROLL_PITCH_STD_RAD ** 2, ROLL_PITCH_STD_RAD ** 2, YAW_STD_RAD ** 2])
    # (stamp, kind order, kind, index): one merged stream in stamp order
    events = [(acc.t_ns, 0), (mag.t_ns, 1), (rv.t_ns, 2), (np.array([s.stamp_ns for s in trace.scans], np.int64), 3),
              (np.array([s.stamp_ns for s in trace.ble], np.int64), 4)]
    stamps = np.concatenate([e[0] for e in events]) if events else np.zeros(0, np.int64)
    kinds = np.concatenate([np.full(len(e[0]), e[1], np.int8) for e in events])
    idx = np.concatenate([np.arange(len(e[0])) for e in events])
    order = np.lexsort((kinds, stamps))
    with BagWriter(path) as bag:
        if len(trace.waypoint_t) > 1:          # one waypoint spans no time: no truth to interpolate
            t0 = int(min(trace.start_ns, trace.waypoint_t[0]))
            bag.add_topic(t_gt, "nav_msgs/msg/Path", qos_profiles=LATCHED)
            bag.write(t_gt, path_to_msg(trace.waypoint_t, trace.waypoint_xy, None, frame_id="map", stamp_ns=t0,
                                        z=z_m), t0)
        for o in order.tolist():
            k, i, t = int(kinds[o]), int(idx[o]), int(stamps[o])
            if k == 0:
                j = g_of_a[i]
                bag.write(t_raw, imu_to_msg(t, imu_frame, acc.values[i, :3],
                                            gyro.values[j, :3] if j >= 0 else None), t)
            elif k == 1:
                bag.write(t_mag, mag_to_msg(t, imu_frame, mag.values[i, :3] * 1e-6), t)
            elif k == 2:
                ja = a_of_r[i]
                if ja < 0:
                    continue            # no acceleration yet: an Imu message needs one
                jg = g_of_r[i]
                bag.write(t_imu, imu_to_msg(t, imu_frame, acc.values[ja, :3],
                                            gyro.values[jg, :3] if jg >= 0 else None, quat[i], ori_cov), t)
            elif k == 3:
                scan = trace.scans[i]
                bag.write(t_wifi, scan_to_msg(_with_frame(scan, wifi_frame, "ms_indoor")), t)
            else:
                bag.write(t_ble, ble_to_msg(_with_frame(trace.ble[i], f"{name}/ble_link", "ms_indoor")), t)
        return dict(bag.topic_counts())


def _with_frame(scan, frame_id: str, source: str):
    from dataclasses import replace
    return replace(scan, frame_id=frame_id, source=source)
