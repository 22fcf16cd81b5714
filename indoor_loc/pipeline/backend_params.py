"""Parameters of ``backend_node`` (:class:`BackendParams`): its own, the graph's inherited from
:class:`~indoor_loc.backend.graph.GraphParams`, and the groups it shares with the other estimators
(time policy, odometry increments, floors, barometer, floor snap). The stage is
:mod:`indoor_loc.pipeline.backend_stage`."""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from indoor_loc.backend.graph import GraphParams
from indoor_loc.baro.detector import BaroParams
from indoor_loc.baro.floors import FloorFilterParams
from indoor_loc.baro.snap import FloorSnapParams
from indoor_loc.fusion.position_trust import POSE_INTERVAL_MIN_S
from indoor_loc.odometry.increments import OdomIncrementParams
from indoor_loc.params import field as pfield, group, require
from indoor_loc.pipeline.motion_source import MOTION_DOC, ODOM_GROUP_DOC, validate_source
from indoor_loc.pipeline.stage import ORDERS
from indoor_loc.pipeline.time_policy import TimeParams


@dataclass(frozen=True)
class BackendParams(GraphParams):
    """Parameters of ``backend_node``: its own, and the graph's inherited from :class:`GraphParams`
    (same names, defaults and docs, declared once)."""
    radiomap: str = pfield("", "pre-surveyed radio map directory (fixed map scans); '' = none: with wifi_source "
                           "'scan' no user can start (a user starts at a scan localised against the survey), so "
                           "scans are rejected as 'no_survey'; with 'fix' the fixes place the users and only the "
                           "map's scan positions are read, for backend/wifi_map (all of it with save_map)")
    floor_plans: str = pfield("", "the floor plans for the walkable factor (walkable_std_m > 0): the importer's "
                                  "floors/ directory (<floor>/map.yaml + geojson_map.json); a pose takes the plan "
                                  "of its user's newest fix's floor height; '' = none")
    users: list = pfield([], "live: user namespaces to follow; [] = discover them from the ROS graph")
    pose_interval_min_s: float = pfield(POSE_INTERVAL_MIN_S, "an initialpose of a user received less than this after "
                                        "its previous one is refused (pose_burst: faster than a person gives poses; "
                                        "s of the node's clock, indoor_loc/fusion/position_trust.py)")
    user_timeout_s: float = pfield(10.0, "live: a user whose inputs have had no publisher for this long has "
                                         "left (its path is published), s")
    offline_order: str = pfield("merged", "indoor-loc run --order auto: 'sequential' plays bags one after "
                                "another (the paper's joint configuration), 'merged' in one stamp order")
    odom_step_length_m: float = pfield(0.65, "step length imu_node used: steps = |Δp| / this, m")
    reorder_window_s: float = pfield(0.5, "events wait until the user's pdr/odom is this far past them, s")
    max_scan_wait_s: float = pfield(10.0, "a scan waits at most this long (stamp time of newer scans) for PDR, s")
    fix_wait_s: float = pfield(5.0, "wifi_source 'fix': a scan whose wifi/fix has not come holds its user's events "
                                    "at most this long (the user's clock: its pdr/odom, scans without odometry), "
                                    "then they go on without it, s")
    path_period_s: float = pfield(0.0, "republish a user's path at most this often (stamp time, after a window "
                                       "optimisation), s; 0 = only when the user finishes and at the end")
    finish_budget_s: float = pfield(3.0, "end of input: the whole-graph optimisation and the final poses' "
                                         "covariances take at most about this long (wall clock), s; every path "
                                         "is published from the best state reached and the users whose final "
                                         "optimisation did not complete are named; 0 = no limit")
    save_map: str = pfield("", "directory to save the evolving WiFi map to at the end (radio map format); '' = no")
    frame_id: str = pfield("map", "frame of the estimates")
    time: TimeParams = group(TimeParams, "which stamps are taken, clock jumps (indoor_loc/pipeline/time_policy.py); "
                                         "a jump back starts the user afresh, its track so far kept as a finished "
                                         "user's")
    motion_source: str = pfield("pdr", MOTION_DOC + "; any = each user's from the first of the two it "
                                "publishes (walkers and robots on one back-end)")
    odom: OdomIncrementParams = group(OdomIncrementParams, ODOM_GROUP_DOC)
    floors: FloorFilterParams = group(FloorFilterParams, "each user's floor from the fixes' floors and the "
                                                         "barometer (floors.switch_prob, ...)")
    baro: BaroParams = group(BaroParams, "barometer floor-change detector for baro/pressure (baro.hold_s, ...)")
    snap: FloorSnapParams = group(FloorSnapParams, "the floor snapped to the barometric height during "
                                                          "a transit (snap.hysteresis, snap.enabled, ...)")

    def validate(self) -> None:
        n = type(self).__name__
        self.time.validate()
        if self.motion_source != "any":
            validate_source(n, self.motion_source)
        self.odom.validate()
        self.floors.validate()
        self.baro.validate()
        self.snap.validate()
        require(self.offline_order in ORDERS, n, "offline_order", f"one of {ORDERS}", self.offline_order)
        require(self.odom_step_length_m > 0, n, "odom_step_length_m", "> 0", self.odom_step_length_m)
        require(self.reorder_window_s >= 0, n, "reorder_window_s", ">= 0", self.reorder_window_s)
        require(self.max_scan_wait_s >= 0, n, "max_scan_wait_s", ">= 0", self.max_scan_wait_s)
        require(self.fix_wait_s >= 0, n, "fix_wait_s", ">= 0", self.fix_wait_s)
        require(self.time.jump_s > self.reorder_window_s, n, "time.jump_s",
                "> reorder_window_s (a message late within the window is not a jump)", self.time.jump_s)
        require(self.pose_interval_min_s >= 0, n, "pose_interval_min_s", ">= 0", self.pose_interval_min_s)
        require(self.user_timeout_s > 0, n, "user_timeout_s", "> 0", self.user_timeout_s)
        require(self.path_period_s >= 0, n, "path_period_s", ">= 0", self.path_period_s)
        require(self.finish_budget_s >= 0, n, "finish_budget_s", ">= 0", self.finish_budget_s)
        require(all(isinstance(u, str) and u.strip("/") for u in self.users), n, "users", "namespace names",
                self.users)
        GraphParams.validate(self)

    def graph_params(self) -> GraphParams:
        return GraphParams(**{f.name: getattr(self, f.name) for f in dataclasses.fields(GraphParams)})
