"""PfStage: the TLL particle filter on the building graph (``tll_pf`` node, ``--nodes pf`` offline).

Inputs: ``pdr/odom`` (distance and heading per stepometer hop: the particles walk it, the graph
gates them), ``wifi/fix`` (Gaussian position likelihood; ``wifi_update: fix``) or ``wifi/scan``
(the radio map's fingerprints interpolated along the links, :mod:`indoor_loc.pf.wifi_field`;
``wifi_update: scan``, with ``radiomap``), ``initialpose`` (re-initialise around a
pose, as nav2_amcl). Without ``pdr/odom`` the particles move by the two-mode speed model between
fixes. Outputs: ``pf/pose`` (constrained mean + particle covariance + direction of travel, per PDR
hop and per fix), ``pf/particles`` (every ``particles_every`` outputs), ``pf/path`` (the filtered
history every ``path_period_s`` of stamp time; at the end of input the backward-simulation
smoothed path when ``smooth``), ``map/graph`` (latched, once).

Link choices at nodes follow the ``rule`` table computed from the graph, or a learned table
(``transitions_file``, written by ``indoor-loc map learn``; refused, as a ConfigError, unless it
was made for this very graph file).

Fixes (and scans) wait until PDR has reached their stamp (the stepometer publishes about half a window late),
bounded by ``max_fix_delay_s``, so every fix is applied at its place in time; ``pdr/odom`` and
``baro/pressure`` are taken in stamp order across the two topics (the shared reorder buffer,
:mod:`indoor_loc.pipeline.reorder`, at most ``reorder_window_s``): a floor change is applied where
the walker was when the pressure was read, whichever topic arrives first. Stamps are judged by
the time policy every stage shares (:mod:`indoor_loc.pipeline.time_policy`); a confirmed jump back (a
bag played in a loop, a restarted recording) resets the filter (:meth:`PfStage.reset_user`).

Floors (docs/floors.md): on a graph with several floors the particles live on the 3-D graph; a
fix's floor (``wifi/fix`` pose z, covariance[14]) weighs them (``floors.*``) and ``baro/pressure``
(optional) gates their vertical transitions (``baro.*``, :mod:`indoor_loc.pf.floors`). ``pf/pose``
and ``pf/path`` carry z = the height of the estimated floor in ``map`` (covariance[14]: the
variance of the particles' floor heights); the floor id is the graph's floor at that height
(``/diagnostics``: ``floor``).
"""
from __future__ import annotations

import bisect
from dataclasses import dataclass
from typing import Any
from pathlib import Path

import numpy as np

from indoor_loc import params as P
from indoor_loc.contract import Qos
from indoor_loc.errors import ConfigError, InvalidMessageError, MapError
from indoor_loc.pipeline.path_store import PathStore
from indoor_loc.pipeline.reorder import ReorderBuffer
from indoor_loc.fusion.position_trust import (FIX_LATE_MAX_S, FIX_SIGMA_MIN_M, POSE_INTERVAL_MIN_S,
                                              POSE_SIGMA_MIN_M, CommandRate, check_fix_timely,
                                              check_pose_current, floor_cov)
from indoor_loc.graph.io import load_graph
from indoor_loc.graph.tll import TransitionParams, cached_transitions, load_transitions
from msg_adapters.markers import graph_markers
from msg_adapters.odom import OdomJumpGuard, odom_from_msg
from msg_adapters.path import path_to_msg
from msg_adapters.path_cdr import path_cdr
from msg_adapters.pose import fix_from_msg, pose_array_to_msg, pose_from_msg, pose_to_msg
from msg_adapters.pose_cdr import pose_cdr
from indoor_loc.baro.detector import BaroParams
from indoor_loc.baro.snap import FloorSnapParams
from indoor_loc.pf.filter import PfParams
from indoor_loc.pf.floors import PfFloorParams
from indoor_loc.pf.smoother_budget import SmootherBudget
from indoor_loc.pf.tracker import Estimate, GraphTracker, MonitorParams
from indoor_loc.pf.wifi_field import EdgeFingerprintField, ScanFieldParams
from indoor_loc.wifi.radiomap import load_radiomap
from msg_adapters.pressure import pressure_from_msg
from msg_adapters.wifi_scan import scan_from_msg
from indoor_loc.pipeline.bounds import MapBox
from indoor_loc.pipeline.map_odom import MapOdomSpec
from indoor_loc.pipeline.stage import Output, Port, Stage
from indoor_loc.pipeline.time_policy import Order, TimeParams
from indoor_loc.odometry.increments import OdomIncrement, OdomIncrementParams
from indoor_loc.pipeline.motion_source import MOTION_DOC, ODOM_GROUP_DOC, motion_port, require_source, validate_source
from msg_adapters.robot_odom import RobotOdomReader

POSE_T = "geometry_msgs/msg/PoseWithCovarianceStamped"



#: Estimates the tracker keeps as objects (the newest; one is replaced when a fix re-initialises at its stamp) ...
ESTIMATES_KEPT = 8
#: ... and how many more it gathers before they move to the stage's path arrays (amortised).
ARCHIVE_EVERY = 256


def _pose_arrays(ests: list[Estimate]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """stamps (K,), xy (K, 2), yaw (K,) (0 where not finite, as published), z (K,) of estimates."""
    return (np.array([e.stamp_ns for e in ests], np.int64).reshape(-1),
            np.array([e.xy for e in ests], float).reshape(-1, 2),
            np.array([e.yaw if np.isfinite(e.yaw) else 0.0 for e in ests], float).reshape(-1),
            np.array([e.z for e in ests], float).reshape(-1))

@dataclass(frozen=True)
class PfStageParams:
    """Parameters of ``tll_pf`` (see config/tll_pf.yaml)."""
    graph_file: str = P.field("", "building graph file (format indoor_loc.graph v1); its TLL table is cached beside it")
    wifi_update: str = P.field("fix", "WiFi measurement: fix (wifi/fix, Gaussian) or scan (wifi/scan against the radio "
                                      "map interpolated along the links)")
    radiomap: str = P.field("", "radio map directory for wifi_update: scan")
    transitions_file: str = P.field("", "learned transition table for graph_file (`indoor-loc map learn`); "
                                        "empty = the table of rule from the graph")
    rule: str = P.field("tll", "link transition rule at nodes: tll, uniform or angle")
    l_max_m: float = P.field(40.0, "TLL destination horizon l_MAX (m)")
    p_min: float = P.field(0.02, "smallest transition probability at a junction")
    p_max: float = P.field(0.98, "largest transition probability at a junction")
    n_particles: int = P.field(1000, "number of particles (the initial count when adaptive)")
    adaptive: bool = P.field(False, "adapt the particle count: KLD-sampling bound at resampling, covariance rule at "
                                    "(re)initialisation")
    n_min: int = P.field(200, "fewest particles when adaptive")
    n_max: int = P.field(20000, "most particles when adaptive")
    kld_epsilon: float = P.field(0.05, "KLD-sampling bound epsilon")
    kld_bin_m: float = P.field(1.0, "KLD bin length along a link (m)")
    heading_sigma_rad: float = P.field(1.2, "PDR heading vs direction of travel on the link (rad)")
    yaw_offset_sigma_rad: float = P.field(3.2, "odom->map heading offset spread at start (rad); >= pi = unknown, learnt by the filter")
    fix_sigma_extra_m: float = P.field(0.76, "added to each WiFi fix's standard deviation per axis (m)")
    fix_cov_scale: float = P.field(0.73, "each WiFi fix's covariance is multiplied by this before fix_sigma_extra_m is "
                                         "added (its calibration against measured errors)")
    fix_dof: float = P.field(6.0, "WiFi fix likelihood: 0 = Gaussian, > 0 = Student-t with this many degrees of freedom")
    inject_mass: float = P.field(0.15, "prior probability mass of the particles redrawn around each WiFi fix")
    fix_late_max_s: float = P.field(FIX_LATE_MAX_S, "a wifi/fix stamped more than this before the newest pdr/odom "
                                                  "applied is refused (fix_too_late; s, indoor_loc/fusion/position_trust.py)")
    fix_sigma_min_m: float = P.field(FIX_SIGMA_MIN_M, "a wifi/fix is never taken as more precise than this std per "
                                                      "direction (m; indoor_loc/fusion/position_trust.py)")
    pose_sigma_min_m: float = P.field(POSE_SIGMA_MIN_M, "an initialpose is never taken as more precise than this std "
                                                        "per direction (m; indoor_loc/fusion/position_trust.py)")
    pose_interval_min_s: float = P.field(POSE_INTERVAL_MIN_S, "an initialpose received less than this after the "
                                         "previous one is refused (pose_burst: faster than a person gives "
                                         "poses; s of the node's clock, indoor_loc/fusion/position_trust.py)")
    max_fix_delay_s: float = P.field(5.0, "a WiFi fix waits at most this long for pdr/odom to reach its stamp (s)")
    reorder_window_s: float = P.field(1.0, "pdr/odom and baro/pressure are taken in stamp order across the two "
                                           "topics: a message waits until the other stream has reached its stamp, "
                                           "at most this long (s of stamp time, or of the node's clock when both "
                                           "stop; indoor_loc/pipeline/reorder.py)")
    particles_every: int = P.field(5, "publish pf/particles every this many pose outputs; 0 = never")
    path_period_s: float = P.field(10.0, "republish the filtered pf/path at most this often (s of stamp time); 0 = only at the end")
    smooth: bool = P.field(True, "at the end of input publish the backward-simulation smoothed pf/path")
    smooth_samples: int = P.field(50, "backward-simulated trajectories averaged by the smoother")
    smooth_window_s: float = P.field(600.0, "the smoother keeps the particles of this much stamp time (about 40 kB "
                                            "per 1000 particles and pose: 10 min of walking ≈ 90 MB), so memory "
                                            "stays bounded in long runs; the path before it stays filtered, s")
    path_max_poses: int = P.field(20000, "pf/path holds the newest this many poses (≈ 1.8 h of walking)")
    smooth_max_mb: float = P.field(160.0, "the smoother's particles never hold more than this (MB), whatever the "
                                          "input rate: past it the oldest steps go before smooth_window_s ends "
                                          "(fast odometry, many particles); 0 = only smooth_window_s bounds them "
                                          "(indoor_loc/pf/smoother_budget.py)")
    smooth_redrawn: str = P.field("chain", "smoother: predecessor of a particle redrawn around a WiFi fix (sensor "
                                           "resetting): chain = its nearest particles by the motion model (fixes "
                                           "trusted to correct a lagging filter, as on PUTMC); mixture = the filter's "
                                           "own transition, (1 - inject_mass) motion + inject_mass jump, so a jump far "
                                           "from every particle does not drag the smoothed past (broad, sometimes "
                                           "wrong fixes, as on the ms_site2 mall); wifi_update fix only (the scan "
                                           "update's redrawn particles are always chained)")
    seed: int = P.field(0, "random seed of the filter (runs are reproducible)")
    frame_id: str = P.field("map", "frame of the graph and the estimates")
    scan: ScanFieldParams = P.group(ScanFieldParams, "scan likelihood on the links for wifi_update: scan "
                                                     "(scan.sigma_db, scan.kernel_m, ...)")
    monitor: MonitorParams = P.group(MonitorParams, "divergence monitoring by the linear PDR Kalman filter "
                                                    "(monitor.enabled, monitor.gate_prob, ...)")
    floors: PfFloorParams = P.group(PfFloorParams, "floors on a multi-floor graph: the fixes' floors and the "
                                                   "barometer gate (floors.fix_floor, floors.baro_floor_wrong, ...)")
    baro: BaroParams = P.group(BaroParams, "barometer floor-change detector for baro/pressure (baro.hold_s, ...)")
    snap: FloorSnapParams = P.group(FloorSnapParams, "the floor snapped to the barometric height during "
                                                          "a transit (snap.hysteresis, snap.enabled, ...)")
    time: TimeParams = P.group(TimeParams, "which stamps are taken, clock jumps (indoor_loc/pipeline/time_policy.py)")
    motion_source: str = P.field("pdr", MOTION_DOC)
    odom: OdomIncrementParams = P.group(OdomIncrementParams, ODOM_GROUP_DOC)

    def validate(self) -> None:
        n = type(self).__name__
        validate_source(n, self.motion_source)
        self.odom.validate()
        P.require(self.max_fix_delay_s >= 0, n, "max_fix_delay_s", ">= 0", self.max_fix_delay_s)
        P.require(self.reorder_window_s >= 0, n, "reorder_window_s", ">= 0", self.reorder_window_s)
        P.require(self.fix_sigma_min_m > 0, n, "fix_sigma_min_m", "> 0", self.fix_sigma_min_m)
        P.require(self.fix_late_max_s > 0, n, "fix_late_max_s", "> 0", self.fix_late_max_s)
        P.require(self.pose_sigma_min_m > 0, n, "pose_sigma_min_m", "> 0", self.pose_sigma_min_m)
        P.require(self.pose_interval_min_s >= 0, n, "pose_interval_min_s", ">= 0", self.pose_interval_min_s)
        self.time.validate()
        P.require(self.particles_every >= 0, n, "particles_every", ">= 0", self.particles_every)
        P.require(self.path_period_s >= 0, n, "path_period_s", ">= 0", self.path_period_s)
        P.require(self.smooth_samples >= 1, n, "smooth_samples", ">= 1", self.smooth_samples)
        P.require(self.smooth_window_s > 0, n, "smooth_window_s", "> 0", self.smooth_window_s)
        P.require(self.path_max_poses >= 1, n, "path_max_poses", ">= 1", self.path_max_poses)
        P.require(self.smooth_max_mb >= 0, n, "smooth_max_mb", ">= 0", self.smooth_max_mb)
        P.require(self.smooth_redrawn in ("chain", "mixture"), n, "smooth_redrawn", "chain or mixture",
                  self.smooth_redrawn)
        P.require(self.wifi_update in ("fix", "scan"), n, "wifi_update", "fix or scan", self.wifi_update)
        P.require(self.wifi_update != "scan" or bool(self.radiomap), n, "radiomap", "a radio map directory when "
                  "wifi_update is scan", self.radiomap)
        self.scan.validate()
        self.transition_params().validate()
        self.pf_params().validate()
        self.monitor.validate()
        self.floors.validate()
        self.baro.validate()
        self.snap.validate()

    def transition_params(self) -> TransitionParams:
        return TransitionParams(rule=self.rule, l_max_m=self.l_max_m, p_min=self.p_min, p_max=self.p_max)

    def pf_params(self) -> PfParams:
        return PfParams(n_particles=self.n_particles, heading_sigma_rad=self.heading_sigma_rad,
                        yaw_offset_sigma_rad=self.yaw_offset_sigma_rad, fix_sigma_extra_m=self.fix_sigma_extra_m,
                        fix_cov_scale=self.fix_cov_scale, fix_dof=self.fix_dof, inject_mass=self.inject_mass,
                        adaptive=self.adaptive, n_min=self.n_min, n_max=self.n_max, kld_epsilon=self.kld_epsilon,
                        kld_bin_m=self.kld_bin_m)


class PfStage(Stage):
    """TLL particle filter: pdr/odom + wifi/fix (+ initialpose) -> pf/pose, pf/particles, pf/path, map/graph."""
    NODE_NAME = "tll_pf"
    PARAMS = PfStageParams
    STAMP_ORDER = {"pdr/odom": Order.STRICT, "odom": Order.STRICT, "wifi/fix": Order.NONDECREASING,
                   "wifi/scan": Order.NONDECREASING, "initialpose": Order.EXEMPT, "baro/pressure": Order.STRICT}
    MAP_ODOM = MapOdomSpec(motion=("pdr/odom", "odom"), estimate="pf/pose", out="pf/map_odom")

    def __init__(self, params: PfStageParams, *, namespace: str = "", shared: PfStage | None = None) -> None:
        """``shared``: another instance whose graph, transition table and radio-map field (read-only)
        this one uses instead of loading them again (:meth:`for_user`)."""
        super().__init__(params, namespace=namespace)
        self._pending: list[tuple[int, int, Any]] = []
        #: pdr/odom and baro/pressure in stamp order across the two topics (indoor_loc/pipeline/reorder.py)
        self._order = ReorderBuffer()
        self._order_recv_ns: int | None = None      # node clock at the newest message queued in it
        self.reorder_late = 0                       # taken at once: older than a message of the other topic taken
        self.floored = 0                    # fixes / poses claiming more precision than granted
        self._pose_rate = CommandRate(params.pose_interval_min_s)   # pose_burst
        self._newest_fix_ns: int | None = None      # newest wifi/fix stamp received (superseded_pose)
        self.on("pdr/odom", self._on_odom)
        self.on("wifi/fix", self._on_fix)
        self.on("wifi/scan", self._on_scan)
        self.field: EdgeFingerprintField | None = None
        self.on("initialpose", self._on_initialpose)
        self.on("odom", self._on_robot_odom)
        self._robot = RobotOdomReader(params.odom)
        self.on("baro/pressure", self._on_baro)
        self._odom_guard = OdomJumpGuard()
        self.map_box: MapBox | None = None
        if shared is not None:
            self.graph, self.map_box, self.field = shared.graph, shared.map_box, shared.field
            if self.graph is None:
                return
            self.transitions, self.cache_hit = shared.transitions, shared.cache_hit
        elif not params.graph_file:
            # the node starts (so parameters can be inspected) but rejects every message, counted
            # under "no_graph" in /diagnostics
            self.graph = None
            return
        else:
            self._load(params)
        self.tracker = self._new_tracker()
        #: estimates older than the tracker's newest few, as arrays (pipeline/path_store.py): the bound of pf/path
        self._archive = PathStore(self.params.path_max_poses)
        #: the smoother's particles within smooth_max_mb, whatever the input rate (pf/smoother_budget.py)
        self._budget = SmootherBudget(int(self.params.smooth_max_mb * 2**20))
        self._seq = 0
        self._last_odom_ns: int | None = None
        self._graph_sent = False
        self._n_pose = 0
        self._last_path_ns: int | None = None

    def _load(self, params: PfStageParams) -> None:
        """The graph, its transition table and (``wifi_update: scan``) the radio-map field."""
        path = Path(params.graph_file)
        try:
            self.graph = load_graph(path)
        except MapError as err:
            raise ConfigError(f"tll_pf: graph_file: {err}") from err
        self.map_box = MapBox.around(self.graph.node_xyz[:, :2])     # fixes and initial poses far off it: off_map
        if params.transitions_file:
            # a learned table (Dirichlet-updated link choices) replaces the rule's: it must have been
            # made for this very graph file, else the start-up fails (exit 2) rather than run on a
            # table whose rows belong to other junctions
            try:
                self.transitions = load_transitions(Path(params.transitions_file).expanduser(), self.graph, path)
            except MapError as err:
                raise ConfigError(f"tll_pf: transitions_file: {err}") from err
            self.cache_hit = False
        else:
            self.transitions, self.cache_hit = cached_transitions(self.graph, path, params.transition_params())
        if params.wifi_update == "scan":
            try:
                self.field = EdgeFingerprintField(self.graph, load_radiomap(Path(params.radiomap).expanduser()),
                                                  params.scan)
            except MapError as err:
                raise ConfigError(f"tll_pf: radiomap: {err}") from err

    def for_user(self, namespace: str) -> PfStage:
        """A fresh filter for another user, sharing this one's graph, table and field."""
        return type(self)(self.params, namespace=namespace, shared=self)

    def reset_user(self, user: str) -> list[Output]:
        """A jump back in time: the old pass's path is published (as at the end of input), then the
        filter waits for the new pass's first fix or initial pose (as at start-up)."""
        outs = self.finish()
        self.tracker = self._new_tracker()          # its seed again: the same pass, the same output
        self._archive.clear()
        self._pending.clear()
        self._order = ReorderBuffer()
        self._order_recv_ns = None
        self._newest_fix_ns = None
        self._last_odom_ns = None
        self._last_path_ns = None
        self._n_pose = 0
        self._odom_guard = OdomJumpGuard()
        self._robot = RobotOdomReader(self.params.odom)
        self._pose_rate.reset()
        return outs

    def upstream_restarted(self, topic: str, user: str) -> list[Output]:
        """A restarted ``pdr/odom`` producer (``imu_node`` killed and started again) publishes from
        its origin: its first pose starts a new odometry frame (no walk across the restart, no
        ``odom_jump`` refusal of the poses after it; the particles stay where they are)."""
        if topic == "pdr/odom":
            outs = self._drain_order()             # the old frame's hops first
            self._odom_guard.restart()
            self.tracker.new_odom_frame()
            self.notice("pdr/odom: its publisher restarted: a new odometry frame from its next pose")
            return outs
        return []

    def _new_tracker(self) -> GraphTracker:
        p = self.params
        assert self.graph is not None
        return GraphTracker(self.graph, self.transitions, p.pf_params(), rng=np.random.default_rng(p.seed),
                            monitor=p.monitor, floors=p.floors, baro=p.baro, snap=p.snap)

    def inputs(self) -> list[Port]:
        wifi = (Port("wifi/scan", "diagnostic_msgs/msg/DiagnosticArray", Qos.RELIABLE)
                if self.params.wifi_update == "scan" else Port("wifi/fix", POSE_T, Qos.RELIABLE))
        return [motion_port(self.params.motion_source),
                wifi,
                Port("initialpose", POSE_T, Qos.RELIABLE, stream=False),
                Port("baro/pressure", "sensor_msgs/msg/FluidPressure", Qos.SENSOR)]

    def outputs(self) -> list[Port]:
        return [Port("pf/pose", POSE_T, Qos.LATCHED),
                Port("pf/particles", "geometry_msgs/msg/PoseArray", Qos.BEST_EFFORT),
                Port("pf/path", "nav_msgs/msg/Path", Qos.LATCHED),
                Port("map/graph", "visualization_msgs/msg/MarkerArray", Qos.LATCHED),
                Port("pf/map_odom", "geometry_msgs/msg/TransformStamped", Qos.LATCHED)]

    # ------------------------------------------------------------------------------------------
    def _start(self, stamp_ns: int) -> list[Output]:
        """map/graph once."""
        if self.graph is None:
            raise InvalidMessageError("no_graph", "graph_file is not set: give the tll_pf node a building graph "
                                      "(format indoor_loc.graph v1; `indoor-loc import putmc` writes one)")
        outs: list[Output] = []
        if not self._graph_sent:
            self._graph_sent = True
            outs.append(("map/graph", graph_markers(self.graph.node_xyz[:, :2], self.graph.link_nodes.astype(np.int64),
                                                    self.params.frame_id, stamp_ns, ns="map/graph")))
        return outs

    def _on_robot_odom(self, msg, recv_ns: int) -> list[Output]:
        """A robot's odometry (``motion_source: odom``): fixes before its stamp go first (the open
        increment closed before them), then its increment, when one closes, moves the particles."""
        require_source(self.params.motion_source, "odom")
        od = self._robot.check(msg)
        if self.map_odom is not None:
            self.map_odom.decoded(msg, od)
        outs = self._start(od.stamp_ns)
        outs += self._apply_pending(lambda s: s < od.stamp_ns)
        inc = self._robot.take(od)
        self._last_odom_ns = od.stamp_ns
        return outs + self._apply_increment(inc)

    def _apply_increment(self, inc: OdomIncrement | None) -> list[Output]:
        if inc is None:
            return []
        est = self.tracker.increment(inc.t_end_ns, inc.distance_m, inc.travel_rad, var_along=inc.var_along,
                                     var_yaw=inc.var_yaw)
        return self._publish(est) if est is not None else []

    def _on_odom(self, msg, recv_ns: int) -> list[Output]:
        require_source(self.params.motion_source, "pdr/odom")
        od = odom_from_msg(msg)
        if self.map_odom is not None:
            self.map_odom.decoded(msg, od)
        self._odom_guard.check(od)                     # odom_jump: refused before anything moves
        outs = self._start(od.stamp_ns)
        self._odom_guard.accept(od)
        return outs + self._in_order(od.stamp_ns, "pdr/odom", od, recv_ns)

    def _take_odom(self, od) -> list[Output]:
        outs = self._apply_pending(lambda s: s < od.stamp_ns)
        self._last_odom_ns = od.stamp_ns
        est = self.tracker.odom(od.stamp_ns, od.x, od.y, od.yaw)
        if est is not None:
            outs += self._publish(est)
        return outs

    def _in_order(self, stamp_ns: int, topic: str, payload, recv_ns: int) -> list[Output]:
        """pdr/odom and baro/pressure through the reorder buffer: taken once the other stream (while it
        flows) has reached their stamp. One older than a message already taken (the other stream more
        than the window behind) is taken at once and counted (``reorder_late``)."""
        self._order.note(topic, stamp_ns)          # (a stream's first message may come late: it flows now)
        if self._order.late(stamp_ns):
            self.reorder_late += 1
            return self._take(topic, payload)
        self._order.push(stamp_ns, 0 if topic == "baro/pressure" else 1, (topic, payload))
        self._order_recv_ns = recv_ns
        outs: list[Output] = []
        for _, _, (t, item) in self._order.due(self._order.mark(int(self.params.reorder_window_s * 1e9))):
            outs += self._take(t, item)
        return outs

    def _take(self, topic: str, payload) -> list[Output]:
        return self._take_baro(payload) if topic == "baro/pressure" else self._take_odom(payload)

    def _drain_order(self) -> list[Output]:
        outs: list[Output] = []
        for _, _, (t, item) in self._order.drain():
            outs += self._take(t, item)
        return outs

    def _on_fix(self, msg, recv_ns: int) -> list[Output]:
        if self.params.wifi_update != "fix":
            raise InvalidMessageError("wrong_wifi_update", "wifi/fix received but wifi_update is scan")
        fix = fix_from_msg(msg)
        if self.map_box is not None:
            self.map_box.check("wifi/fix", fix.xy)
        if self.graph is not None:                                   # (else no_graph below)
            check_fix_timely(fix.stamp_ns, self._last_odom_ns, self.params.fix_late_max_s)   # fix_too_late
        cov, floored = floor_cov(fix.cov, self.params.fix_sigma_min_m)
        self.floored += int(floored)
        self._newest_fix_ns = max(fix.stamp_ns, self._newest_fix_ns or fix.stamp_ns)
        return self._queue(fix.stamp_ns, "wifi/fix", (fix.xy, cov, fix.z, fix.z_var))

    def _on_scan(self, msg, recv_ns: int) -> list[Output]:
        if self.graph is not None and self.field is None:
            raise InvalidMessageError("wrong_wifi_update", "wifi/scan received but wifi_update is fix")
        scan = scan_from_msg(msg)
        if self.field is not None and self.field.known_aps(scan) == 0:
            raise InvalidMessageError("no_known_ap", f"wifi/scan at {scan.stamp_ns}: none of its {len(scan)} APs is "
                                      "in the radio map")
        return self._queue(scan.stamp_ns, "wifi/scan", scan)

    def _queue(self, stamp_ns: int, topic: str, payload) -> list[Output]:
        outs = self._start(stamp_ns)
        self._seq += 1
        bisect.insort(self._pending, (stamp_ns, self._seq, payload))
        if self._last_odom_ns is None:
            # no PDR (yet): a fix waits max_fix_delay_s for it — the stepometer reports its first hop
            # seconds after the first scan, and a pose applied now would be followed by older ones —
            # then the speed model moves the particles (:meth:`tick` releases it on the node's clock)
            horizon = self._pending[-1][0] - int(self.params.max_fix_delay_s * 1e9)
            return outs + self._apply_pending(lambda s: s <= horizon, speed=True)
        horizon = self._pending[-1][0] - int(self.params.max_fix_delay_s * 1e9)
        last = self._last_odom_ns
        return outs + self._apply_pending(lambda s: s <= horizon or s < last)

    def _on_baro(self, msg, recv_ns: int) -> list[Output]:
        ps = pressure_from_msg(msg)
        outs = self._start(ps.stamp_ns)
        return outs + self._in_order(ps.stamp_ns, "baro/pressure", ps, recv_ns)

    def _take_baro(self, ps) -> list[Output]:
        outs: list[Output] = []
        self.tracker.baro(ps.stamp_ns, ps.pressure_pa)
        last = self.tracker.estimates[-1].stamp_ns if self.tracker.estimates else None
        if self.tracker.baro_track.moved and self.tracker.pf.initialised and last is not None and ps.stamp_ns > last:
            # the floor changed with no step or fix to carry it (standing in a lift): the pose now
            outs += self._publish(self.tracker.current(ps.stamp_ns))
        return outs

    def _on_initialpose(self, msg, recv_ns: int) -> list[Output]:
        ps = pose_from_msg(msg)
        if self.map_box is not None:
            self.map_box.check("initialpose", ps.xy)
        check_pose_current(ps.stamp_ns, self._newest_fix_ns,                 # superseded_pose, pose_ahead
                           self._last_odom_ns if self.graph is not None else None, self.params.time.max_future_s)
        self._pose_rate.check(recv_ns, self.set_pose_call)   # pose_burst (a pose refused above is no command)
        outs = self._start(ps.stamp_ns)
        cov, floored = floor_cov(ps.cov_xy, self.params.pose_sigma_min_m)   # (a zero covariance: the floor)
        self.floored += int(floored)
        floor = self.tracker.fix_floor(float(msg.pose.pose.position.z), 0.0)       # z: the floor's height
        return outs + self._publish(self.tracker.reset_at(ps.stamp_ns, ps.xy, cov, inflate=False,   # as given
                                                          floor=None if floor is None else floor[0]))

    def global_localization(self, stamp_ns: int) -> list[Output]:
        """Spread the particles over the whole graph (the ``~/global_localization`` service)."""
        if self.graph is None:
            return []
        return self._publish(self.tracker.global_localization(stamp_ns))

    def tick(self, now_ns: int) -> list[Output]:
        """Without PDR (yet): the fixes waiting longer than ``max_fix_delay_s`` of the node's clock go on
        the speed model. Messages in the reorder buffer go when nothing came for ``reorder_window_s``."""
        outs: list[Output] = []
        if len(self._order) and now_ns and self._order_recv_ns is not None and (
                now_ns - self._order_recv_ns >= int(self.params.reorder_window_s * 1e9)):
            outs += self._drain_order()           # both streams stopped: what waits for them goes now
        if self._last_odom_ns is not None or not self._pending or not now_ns:
            return outs
        horizon = now_ns - int(self.params.max_fix_delay_s * 1e9)
        return outs + self._apply_pending(lambda s: s <= horizon, speed=True)

    def _apply_pending(self, due, *, speed: bool = False) -> list[Output]:
        outs: list[Output] = []
        if self.params.motion_source == "odom" and self._pending and due(self._pending[0][0]):
            outs += self._apply_increment(self._robot.flush())     # the robot's motion up to now first
        while self._pending and due(self._pending[0][0]):
            stamp, _, payload = self._pending.pop(0)
            if isinstance(payload, tuple):
                est = self.tracker.fix(stamp, payload[0], payload[1], use_speed_model=speed, z=payload[2],
                                       z_var=payload[3])
            else:
                assert self.field is not None
                est = self.tracker.scan(stamp, self.field, payload, use_speed_model=speed)
            if est is not None:
                outs += self._publish(est)
        return outs

    # ------------------------------------------------------------------------------------------
    def _publish(self, est: Estimate) -> list[Output]:
        fid = self.params.frame_id
        pose = pose_cdr if self.raw_outputs else pose_to_msg        # multi-user nodes: the CDR bytes
        outs: list[Output] = [("pf/pose", pose(est.stamp_ns, est.xy, est.yaw, est.cov, frame_id=fid,
                                               yaw_var=0.1, z=est.z, z_var=est.z_var))]
        self._n_pose += 1
        every = self.params.particles_every
        p = self.tracker.pf.p
        if every and p is not None and self._n_pose % every == 0:
            xy = self.tracker.pf.xy()
            yaw = self.tracker.pf._travel_heading(p.link, p.direction)
            outs.append(("pf/particles", pose_array_to_msg(est.stamp_ns, xy, yaw, frame_id=fid)))
        period = self.params.path_period_s
        if period > 0 and (self._last_path_ns is None or est.stamp_ns - self._last_path_ns >= period * 1e9):
            self._last_path_ns = est.stamp_ns
            outs += self._path(self.tracker.estimates)
        self._bound_memory(est.stamp_ns)
        return outs

    def _bound_memory(self, stamp_ns: int) -> None:
        """Keep the smoother's particles of the last ``smooth_window_s`` (trimmed in steps of a quarter
        window, so the work per pose stays small) and the newest ``path_max_poses`` estimates: all but
        the tracker's newest :data:`ESTIMATES_KEPT` move, every :data:`ARCHIVE_EVERY`, to the arrays of
        ``_archive`` (40 bytes a pose instead of ~460: memory stays flat while the path fills)."""
        window = int(self.params.smooth_window_s * 1e9)
        oldest = next((seg[0].stamp_ns for seg in self.tracker.segments + [self.tracker.history] if seg), None)
        if oldest is not None and stamp_ns - oldest > window + window // 4:
            self.tracker.forget_before(stamp_ns - window, self.params.path_max_poses)
        self._budget.after_step(self.tracker, self.params.path_max_poses)
        ests = self.tracker.estimates
        if len(ests) >= ESTIMATES_KEPT + ARCHIVE_EVERY:
            moved = ests[:len(ests) - ESTIMATES_KEPT]
            self._archive.extend(*_pose_arrays(moved))
            del ests[:len(moved)]

    def _path(self, ests: list[Estimate], *, before_ns: int | None = None) -> list[Output]:
        """``pf/path``: the archived estimates (those stamped before ``before_ns`` if given), then
        ``ests``; the newest ``path_max_poses`` of them, in stamp order."""
        a_st, a_xy, a_yaw, a_z = self._archive.arrays()
        if before_ns is not None:
            keep = a_st < before_ns
            a_st, a_xy, a_yaw, a_z = a_st[keep], a_xy[keep], a_yaw[keep], a_z[keep]
        e_st, e_xy, e_yaw, e_z = _pose_arrays(ests)
        cap = self.params.path_max_poses
        stamps = np.concatenate([a_st, e_st])[-cap:]
        if not len(stamps):
            return []
        xy = np.concatenate([a_xy, e_xy])[-cap:]
        yaw = np.concatenate([a_yaw, e_yaw])[-cap:]
        z = np.concatenate([a_z, e_z])[-cap:]
        order = np.argsort(stamps, kind="stable")
        encode = path_cdr if self.raw_outputs else path_to_msg      # the same message (msg_adapters/path_cdr.py)
        return [("pf/path", encode(stamps[order], xy[order], yaw[order], frame_id=self.params.frame_id,
                                   stamp_ns=int(stamps.max()), z=z[order]))]

    def finish(self) -> list[Output]:
        outs = self._drain_order() if self.graph is not None else []
        outs += self._apply_pending(lambda s: True)
        if self.params.smooth and self.tracker.initialised:
            smoothed = self.tracker.smooth(self.params.smooth_samples, redrawn=self.params.smooth_redrawn)
            first = min((e.stamp_ns for e in smoothed), default=None)
            older = [e for e in self.tracker.estimates if first is not None and e.stamp_ns < first]
            # filtered before the window (archived ones too), then the smoothed window
            return outs + self._path(older + smoothed, before_ns=first if first is not None else -1)
        return outs + self._path(self.tracker.estimates)

    def extra_diagnostics(self) -> dict[str, str]:
        if self.graph is None:
            return {"initialised": "false (graph_file not set)"}
        pf = self.tracker.pf
        d = {"graph": f"{self.graph.n_nodes} nodes, {self.graph.n_links} links", "rule": self.transitions.rule,
             "wifi_update": self.params.wifi_update,
             "tll_cache": ("loaded " + self.params.transitions_file if self.params.transitions_file
                           else "hit" if self.cache_hit else "computed"),
             "pending_fixes": str(len(self._pending)), "motion_source": self.params.motion_source,
             "precision_floored": str(self.floored), "reorder_buffered": str(len(self._order)),
             "reorder_late": str(self.reorder_late),
             # the smoother's particles at the last check, and steps dropped for smooth_max_mb
             "smoother_mb": f"{self._budget.held / 2**20:.1f}", "smoother_trimmed": str(self._budget.trimmed_steps)}
        if self.params.motion_source == "odom":
            d.update(self._robot.diagnostics())
        if pf.p is None:
            d["initialised"] = "false (waiting for the first wifi/fix or initialpose)"
        else:
            from indoor_loc.pf.filter import effective_sample_size
            mon = self.tracker.monitor
            d.update(initialised="true", particles=str(len(pf.p)), n_eff=f"{effective_sample_size(pf.p.log_w):.0f}",
                     resamples=str(pf.n_resample), reinitialisations=str(pf.n_reinit),
                     kf_reinitialisations=str(mon.reinits), kf_restarts=str(mon.kf_restarts),
                     kf_deviance=f"{mon.last_deviance:.1f}",
                     kf_disagreeing="true" if mon.disagree_since_ns is not None else "false")
            if pf.floors.n_floors > 1:
                k, _, _ = pf.estimate_floor()
                d.update(floor=f"{self.graph.floors[k].id} ({self.graph.floors[k].name}, z={pf.floors.fz[k]:g} m)")
            det = self.tracker.baro_det.s
            if det.last_ns is not None:
                d.update(baro_floor_changes=str(det.changes), baro_spikes=str(det.spikes),
                         baro_in_transit="true" if det.in_transit else "false",
                         baro_particles_moved=str(self.tracker.baro_moved))
        return d
