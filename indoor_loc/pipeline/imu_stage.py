"""ImuStage (``imu_node``): FFT stepometer + heading -> ``pdr/odom`` (and ``imu/data`` from the filter).

Inputs
- ``imu/data_raw`` (sensor_msgs/Imu, REP 145): the accelerometer feeds the stepometer; with a
  gyroscope (``angular_velocity_covariance[0] != -1``) it also drives the adaptive EKF.
- ``imu/mag`` (sensor_msgs/MagneticField, optional) at its own rate: merged with ``imu/data_raw``
  in stamp order (:class:`indoor_loc.imu.mag_sync.MagSync`: an IMU sample waits at most
  ``mag_max_delay_s`` for the magnetometer), each sample used once at its stamp, after subtracting
  the hard-iron bias ``mag_bias_{x,y,z}`` (tesla, as imu_tools' ``mag_bias_*``). A sample later
  than that is dropped and counted (``mag_late``). Without it the filter runs 6-D and its heading
  variance grows (and says so in ``pdr/odom``).
- ``imu/data`` (sensor_msgs/Imu with orientation, e.g. the PUTMC phones' OS quaternion): heading
  source for ``heading_source: orientation`` (and ``auto`` once it arrives); if no ``imu/data_raw``
  carries the accelerometer, the acceleration of ``imu/data`` feeds the stepometer.

``heading_source``: ``orientation`` = yaw of ``imu/data``; ``aekf`` = the adaptive EKF
(:mod:`indoor_loc.imu.aekf`) on ``imu/data_raw`` (+ ``imu/mag``); ``vqf`` = VQF's compiled core
(:mod:`indoor_loc.imu.vqf_filter`) on the same inputs; ``auto`` = the orientation of ``imu/data`` if
that topic arrives from elsewhere (our own output echoed back is recognised by its stamps and
ignored), else :data:`AUTO_FILTER`, the filter ``indoor-loc bench heading`` finds better on walking
phones (VQF, see docs/benchmarks/heading.md).
Heading = yaw (ZYX, CCW from the world x axis) of the device->world quaternion plus
``heading_offset_rad`` (π/2 for a phone walking along its +y axis). No heading at all
(accelerometer only): the yaw is held and published with variance 1e6 rad² (unknown).

Outputs
- ``pdr/odom`` (nav_msgs/Odometry): one message per stepometer hop, stamped at the hop's end; see
  :mod:`indoor_loc.imu.pdr` for the contract (steps = |Δp| / step_length_m, Δψ = wrap(Δyaw)).
  Latency: about (window_s + hop_s)/2 behind the newest sample.
- ``imu/data`` (sensor_msgs/Imu): the filter's orientation + covariance, one per raw sample, when a
  filter runs.

Bad input (NaN/inf, stamps going backwards, non-unit quaternions) raises InvalidMessageError before
any state changes: counted by reason and dropped.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from indoor_loc.params import field, group, require, validate_groups
from indoor_loc.contract import Qos
from indoor_loc.errors import InvalidInputError, InvalidMessageError
from indoor_loc.imu.aekf import Aekf, AekfParams
from indoor_loc.imu.mag_sync import IMU, MagSync
from indoor_loc.imu.pdr import UNKNOWN_YAW_VAR, HeadingHistory, Pdr, PdrParams
from indoor_loc.imu.quaternion import yaw_xyzw
from indoor_loc.imu.stepometer import Stepometer
from indoor_loc.imu.stepometer_types import StepHop, StepometerParams
from indoor_loc.imu.vqf_filter import VqfFilter, VqfParams
from msg_adapters.imu import ImuSample, imu_from_msg, imu_to_msg, mag_from_msg
from msg_adapters.imu_cdr import imu_cdr
from msg_adapters.odom import odom_to_msg
from indoor_loc.pipeline import imu_raw_run
from indoor_loc.pipeline.stage import Output, Port, Stage
from indoor_loc.pipeline.time_policy import Order, TimeParams


HEADING_SOURCES = ("auto", "aekf", "vqf", "orientation")
#: the filter ``auto`` runs when no external orientation arrives: the better one on walking phones in
#: ``indoor-loc bench heading`` (TyRex walking trials, docs/benchmarks/heading.md).
AUTO_FILTER = "vqf"


@dataclass(frozen=True)
class ImuStageParams:
    """Parameters of ``imu_node`` (see config/imu_node.yaml): its own, and the stepometer's and the
    AEKF's as groups (ROS parameters ``stepometer.window_s``, ``aekf.gyro_noise``, ...; defaults and
    docs live in :class:`StepometerParams` and :class:`AekfParams`)."""
    heading_source: str = field("auto", "'auto' (imu/data orientation if it arrives, else the better filter "
                                          "on walking phones, VQF), 'aekf', 'vqf' or 'orientation'")
    step_length_m: float = field(0.65, "nominal step length, m: distance = steps x this")
    step_length_rel_std: float = field(0.1, "relative std of the walked distance per hop, 1")
    heading_offset_rad: float = field(0.0, "added to the device yaw to get the walking heading, rad "
                                           "(0: device x forward, REP 103; pi/2: phone +y forward)")
    default_yaw_std_rad: float = field(0.2, "yaw std used when imu/data carries no covariance (zeros), rad")
    odom_frame: str = field("", "pdr/odom header frame; '' = '<namespace>/odom' (REP 105, per user)")
    base_frame: str = field("", "pdr/odom child frame; '' = '<namespace>/base_link'")
    mag_max_delay_s: float = field(0.1, "an imu/data_raw sample waits at most this long (stamp time) for "
                                        "imu/mag samples up to its stamp; later ones are dropped and counted, s")
    mag_bias_x: float = field(0.0, "hard-iron bias subtracted from imu/mag x, T (docs/nodes.md: how to estimate it)")
    mag_bias_y: float = field(0.0, "hard-iron bias subtracted from imu/mag y, T")
    mag_bias_z: float = field(0.0, "hard-iron bias subtracted from imu/mag z, T")
    stepometer: StepometerParams = group(StepometerParams, "FFT stepometer (indoor_loc/imu/stepometer.py)")
    aekf: AekfParams = group(AekfParams, "adaptive EKF orientation (indoor_loc/imu/aekf.py), used when the "
                                         "heading comes from the AEKF")
    vqf: VqfParams = group(VqfParams, "VQF orientation (indoor_loc/imu/vqf_filter.py), used when the heading "
                                      "comes from VQF")
    time: TimeParams = group(TimeParams, "which stamps are taken, clock jumps (indoor_loc/pipeline/time_policy.py)")

    def validate(self) -> None:
        n = type(self).__name__
        require(self.heading_source in HEADING_SOURCES, n, "heading_source", f"one of {HEADING_SOURCES}",
                  self.heading_source)
        require(self.default_yaw_std_rad > 0, n, "default_yaw_std_rad", "> 0", self.default_yaw_std_rad)
        require(self.mag_max_delay_s >= 0, n, "mag_max_delay_s", ">= 0", self.mag_max_delay_s)
        for ax in "xyz":
            v = getattr(self, "mag_bias_" + ax)
            require(math.isfinite(v), n, "mag_bias_" + ax, "finite", v)
        require(math.isfinite(self.heading_offset_rad), n, "heading_offset_rad", "finite", self.heading_offset_rad)
        validate_groups(self)
        self.pdr_params().validate()

    def pdr_params(self) -> PdrParams:
        return PdrParams(step_length_m=self.step_length_m, step_length_rel_std=self.step_length_rel_std)


class ImuStage(Stage):
    """FFT stepometer + heading (AEKF, VQF or given orientation) -> pdr/odom [+ imu/data]."""
    NODE_NAME = "imu_node"
    PARAMS = ImuStageParams
    STAMP_ORDER = {"imu/data_raw": Order.STRICT, "imu/mag": Order.STRICT, "imu/data": Order.STRICT}
    #: a multi-user imu_node takes its users' samples every 0.2 s (not 0.05 s): a user's run of 10 samples
    #: at 50 Hz costs about a third less CPU per sample than runs of 2-3 (imu_raw_run.py; the same
    #: outputs), for at most 0.15 s more on a pdr/odom that is already ~2 s behind its samples
    MULTI_USER_POLL_S = 0.2

    def __init__(self, params: ImuStageParams, *, namespace: str = "") -> None:
        super().__init__(params, namespace=namespace)
        ns = namespace.strip("/")
        self.odom_frame = params.odom_frame or (f"{ns}/odom" if ns else "odom")
        self.base_frame = params.base_frame or (f"{ns}/base_link" if ns else "base_link")
        self._mag_bias = np.array([params.mag_bias_x, params.mag_bias_y, params.mag_bias_z])
        self.counts = {"mag_used": 0, "no_gyro": 0, "odom": 0}
        self._fresh_state()
        self.on("imu/data_raw", self._on_raw)
        self.on("imu/mag", self._on_mag)
        self.on("imu/data", self._on_orientation)
        # offline runs: runs of messages decoded in bulk (indoor_loc.bag.bulk), same handlers
        self.on_batch("imu/data_raw", self._raw_sample)
        self.on_batch("imu/mag", self._mag_sample)
        self.on_batch("imu/data", self._orientation_sample)

    def _fresh_state(self) -> None:
        """The estimators' state as before the first message (start-up, and a jump back in time)."""
        params = self.params
        self.stepometer = Stepometer(params.stepometer)
        self.pdr = Pdr(params.pdr_params())
        self.headings = HeadingHistory(horizon_s=max(10.0, 4.0 * params.stepometer.window_s))
        self.filter_name = AUTO_FILTER if params.heading_source in ("auto", "orientation") else params.heading_source
        self.filter: Aekf | VqfFilter = Aekf(params.aekf) if self.filter_name == "aekf" else VqfFilter(params.vqf)
        self.mag_sync = MagSync(params.mag_max_delay_s)
        self._last_mag_ns: int | None = None
        self._acc_topic: str | None = None          # which input feeds the stepometer
        self._last_raw_ns: int | None = None
        self._last_orient_ns: int | None = None
        self._external_orientation = params.heading_source == "orientation"

    def reset_user(self, user: str) -> list[Output]:
        """A jump back in time: the hops of the old pass still in the stepometer are published, then
        every estimator starts afresh (the odometry from the origin again)."""
        outs = self.finish()
        self._fresh_state()
        return outs

    # -- ports ------------------------------------------------------------------------------------
    def inputs(self) -> list[Port]:
        return [Port("imu/data_raw", "sensor_msgs/msg/Imu", Qos.SENSOR, required=True),
                Port("imu/mag", "sensor_msgs/msg/MagneticField", Qos.SENSOR),
                Port("imu/data", "sensor_msgs/msg/Imu", Qos.SENSOR)]

    def outputs(self) -> list[Port]:
        outs = [Port("pdr/odom", "nav_msgs/msg/Odometry", Qos.RELIABLE)]
        if self.params.heading_source != "orientation":
            outs.append(Port("imu/data", "sensor_msgs/msg/Imu", Qos.SENSOR))
        return outs

    @property
    def heading_mode(self) -> str:
        """The heading source in use now: 'orientation', 'aekf', 'vqf' or 'none'."""
        if self._external_orientation:
            return "orientation" if len(self.headings) else "none"
        if self.filter.initialised:
            return self.filter_name
        return "none"

    # -- handlers ---------------------------------------------------------------------------------
    def _on_mag(self, msg, recv_ns: int) -> list[Output]:
        return self._mag_sample(mag_from_msg(msg), recv_ns)

    def _mag_sample(self, sample: tuple[int, np.ndarray], recv_ns: int) -> list[Output]:
        stamp, field_t = sample
        if self._last_mag_ns is not None and stamp <= self._last_mag_ns:
            raise InvalidMessageError("non_monotonic_stamp", f"imu/mag stamp {stamp} <= previous {self._last_mag_ns}")
        if self._external_orientation:
            return []
        self._last_mag_ns = stamp
        late = self.mag_sync.n_late
        events = self.mag_sync.push_mag(stamp, field_t - self._mag_bias)
        if self.mag_sync.n_late > late:
            self._reject("mag_late", f"imu/mag stamp {stamp} is older than imu/data_raw samples already "
                                     f"used (more than mag_max_delay_s late): dropped")
        return self._run_events(events)

    def _on_raw(self, msg, recv_ns: int) -> list[Output]:
        return self._raw_sample(imu_from_msg(msg), recv_ns)

    def _raw_sample(self, s: ImuSample, recv_ns: int) -> list[Output]:
        if self._last_raw_ns is not None and s.stamp_ns <= self._last_raw_ns:
            raise InvalidMessageError("non_monotonic_stamp",
                                      f"imu/data_raw stamp {s.stamp_ns} <= previous {self._last_raw_ns}")
        outs: list[Output] = []
        if self._acc_topic is None:
            self._acc_topic = "imu/data_raw"
        if self._acc_topic == "imu/data_raw":
            hops = self.stepometer.update(s.stamp_ns, s.acc)      # may raise: nothing changed yet
        else:
            hops = []
        self._last_raw_ns = s.stamp_ns
        if not self._external_orientation:
            if s.gyro is None:
                self.counts["no_gyro"] += 1
            else:
                outs += self._run_events(self.mag_sync.push_imu(s.stamp_ns, s))
        return outs + self._hops(hops)

    def _run_events(self, events) -> list[Output]:
        """Feed merged IMU/magnetometer events (stamp order) to the filter; imu/data per IMU sample.
        A sample the filter refuses is counted by its reason and the rest still run."""
        outs: list[Output] = []
        for kind, stamp, payload in events:
            try:
                if kind == IMU:
                    self.filter.update_imu(stamp, payload.gyro, payload.acc)
                else:
                    self.filter.update_mag(stamp, payload)
            except InvalidInputError as err:
                self._reject(err.reason, f"{self.filter_name}: {err}")
                continue
            if kind != IMU:
                self.counts["mag_used"] += 1
                continue
            if not self.filter.initialised:
                continue
            q = self.filter.quat_wxyz
            cov = self.filter.orientation_cov
            q_xyzw = np.array([q[1], q[2], q[3], q[0]])
            yaw = yaw_xyzw(q_xyzw)
            self.headings.add(stamp, yaw + self.params.heading_offset_rad, float(cov[2, 2]))
            self.stepometer.add_heading(stamp, yaw)
            encode = imu_cdr if self.raw_outputs else imu_to_msg        # the same message (msg_adapters/imu_cdr.py)
            outs.append(("imu/data", encode(stamp, payload.frame_id, payload.acc, payload.gyro, q_xyzw, cov)))
        return outs

    def _on_orientation(self, msg, recv_ns: int) -> list[Output]:
        return self._orientation_sample(imu_from_msg(msg), recv_ns)

    def _orientation_sample(self, s: ImuSample, recv_ns: int) -> list[Output]:
        # our own imu/data coming back never gets here: the time policy recognises it (Stage._judged)
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
                self.stepometer.clear_headings()
            self._external_orientation = True
            var = float(s.orientation_cov[2, 2]) if s.orientation_cov is not None else 0.0
            if not math.isfinite(var) or var <= 0.0:
                var = self.params.default_yaw_std_rad ** 2
            yaw = yaw_xyzw(s.quat_xyzw)
            self.headings.add(s.stamp_ns, yaw + self.params.heading_offset_rad, var)
            self.stepometer.add_heading(s.stamp_ns, yaw)
        return outs + self._hops(hops)

    def process_batch(self, topic: str, items: list, recv_ns: list[int]) -> list[tuple[int, str, Any]]:
        """:meth:`Stage.process_batch`; a run of phone orientations (``imu/data`` as the heading and
        step source, the steady state of a PUTMC-style recording) goes through the stepometer and
        the heading history in column operations between the samples that complete a window — the
        same values, state and outputs as one sample at a time (``Stepometer.extend_steady``)."""
        if topic == "imu/data_raw" and imu_raw_run.run_ok(self, items, recv_ns):
            return imu_raw_run.process_raw_run(self, items, recv_ns)     # the same, in columns (its module doc)
        arrays = getattr(items, "arrays", None)
        if topic != "imu/data" or arrays is None or not self._orientation_run_ok(items, recv_ns):
            return super().process_batch(topic, items, recv_ns)
        n = len(items)
        t_all = arrays.sec * 1_000_000_000 + arrays.nanosec
        x, y, z, w = np.asarray(arrays.orientation_xyzw, dtype=float).T
        # yaw_xyzw: the same float operations column-wise, math.atan2 per sample
        yaw = list(map(math.atan2, (2.0 * (w * z + x * y)).tolist(), (1.0 - 2.0 * (y * y + z * z)).tolist()))
        var_c = arrays.orientation_cov[:, 8]
        default_var = self.params.default_yaw_std_rad ** 2
        var = np.where(np.isfinite(var_c) & (var_c > 0.0), var_c, default_var).tolist()
        offset = self.params.heading_offset_rad
        yaw_off = [y + offset for y in yaw]
        stamps = t_all.tolist()
        acc = arrays.linear_acceleration
        diag = self.diag
        stats = diag.received[topic]
        t0 = time.perf_counter()
        out: list[tuple[int, str, Any]] = []
        self.stepometer.prefetch(t_all, acc)        # the run's windows analysed together
        plan = self.stepometer.quiet_plan(t_all)
        i = 0
        while i < n:
            quiet = None if plan is None else plan.count(i)
            if quiet is None:
                break
            j = min(i + quiet, n - 1)               # the sample completing a window, or the last
            trigger = i + quiet < n
            diag.now_ns = recv_ns[j]
            try:
                self.stepometer.add_headings(stamps[i:j], yaw[i:j])
                hops = self.stepometer.extend_steady(t_all[i:j + 1], acc[i:j + 1])
                self.stepometer.add_headings(stamps[j:j + 1], yaw[j:j + 1])
                self._last_orient_ns = stamps[j]
                self.headings.add_many(stamps[i:j + 1], yaw_off[i:j + 1], var[i:j + 1])
                outs = self._hops(hops)
            except Exception as err:  # noqa: BLE001 - as process(): counted, the run goes on
                self._reject("internal_error", f"{topic} (batch of {j + 1 - i}): {type(err).__name__}: {err}")
                outs = []
            for o_topic, o_msg in outs:
                diag.published[o_topic] += 1
                out.append((recv_ns[j], o_topic, o_msg))
            i = j + 1
            if not trigger:
                break
        if i:
            self.time.accepted("", topic, stamps[i - 1])
            stats.count += i
            stats.first_ns = recv_ns[0] if stats.first_ns is None else stats.first_ns
            stats.last_ns = recv_ns[i - 1]
            diag.process_s.append((time.perf_counter() - t0) / i)       # one entry per run: its mean
        if i < n:                                   # not steady (a gap): the rest one by one
            out += super().process_batch(topic, items[i:], recv_ns[i:])
        return out

    def _orientation_run_ok(self, items: list, recv_ns: list[int]) -> bool:
        """Whether :meth:`_orientation_sample` would take every item of the run the same plain way:
        orientation already the heading source, its acceleration feeding the stepometer, every item
        with an orientation, stamps increasing, none of them our own output echoed back."""
        if not (self._external_orientation and self._acc_topic == "imu/data" and self.params.heading_source != "aekf"
                and len(self.headings) and getattr(items, "all_oriented", False)):
            return False
        t = items.arrays.sec * 1_000_000_000 + items.arrays.nanosec
        if (self._last_orient_ns is not None and int(t[0]) <= self._last_orient_ns) or np.any(np.diff(t) <= 0):
            return False
        if not self.time.passes_run("", "imu/data", t.tolist(), list(recv_ns), Order.STRICT):
            return False
        return not any(self.time.echo("", "imu/data", int(v)) for v in t)

    def _hops(self, hops: list[StepHop]) -> list[Output]:
        outs: list[Output] = []
        for h in hops:
            head = self.headings.at(h.t_end_ns) if self.heading_mode != "none" else None
            yaw, var = (None, UNKNOWN_YAW_VAR) if head is None else head
            pose = self.pdr.update(h.t_start_ns, h.t_end_ns, h.steps, yaw, var, h.steps_std)
            outs.append(("pdr/odom", odom_to_msg(pose.stamp_ns, self.odom_frame, self.base_frame, pose.x, pose.y,
                                                 pose.yaw, pose.cov, pose.speed, pose.yaw_rate, pose.speed_var,
                                                 pose.yaw_rate_var)))
            self.counts["odom"] += 1
        return outs

    def finish(self) -> list[Output]:
        outs = [] if self._external_orientation else self._run_events(self.mag_sync.flush())
        return outs + self._hops(self.stepometer.finish())

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
            "mag_late": str(self.mag_sync.n_late),
            "raw_without_gyro": str(self.counts["no_gyro"]),
            "latency_s": f"{self.stepometer.latency_s:.2f}",
        }
