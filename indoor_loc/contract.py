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
SCHEMA_BLE_SCAN = "ble_scan.v1"

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
          "A pose to (re)initialise an estimator around (tll_pf, pdr_kf_node, backend_node per user), as RViz's 2D "
          "Pose Estimate sends it, its x/y covariance honoured; also the ~/set_pose service (nav_msgs/srv/SetMap)"),
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
    Topic("baro/pressure", "sensor_msgs/msg/FluidPressure", Qos.SENSOR, "<user>/imu_link",
          "Barometer (REP 145): fluid_pressure in Pa, variance in Pa^2 (0 = unknown)"),
    Topic("ble/scan", "diagnostic_msgs/msg/DiagnosticArray", Qos.RELIABLE, "<user>/ble_link",
          "BLE beacons heard at one instant, schema ble_scan.v1 = the wifi/scan layout: status[0] name='scan' "
          "(schema, ap_count, source); then one status per beacon: name=beacon id (iBeacon "
          "'<uuid>-<major>-<minor>', Eddystone '<namespace>-<instance>' or its instance, else the MAC; lower "
          "case), message=MAC or label, values rssi_dbm, frequency_mhz (0 = unknown)[, age_ms][, tx_power_dbm]"),
    Topic("/diagnostics", "diagnostic_msgs/msg/DiagnosticArray", Qos.RELIABLE, "",
          "Per-node health about once a second: input rates, last stamps, rejected messages by reason"),
    Topic("/clock", "rosgraph_msgs/msg/Clock", Qos.RELIABLE, "", "Bag time from the player (use_sim_time)"),
    Topic("pf/map_odom", "geometry_msgs/msg/TransformStamped", Qos.LATCHED, "map -> <user>/odom",
          "Particle filter's map -> odom correction at its newest estimate's stamp (T_map_base(t) * "
          "T_odom_base(t)^-1, the odometry interpolated at t); also on /tf when publish_tf (docs/robots.md)"),
    Topic("pdr_kf/map_odom", "geometry_msgs/msg/TransformStamped", Qos.LATCHED, "map -> <user>/odom",
          "Linear PDR Kalman filter's map -> odom correction, as pf/map_odom"),
    Topic("/tf", "tf2_msgs/msg/TFMessage", Qos.RELIABLE, "map -> <user>/odom",
          "The map -> odom corrections of the nodes with publish_tf (tll_pf by default), stamped "
          "transform_tolerance s ahead as nav2_amcl does; tf2_msgs is built into the venv by make venv"),
]}

#: A robot's own odometry, the estimators' motion input with ``motion_source: odom`` (issue 24).
ODOM = "odom"
MOTION_SOURCES = ("pdr", "odom")
TOPICS[ODOM] = Topic(
    ODOM, "nav_msgs/msg/Odometry", Qos.SENSOR, "<robot>/odom -> <robot>/base_link (any names, fixed per stream)",
    "A robot's odometry (wheel encoders, VIO), any rate: only the increments between consecutive poses are used "
    "(decimated per distance / angle / time), with the pose covariance's growth as their covariance, or the "
    "documented model when it is zeros, -1 (not given) or constant (docs/robot_odometry.md). Read by tll_pf, "
    "pdr_kf_node and backend_node with motion_source: odom, in place of pdr/odom; remappable. Bounds as pdr/odom "
    "(odom_position, odom_speed, odom_yaw_rate, odom_jump)")

#: Topics of multi-user stages, parameterised by the user name (``{user}``), outside any namespace.
USER_TOPICS: dict[str, Topic] = {t.name: t for t in [
    Topic("backend/{user}/path", "nav_msgs/msg/Path", Qos.LATCHED, "map",
          "Multi-user back-end: the user's whole optimised trajectory (z = floor height of its nearest fix), "
          "republished as the graph changes and when the user leaves"),
    Topic("backend/{user}/pose", "geometry_msgs/msg/PoseWithCovarianceStamped", Qos.RELIABLE, "map",
          "Multi-user back-end: the user's newest optimised pose with its marginal covariance"),
    Topic("backend/{user}/map_odom", "geometry_msgs/msg/TransformStamped", Qos.LATCHED, "map -> <user>/odom",
          "Multi-user back-end: the user's map -> odom correction at its newest pose, as pf/map_odom"),
]}
BACKEND_MAP_ODOM = "backend/{user}/map_odom"
BACKEND_PATH = "backend/{user}/path"
BACKEND_POSE = "backend/{user}/pose"


@dataclass(frozen=True)
class Bound:
    """A physical limit an input value must keep: ``lo <= value <= hi`` in ``unit`` (per axis for a
    vector), else the message is rejected under ``reason`` with a detail naming the field, the value
    and the bound. ``applies`` names the topics and fields; ``why`` says why no real input exceeds it."""
    name: str
    lo: float
    hi: float
    unit: str
    applies: str
    why: str
    reason: str = "out_of_range"

    def holds(self, value: float) -> bool:
        return self.lo <= value <= self.hi


#: Yaw (or yaw-rate) variance meaning "unknown" in ``pdr/odom``, ``wifi/fix`` and the estimates, rad²
#: (robot_localization's "ignore this axis"); the largest variance an angle may carry.
VAR_UNKNOWN = 1e6
#: Relative tolerance of the covariance checks: ``|C_ij - C_ji| <= COV_RTOL * max(|C_ii|, |C_jj|,
#: |C_ij|, |C_ji|)`` (symmetric within rounding) and every principal minor at least ``-COV_RTOL`` times
#: the product of its variances (positive semi-definite within rounding; msg_adapters/plausible.py).
COV_RTOL = 1e-9
#: A map-frame position (``wifi/fix``, ``initialpose``) farther than this outside the stage's map
#: (bounding box of the building graph, the radio map's scan positions) is ``off_map``, m.
OFF_MAP_MARGIN_M = 100.0

#: The plausibility bounds every adapter applies (``msg_adapters/plausible.py``; ``indoor-loc contract``
#: prints them, docs/nodes.md lists them).
BOUNDS: dict[str, Bound] = {b.name: b for b in [
    Bound("acceleration", -200.0, 200.0, "m/s^2", "imu/data_raw, imu/data: linear_acceleration, per axis",
          "about 20 g: phone and robot IMUs saturate at 2-16 g full scale"),
    Bound("angular_rate", -100.0, 100.0, "rad/s", "imu/data_raw, imu/data: angular_velocity, per axis "
          "(unless angular_velocity_covariance[0] = -1: no gyroscope)",
          "about 5700 deg/s: gyroscopes saturate at 2000-4000 deg/s full scale"),
    Bound("magnetic_field", -5e-3, 5e-3, "T", "imu/mag: magnetic_field, per axis",
          "5 mT: the Earth's field is 25-65 uT, indoor disturbances a few hundred uT, phone "
          "magnetometers saturate at 1.3-4.9 mT"),
    Bound("angle_variance", 0.0, VAR_UNKNOWN, "rad^2", "imu/data: orientation_covariance diagonal; pdr/odom: "
          "pose yaw variance; wifi/fix, initialpose: yaw variance",
          "1e6 rad^2 is the 'unknown' value the contract uses; a variance cannot be negative", "bad_covariance"),
    Bound("rate_variance", 0.0, VAR_UNKNOWN, "rad^2/s^2 or m^2/s^2", "pdr/odom: twist.covariance[0] "
          "(walking speed) and [35] (yaw rate)", "1e6 = unknown (yaw rate); a variance cannot be negative",
          "bad_covariance"),
    Bound("position_variance", 0.0, 1e10, "m^2", "pdr/odom: pose x/y variances; wifi/fix, initialpose: x/y and z "
          "variances", "a standard deviation of 100 km says nothing any more; beyond is garbage",
          "bad_covariance"),
    Bound("fix_variance_min", 1e-6, 1e10, "m^2", "wifi/fix: smallest eigenvalue of the x/y covariance",
          "no WiFi fix is better than a millimetre; a smaller variance makes its information overflow",
          "bad_covariance"),
    Bound("odom_position", -1e5, 1e5, "m", "pdr/odom: pose.position x, y, z",
          "100 km of walking from the odometry origin is more than a day"),
    Bound("odom_speed", -10.0, 10.0, "m/s", "pdr/odom: twist.linear.x (walking speed)",
          "sprinters reach 10-12 m/s for seconds; walkers 1-2 m/s"),
    Bound("odom_yaw_rate", -100.0, 100.0, "rad/s", "pdr/odom: twist.angular.z", "as angular_rate"),
    Bound("odom_jump", 0.0, 10.0, "m", "pdr/odom: distance from the stream's previous accepted pose, less "
          "odom_speed's bound times their stamp difference",
          "a pedestrian does not move 10 m between two hops (0.3 s); a restarted odometry far from its "
          "origin is taken once the stamps allow the distance", "odom_jump"),
    Bound("map_position", -1e7, 1e7, "m", "wifi/fix, initialpose: pose.position x, y, z",
          "a map frame is local; 1e7 m still holds UTM coordinates"),
    Bound("off_map", 0.0, OFF_MAP_MARGIN_M, "m", "wifi/fix, initialpose: distance outside the stage's map "
          "(tll_pf: the graph's bounding box; backend_node: the radio map's scan positions)",
          "nobody is located 100 m outside the building the map covers", "off_map"),
    Bound("rssi", -120.0, 0.0, "dBm", "wifi/scan, wifi/scan_raw: rssi_dbm",
          "receivers report -100..-20 dBm; 0 dBm is at the antenna", "rssi_range"),
    Bound("frequency", 700.0, 75000.0, "MHz", "wifi/scan, wifi/scan_raw: frequency_mhz (0 = unknown also passes)",
          "802.11 channels lie from 0.9 GHz (802.11ah) to 71 GHz (802.11ad/ay); a value in GHz or kHz is a "
          "unit mistake"),
    Bound("age", 0.0, 3.6e6, "ms", "wifi/scan, wifi/scan_raw: age_ms",
          "a cached reading older than an hour is not of this scan"),
    Bound("pressure", 3.0e4, 1.2e5, "Pa", "baro/pressure: fluid_pressure",
          "300 hPa is above Everest's summit (~330 hPa), 1200 hPa beyond the deepest mine's air (~1080 hPa at "
          "4 km down); a value in hPa or kPa is a unit mistake"),
    Bound("pressure_variance", 0.0, 1e8, "Pa^2", "baro/pressure: variance",
          "a standard deviation of 100 hPa says nothing; a variance cannot be negative", "bad_covariance"),
    Bound("tx_power_dbm", -100.0, 20.0, "dBm", "ble/scan: tx_power_dbm (the advertised power at 1 m)",
          "BLE transmitters radiate -40..+20 dBm; their 1 m calibration is about -100..0 dBm"),
    Bound("scan_aps", 1.0, 5000.0, "APs", "wifi/scan, wifi/scan_raw: access points in one scan",
          "a receiver hears at most a few hundred BSSIDs even in a dense mall; 100 000 would cost the "
          "node seconds per scan", "too_many_aps"),
]}


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
