"""The message contract: every topic the package reads or writes, with type, QoS and frame.

Topic names are relative, so one user's nodes live under a namespace (``/alice/imu/data``).
``indoor-loc contract`` prints ``TOPICS`` and ``USER_TOPICS`` as a table (the users' table is in
docs/nodes.md). Message types are given
as ``"pkg/msg/Name"`` strings so this module stays importable without any ROS package.
"""
from __future__ import annotations

import importlib
from dataclasses import dataclass
from enum import Enum


class Qos(str, Enum):
    """QoS profiles by role (see nodes/qos.py for the rclpy profiles)."""
    SENSOR = "sensor"        # best effort, keep last 200: raw high-rate input (also matches reliable pubs)
    RELIABLE = "reliable"    # reliable, volatile, keep last 50: estimates and scans
    LATCHED = "latched"      # reliable, transient_local, keep last 1: maps, last pose (like amcl_pose)
    BEST_EFFORT = "best_effort"  # best effort, keep last 5: heavy visualisation (particles)


@dataclass(frozen=True)
class Topic:
    name: str          # relative name (no leading slash) unless absolute (/diagnostics, /clock)
    type: str          # "sensor_msgs/msg/Imu"
    qos: Qos
    frame: str         # header.frame_id convention
    doc: str


SCHEMA_WIFI_SCAN = "wifi_scan.v1"

TOPICS: dict[str, Topic] = {t.name: t for t in [
    Topic("imu/data_raw", "sensor_msgs/msg/Imu", Qos.SENSOR, "<user>/imu_link",
          "Raw IMU (REP 145): linear_acceleration m/s^2 incl. gravity, angular_velocity rad/s; "
          "orientation_covariance[0] = -1"),
    Topic("imu/mag", "sensor_msgs/msg/MagneticField", Qos.SENSOR, "<user>/imu_link",
          "Magnetometer, tesla, sensor frame"),
    Topic("imu/data", "sensor_msgs/msg/Imu", Qos.SENSOR, "<user>/imu_link",
          "Orientation device->ENU (map-aligned) with covariance (roll, pitch, yaw rad^2), plus the "
          "raw acceleration/rate. Output of the heading filter; also accepted as input (phones that "
          "log an OS orientation, e.g. PUTMC)"),
    Topic("wifi/scan", "diagnostic_msgs/msg/DiagnosticArray", Qos.RELIABLE, "<user>/wifi_link",
          "WiFi scan, schema wifi_scan.v1: status[0] name='scan' (schema, ap_count, source); then one "
          "status per AP: name=BSSID (lower-case, colon-separated), message=SSID, values rssi_dbm, "
          "frequency_mhz[, age_ms]. header.stamp = scan time"),
    Topic("wifi/scan_raw", "diagnostic_msgs/msg/DiagnosticArray", Qos.RELIABLE, "<user>/wifi_link",
          "A driver's WiFi scan in the wifi/scan schema, before wifi_scan_node normalises it"),
    Topic("wifi/scan_json", "std_msgs/msg/String", Qos.RELIABLE, "",
          "A driver's WiFi scan as JSON text (e.g. CMU cabot's), parsed by wifi_scan_node"),
    Topic("pdr/odom", "nav_msgs/msg/Odometry", Qos.RELIABLE, "<user>/odom -> <user>/base_link",
          "Integrated PDR pose, one message per stepometer hop (stamped at the hop's end). Per interval: "
          "steps = |p_i - p_(i-1)| / step_length_m (each hop is laid straight along its mean heading), "
          "heading change = wrap(yaw_i - yaw_(i-1)); twist.linear.x = walking speed m/s, twist.angular.z "
          "= yaw rate rad/s; yaw variance 1e6 rad^2 = heading unknown; twist.covariance[0] = walking-speed "
          "variance m^2/s^2, which carries the step-count confidence of the hop (see imu/pdr.py); "
          "twist.covariance[35] = yaw-rate variance rad^2/s^2 (1e6 = unknown)"),
    Topic("wifi/fix", "geometry_msgs/msg/PoseWithCovarianceStamped", Qos.RELIABLE, "map",
          "WiFi-only position of one scan; covariance x/y in m^2, yaw variance set huge (unknown)"),
    Topic("pdr_kf/pose", "geometry_msgs/msg/PoseWithCovarianceStamped", Qos.RELIABLE, "map",
          "Linear PDR Kalman filter (Raitoharju et al. 2015) estimate: PDR + WiFi fixes, per PDR interval and fix; "
          "orientation = heading of the footstep vector, yaw variance its first-order variance (1e6 = unknown)"),
    Topic("pdr_kf/path", "nav_msgs/msg/Path", Qos.LATCHED, "map",
          "RTS-smoothed history of the linear PDR Kalman filter (republished periodically and at the end)"),
    Topic("initialpose", "geometry_msgs/msg/PoseWithCovarianceStamped", Qos.RELIABLE, "map",
          "A pose to (re)initialise the particle filter around, as RViz's 2D Pose Estimate sends it"),
    Topic("pf/pose", "geometry_msgs/msg/PoseWithCovarianceStamped", Qos.LATCHED, "map",
          "Particle-filter pose estimate (transient_local like amcl_pose)"),
    Topic("pf/particles", "geometry_msgs/msg/PoseArray", Qos.BEST_EFFORT, "map", "Particle cloud"),
    Topic("pf/path", "nav_msgs/msg/Path", Qos.LATCHED, "map",
          "Particle-filter history: the filtered estimates (republished every path_period_s), then the "
          "backward-simulation smoothed path at the end of input"),
    Topic("ground_truth", "nav_msgs/msg/Path", Qos.LATCHED, "map",
          "Ground-truth route or time-stamped trajectory of the user, when known"),
    Topic("ground_truth/route", "visualization_msgs/msg/MarkerArray", Qos.LATCHED, "map",
          "Ground-truth route of the user as LINE_LIST markers, when known (PUTMC: the GT route graph)"),
    Topic("map/graph", "visualization_msgs/msg/MarkerArray", Qos.LATCHED, "map", "Building link graph"),
    Topic("backend/wifi_map", "visualization_msgs/msg/MarkerArray", Qos.LATCHED, "map",
          "WiFi map scan positions (fixed survey + grown from users)"),
    Topic("/diagnostics", "diagnostic_msgs/msg/DiagnosticArray", Qos.RELIABLE, "",
          "Per-node health about once a second: input rates, last stamps, rejected messages by reason"),
    Topic("/clock", "rosgraph_msgs/msg/Clock", Qos.RELIABLE, "", "Bag time from the player (use_sim_time)"),
]}

#: Topics of multi-user stages, parameterised by the user name (``{user}``), outside any namespace.
USER_TOPICS: dict[str, Topic] = {t.name: t for t in [
    Topic("backend/{user}/path", "nav_msgs/msg/Path", Qos.LATCHED, "map",
          "Multi-user back-end: the user's whole optimised trajectory (z = floor height of its nearest fix), "
          "republished as the graph changes and when the user leaves"),
    Topic("backend/{user}/pose", "geometry_msgs/msg/PoseWithCovarianceStamped", Qos.RELIABLE, "map",
          "Multi-user back-end: the user's newest optimised pose with its marginal covariance"),
]}
BACKEND_PATH = "backend/{user}/path"
BACKEND_POSE = "backend/{user}/pose"


def msg_class(type_name: str) -> type:
    """Import a message class from ``"pkg/msg/Name"``."""
    pkg, kind, name = type_name.split("/")
    return getattr(importlib.import_module(f"{pkg}.{kind}"), name)


def type_name_of(msg_or_cls: object) -> str:
    cls = msg_or_cls if isinstance(msg_or_cls, type) else type(msg_or_cls)
    pkg = cls.__module__.split(".")[0]
    return f"{pkg}/msg/{cls.__name__}"


def join_ns(namespace: str, topic: str) -> str:
    """Resolve a relative topic under a namespace: ``join_ns('/walk07', 'imu/data') == '/walk07/imu/data'``."""
    if topic.startswith("/"):
        return topic
    ns = namespace.strip("/")
    return f"/{ns}/{topic}" if ns else f"/{topic}"


def namespace_of_topic(full: str, rel: str) -> str | None:
    """The namespace under which ``full`` is the relative topic ``rel``: ``('/walk07/imu/data',
    'imu/data') -> '/walk07'``, ``('/imu/data', 'imu/data') -> ''``; None when it is not ``rel``."""
    rel = rel.lstrip("/")
    if full == "/" + rel or full == rel:
        return ""
    if full.endswith("/" + rel):
        return full[: -len(rel) - 1]
    return None


def split_ns(full: str, relative_names: set[str] | None = None) -> tuple[str, str]:
    """Split ``/walk07/imu/data`` into (``/walk07``, ``imu/data``) by matching known relative names."""
    names = relative_names or {t for t in TOPICS if not t.startswith("/")}
    for rel in sorted(names, key=len, reverse=True):
        ns = namespace_of_topic(full, rel)
        if ns is not None:
            return ns, rel
    return "", full
