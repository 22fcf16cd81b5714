"""ImuStage (``imu_node``): FFT stepometer + heading -> ``pdr/odom`` (and ``imu/data`` from the AEKF).

Inputs
- ``imu/data_raw`` (sensor_msgs/Imu, REP 145): the accelerometer feeds the stepometer; with a
  gyroscope (``angular_velocity_covariance[0] != -1``) it also drives the adaptive EKF.
- ``imu/mag`` (sensor_msgs/MagneticField, optional): the latest sample (at most ``mag_max_age_s``
  old) goes into the AEKF with the next raw IMU sample; without it the AEKF runs in 6-D mode and its
  heading variance grows (and says so in ``pdr/odom``).
- ``imu/data`` (sensor_msgs/Imu with orientation, e.g. the PUTMC phones' OS quaternion): heading
  source for ``heading_source: orientation`` (and ``auto`` once it arrives); if no ``imu/data_raw``
  carries the accelerometer, the acceleration of ``imu/data`` feeds the stepometer.

``heading_source``: ``orientation`` = yaw of ``imu/data``; ``aekf`` = the AEKF on ``imu/data_raw``
(+ ``imu/mag``); ``auto`` = the orientation of ``imu/data`` if that topic arrives from elsewhere
(our own AEKF output echoed back is recognised by its stamps and ignored), else the AEKF.
Heading = yaw (ZYX, CCW from the world x axis) of the device->world quaternion plus
``heading_offset_rad`` (π/2 for a phone walking along its +y axis). No heading at all
(accelerometer only): the yaw is held and published with variance 1e6 rad² (unknown).

Outputs
- ``pdr/odom`` (nav_msgs/Odometry): one message per stepometer hop, stamped at the hop's end; see
  :mod:`indoor_loc.imu.pdr` for the contract (steps = |Δp| / step_length_m, Δψ = wrap(Δyaw)).
  Latency: about (window_s + hop_s)/2 behind the newest sample.
- ``imu/data`` (sensor_msgs/Imu): AEKF orientation + covariance, one per raw sample, when the AEKF
  runs.

Bad input (NaN/inf, stamps going backwards, non-unit quaternions) raises InvalidMessageError before
any state changes: counted by reason and dropped.
"""
from __future__ import annotations

import dataclasses
import math
from collections import deque
from typing import Any

import numpy as np

from indoor_loc import params as P
from indoor_loc.contract import Qos
from indoor_loc.errors import InvalidMessageError
from indoor_loc.imu.aekf import Aekf, AekfParams
from indoor_loc.imu.pdr import UNKNOWN_YAW_VAR, HeadingHistory, Pdr, PdrParams
from indoor_loc.imu.quaternion import yaw_xyzw
from indoor_loc.imu.stepometer import StepHop, Stepometer, StepometerParams
from indoor_loc.msg_adapters.imu import imu_from_msg, imu_to_msg, mag_from_msg
from indoor_loc.msg_adapters.odom import odom_to_msg
from indoor_loc.pipeline.stage import Output, Port, Stage


HEADING_SOURCES = ("auto", "aekf", "orientation")
AEKF_PREFIX = "aekf_"


def _copy_field(f: dataclasses.Field, name: str | None = None) -> tuple[str, type, Any]:
    default = f.default if f.default is not dataclasses.MISSING else f.default_factory()  # type: ignore[misc]
    return (name or f.name, f.type, P.field(default, f.metadata.get("doc", "")))


_OWN_FIELDS: list[tuple[str, Any, Any]] = [
    ("heading_source", str, P.field("auto", "'auto' (imu/data orientation if it arrives, else the AEKF), "
                                            "'aekf' or 'orientation'")),
    ("step_length_m", float, P.field(0.65, "nominal step length, m: distance = steps x this")),
    ("step_length_rel_std", float, P.field(0.1, "relative std of the walked distance per hop, 1")),
    ("heading_offset_rad", float, P.field(0.0, "added to the device yaw to get the walking heading, rad "
                                               "(0: device x forward, REP 103; pi/2: phone +y forward)")),
    ("default_yaw_std_rad", float, P.field(0.2, "yaw std used when imu/data carries no covariance (zeros), rad")),
    ("odom_frame", str, P.field("", "pdr/odom header frame; '' = '<namespace>/odom' (REP 105, per user)")),
    ("base_frame", str, P.field("", "pdr/odom child frame; '' = '<namespace>/base_link'")),
    ("mag_max_age_s", float, P.field(0.2, "a magnetometer sample older than this is not used, s")),
]


def _validate(self) -> None:
    n = type(self).__name__
    P.require(self.heading_source in HEADING_SOURCES, n, "heading_source", f"one of {HEADING_SOURCES}",
              self.heading_source)
    P.require(self.default_yaw_std_rad > 0, n, "default_yaw_std_rad", "> 0", self.default_yaw_std_rad)
    P.require(self.mag_max_age_s >= 0, n, "mag_max_age_s", ">= 0", self.mag_max_age_s)
    P.require(math.isfinite(self.heading_offset_rad), n, "heading_offset_rad", "finite", self.heading_offset_rad)
    self.stepometer_params().validate()
    self.pdr_params().validate()
    self.aekf_params().validate()


def _stepometer_params(self) -> StepometerParams:
    return StepometerParams(**{f.name: getattr(self, f.name) for f in dataclasses.fields(StepometerParams)})


def _pdr_params(self) -> PdrParams:
    return PdrParams(step_length_m=self.step_length_m, step_length_rel_std=self.step_length_rel_std)


def _aekf_params(self) -> AekfParams:
    return AekfParams(**{f.name: getattr(self, AEKF_PREFIX + f.name) for f in dataclasses.fields(AekfParams)})


_fields = (list(_OWN_FIELDS) + [_copy_field(f) for f in dataclasses.fields(StepometerParams)]
           + [_copy_field(f, AEKF_PREFIX + f.name) for f in dataclasses.fields(AekfParams)])

#: Parameters of ``imu_node``: its own, every :class:`StepometerParams` field under the same name and
#: every ``AekfParams`` field prefixed ``aekf_`` (defaults and docs live in those classes).
ImuStageParams = dataclasses.make_dataclass(
    "ImuStageParams", _fields, frozen=True,
    namespace={"validate": _validate, "stepometer_params": _stepometer_params, "pdr_params": _pdr_params,
               "aekf_params": _aekf_params,
               "__doc__": "Parameters of imu_node (see config/imu_node.yaml)."})


class ImuStage(Stage):
    """FFT stepometer + heading (AEKF or given orientation) -> pdr/odom [+ imu/data]."""
    NODE_NAME = "imu_node"
    PARAMS = ImuStageParams

    def __init__(self, params, *, namespace: str = "") -> None:
        super().__init__(params, namespace=namespace)
        ns = namespace.strip("/")
        self.odom_frame = params.odom_frame or (f"{ns}/odom" if ns else "odom")
        self.base_frame = params.base_frame or (f"{ns}/base_link" if ns else "base_link")
        self.stepometer = Stepometer(params.stepometer_params())
        self.pdr = Pdr(params.pdr_params())
        self.headings = HeadingHistory(horizon_s=max(10.0, 4.0 * params.window_s))
        self.aekf = Aekf(params.aekf_params())
        self._acc_topic: str | None = None          # which input feeds the stepometer
        self._last_raw_ns: int | None = None
        self._last_orient_ns: int | None = None
        self._mag: tuple[int, np.ndarray] | None = None
        self._external_orientation = params.heading_source == "orientation"
        self._published_stamps: deque = deque(maxlen=512)   # our imu/data stamps (echo detection)
        self._published_set: set = set()
        self.counts = {"mag_used": 0, "no_gyro": 0, "odom": 0}
        self.on("imu/data_raw", self._on_raw)
        self.on("imu/mag", self._on_mag)
        self.on("imu/data", self._on_orientation)

    # -- ports ------------------------------------------------------------------------------------
    def inputs(self) -> list[Port]:
        return [Port("imu/data_raw", "sensor_msgs/msg/Imu", Qos.SENSOR),
                Port("imu/mag", "sensor_msgs/msg/MagneticField", Qos.SENSOR),
                Port("imu/data", "sensor_msgs/msg/Imu", Qos.SENSOR)]

    def outputs(self) -> list[Port]:
        outs = [Port("pdr/odom", "nav_msgs/msg/Odometry", Qos.RELIABLE)]
        if self.params.heading_source != "orientation":
            outs.append(Port("imu/data", "sensor_msgs/msg/Imu", Qos.SENSOR))
        return outs

    @property
    def heading_mode(self) -> str:
        """The heading source in use now: 'orientation', 'aekf' or 'none'."""
        if self._external_orientation:
            return "orientation" if len(self.headings) else "none"
        if self.params.heading_source in ("aekf", "auto") and self.aekf.initialised:
            return "aekf"
        return "none"

    # -- handlers ---------------------------------------------------------------------------------
    def _on_mag(self, msg, recv_ns: int) -> list[Output]:
        stamp, field_t = mag_from_msg(msg)
        self._mag = (stamp, field_t)
        return []

    def _on_raw(self, msg, recv_ns: int) -> list[Output]:
        s = imu_from_msg(msg)
        if self._last_raw_ns is not None and s.stamp_ns <= self._last_raw_ns:
            raise InvalidMessageError("non_monotonic_stamp",
                                      f"imu/data_raw stamp {s.stamp_ns} <= previous {self._last_raw_ns}")
        outs: list[Output] = []
        run_aekf = not self._external_orientation and self.params.heading_source in ("aekf", "auto")
        if run_aekf:
            if s.gyro is None:
                self.counts["no_gyro"] += 1
            else:
                mag = None
                if self._mag is not None and abs(s.stamp_ns - self._mag[0]) <= self.params.mag_max_age_s * 1e9:
                    mag = self._mag[1]
                    self._mag = None
                try:
                    self.aekf.update(s.stamp_ns, s.gyro, s.acc, mag)
                except ValueError as err:
                    raise InvalidMessageError("aekf_input", str(err)) from err
                if mag is not None:
                    self.counts["mag_used"] += 1
                q = self.aekf.quat_wxyz
                cov = self.aekf.orientation_cov
                q_xyzw = np.array([q[1], q[2], q[3], q[0]])
                self.headings.add(s.stamp_ns, yaw_xyzw(q_xyzw) + self.params.heading_offset_rad,
                                  float(cov[2, 2]))
                outs.append(("imu/data", imu_to_msg(s.stamp_ns, s.frame_id, s.acc, s.gyro, q_xyzw, cov)))
                if len(self._published_stamps) == self._published_stamps.maxlen:
                    self._published_set.discard(self._published_stamps[0])
                self._published_stamps.append(s.stamp_ns)
                self._published_set.add(s.stamp_ns)
        self._last_raw_ns = s.stamp_ns
        if self._acc_topic is None:
            self._acc_topic = "imu/data_raw"
        if self._acc_topic == "imu/data_raw":
            outs += self._hops(self.stepometer.update(s.stamp_ns, s.acc))
        return outs

    def _on_orientation(self, msg, recv_ns: int) -> list[Output]:
        s = imu_from_msg(msg)
        if s.stamp_ns in self._published_set:
            return []                                   # our own AEKF output coming back
        if self.params.heading_source == "aekf":
            return []
        if self._last_orient_ns is not None and s.stamp_ns <= self._last_orient_ns:
            raise InvalidMessageError("non_monotonic_stamp",
                                      f"imu/data stamp {s.stamp_ns} <= previous {self._last_orient_ns}")
        outs: list[Output] = []
        use_acc = self._acc_topic == "imu/data" or (self._acc_topic is None and float(np.linalg.norm(s.acc)) > 0)
        if use_acc:
            hops = self.stepometer.update(s.stamp_ns, s.acc)   # may raise: nothing changed yet
            self._acc_topic = "imu/data"
        else:
            hops = []
        self._last_orient_ns = s.stamp_ns
        if s.quat_xyzw is not None:
            if not self._external_orientation:     # auto: drop AEKF headings (another world frame)
                self.headings = HeadingHistory(horizon_s=self.headings.horizon_ns * 1e-9)
            self._external_orientation = True
            var = float(s.orientation_cov[2, 2]) if s.orientation_cov is not None else 0.0
            if not math.isfinite(var) or var <= 0.0:
                var = self.params.default_yaw_std_rad ** 2
            self.headings.add(s.stamp_ns, yaw_xyzw(s.quat_xyzw) + self.params.heading_offset_rad, var)
        return outs + self._hops(hops)

    def _hops(self, hops: list[StepHop]) -> list[Output]:
        outs: list[Output] = []
        for h in hops:
            head = self.headings.at(h.t_end_ns) if self.heading_mode != "none" else None
            yaw, var = (None, UNKNOWN_YAW_VAR) if head is None else head
            pose = self.pdr.update(h.t_start_ns, h.t_end_ns, h.steps, yaw, var, h.steps_std)
            outs.append(("pdr/odom", odom_to_msg(pose.stamp_ns, self.odom_frame, self.base_frame, pose.x, pose.y,
                                                 pose.yaw, pose.cov, pose.speed, pose.yaw_rate, pose.speed_var)))
            self.counts["odom"] += 1
        return outs

    def finish(self) -> list[Output]:
        return self._hops(self.stepometer.finish())

    def extra_diagnostics(self) -> dict[str, str]:
        st = self.pdr.state()
        return {
            "steps": f"{self.stepometer.total_steps:.1f}",
            "walking": str(self.stepometer.walking).lower(),
            "step_freq_hz": f"{self.stepometer.freq_hz:.3f}",
            "step_confidence": f"{self.stepometer.confidence:.2f}",
            "rate_hz": f"{self.stepometer.rate_hz:.1f}",
            "acc_source": self._acc_topic or "",
            "heading_source": self.heading_mode,
            "yaw_std_rad": f"{math.sqrt(st.cov[2, 2]):.3g}",
            "distance_m": f"{st.distance_m:.2f}",
            "mag_used": str(self.counts["mag_used"]),
            "raw_without_gyro": str(self.counts["no_gyro"]),
            "latency_s": f"{self.stepometer.latency_s:.2f}",
        }
