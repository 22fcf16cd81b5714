"""PdrKfStage: the linear PDR Kalman filter of Raitoharju, Nurminen and Piché (2015, Sec. 4; see
docs/references.md) fusing ``pdr/odom`` with ``wifi/fix``.

Per ``pdr/odom`` message the filter predicts with the interval's step count and heading change
(decoded once by :class:`msg_adapters.odom.PdrOdomReader`, see :mod:`indoor_loc.measurements`) and
publishes ``pdr_kf/pose``; per ``wifi/fix`` it applies a gated linear position update.
``pdr_kf/path`` is the RTS-smoothed history (the paper's offline smoother), republished at most
every ``smooth_period_s`` of stamp time and at the end of input. The filter starts at the first
WiFi fix (position and covariance from the fix; step vector 0 with no heading needed). Integrity
(the paper's Sec. 5.2): when ``max_rejected_fixes`` fixes in a row fail the innovation gate, the
PDR track has left the truth (a wrong turn, a heading jump), so the filter restarts at the latest
fix and a new smoother segment begins; the smoothed path is the concatenation of the segments.
Later waves use it to initialise and monitor the particle filter.

Floors (docs/floors.md): the filter is planar; the floor is a separate discrete state
(:class:`~indoor_loc.baro.track.FloorTrack`: the floor HMM fed by the fixes' floors, ``wifi/fix``
pose z and covariance[14], and the floor changes the barometer detector finds in ``baro/pressure``,
optional). It changes only on evidence (one barometer floor change, or consistent fixes); ``pdr_kf/pose``
carries z = the filtered floor's height (covariance[14] its variance), ``pdr_kf/path`` the smoothed one.
"""
from __future__ import annotations

import bisect
import math
from collections import deque
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from indoor_loc.params import field, group, require
from indoor_loc.contract import Qos
from indoor_loc.measurements import Fix
from indoor_loc.errors import ConfigError
from indoor_loc.fusion.linear_pdr import (KfTrack, LinearPdrKf, LinearPdrParams, filter_batch, fixes_to_arrays,
                                          rts_smooth)
from msg_adapters.initial_pose import initial_pose_from_msg
from msg_adapters.odom import PdrOdomReader
from indoor_loc.baro.detector import BaroParams
from indoor_loc.baro.floors import FloorFilterParams
from indoor_loc.baro.snap import FloorSnapParams
from indoor_loc.baro.track import FloorTrack
from msg_adapters.path import path_to_msg
from msg_adapters.path_cdr import path_cdr
from msg_adapters.pressure import pressure_from_msg
from msg_adapters.pose import YAW_VAR_UNKNOWN, fix_from_msg, pose_to_msg
from msg_adapters.pose_cdr import pose_cdr
from indoor_loc.pipeline.map_odom import MapOdomSpec
from indoor_loc.pipeline.path_store import PathStore
from indoor_loc.pipeline.stage import Output, Port, Stage
from indoor_loc.pipeline.time_policy import Order, TimeParams
from indoor_loc.fusion.linear_pdr import process_noise, transition_matrix
from indoor_loc.fusion.odom_kf import odom_transition
from indoor_loc.fusion.position_trust import (FIX_LATE_MAX_S, FIX_SIGMA_MIN_M, POSE_INTERVAL_MIN_S,
                                              POSE_SIGMA_MIN_M, CommandRate, check_fix_timely,
                                              check_pose_current, fixes_agree, floor_cov)
from indoor_loc.odometry.increments import OdomIncrement, OdomIncrementParams
from indoor_loc.pipeline.motion_source import MOTION_DOC, ODOM_GROUP_DOC, motion_port, require_source, validate_source
from msg_adapters.robot_odom import RobotOdomReader


@dataclass(frozen=True)
class PdrKfStageParams:
    """Parameters of ``pdr_kf_node``."""
    step_length_m: float = field(0.65, "nominal step length the PDR node used (m): steps = distance / this")
    kf_step_length_m: float = field(0.7, "footstep length s in the heading-noise model (m)")
    sigma_dtheta_rad: float = field(0.2, "heading-change noise per footstep (rad); 0.2 measured best on PUTMC (0.1 and 0.3 also tried)")
    sigma_ds_m: float = field(0.07, "step-vector length change noise per footstep (m)")
    heading_prior_std_rad: float = field(0.0, "trust pdr/odom's yaw as the map-frame heading at each (re)start, with "
                                              "this std (rad; an importer that calibrated the phone's heading offset "
                                              "sets it); 0 = no initial heading (the paper's filter)")
    gate_prob: float = field(0.999, "chi-square (2 dof) probability of the WiFi innovation gate; 1.0 = no gate")
    fix_late_max_s: float = field(FIX_LATE_MAX_S, "a wifi/fix stamped more than this before the newest pdr/odom "
                                                  "applied is refused (fix_too_late; s, indoor_loc/fusion/position_trust.py)")
    fix_sigma_min_m: float = field(FIX_SIGMA_MIN_M, "a wifi/fix is never taken as more precise than this std per "
                                                    "direction (m; indoor_loc/fusion/position_trust.py)")
    pose_sigma_min_m: float = field(POSE_SIGMA_MIN_M, "an initialpose is never taken as more precise than this std "
                                                      "per direction (m; indoor_loc/fusion/position_trust.py)")
    pose_interval_min_s: float = field(POSE_INTERVAL_MIN_S, "an initialpose received less than this after the "
                                       "previous one is refused (pose_burst: faster than a person gives "
                                       "poses; s of the node's clock, indoor_loc/fusion/position_trust.py)")
    max_rejected_fixes: int = field(2, "restart the filter at a fix after this many consecutive gated-out fixes; 0 = never")
    max_fix_delay_s: float = field(5.0, "a WiFi fix waits at most this long (s of stamp time) for pdr/odom to reach its stamp")
    odom_hold_s: float = field(0.0, "hold each pdr/odom hop this long (s of stamp time, on the odom stream) before "
                                    "applying it, so a wifi/fix that reaches the node after later hops (a busy "
                                    "machine, a replay faster than real time) is still applied in stamp order, as "
                                    "offline; delays pdr_kf/pose by as much. 0 = apply at once")
    smooth_period_s: float = field(10.0, "republish the RTS-smoothed path at most this often (s of stamp time); 0 = only at the end")
    smooth_lag_s: float = field(60.0, "fixed-lag smoother window (s of stamp time): poses older than this are final and "
                                        "never re-smoothed, so the cost per update stays bounded in long runs")
    path_max_poses: int = field(20000, "pdr_kf/path keeps the newest this many poses (≈ 1.8 h at 0.32 s hops); older "
                                         "ones leave the message (bounded size and memory)")
    frame_id: str = field("map", "frame of the estimates")
    time: TimeParams = group(TimeParams, "which stamps are taken, clock jumps (indoor_loc/pipeline/time_policy.py)")
    motion_source: str = field("pdr", MOTION_DOC)
    odom: OdomIncrementParams = group(OdomIncrementParams, ODOM_GROUP_DOC)
    odom_scale_var_per_m: float = field(1e-5, "motion_source odom: random walk of the odometry's scale error on the "
                                              "travel vector, per metre travelled (1/m)")
    floors: FloorFilterParams = group(FloorFilterParams, "the floor from the fixes' floors and the barometer "
                                                         "(floors.switch_prob, ...)")
    baro: BaroParams = group(BaroParams, "barometer floor-change detector for baro/pressure (baro.hold_s, ...)")
    snap: FloorSnapParams = group(FloorSnapParams, "the floor snapped to the barometric height during "
                                                          "a transit (snap.hysteresis, snap.enabled, ...)")

    def validate(self) -> None:
        n = type(self).__name__
        self.time.validate()
        validate_source(n, self.motion_source)
        self.odom.validate()
        require(self.odom_scale_var_per_m >= 0, n, "odom_scale_var_per_m", ">= 0", self.odom_scale_var_per_m)
        require(self.step_length_m > 0, n, "step_length_m", "> 0", self.step_length_m)
        require(self.smooth_period_s >= 0, n, "smooth_period_s", ">= 0", self.smooth_period_s)
        require(self.smooth_lag_s > 0, n, "smooth_lag_s", "> 0", self.smooth_lag_s)
        require(self.path_max_poses >= 1, n, "path_max_poses", ">= 1", self.path_max_poses)
        require(self.max_fix_delay_s >= 0, n, "max_fix_delay_s", ">= 0", self.max_fix_delay_s)
        require(self.odom_hold_s >= 0, n, "odom_hold_s", ">= 0", self.odom_hold_s)
        require(0.0 < self.gate_prob <= 1.0, n, "gate_prob", "in (0, 1]", self.gate_prob)
        require(self.max_rejected_fixes >= 0, n, "max_rejected_fixes", ">= 0", self.max_rejected_fixes)
        require(self.heading_prior_std_rad >= 0, n, "heading_prior_std_rad", ">= 0", self.heading_prior_std_rad)
        require(self.fix_sigma_min_m > 0, n, "fix_sigma_min_m", "> 0", self.fix_sigma_min_m)
        require(self.fix_late_max_s > 0, n, "fix_late_max_s", "> 0", self.fix_late_max_s)
        require(self.pose_sigma_min_m > 0, n, "pose_sigma_min_m", "> 0", self.pose_sigma_min_m)
        require(self.pose_interval_min_s >= 0, n, "pose_interval_min_s", ">= 0", self.pose_interval_min_s)
        self.kf_params().validate()
        self.floors.validate()
        self.baro.validate()
        self.snap.validate()

    def kf_params(self) -> LinearPdrParams:
        gate = self.gate_prob < 1.0
        return LinearPdrParams(step_length_m=self.kf_step_length_m, sigma_dtheta_rad=self.sigma_dtheta_rad,
                               sigma_ds_m=self.sigma_ds_m, gate=gate, gate_prob=self.gate_prob if gate else 0.5)


def step_heading(x: np.ndarray, P: np.ndarray) -> tuple[float, float]:
    """Heading (rad, map frame) and its variance (rad^2) from the KF's footstep vector ``x[2:4]``:
    ``atan2(v2, v1)``, variance ``J P_vv J^T`` with ``J = [-v2, v1] / |v|^2`` (first order). A step
    vector within one standard deviation (along v) of zero -- not yet observed by fixes -- gives an
    unknown heading: yaw 0 with variance ``YAW_VAR_UNKNOWN``. With WiFi fixes of a few metres the
    variance is typically 0.3-1 rad^2: the filter's heading is weak, and the message says so."""
    v = np.asarray(x[2:4], float)
    Pv = np.asarray(P[2:4, 2:4], float)
    n2 = float(v @ v)
    if n2 <= 0.0 or not np.all(np.isfinite(v)) or n2 < float(v @ Pv @ v) / n2:
        return 0.0, YAW_VAR_UNKNOWN
    J = np.array([-v[1], v[0]]) / n2
    return float(math.atan2(v[1], v[0])), float(min(J @ Pv @ J, YAW_VAR_UNKNOWN))


class PdrKfStage(Stage):
    """Linear PDR Kalman filter + RTS smoother (Raitoharju et al. 2015): pdr/odom + wifi/fix -> pdr_kf/pose, pdr_kf/path."""
    NODE_NAME = "pdr_kf_node"
    PARAMS = PdrKfStageParams
    STAMP_ORDER = {"pdr/odom": Order.STRICT, "odom": Order.STRICT, "wifi/fix": Order.NONDECREASING,
                   "initialpose": Order.EXEMPT, "baro/pressure": Order.STRICT}
    MAP_ODOM = MapOdomSpec(motion=("pdr/odom", "odom"), estimate="pdr_kf/pose", out="pdr_kf/map_odom")

    def __init__(self, params: PdrKfStageParams, *, namespace: str = "") -> None:
        super().__init__(params, namespace=namespace)
        self.n_epochs = 0
        self.smoother_runs = 0
        self.restarts = 0
        self.late_fixes = 0                                # fixes that arrived after later hops were applied
        self.initial_poses = 0                             # restarts at an initialpose / set_pose
        self.floored = 0                                   # fixes / poses claiming more precision than granted
        self._pose_rate = CommandRate(params.pose_interval_min_s)   # pose_burst
        self._fresh_state()
        self.on("pdr/odom", self._on_odom)
        self.on("wifi/fix", self._on_fix)
        self.on("odom", self._on_robot_odom)
        self.on("initialpose", self._on_initialpose)
        self.on("baro/pressure", self._on_baro)

    def _fresh_state(self) -> None:
        """The filter, smoother and queues as before the first message (start-up, a jump back in time)."""
        params = self.params
        self.kf: LinearPdrKf | None = None
        self._odom = PdrOdomReader(params.step_length_m)
        self._robot = RobotOdomReader(params.odom)
        # Fixed-lag smoothing of the current segment: the epochs still inside the window, each
        # [stamp, steps, dtheta, fix or None, online state x (4,)], and the filtered state (x, P)
        # just before the window's first epoch. Epochs leaving the window are final: their
        # smoothed poses go to ``_final`` (stamp, x, y, yaw), bounded by path_max_poses.
        self._epochs: list[list] = []
        self._prior: tuple[np.ndarray, np.ndarray] | None = None
        self._final = PathStore(params.path_max_poses)   # as arrays, 40 bytes a pose (pipeline/path_store.py)
        self._rejected_in_row = 0
        self._last_rejected: tuple[int, np.ndarray, np.ndarray] | None = None   # the run's latest gated-out fix
        self._newest_fix_ns: int | None = None             # newest wifi/fix stamp received (superseded_pose)
        self._pending: list[tuple[int, int, Fix]] = []   # (stamp, arrival seq, fix) waiting for PDR
        self._held: deque[tuple[int, Any, Any]] = deque()  # (stamp, odom, interval) held for odom_hold_s
        self._last_odom_ns: int | None = None             # stamp of the last odom applied
        self._last_yaw: float | None = None                 # yaw of the last odom applied (map frame if calibrated)
        self._seq = 0
        self._last_smooth_ns: int | None = None
        self.floor = FloorTrack(params.baro, params.floors, snap=params.snap)

    def reset_user(self, user: str) -> list[Output]:
        """A jump back in time: the old pass ends as at the end of input (its smoothed path published),
        then the filter waits for the new pass's first fix."""
        outs = self.finish()
        self._fresh_state()
        self._pose_rate.reset()
        return outs

    def upstream_restarted(self, topic: str, user: str) -> list[Output]:
        """A restarted ``pdr/odom`` producer (``imu_node`` killed and started again) publishes from
        its origin: its first pose starts a new odometry frame (no hop across the restart, no
        ``odom_jump`` refusal of the poses after it)."""
        if topic == "pdr/odom":
            self._odom.restart()
            self.notice("pdr/odom: its publisher restarted: a new odometry frame from its next pose")
        return []

    def inputs(self) -> list[Port]:
        return [motion_port(self.params.motion_source),
                Port("wifi/fix", "geometry_msgs/msg/PoseWithCovarianceStamped", Qos.RELIABLE),
                Port("initialpose", "geometry_msgs/msg/PoseWithCovarianceStamped", Qos.RELIABLE, stream=False),
                Port("baro/pressure", "sensor_msgs/msg/FluidPressure", Qos.SENSOR)]

    def outputs(self) -> list[Port]:
        return [Port("pdr_kf/pose", "geometry_msgs/msg/PoseWithCovarianceStamped", Qos.RELIABLE),
                Port("pdr_kf/path", "nav_msgs/msg/Path", Qos.LATCHED),
                Port("pdr_kf/map_odom", "geometry_msgs/msg/TransformStamped", Qos.LATCHED)]

    # ------------------------------------------------------------------------------------------
    def _on_robot_odom(self, msg, recv_ns: int) -> list[Output]:
        """A robot's odometry (``motion_source: odom``): fixes before its stamp go first (the open
        increment closed before them), then its increment, when one closes, is a prediction."""
        require_source(self.params.motion_source, "odom")
        od = self._robot.check(msg)
        if self.map_odom is not None:
            self.map_odom.decoded(msg, od)
        outs = self._apply_pending(lambda s: s < od.stamp_ns)
        inc = self._robot.take(od)
        self._last_odom_ns = od.stamp_ns
        return outs + self._apply_increment(inc)

    def _apply_increment(self, inc: OdomIncrement | None) -> list[Output]:
        if inc is None or self.kf is None:
            return []
        F, Q = odom_transition(inc.distance_m, inc.dtravel_rad, inc.var_along, inc.var_yaw,
                               scale_var_per_m=self.params.odom_scale_var_per_m)
        self.kf.predict_matrix(F, Q, stamp_ns=inc.t_end_ns)
        self._add_epoch(inc.t_end_ns, inc.distance_m, inc.dtravel_rad, (F, Q))
        return [("pdr_kf/pose", self._pose_msg(inc.t_end_ns))] + self._maybe_smooth(inc.t_end_ns)

    def _on_odom(self, msg, recv_ns: int) -> list[Output]:
        require_source(self.params.motion_source, "pdr/odom")
        od, interval = self._odom.read(msg)
        if self.map_odom is not None:
            self.map_odom.decoded(msg, od)
        self._held.append((od.stamp_ns, od, interval))
        hold_ns = int(self.params.odom_hold_s * 1e9)
        return self._release(lambda s: s <= od.stamp_ns - hold_ns)

    def _release(self, due) -> list[Output]:
        """Apply the held hops whose stamp is ``due``, in order."""
        outs: list[Output] = []
        while self._held and due(self._held[0][0]):
            _, od, interval = self._held.popleft()
            outs += self._apply_odom(od, interval)
        return outs

    def _apply_odom(self, od, interval) -> list[Output]:
        outs = self._apply_pending(lambda s: s < od.stamp_ns)   # fixes inside the interval just closed
        self._last_odom_ns = od.stamp_ns
        self._last_yaw = od.yaw
        if interval is None or self.kf is None:
            return outs
        self.kf.predict(interval.steps, interval.dtheta, stamp_ns=od.stamp_ns)
        self._add_epoch(od.stamp_ns, interval.steps, interval.dtheta)
        outs.append(("pdr_kf/pose", self._pose_msg(od.stamp_ns)))
        return outs + self._maybe_smooth(od.stamp_ns)

    def _add_epoch(self, stamp_ns: int, steps: float, dtheta: float, fq: tuple | None = None) -> None:
        assert self.kf is not None
        self._epochs.append([stamp_ns, steps, dtheta, None, self.kf.state.x.copy(), fq])
        self.n_epochs += 1
        lag_ns = int(self.params.smooth_lag_s * 1e9)
        if stamp_ns - self._epochs[0][0] > 2 * lag_ns:     # amortised: every lag, O(2 lag) work
            self._smooth_window(finalize_before=stamp_ns - lag_ns)

    def _on_fix(self, msg, recv_ns: int) -> list[Output]:
        """Fixes wait until PDR has caught up with their stamp (the stepometer publishes each hop
        about half a window late), so each is applied at its place in stamp order; one older than
        the newest odom, or waiting longer than ``max_fix_delay_s``, is applied at once."""
        fix = fix_from_msg(msg, frame_id=self.params.frame_id)   # bad_covariance, wrong_frame
        check_fix_timely(fix.stamp_ns, self._last_odom_ns, self.params.fix_late_max_s)   # fix_too_late
        cov, floored = floor_cov(fix.cov, self.params.fix_sigma_min_m)
        if floored:
            self.floored += 1
            fix = replace(fix, cov=cov)
        self._newest_fix_ns = max(fix.stamp_ns, self._newest_fix_ns or fix.stamp_ns)
        self._seq += 1
        bisect.insort(self._pending, (fix.stamp_ns, self._seq, fix))
        last_odom = self._last_odom_ns
        if last_odom is not None and fix.stamp_ns < last_odom:
            self.late_fixes += 1          # applied now, out of stamp order (see odom_hold_s)
        horizon = self._pending[-1][0] - int(self.params.max_fix_delay_s * 1e9)
        return self._apply_pending(lambda s: s <= horizon or (last_odom is not None and s < last_odom))

    def _on_initialpose(self, msg, recv_ns: int) -> list[Output]:
        """Restart the filter at a pose with its covariance (as at a first fix; the segment before is
        final). Stamp 0 (a command) is taken as the newest hop's; fixes older than it are dropped."""
        fix = initial_pose_from_msg(msg, frame_id=self.params.frame_id)
        check_pose_current(fix.stamp_ns, self._newest_fix_ns, self._last_odom_ns,   # superseded_pose, pose_ahead
                           self.params.time.max_future_s)
        self._pose_rate.check(recv_ns, self.set_pose_call)   # pose_burst (a pose refused above is no command)
        cov, floored = floor_cov(fix.cov, self.params.pose_sigma_min_m)
        self.floored += int(floored)
        stamp = fix.stamp_ns or (self._last_odom_ns or 0)
        outs = self._release(lambda s: s <= stamp)              # hops before it belong to the old segment
        self._pending = [p for p in self._pending if p[0] > stamp]
        self._start(replace(fix, stamp_ns=stamp, cov=cov))
        self.initial_poses += 1
        return outs + [("pdr_kf/pose", self._pose_msg(stamp))]

    def _on_baro(self, msg, recv_ns: int) -> list[Output]:
        ps = pressure_from_msg(msg)
        self.floor.baro(ps.stamp_ns, ps.pressure_pa)
        if self.floor.moved and self.kf is not None and ps.stamp_ns > self.kf.state.stamp_ns:
            # the floor changed with no step or fix to carry it (standing in a lift): the pose now
            return [("pdr_kf/pose", self._pose_msg(ps.stamp_ns))]
        return []

    def _apply_pending(self, due) -> list[Output]:
        outs: list[Output] = []
        if self.params.motion_source == "odom" and self._pending and due(self._pending[0][0]):
            outs += self._apply_increment(self._robot.flush())     # the robot's motion up to now first
        while self._pending and due(self._pending[0][0]):
            stamp, _, fix = self._pending.pop(0)
            outs += self._release(lambda s, f=stamp: s < f)      # held hops before the fix come first
            outs.append(self._apply_fix(fix))
        return outs

    def _apply_fix(self, fix: Fix) -> Output:
        self.floor.fix(fix.stamp_ns, fix.z, fix.z_var)
        if self.kf is None:
            self._start(fix)
            return ("pdr_kf/pose", self._pose_msg(fix.stamp_ns))
        if self._epochs[-1][3] is not None:   # second fix in one PDR interval: a zero-step epoch
            self.kf.predict(0.0, 0.0, stamp_ns=fix.stamp_ns)
            self._add_epoch(fix.stamp_ns, 0.0, 0.0)
        if self.kf.update(fix):
            self._rejected_in_row = 0
            self._last_rejected = None
            self._epochs[-1][3] = fix
            self._epochs[-1][4] = self.kf.state.x.copy()
        else:
            # a run of gated-out fixes counts only while its fixes agree with each other (the filter
            # left the truth); a fix far from the previous rejected one starts a new run (scattered
            # outliers, hostile fixes) -- indoor_loc/fusion/position_trust.py
            prev, self._last_rejected = self._last_rejected, (fix.stamp_ns, fix.xy, fix.cov)
            agree = prev is not None and fixes_agree(prev, self._last_rejected, self.params.kf_params().gate_threshold)
            self._rejected_in_row = self._rejected_in_row + 1 if agree or prev is None else 1
            limit = self.params.max_rejected_fixes
            if limit and self._rejected_in_row >= limit:
                self.restarts += 1
                self._start(fix)
        return ("pdr_kf/pose", self._pose_msg(fix.stamp_ns))

    def _start(self, fix: Fix) -> None:
        """(Re)start the filter at a fix: the previous segment becomes final, a new one begins."""
        if self._epochs:
            self._smooth_window(finalize_before=None)
        sd = self.params.heading_prior_std_rad
        heading = (self._last_yaw, sd) if sd > 0 and self._last_yaw is not None else None
        self.kf = LinearPdrKf(self.params.kf_params(), xy0=fix.xy, pos_cov0=fix.cov, stamp_ns=fix.stamp_ns,
                              heading=heading)
        st = self.kf.state
        self._prior = (st.x.copy(), st.P.copy())
        self._epochs = [[fix.stamp_ns, 0.0, 0.0, None, st.x.copy(), None]]
        self.n_epochs += 1
        self._rejected_in_row = 0
        self._last_rejected = None

    def _pose_msg(self, stamp_ns: int):
        assert self.kf is not None
        yaw, yaw_var = step_heading(self.kf.state.x, self.kf.state.P)
        z, z_var = self.floor.z()
        pose = pose_cdr if self.raw_outputs else pose_to_msg        # multi-user nodes: the CDR bytes
        return pose(stamp_ns, self.kf.position, yaw, self.kf.position_cov, frame_id=self.params.frame_id,
                    yaw_var=yaw_var, z=z, z_var=z_var)

    def _maybe_smooth(self, now_ns: int) -> list[Output]:
        period = self.params.smooth_period_s
        if period <= 0:
            return []
        if self._last_smooth_ns is not None and now_ns - self._last_smooth_ns < period * 1e9:
            return []
        self._last_smooth_ns = now_ns
        return self._smoothed()

    def _run_window(self) -> tuple[np.ndarray, KfTrack | None]:
        """Smooth the window: filter from its prior with the fixes kept online (the gate already
        decided), then RTS (seed 004, eqs. 23-25). Returns the smoothed states (T, 4) and the
        track; if the estimator fails (a singular matrix...), the online filtered states are
        returned instead and ``smoother_failed`` is counted: what was estimated is never lost."""
        ep = self._epochs
        try:
            assert self._prior is not None
            z, R = fixes_to_arrays([e[3] for e in ep])
            params = replace(self.params.kf_params(), gate=False)
            F = Q = None
            if any(e[5] is not None for e in ep):      # odometry increments: each epoch's own model
                F = np.array([transition_matrix(e[1], e[2]) if e[5] is None else e[5][0] for e in ep])
                Q = np.array([process_noise(params, e[1]) if e[5] is None else e[5][1] for e in ep])
            track = filter_batch(params, np.array([e[1] for e in ep], float), np.array([e[2] for e in ep], float),
                                 z, R, x0=self._prior[0], P0=self._prior[1], F=F, Q=Q)
            xs, _ = rts_smooth(track)
            if not np.all(np.isfinite(xs)):
                raise np.linalg.LinAlgError("non-finite smoothed states")
            self.smoother_runs += 1
            return xs, track
        except (np.linalg.LinAlgError, ValueError, ConfigError) as err:
            self._reject("smoother_failed", f"RTS over {len(ep)} epochs: {type(err).__name__}: {err}; "
                                            "the filtered estimates are kept")
            return np.array([e[4] for e in ep], float).reshape(-1, 4), None

    def _smooth_window(self, finalize_before: int | None) -> tuple[np.ndarray, np.ndarray]:
        """Smooth the window; epochs stamped before ``finalize_before`` (all if None) become final.
        Returns the smoothed states and stamps of the epochs still in the window."""
        if not self._epochs:
            return np.zeros((0, 4)), np.zeros(0, np.int64)
        xs, track = self._run_window()
        stamps = np.array([e[0] for e in self._epochs], np.int64)
        k = len(stamps) if finalize_before is None else int(np.searchsorted(stamps, finalize_before))
        k = min(k, len(stamps) - 1) if finalize_before is not None else k   # keep >= 1 epoch as the window
        if k > 0:
            self._final.extend(stamps[:k], xs[:k, :2], np.arctan2(xs[:k, 3], xs[:k, 2]), np.zeros(k))
        if k > 0:
            if track is not None:
                self._prior = (track.x_filt[k - 1].copy(), track.P_filt[k - 1].copy())
            else:       # no batch track: restart the window from the online state (covariance kept)
                assert self._prior is not None
                self._prior = (np.asarray(self._epochs[k - 1][4], float).copy(), self._prior[1])
            self._epochs = self._epochs[k:]
        return xs[k:], stamps[k:]

    def smoothed(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The path: final poses (fixed-lag smoothed, at most ``path_max_poses``) then the window
        smoothed now: stamps (T,), xy (T, 2), heading (T,) rad (from the step vector)."""
        xs, stamps = self._smooth_window(finalize_before=-1) if self._epochs else (np.zeros((0, 4)),
                                                                                     np.zeros(0, np.int64))
        f_st, f_xy, f_yaw, _ = self._final.arrays()
        keep = max(0, self.params.path_max_poses - len(stamps))
        cut = max(0, len(f_st) - keep)
        f_st, f_xy, f_yaw = f_st[cut:], f_xy[cut:], f_yaw[cut:]
        xs, stamps = xs[-self.params.path_max_poses:], stamps[-self.params.path_max_poses:]
        return (np.concatenate([f_st, np.asarray(stamps, np.int64)]),
                np.concatenate([f_xy, xs[:, :2]]),
                np.concatenate([f_yaw, np.arctan2(xs[:, 3], xs[:, 2])]))

    def _smoothed(self) -> list[Output]:
        stamps, xy, yaw = self.smoothed()
        if len(stamps) == 0:
            return []
        encode = path_cdr if self.raw_outputs else path_to_msg      # the same message (msg_adapters/path_cdr.py)
        return [("pdr_kf/path", encode(stamps, xy, yaw, frame_id=self.params.frame_id,
                                       stamp_ns=int(stamps[-1]), z=self.floor.z_at(stamps)))]

    def finish(self) -> list[Output]:
        outs = self._release(lambda s: True)
        return outs + self._apply_pending(lambda s: True) + self._smoothed()

    def extra_diagnostics(self) -> dict[str, str]:
        if self.kf is None:
            return {"initialised": "false (waiting for the first wifi/fix)", "late_fixes": str(self.late_fixes),
                    **self.floor.diagnostics()}
        st = self.kf.state
        return {"initialised": "true", "epochs": str(self.n_epochs), "window_epochs": str(len(self._epochs)),
                "path_poses": str(len(self._final) + len(self._epochs)),
                "fixes_used_in_segment": str(st.n_updates), "fixes_gated_out_in_segment": str(st.n_rejected),
                "restarts": str(self.restarts), "late_fixes": str(self.late_fixes),
                "precision_floored": str(self.floored),
                "held_odom": str(len(self._held)), "motion_source": self.params.motion_source,
                **(self._robot.diagnostics() if self.params.motion_source == "odom" else {}),
                "position_sigma_m": f"{math.sqrt(max(np.linalg.eigvalsh(self.kf.position_cov))):.2f}",
                **self.floor.diagnostics()}
