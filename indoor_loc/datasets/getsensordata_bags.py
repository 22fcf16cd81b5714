"""GetSensorData logs -> MCAP bags in the message contract, ground truth and radio-map fingerprints.

One bag per log, namespace ``/<log name>`` (lower case, ``_`` for what a ROS name cannot hold), log time =
header stamp = ``t0 + AppTimestamp`` (ns; :attr:`GsdLog.t0_ns`, the header's creation date):

- ``imu/data_raw`` (sensor_msgs/Imu, frame ``<ns>/imu_link``): one per ``ACCE`` sample stamped on its
  sensor clock aligned to the app clock, with the latest ``GYRO`` sample at or before it (none yet, or no
  gyroscope: angular_velocity_covariance[0] = -1); no orientation (REP 145).
- ``imu/mag`` (sensor_msgs/MagneticField): ``MAGN``, µT -> T.
- ``imu/data`` (sensor_msgs/Imu): one per ``AHRS`` sample, orientation = the logged rotation vector
  (device -> ENU, magnetic north) with the latest acceleration and rate; orientation_covariance diag(2°, 2°,
  10°)² (the log gives no figure).
- ``baro/pressure`` (sensor_msgs/FluidPressure): ``PRES``, hPa -> Pa, variance 0 (unknown).
- ``wifi/scan`` (``wifi_scan.v1``, frame ``<ns>/wifi_link``) and ``ble/scan`` (``ble_scan.v1``, frame
  ``<ns>/ble_link``): :func:`~indoor_loc.datasets.getsensordata.wifi_scans`, ``ble_scans``.
- ``ground_truth`` (nav_msgs/Path, frame ``map``, latched, written once at the first stamp): the ``POSI``
  reference points, stamped, in the local ENU map frame (:mod:`indoor_loc.datasets.geodesy`), z = floor
  id × storey height; not written with fewer than two points.
"""
from __future__ import annotations

import math
import re
from collections import Counter
from dataclasses import replace
from pathlib import Path
from typing import Sequence

import numpy as np

from indoor_loc.bag import BagWriter
from indoor_loc.bag.schemas import qos_dict
from indoor_loc.contract import join_ns
from indoor_loc.datasets.geodesy import geodetic_to_enu
from indoor_loc.datasets.getsensordata import GsdLog, ble_scans, rotation_quaternions, wifi_scans
from indoor_loc.errors import InvalidMessageError
from indoor_loc.wifi.ble import BleScan
from indoor_loc.wifi.types import WifiScan

ROLL_PITCH_STD_RAD = math.radians(2.0)
YAW_STD_RAD = math.radians(10.0)
LATCHED = [qos_dict(reliability="reliable", durability="transient_local", depth=1)]


def log_name(path: Path) -> str:
    """The log's file name without ``.txt`` / ``.txt.gz`` / ``.log``."""
    name = Path(path).name
    for suf in (".txt.gz", ".log.gz", ".gz", ".txt", ".log", ".csv"):
        if name.lower().endswith(suf):
            return name[: -len(suf)]
    return name


def log_namespace(path: Path) -> str:
    """``/<log name>`` as a valid ROS namespace (lower case; a leading digit gets ``log_``)."""
    part = re.sub(r"_+", "_", re.sub(r"[^a-z0-9_]", "_", log_name(path).lower())).strip("_") or "log"
    if not part[:1].isalpha():
        part = f"log_{part}"
    return f"/{part}"


def truth_of(log: GsdLog, origin: tuple[float, float], storey_height_m: float
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(stamps ns (K,), xy (K, 2) m ENU, z (K,) m, floor (K,) int) of the log's reference points."""
    p = log.posi
    xy = geodetic_to_enu(p.lat, p.lon, *origin) if len(p) else np.zeros((0, 2))
    return log.ns(p.app_s), xy, p.floor.astype(float) * storey_height_m, p.floor.copy()


def positions_at(stamps_ns: Sequence[int], truth_t: np.ndarray, truth_xy: np.ndarray, truth_floor: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Positions interpolated linearly in time between reference points: (xy (N, 2), floor (N,), ok (N,)).
    Not ok: outside the reference span, or between two points on different floors (the walker changed
    floor somewhere between them: the floor of a scan there is unknown)."""
    t = np.asarray(stamps_ns, np.int64)
    xy = np.full((len(t), 2), np.nan)
    floor = np.zeros(len(t), np.int64)
    ok = np.zeros(len(t), bool)
    if len(truth_t) < 2:
        return xy, floor, ok
    inside = (t >= truth_t[0]) & (t <= truth_t[-1])
    k = np.clip(np.searchsorted(truth_t, t, side="right") - 1, 0, len(truth_t) - 2)
    same = truth_floor[k] == truth_floor[k + 1]
    exact = np.isin(t, truth_t)
    ok = inside & (same | exact)
    tr = (t - truth_t[0]).astype(float)
    pr = (truth_t - truth_t[0]).astype(float)
    for c in range(2):
        xy[ok, c] = np.interp(tr[ok], pr, truth_xy[:, c])
    at = np.searchsorted(truth_t, t)
    floor[ok] = np.where(exact[ok], truth_floor[np.clip(at[ok], 0, len(truth_t) - 1)], truth_floor[k[ok]])
    return xy, floor, ok


def _causal(t_query: np.ndarray, t_ref: np.ndarray) -> np.ndarray:
    return np.searchsorted(t_ref, t_query, side="right") - 1


def write_log_bag(log: GsdLog, path: str | Path, *, origin: tuple[float, float], storey_height_m: float,
                  namespace: str | None = None, scans: list[WifiScan] | None = None,
                  bles: list[BleScan] | None = None) -> dict[str, int]:
    """Write one log's bag (module doc); returns messages per full topic name."""
    from msg_adapters.ble_scan import ble_to_msg
    from msg_adapters.pressure import pressure_to_msg
    from msg_adapters.imu import imu_to_msg, mag_to_msg
    from msg_adapters.path import path_to_msg
    from msg_adapters.wifi_scan import scan_to_msg

    ns = namespace or log_namespace(log.path)
    name = ns.strip("/")
    imu_frame, wifi_frame, ble_frame = f"{name}/imu_link", f"{name}/wifi_link", f"{name}/ble_link"
    topics = {k: join_ns(ns, k) for k in ("imu/data_raw", "imu/mag", "imu/data", "baro/pressure", "wifi/scan",
                                          "ble/scan", "ground_truth")}
    acc, gyr, mag, pres, ahrs = (log.sensors.get(k) for k in ("ACCE", "GYRO", "MAGN", "PRES", "AHRS"))
    t_acc = log.ns(acc.stamp_s) if acc is not None else np.zeros(0, np.int64)
    t_gyr = log.ns(gyr.stamp_s) if gyr is not None else np.zeros(0, np.int64)
    t_mag = log.ns(mag.stamp_s) if mag is not None else np.zeros(0, np.int64)
    t_pres = log.ns(pres.stamp_s) if pres is not None else np.zeros(0, np.int64)
    t_ahrs = log.ns(ahrs.stamp_s) if ahrs is not None else np.zeros(0, np.int64)
    scans = wifi_scans(log)[0] if scans is None else scans
    bles = ble_scans(log) if bles is None else bles
    g_of_a = _causal(t_acc, t_gyr)
    a_of_r, g_of_r = _causal(t_ahrs, t_acc), _causal(t_ahrs, t_gyr)
    quat = rotation_quaternions(ahrs) if ahrs is not None else np.zeros((0, 4))
    ori_cov = np.diag([ROLL_PITCH_STD_RAD ** 2, ROLL_PITCH_STD_RAD ** 2, YAW_STD_RAD ** 2])
    streams = [t_acc, t_mag, t_ahrs, t_pres, np.array([s.stamp_ns for s in scans], np.int64),
               np.array([s.stamp_ns for s in bles], np.int64)]
    stamps = np.concatenate(streams)
    kinds = np.concatenate([np.full(len(s), k, np.int8) for k, s in enumerate(streams)])
    idx = np.concatenate([np.arange(len(s)) for s in streams])
    order = np.lexsort((kinds, stamps))
    with BagWriter(path) as bag:
        tt, xy, z, _fl = truth_of(log, origin, storey_height_m)
        if len(tt) > 1:
            t0 = int(min(tt[0], stamps.min() if len(stamps) else tt[0]))
            msg = path_to_msg(tt, xy, None, frame_id="map", stamp_ns=t0)
            for ps, zz in zip(msg.poses, z.tolist()):
                ps.pose.position.z = float(zz)
            bag.add_topic(topics["ground_truth"], "nav_msgs/msg/Path", qos_profiles=LATCHED)
            bag.write(topics["ground_truth"], msg, t0)

        def message(k: int, i: int, t: int):
            """The message of stream ``k``'s sample ``i`` (InvalidMessageError: outside the contract)."""
            if k == 0:
                assert acc is not None
                j = g_of_a[i]
                return imu_to_msg(t, imu_frame, acc.values[i], gyr.values[j] if (gyr is not None and j >= 0) else None)
            if k == 1:
                assert mag is not None
                return mag_to_msg(t, imu_frame, mag.values[i] * 1e-6)
            if k == 2:
                ja, jg = a_of_r[i], g_of_r[i]
                if ja < 0 or acc is None:
                    return None             # no acceleration yet: an Imu message needs one
                return imu_to_msg(t, imu_frame, acc.values[ja], gyr.values[jg] if (gyr is not None and jg >= 0)
                                  else None, quat[i], ori_cov)
            if k == 3:
                assert pres is not None
                return pressure_to_msg(t, imu_frame, pres.values[i, 0] * 100.0)
            if k == 4:
                return scan_to_msg(replace(scans[i], frame_id=wifi_frame))
            return ble_to_msg(replace(bles[i], frame_id=ble_frame))

        rejected: Counter = Counter()
        for o in order.tolist():
            k, i, t = int(kinds[o]), int(idx[o]), int(stamps[o])
            try:
                msg = message(k, i, t)
            except InvalidMessageError as err:        # a value outside the contract: counted, not fatal
                rejected[f"{_KIND_TOPIC[k]}: {err.reason}"] += 1
                continue
            if msg is not None:
                bag.write(topics[_KIND_TOPIC[k]], msg, t)
        for what, n in sorted(rejected.items()):
            log.oddities.append(f"{n} messages not written, outside the message contract ({what})")
        return dict(bag.topic_counts())


_KIND_TOPIC = ("imu/data_raw", "imu/mag", "imu/data", "baro/pressure", "wifi/scan", "ble/scan")
