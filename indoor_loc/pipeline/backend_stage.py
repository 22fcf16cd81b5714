"""BackendStage (``backend_node``): the multi-user factor-graph back-end, one instance for all users.

Inputs, from every user namespace (a multi-user stage, see :mod:`indoor_loc.pipeline.stage`):
``pdr/odom`` (one message per stepometer hop; per interval ``steps = |p_i − p_(i−1)| /
odom_step_length_m`` and ``Δψ = wrap(yaw_i − yaw_(i−1))``, the contract of ``imu_node``) and
``wifi/scan`` (and ``wifi/fix`` with ``wifi_source: fix``: the front end's fixes as position factors;
their floor height, of the newest fix, is the z of the user's outputs — a walk on one floor).
Outputs: ``backend/<user>/pose`` (PoseWithCovarianceStamped, the newest pose with its
marginal covariance, at every new pose), ``backend/<user>/path`` (the user's whole optimised
trajectory: every ``path_period_s`` of stamp time, when the user finishes and at the end of input,
after a whole-graph optimisation), ``backend/wifi_map`` (the survey and users' scans at their
current positions, latched, with every path) and per-user step length, pose counts and the share of
scans matched to other users in ``/diagnostics``.

Ordering. Each user's messages go through a reorder buffer: an event is taken into the graph once
the newest ``pdr/odom`` of that user is ``reorder_window_s`` past its stamp (a scan therefore waits
until PDR has reached it — the stepometer reports a hop about half a window late), or once a newer
scan is ``max_scan_wait_s`` ahead (PDR stopped). Late messages within that window are inserted in
stamp order; a message older than what the graph already holds is counted (``too_late``) and
dropped. Method, insertion policy, solver and the bound on the graph's size:
:mod:`indoor_loc.backend.graph`.
"""
from __future__ import annotations

import dataclasses
import heapq
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from indoor_loc.params import field as pfield, require
from indoor_loc.backend.graph import GraphParams, MultiUserGraph
from indoor_loc.contract import BACKEND_PATH, BACKEND_POSE, Qos
from indoor_loc.errors import InvalidMessageError
from msg_adapters.markers import points_markers
from msg_adapters.odom import odom_from_msg
from msg_adapters.path import path_to_msg
from msg_adapters.pose import fix_from_msg, pose_to_msg
from msg_adapters.wifi_scan import scan_from_msg
from indoor_loc.pipeline.stage import ORDERS, Output, Port, Stage
from indoor_loc.wifi.radiomap import load_radiomap, save_radiomap

NODE_NAME = "backend_node"

@dataclass(frozen=True)
class BackendParams(GraphParams):
    """Parameters of ``backend_node``: its own, and the graph's inherited from :class:`GraphParams`
    (same names, defaults and docs, declared once)."""
    radiomap: str = pfield("", "pre-surveyed radio map directory (fixed map scans); '' = none: with wifi_source "
                           "'scan' no user can start (a user starts at a scan localised against the survey), so "
                           "scans are rejected as 'no_survey'; with 'fix' the fixes place the users")
    users: list = pfield([], "live: user namespaces to follow; [] = discover them from the ROS graph")
    user_timeout_s: float = pfield(10.0, "live: a user whose inputs have had no publisher for this long has "
                                         "left (its path is published), s")
    offline_order: str = pfield("merged", "indoor-loc run --order auto: 'sequential' plays bags one after "
                                "another (the paper's joint configuration), 'merged' in one stamp order")
    odom_step_length_m: float = pfield(0.65, "step length imu_node used: steps = |Δp| / this, m")
    reorder_window_s: float = pfield(0.5, "events wait until the user's pdr/odom is this far past them, s")
    max_scan_wait_s: float = pfield(10.0, "a scan waits at most this long (stamp time of newer scans) for PDR, s")
    path_period_s: float = pfield(0.0, "republish a user's path at most this often (stamp time, after a window "
                                       "optimisation), s; 0 = only when the user finishes and at the end")
    save_map: str = pfield("", "directory to save the evolving WiFi map to at the end (radio map format); '' = no")
    frame_id: str = pfield("map", "frame of the estimates")

    def validate(self) -> None:
        n = type(self).__name__
        require(self.offline_order in ORDERS, n, "offline_order", f"one of {ORDERS}", self.offline_order)
        require(self.odom_step_length_m > 0, n, "odom_step_length_m", "> 0", self.odom_step_length_m)
        require(self.reorder_window_s >= 0, n, "reorder_window_s", ">= 0", self.reorder_window_s)
        require(self.max_scan_wait_s >= 0, n, "max_scan_wait_s", ">= 0", self.max_scan_wait_s)
        require(self.user_timeout_s > 0, n, "user_timeout_s", "> 0", self.user_timeout_s)
        require(self.path_period_s >= 0, n, "path_period_s", ">= 0", self.path_period_s)
        require(all(isinstance(u, str) and u.strip("/") for u in self.users), n, "users", "namespace names",
                self.users)
        GraphParams.validate(self)

    def graph_params(self) -> GraphParams:
        return GraphParams(**{f.name: getattr(self, f.name) for f in dataclasses.fields(GraphParams)})


@dataclass
class _UserInput:
    """Reorder buffer and odometry decoding state of one user."""
    heap: list = field(default_factory=list)           # (stamp, kind, seq, payload); kind 0 odom, 1 fix, 2 scan
    newest_odom_ns: int | None = None
    newest_scan_ns: int | None = None
    taken_ns: int | None = None                        # newest stamp taken into the graph
    prev_odom: Any = None                              # last odometry sample taken (x, y, yaw, stamp)
    last_path_ns: int | None = None
    dropped_late: int = 0
    floor_z: float = 0.0                               # z (floor height) of the user's newest fix taken, m


class BackendStage(Stage):
    """Multi-user factor-graph back-end: <user>/pdr/odom + <user>/wifi/scan -> backend/<user>/{pose,path}."""
    NODE_NAME = NODE_NAME
    PARAMS = BackendParams
    MULTI_USER = True

    def __init__(self, params, *, namespace: str = "", survey=None) -> None:
        super().__init__(params, namespace=namespace)
        if survey is None and params.radiomap:
            survey = load_radiomap(Path(params.radiomap).expanduser())     # MapError -> start-up fails
        self.graph = MultiUserGraph(params.graph_params(), survey)
        self._no_survey = params.wifi_source == "scan" and (survey is None or not survey.n_scans)
        self.inputs_by_user: dict[str, _UserInput] = {}
        self._seq = 0
        self.on("pdr/odom", self._on_odom)
        self.on("wifi/scan", self._on_scan)
        if params.wifi_source == "fix":
            self.on("wifi/fix", self._on_fix)

    def inputs(self) -> list[Port]:
        return [Port("pdr/odom", "nav_msgs/msg/Odometry", Qos.RELIABLE),
                Port("wifi/scan", "diagnostic_msgs/msg/DiagnosticArray", Qos.RELIABLE)] + (
                [Port("wifi/fix", "geometry_msgs/msg/PoseWithCovarianceStamped", Qos.RELIABLE)]
                if self.params.wifi_source == "fix" else [])

    def outputs(self) -> list[Port]:
        return [Port("backend/wifi_map", "visualization_msgs/msg/MarkerArray", Qos.LATCHED)]

    def user_outputs(self) -> list[Port]:
        return [Port(BACKEND_POSE, "geometry_msgs/msg/PoseWithCovarianceStamped", Qos.RELIABLE),
                Port(BACKEND_PATH, "nav_msgs/msg/Path", Qos.LATCHED)]

    def offline_order(self) -> str:
        return self.params.offline_order

    # -- input ----------------------------------------------------------------------------------
    def _buffer(self, user: str) -> _UserInput:
        b = self.inputs_by_user.get(user)
        if b is None:
            b = self.inputs_by_user[user] = _UserInput()
        return b

    def _push(self, user: str, stamp: int, kind: int, payload: Any) -> None:
        b = self._buffer(user)
        if b.taken_ns is not None and stamp < b.taken_ns:
            b.dropped_late += 1
            raise InvalidMessageError("too_late", f"{user}: stamp {stamp} older than the graph's newest "
                                                  f"{b.taken_ns} by more than reorder_window_s")
        self._seq += 1
        heapq.heappush(b.heap, (stamp, kind, self._seq, payload))

    def _on_odom(self, msg, recv_ns: int, user: str) -> list[Output]:
        od = odom_from_msg(msg)
        self._push(user, od.stamp_ns, 0, od)
        b = self._buffer(user)
        b.newest_odom_ns = od.stamp_ns if b.newest_odom_ns is None else max(b.newest_odom_ns, od.stamp_ns)
        return self._release(user)

    def _on_scan(self, msg, recv_ns: int, user: str) -> list[Output]:
        scan = scan_from_msg(msg)
        if self._no_survey:
            raise InvalidMessageError("no_survey", "no radio map (radiomap ''): a user starts at a scan WKNN "
                                                   "localises against the survey, so none can; set radiomap")
        self._push(user, scan.stamp_ns, 2, scan)
        b = self._buffer(user)
        b.newest_scan_ns = scan.stamp_ns if b.newest_scan_ns is None else max(b.newest_scan_ns, scan.stamp_ns)
        return self._release(user)

    def _on_fix(self, msg, recv_ns: int, user: str) -> list[Output]:
        """A front-end fix (``wifi_source: fix``); it sorts before its own scan (same stamp), so the
        scan attaches to the fix's pose. A fix has its scan's stamp: it moves the scans' wait mark too,
        so a user without odometry is not held back until it leaves."""
        fix = fix_from_msg(msg, frame_id=self.params.frame_id)
        self._push(user, fix.stamp_ns, 1, fix)
        b = self._buffer(user)
        b.newest_scan_ns = fix.stamp_ns if b.newest_scan_ns is None else max(b.newest_scan_ns, fix.stamp_ns)
        return self._release(user)

    def _release(self, user: str, *, everything: bool = False) -> list[Output]:
        """Take the user's due events into the graph, in stamp order; outputs for new poses."""
        b = self._buffer(user)
        p = self.params
        odom_mark = -math.inf if b.newest_odom_ns is None else b.newest_odom_ns - p.reorder_window_s * 1e9
        scan_mark = -math.inf if b.newest_scan_ns is None else b.newest_scan_ns - p.max_scan_wait_s * 1e9
        new_pose = False
        while b.heap:
            stamp, kind, _, payload = b.heap[0]
            if not (everything or stamp <= odom_mark or (kind >= 1 and stamp <= scan_mark)):
                break
            heapq.heappop(b.heap)
            b.taken_ns = stamp
            if kind == 0:
                new_pose |= self._take_odom(user, b, payload)
            elif kind == 1:
                self.graph.add_fix(user, payload.stamp_ns, payload.xy, payload.cov)
                b.floor_z = payload.z
                new_pose = True
            else:
                pose, _match = self.graph.add_scan(user, payload)
                new_pose |= pose is not None
        outs: list[Output] = []
        if new_pose:
            outs.append(self._pose_output(user))
            if p.path_period_s and b.taken_ns is not None and (
                    b.last_path_ns is None or b.taken_ns - b.last_path_ns >= p.path_period_s * 1e9):
                b.last_path_ns = b.taken_ns
                outs.append(self._path_output(user))
        return outs

    def _take_odom(self, user: str, b: _UserInput, od) -> bool:
        prev = b.prev_odom
        b.prev_odom = od
        d = math.hypot(od.x - (prev.x if prev else 0.0), od.y - (prev.y if prev else 0.0))
        steps = d / self.params.odom_step_length_m
        if prev is not None:
            start = prev.stamp_ns
        else:     # the first hop starts at the odom origin; its duration from the walking speed
            start = od.stamp_ns - (int(d / od.speed * 1e9) if od.speed > 1e-6 else 0)
        if prev is not None and od.stamp_ns == prev.stamp_ns:
            return False                       # a duplicate: nothing moved in zero time
        return self.graph.add_hop(user, start, od.stamp_ns, steps, od.yaw) is not None

    # -- output ---------------------------------------------------------------------------------
    def _pose_output(self, user: str) -> Output:
        tr = self.graph.users[user]
        i = tr.poses[-1]
        x = self.graph.poses.x[i]
        cov = self.graph.marginal_cov(i)
        cov_xy, yaw_var = (cov[:2, :2], float(cov[2, 2])) if cov is not None else (np.eye(2) * 1e2, 1e2)
        msg = pose_to_msg(int(self.graph.poses.stamp[i]), x[:2], float(x[2]), cov_xy, frame_id=self.params.frame_id,
                          yaw_var=yaw_var, z=self._buffer(user).floor_z)
        return (BACKEND_POSE.format(user=user), msg)

    def _path_output(self, user: str) -> Output:
        st, x = self.graph.trajectory(user)
        stamp = int(st[-1]) if len(st) else 0
        return (BACKEND_PATH.format(user=user), path_to_msg(st, x[:, :2], x[:, 2], frame_id=self.params.frame_id,
                                                            stamp_ns=stamp, z=self._buffer(user).floor_z))

    def _map_output(self, stamp_ns: int) -> Output:
        rm = self.graph.wifi_radio_map()
        return ("backend/wifi_map", points_markers("wifi_map", rm.positions, self.params.frame_id, stamp_ns,
                                                   scale=0.25))

    def _started_users(self) -> list[str]:
        return [u for u, tr in self.graph.users.items() if tr.poses]

    def finish_user(self, user: str) -> list[Output]:
        """The user's input ended: take everything buffered, publish its path (window-optimised)."""
        if user not in self.inputs_by_user:
            return []
        outs = self._release(user, everything=True)
        self.graph.finish_user(user)
        if user in self.graph.users and self.graph.users[user].poses:
            if self.params.window_poses:
                self.graph.optimize_window(user)
            outs.append(self._path_output(user))
        return outs

    def finish(self) -> list[Output]:
        """End of input: take everything, optimise the whole graph, publish every path and the map."""
        outs: list[Output] = []
        for user in list(self.inputs_by_user):
            outs += self._release(user, everything=True)
        if not self.graph.poses.n:
            return outs
        self.graph.optimize()
        users = self._started_users()
        outs += [self._pose_output(u) for u in users]
        outs += [self._path_output(u) for u in users]
        end = max(int(self.graph.poses.stamp[self.graph.users[u].poses[-1]]) for u in users)
        outs.append(self._map_output(end))
        if self.params.save_map:
            save_radiomap(self.graph.wifi_radio_map(), Path(self.params.save_map).expanduser(),
                          created_by="indoor_loc backend_node")
        return outs

    def extra_diagnostics(self) -> dict[str, str]:
        out = {k: str(v) for k, v in self.graph.counts().items()}
        if self._no_survey:    # said once at start-up (node log, indoor-loc run), not only per rejected scan
            out["error"] = ("no radio map (radiomap ''): with wifi_source 'scan' a user starts at a scan WKNN "
                            "localises against the survey, so none can; set radiomap (an importer writes one)")
        for u, tr in self.graph.users.items():
            b = self.inputs_by_user.get(u)
            out[f"user.{u}.step_length_m"] = f"{self.graph.step_len[tr.index]:.3f}"
            out[f"user.{u}.poses"] = str(len(tr.poses))
            out[f"user.{u}.scans_localised"] = str(tr.scans_localised)
            out[f"user.{u}.scans_unlocalised"] = str(tr.scans_unlocalised)
            out[f"user.{u}.scans_matched_to_users"] = str(tr.scans_from_users)
            if b is not None:
                out[f"user.{u}.buffered"] = str(len(b.heap))
                out[f"user.{u}.dropped_late"] = str(b.dropped_late)
        if self.graph.last_solve is not None:
            s = self.graph.last_solve
            out["last_solve.poses"] = str(s.n_poses)
            out["last_solve.ms"] = f"{s.wall_s * 1e3:.1f}"
        return out
