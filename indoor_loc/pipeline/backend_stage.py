"""BackendStage (``backend_node``): the multi-user factor-graph back-end, one instance for all users.

Inputs, from every user namespace (a multi-user stage, see :mod:`indoor_loc.pipeline.stage`):
``pdr/odom`` (one message per stepometer hop; per interval ``steps = |p_i − p_(i−1)| /
odom_step_length_m`` and ``Δψ = wrap(yaw_i − yaw_(i−1))``, the contract of ``imu_node``) and
``wifi/scan`` (and ``wifi/fix`` with ``wifi_source: fix``: the front end's fixes as position factors;
each pose's z is the height of the user's floor at its stamp, so a user changing floors gets a path at
the right heights) and ``baro/pressure`` (optional). The floor is a discrete state per user beside the
planar graph (:class:`~indoor_loc.baro.track.FloorTrack`): a chain of floors with the fixes' floors as
evidence and the barometer's floor changes as Δz factors between consecutive epochs — the discrete
form of seed 003's Δz barometer factor; no factor couples it with the planar poses, so solving it
apart (forward-backward smoothing) is the joint solution. It changes only on evidence (docs/floors.md).
Outputs: ``backend/<user>/pose`` (PoseWithCovarianceStamped, the newest pose with its
marginal covariance, at every new pose), ``backend/<user>/path`` (the user's whole optimised
trajectory: every ``path_period_s`` of stamp time, when the user finishes and at the end of input,
after a whole-graph optimisation bounded by ``finish_budget_s``: :meth:`BackendStage.finish`),
``backend/wifi_map`` (the survey and users' scans at their current positions, latched, with every
path) and per-user step length, pose counts and the share of scans matched to other users in
``/diagnostics``.

Ordering. Each user's messages go through a reorder buffer: an event is taken into the graph once
the newest ``pdr/odom`` of that user is ``reorder_window_s`` past its stamp (a scan therefore waits
until PDR has reached it — the stepometer reports a hop about half a window late), or once a newer
scan is ``max_scan_wait_s`` ahead (PDR stopped). Late messages within that window are inserted in
stamp order; a message older than what the graph already holds is counted (``too_late``) and
dropped.

Waiting for fixes (``wifi_source: fix``). A ``wifi/fix`` is computed from a ``wifi/scan``, so it reaches
the back-end later than its scan by the WiFi node's processing time — on a large map easily more than
``reorder_window_s`` — while the user's odometry keeps flowing. A scan seen on ``wifi/scan`` whose fix
has not come yet therefore holds that user's events from its stamp on: they are taken into the graph
once the fix comes (so it is inserted at its place in stamp order), or once the absence of a fix is
known: the WiFi node locates a user's scans in stamp order, so a fix of a later scan settles every
earlier scan that got none (the node declined it). A scan holds them at most ``fix_wait_s`` of the
user's clock (below); once the graph has taken a later event its fix can no longer be used (it would be
``too_late``) and only then is it counted as given up (``scans_given_up``). Pose output latency thus grows only by the WiFi node's real lag,
and the graph — and every path — is the one the same messages give when each fix comes at once
(offline runs); to rounding, as users' poses may interleave differently in the shared arrays (joint,
a scan may also meet another set of other users' scans, as with any wait). ``/diagnostics`` count,
per user and in all, the fixes waited for (arriving more than ``reorder_window_s`` behind the
user's odometry), the longest such lag, scans given up and scans waiting.

Clocks. A user's clock is its newest ``pdr/odom`` stamp (its newest scan or fix for a user without
odometry). Stamps are judged per user and topic by the time policy every stage shares
(:mod:`indoor_loc.pipeline.time_policy`; parameters ``time.*``): a message stamped more than
``time.max_future_s`` ahead of the node's clock is rejected (``future_stamp``); a jump back (a bag
replayed in a loop, a simulation restarted, a device clock reset: ``time.jump_confirm`` messages of one
topic in step, or the node's clock going back) finishes the user's track as when it leaves (kept in
the graph as a finished user's; its scans stay in the map) and starts the user afresh
(:meth:`BackendStage.reset_user`): ``backend/<user>/path`` restarts with the new track, a notice is
logged (WARN) and ``time_jumps`` counted; a lone message that far back is a straggler (``stale_stamp``).
A user's first scan coming before its first odometry is not a jump (each topic is judged on its own).

Method, insertion policy, solver and the bound on the graph's size: :mod:`indoor_loc.backend.graph`.
"""
from __future__ import annotations

import bisect
import dataclasses
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from indoor_loc.baro.track import FloorTrack
from indoor_loc.backend.graph import MultiUserGraph
from indoor_loc.backend.wifi_map import survey_positions
from indoor_loc.contract import BACKEND_MAP_ODOM, BACKEND_PATH, BACKEND_POSE, Qos
from indoor_loc.errors import InvalidMessageError
from indoor_loc.fusion.position_trust import CommandRate
from msg_adapters.markers import points_markers
from msg_adapters.initial_pose import initial_pose_from_msg
from msg_adapters.odom import OdomJumpGuard, odom_from_msg
from msg_adapters.path import path_to_msg
from msg_adapters.path_cdr import path_cdr
from msg_adapters.pose import fix_from_msg, pose_to_msg
from msg_adapters.pressure import pressure_from_msg
from msg_adapters.wifi_scan import scan_from_msg
from indoor_loc.pipeline.bounds import MapBox
from indoor_loc.pipeline.map_odom import MapOdomSpec
from indoor_loc.pipeline.stage import Output, Port, Stage
from indoor_loc.pipeline.time_policy import Order
from indoor_loc.wifi.radiomap import load_radiomap, save_radiomap
from indoor_loc.odometry.increments import OdomIncrement
from indoor_loc.pipeline.motion_source import motion_port, require_source
from msg_adapters.robot_odom import RobotOdomReader
from indoor_loc.pipeline.backend_params import BackendParams
from indoor_loc.pipeline.reorder import ReorderBuffer

NODE_NAME = "backend_node"


@dataclass
class _UserInput(ReorderBuffer):
    """Reorder buffer (the shared :class:`~indoor_loc.pipeline.reorder.ReorderBuffer`: rank = kind 0
    odom, 1 fix, 2 scan; ``taken_ns`` the newest stamp taken into the graph) and odometry decoding
    state of one user."""
    newest_odom_ns: int | None = None
    newest_scan_ns: int | None = None
    prev_odom: Any = None                              # last odometry sample taken (x, y, yaw, stamp)
    last_path_ns: int | None = None
    # waiting for fixes (wifi_source fix)
    fix_known_ns: int | None = None                    # newest wifi/fix stamp received
    pending_scans: list = field(default_factory=list)  # sorted stamps of scans whose fix has not come
    fixes_waited: int = 0                              # fixes more than reorder_window_s behind the odometry
    max_fix_lag_ns: int = 0                            # the largest such lag (stamp time), ns
    scans_given_up: int = 0                            # scans whose fix can no longer be used (graph past them)
    floor: FloorTrack | None = None                    # the user's floor (created by the stage, with its params)
    odom_guard: OdomJumpGuard = field(default_factory=OdomJumpGuard)   # odom_jump against the last accepted
    robot: RobotOdomReader | None = None               # motion_source odom: the user's increments
    motion: str | None = None                          # motion_source any: the user's motion topic
    new_frame: bool = False                            # its pdr/odom producer restarted: next pose is a frame's first
    yaw_offset: float = 0.0                            # added to pdr/odom yaws so a new frame makes no turn, rad
    pose_ns: int | None = None                         # stamp of the newest backend/<user>/pose published

    def clock_ns(self) -> int | None:
        """The user's clock: its newest odometry stamp, or for a user without odometry its newest scan
        (or fix) stamp."""
        return self.newest_odom_ns if self.newest_odom_ns is not None else self.newest_scan_ns

    def afresh(self) -> "_UserInput":
        """A new buffer for the user starting afresh, keeping its counters."""
        return _UserInput(dropped_late=self.dropped_late, fixes_waited=self.fixes_waited,
                          max_fix_lag_ns=self.max_fix_lag_ns, scans_given_up=self.scans_given_up)


@dataclass(frozen=True)
class _FrameStart:
    """The first ``pdr/odom`` pose of a restarted producer (a new odometry frame, from its origin): it
    walks nothing -- the hop across the restart is unknown -- and the hops after it are measured from it."""
    od: Any


def _names(users: list[str], most: int = 10) -> str:
    """``a, b, c`` (the first ``most``, then how many more)."""
    more = f" and {len(users) - most} more" if len(users) > most else ""
    return ", ".join(users[:most]) + more


class BackendStage(Stage):
    """Multi-user factor-graph back-end: <user>/pdr/odom + <user>/wifi/scan -> backend/<user>/{pose,path}."""
    NODE_NAME = NODE_NAME
    PARAMS = BackendParams
    MULTI_USER = True
    #: the reorder buffer puts each user's events in stamp order (too_late beyond it)
    STAMP_ORDER = {"pdr/odom": Order.ANY, "odom": Order.ANY, "wifi/scan": Order.ANY, "wifi/fix": Order.ANY,
                   "initialpose": Order.EXEMPT, "baro/pressure": Order.STRICT}
    MAP_ODOM = MapOdomSpec(motion=("pdr/odom", "odom"), estimate=BACKEND_POSE, out=BACKEND_MAP_ODOM)

    def __init__(self, params, *, namespace: str = "", survey=None) -> None:
        super().__init__(params, namespace=namespace)
        # wifi_source 'fix': the survey's fingerprints never enter the graph (the front end's fixes carry
        # it), so only its positions are read, for the drawing — unless the map is to be saved with them
        self._drawn_survey = np.zeros((0, 2))
        if survey is None and params.radiomap:
            where = Path(params.radiomap).expanduser()                     # MapError -> start-up fails
            if params.wifi_source == "fix" and not params.save_map:
                self._drawn_survey = survey_positions(where)
            else:
                survey = load_radiomap(where)
        walkable = None
        if params.floor_plans and params.walkable_std_m > 0:       # ConfigError -> start-up fails
            from indoor_loc.backend.walkable_term import load_walkable_fields
            walkable = load_walkable_fields(params.floor_plans)
        self.graph = MultiUserGraph(params.graph_params(), survey, walkable)
        self._no_survey = params.wifi_source == "scan" and (survey is None or not survey.n_scans)
        #: fixes farther than the off_map margin outside the radio map's scan positions are refused
        self.map_box = MapBox.around(self._drawn_survey if survey is None else
                                     np.vstack([self._drawn_survey, survey.positions]))
        self.inputs_by_user: dict[str, _UserInput] = {}
        self._pose_rates: dict[str, CommandRate] = {}      # user -> its initialpose rate bound (pose_burst)
        #: what the end of input's time budget cut short (``finish.*`` in /diagnostics; empty before it)
        self.finish_report: dict[str, str] = {}
        self.on("pdr/odom", self._on_odom)
        self.on("odom", self._on_robot_odom)
        self.on("wifi/scan", self._on_scan)
        self.on("baro/pressure", self._on_baro)
        if params.wifi_source == "fix":
            self.on("wifi/fix", self._on_fix)
        self.on("initialpose", self._on_initialpose)

    def inputs(self) -> list[Port]:
        ms = self.params.motion_source
        motion = ([motion_port(ms)] if ms != "any" else        # any: neither alone is required
                  [dataclasses.replace(motion_port(s), required=False) for s in ("pdr", "odom")])
        return motion + [
                Port("wifi/scan", "diagnostic_msgs/msg/DiagnosticArray", Qos.RELIABLE),
                Port("baro/pressure", "sensor_msgs/msg/FluidPressure", Qos.SENSOR)] + (
                [Port("wifi/fix", "geometry_msgs/msg/PoseWithCovarianceStamped", Qos.RELIABLE)]
                if self.params.wifi_source == "fix" else []) + [
                Port("initialpose", "geometry_msgs/msg/PoseWithCovarianceStamped", Qos.RELIABLE, stream=False)]

    def outputs(self) -> list[Port]:
        return [Port("backend/wifi_map", "visualization_msgs/msg/MarkerArray", Qos.LATCHED)]

    def user_outputs(self) -> list[Port]:
        return [Port(BACKEND_POSE, "geometry_msgs/msg/PoseWithCovarianceStamped", Qos.RELIABLE),
                Port(BACKEND_PATH, "nav_msgs/msg/Path", Qos.LATCHED),
                Port(BACKEND_MAP_ODOM, "geometry_msgs/msg/TransformStamped", Qos.LATCHED)]

    def offline_order(self) -> str:
        return self.params.offline_order

    # -- input ----------------------------------------------------------------------------------
    def _buffer(self, user: str) -> _UserInput:
        b = self.inputs_by_user.get(user)
        if b is None:
            b = self.inputs_by_user[user] = _UserInput()
        return b

    def _floor(self, user: str) -> FloorTrack:
        b = self._buffer(user)
        if b.floor is None:
            b.floor = FloorTrack(self.params.baro, self.params.floors, snap=self.params.snap)
        return b.floor

    def _on_baro(self, msg, recv_ns: int, user: str) -> list[Output]:
        ps = pressure_from_msg(msg)
        floor = self._floor(user)
        floor.baro(ps.stamp_ns, ps.pressure_pa)
        tr = self.graph.users.get(user)
        if floor.moved and tr is not None and tr.poses:
            # the floor changed with no step or fix to add a graph pose (standing in a lift): the
            # newest pose, now, on the new floor
            return self._pose_outputs(user, now_ns=ps.stamp_ns)
        return []

    def _push(self, user: str, stamp: int, kind: int, payload: Any) -> None:
        b = self._buffer(user)
        why = ("a fix whose scan was given up after fix_wait_s, a duplicate or out of stamp order"
               if kind == 1 and self.params.fix_wait_s > 0 else "later than reorder_window_s")
        b.push(stamp, kind, payload, who=f"{user}: ", why=why)

    def reset_user(self, user: str) -> list[Output]:
        """A jump back in the user's time (the shared time policy): finish the user's track (everything
        buffered taken, window optimised, its path published, as when a user leaves; it stays in the
        graph as a finished user's track) and give the user a fresh input buffer (its counters kept)
        for a new track."""
        if user not in self.inputs_by_user:
            return []
        p = self.params
        outs = self._release(user, everything=True)
        self.graph.finish_user(user)
        tr = self.graph.users.get(user)
        if tr is not None and tr.poses:
            if p.window_poses:
                self.graph.optimize_window(user)
            outs.append(self._path_output(user))
        self.graph.restart_user(user)
        self.inputs_by_user[user] = self.inputs_by_user[user].afresh()
        rate = self._pose_rates.get(user)
        if rate is not None:
            rate.reset()
        return outs

    def upstream_restarted(self, topic: str, user: str) -> list[Output]:
        """A restarted ``pdr/odom`` producer of ``user`` (``imu_node`` killed and started again) publishes
        from its origin: its first pose starts a new odometry frame -- taken whatever its distance from
        the last one (no ``odom_jump``), walking nothing across the restart, and with no turn (the
        user's heading goes on from the last hop's; the hops after it turn as the new frame does)."""
        b = self.inputs_by_user.get(user)
        if topic == "pdr/odom" and b is not None and b.odom_guard.last is not None:
            b.odom_guard.restart()
            b.new_frame = True
            self.notice(f"{user}: pdr/odom: its publisher restarted: a new odometry frame from its next pose")
        return []

    def _on_robot_odom(self, msg, recv_ns: int, user: str) -> list[Output]:
        """A robot's odometry (``motion_source: odom``): its increments, once they close, enter the
        reorder buffer as the user's hops; each message moves the user's clock."""
        b = self._motion(user, "odom")
        if b.robot is None:
            b.robot = RobotOdomReader(self.params.odom)
        od = b.robot.check(msg)
        b.refuse_late(od.stamp_ns, f"{user}: ", "later than reorder_window_s")
        inc = b.robot.take(od)
        if inc is not None:
            self._push(user, inc.t_end_ns, 0, inc)
        b.newest_odom_ns = od.stamp_ns if b.newest_odom_ns is None else max(b.newest_odom_ns, od.stamp_ns)
        return self._release(user)

    def _motion(self, user: str, topic: str) -> _UserInput:
        """The user's buffer, once the motion topic is the one it takes (``wrong_motion_source`` else):
        the node's ``motion_source``, or with ``any`` the first of the two the user sent."""
        ms = self.params.motion_source
        if ms != "any":
            require_source(ms, topic)
            return self._buffer(user)
        b = self._buffer(user)
        if b.motion is None:
            b.motion = topic
        elif b.motion != topic:
            raise InvalidMessageError("wrong_motion_source", f"{user}: {topic} received, but this user's motion "
                                                             f"is {b.motion} (motion_source any: the first one)")
        return b

    def _flush_robot(self, user: str) -> None:
        """A scan or fix of a robot: its odometry up to now closes first (so the scan's pose has it)."""
        b = self.inputs_by_user.get(user)
        if b is not None and b.robot is not None:
            inc = b.robot.flush()
            if inc is not None:
                if b.taken_ns is not None and inc.t_end_ns < b.taken_ns:   # the graph went on (no odometry
                    inc = dataclasses.replace(inc, t_start_ns=min(inc.t_start_ns, b.taken_ns),  # for a while):
                                              t_end_ns=b.taken_ns)     # its motion comes now, not lost
                self._push(user, inc.t_end_ns, 0, inc)

    def _on_odom(self, msg, recv_ns: int, user: str) -> list[Output]:
        self._motion(user, "pdr/odom")
        od = odom_from_msg(msg)
        if user in self.inputs_by_user:
            self.inputs_by_user[user].odom_guard.check(od)      # odom_jump, before anything moves
        b = self._buffer(user)
        self._push(user, od.stamp_ns, 0, _FrameStart(od) if b.new_frame else od)
        b.new_frame = False
        b.odom_guard.accept(od)
        b.newest_odom_ns = od.stamp_ns if b.newest_odom_ns is None else max(b.newest_odom_ns, od.stamp_ns)
        return self._release(user)

    def _on_scan(self, msg, recv_ns: int, user: str) -> list[Output]:
        scan = scan_from_msg(msg)
        self._flush_robot(user)
        if self._no_survey:
            raise InvalidMessageError("no_survey", "no radio map (radiomap ''): a user starts at a scan WKNN "
                                                   "localises against the survey, so none can; set radiomap")
        b = self._take_wifi(user, scan.stamp_ns, 2, scan)
        if self.params.wifi_source == "fix" and self.params.fix_wait_s > 0 and (
                b.fix_known_ns is None or scan.stamp_ns > b.fix_known_ns):
            bisect.insort(b.pending_scans, scan.stamp_ns)       # its fix is still to come
        return self._release(user)

    def _on_fix(self, msg, recv_ns: int, user: str) -> list[Output]:
        """A front-end fix (``wifi_source: fix``); it sorts before its own scan (same stamp), so the
        scan attaches to the fix's pose. A fix has its scan's stamp: it moves the scans' wait mark too,
        so a user without odometry is not held back until it leaves."""
        fix = fix_from_msg(msg, frame_id=self.params.frame_id)
        if self.map_box is not None:
            self.map_box.check("wifi/fix", fix.xy)
        self._flush_robot(user)
        b = self._take_wifi(user, fix.stamp_ns, 1, fix)
        if b.newest_odom_ns is not None:
            lag = b.newest_odom_ns - fix.stamp_ns
            if lag > self.params.reorder_window_s * 1e9:     # held for: the window alone would have lost it
                b.fixes_waited += 1
                b.max_fix_lag_ns = max(b.max_fix_lag_ns, lag)
        b.fix_known_ns = fix.stamp_ns if b.fix_known_ns is None else max(b.fix_known_ns, fix.stamp_ns)
        # this scan's fix, or a later one: every scan up to its stamp is settled (fixes come in stamp order)
        del b.pending_scans[:bisect.bisect_right(b.pending_scans, b.fix_known_ns)]
        return self._release(user)

    def _on_initialpose(self, msg, recv_ns: int, user: str) -> list[Output]:
        """The user is somewhere else (a kidnap, a wrong start): its track so far ends (as at a jump back
        in time, its path published) and a new one starts at the pose, a position factor with the pose's
        covariance (weighted as a fix, ``wifi_info``). Stamp 0 (a command) is taken as the user's newest."""
        fix = initial_pose_from_msg(msg, frame_id=self.params.frame_id)
        if self.map_box is not None:
            self.map_box.check("initialpose", fix.xy)
        rate = self._pose_rates.get(user)
        if rate is None:
            rate = self._pose_rates[user] = CommandRate(self.params.pose_interval_min_s)
        rate.check(recv_ns, self.set_pose_call)   # pose_burst
        old = self.inputs_by_user.get(user)
        newest = max((s for s in (old.newest_odom_ns, old.newest_scan_ns, old.taken_ns) if s is not None),
                     default=0) if old is not None else 0
        stamp = fix.stamp_ns or newest
        outs = self.reset_user(user)
        if recv_ns:                                    # (the reset forgets it: for a jump in time, not this pose)
            rate.last_ns = recv_ns
        b = self._take_wifi(user, stamp, 1, dataclasses.replace(fix, stamp_ns=stamp))
        b.fix_known_ns = stamp
        return outs + self._release(user, everything=True)

    def _take_wifi(self, user: str, stamp_ns: int, order: int, event) -> _UserInput:
        """A scan's or fix's way in: queued, and the scans' wait mark moved to its stamp."""
        self._push(user, stamp_ns, order, event)
        b = self._buffer(user)
        b.newest_scan_ns = stamp_ns if b.newest_scan_ns is None else max(b.newest_scan_ns, stamp_ns)
        return b

    def _release(self, user: str, *, everything: bool = False) -> list[Output]:
        """Take the user's due events into the graph, in stamp order; outputs for new poses."""
        b = self._buffer(user)
        p = self.params
        odom_mark = -math.inf if b.newest_odom_ns is None else b.newest_odom_ns - p.reorder_window_s * 1e9
        scan_mark = -math.inf if b.newest_scan_ns is None else b.newest_scan_ns - p.max_scan_wait_s * 1e9
        barrier = self._fix_barrier(b, everything)
        new_pose = False
        while b.heap:
            stamp, kind, payload = b.head()          # type: ignore[misc]
            if not (everything or stamp <= odom_mark or (kind >= 1 and stamp <= scan_mark)):
                break
            if barrier is not None and (stamp, kind) >= (barrier, 1):
                break                          # a scan's fix is still to come: it goes in before these
            b.pop()
            if kind == 0:
                new_pose |= self._take_odom(user, b, payload)
            elif kind == 1:
                self.graph.set_floor(user, payload.z)
                self.graph.add_fix(user, payload.stamp_ns, payload.xy, payload.cov)
                self._floor(user).fix(payload.stamp_ns, payload.z, payload.z_var)
                new_pose = True
            else:
                pose, _match = self.graph.add_scan(user, payload)
                new_pose |= pose is not None
        self._give_up(b, everything)
        outs: list[Output] = []
        if new_pose:
            outs += self._pose_outputs(user)
            if p.path_period_s and b.taken_ns is not None and (
                    b.last_path_ns is None or b.taken_ns - b.last_path_ns >= p.path_period_s * 1e9):
                b.last_path_ns = b.taken_ns
                outs.append(self._path_output(user))
        return outs

    def _fix_barrier(self, b: _UserInput, everything: bool) -> int | None:
        """Stamp of the oldest scan still holding its user's events for its fix, or None. A scan holds
        them at most ``fix_wait_s`` of the user's clock (:meth:`_UserInput.clock_ns`) — none at the end
        of the user's input; it keeps waiting for its fix until the graph passes it (:meth:`_give_up`)."""
        clock = b.clock_ns()
        if everything or not b.pending_scans or clock is None:
            return None
        k = bisect.bisect_left(b.pending_scans, clock - self.params.fix_wait_s * 1e9)
        return b.pending_scans[k] if k < len(b.pending_scans) else None

    @staticmethod
    def _give_up(b: _UserInput, everything: bool) -> None:
        """Count as given up the scans waiting for a fix that can no longer be used: the graph holds
        a newer event (the fix would be too_late), or the user's input ended."""
        k = len(b.pending_scans) if everything else (
            0 if b.taken_ns is None else bisect.bisect_left(b.pending_scans, b.taken_ns))
        if k:
            b.scans_given_up += k
            del b.pending_scans[:k]

    def _take_odom(self, user: str, b: _UserInput, od) -> bool:
        if isinstance(od, OdomIncrement):      # a robot's: metres as steps of the prior's length
            steps = od.distance_m / self.graph.params.step_prior_m
            return self.graph.add_hop(user, od.t_start_ns, od.t_end_ns, steps, od.travel_rad,
                                      var=(od.var_along + od.cov[1, 1], od.var_yaw)) is not None
        prev = b.prev_odom
        if isinstance(od, _FrameStart):        # a restarted producer's first pose: no hop, no turn
            od = od.od
            if prev is not None:
                b.yaw_offset += prev.yaw - od.yaw
            b.prev_odom = od
            return False
        b.prev_odom = od
        d = math.hypot(od.x - (prev.x if prev else 0.0), od.y - (prev.y if prev else 0.0))
        steps = d / self.params.odom_step_length_m
        if prev is not None:
            start = prev.stamp_ns
        else:     # the first hop starts at the odom origin; its duration from the walking speed
            start = od.stamp_ns - (int(d / od.speed * 1e9) if od.speed > 1e-6 else 0)
        if prev is not None and od.stamp_ns == prev.stamp_ns:
            return False                       # a duplicate: nothing moved in zero time
        return self.graph.add_hop(user, start, od.stamp_ns, steps, od.yaw + b.yaw_offset) is not None

    # -- output ---------------------------------------------------------------------------------
    def _pose_outputs(self, user: str, now_ns: int | None = None, refined: bool = False) -> list[Output]:
        """The user's newest graph pose as ``backend/<user>/pose`` (``now_ns``: carried to that later
        time, on the floor then). Stamps never go back: a pose a floor change already published at a
        later time (a lift ride seen by the barometer before the hops that lead to it) is not published
        again at an older stamp; the next pose past it is (a pose corrected at the same stamp, by a fix
        there, is). ``refined`` (the final optimisation's estimate): at the newest stamp published."""
        tr = self.graph.users[user]
        i = tr.poses[-1]
        stamp = int(self.graph.poses.stamp[i])
        z = float(self._floor(user).z_at([stamp])[0])
        if now_ns is not None and now_ns > stamp:      # the newest pose carried to now_ns: the floor now
            stamp, z = now_ns, self._floor(user).z()[0]
        b = self._buffer(user)
        if b.pose_ns is not None and stamp < b.pose_ns:
            if not refined:
                return []
            stamp, z = b.pose_ns, self._floor(user).z()[0]
        b.pose_ns = stamp
        x = self.graph.poses.x[i]
        cov = self.graph.marginal_cov(i)
        cov_xy, yaw_var = (cov[:2, :2], float(cov[2, 2])) if cov is not None else (np.eye(2) * 1e2, 1e2)
        msg = pose_to_msg(stamp, x[:2], float(x[2]), cov_xy, frame_id=self.params.frame_id,
                          yaw_var=yaw_var, z=z)
        return [(BACKEND_POSE.format(user=user), msg)]

    def _path_output(self, user: str) -> Output:
        st, x = self.graph.trajectory(user)
        stamp = int(st[-1]) if len(st) else 0
        floor = self._floor(user)
        if len(st):
            floor.filter.forget_before(int(st[0]))     # older poses have left the graph
        z = floor.z_at(st)                             # each pose at its smoothed floor
        # a node hands the path to DDS already serialised (the same message, msg_adapters/path_cdr.py):
        # building one PoseStamped per pose made each periodic path cost ~15 us per pose, the
        # back-end's per-message cost growing with its graph (docs/benchmarks/soak.md)
        encode = path_cdr if self.raw_outputs else path_to_msg
        return (BACKEND_PATH.format(user=user), encode(st, x[:, :2], x[:, 2], frame_id=self.params.frame_id,
                                                       stamp_ns=stamp, z=z))

    def _map_output(self, stamp_ns: int) -> Output:
        xy = np.vstack([self._drawn_survey, self.graph.wifi_radio_map().positions])
        return ("backend/wifi_map", points_markers("wifi_map", xy, self.params.frame_id, stamp_ns, scale=0.25))

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
        """End of input: take everything, optimise the whole graph, publish every path and the map.

        Bounded by ``finish_budget_s`` of wall clock (a stopping node has a few seconds): the
        optimisation stops at half the budget with the best estimates it reached (the live window
        optimisations already made good tracks), every user's path is published from them, and then
        each user's newest pose with its covariance while the budget lasts. What the budget cut short
        is said once (a notice) and in ``/diagnostics`` (``finish.*``)."""
        budget = self.params.finish_budget_s
        deadline = time.monotonic() + budget if budget > 0 else None
        outs: list[Output] = []
        # what was still buffered goes in with its window optimisations for a quarter of the budget at
        # most (hundreds of users stopped in the middle of a burst: seconds of them); the rest is left to
        # the whole-graph optimisation
        self.graph.windows_until = None if deadline is None else deadline - 0.75 * budget
        try:
            for user in list(self.inputs_by_user):
                outs += self._release(user, everything=True)
        finally:
            self.graph.windows_until = None
        if not self.graph.poses.n:
            return outs
        # the optimisation gets half the budget: the paths and final poses of many users take time too
        # (path messages: about 2 ms a user on a loaded machine)
        rep = self.graph.optimize(deadline=None if deadline is None else deadline - budget / 2)
        users = self._started_users()
        outs += [self._path_output(u) for u in users]
        # each user's newest pose with its marginal covariance (one factorisation, then a solve per
        # user): while the budget lasts; the others keep the pose their window optimisation published
        posed = 0
        for u in users:
            if deadline is not None and time.monotonic() > deadline:
                break
            outs += self._pose_outputs(u, refined=True)
            posed += 1
        # every track's newest pose: a user restarted by a jump back may not have a pose on its new track yet
        end = int(self.graph.poses.view("stamp").max())
        outs.append(self._map_output(end))
        if self.params.save_map:
            save_radiomap(self.graph.wifi_radio_map(), Path(self.params.save_map).expanduser(),
                          created_by="indoor_loc backend_node")
        self._say_finish(rep, users, posed, budget)
        return outs

    def _say_finish(self, rep, users: list[str], posed: int, budget_s: float) -> None:
        """The notice and ``finish.*`` diagnostics of :meth:`finish`: whose final optimisation the
        budget cut short, whose final pose was not published."""
        incomplete = self.graph.solved_users() if rep is not None and not rep.completed else []
        unposed = users[posed:]
        self.finish_report = {"finish.users": str(len(users)),
                              "finish.optimisation": ("none" if rep is None else "completed" if rep.completed
                                                      else f"stopped at the {budget_s:g} s budget"),
                              "finish.incomplete_users": str(len(incomplete)),
                              "finish.incomplete": ",".join(incomplete),
                              "finish.final_poses_not_published": str(len(unposed))}
        if rep is not None and not rep.completed:
            self.notice(f"end of input: the whole-graph optimisation stopped at the {budget_s:g} s budget "
                        f"(finish_budget_s) after {rep.iterations} evaluations, cost {rep.cost0:.4g} -> "
                        f"{rep.cost:.4g}; the paths of all {len(users)} users are published from that state, the "
                        f"final optimisation of {len(incomplete)} did not complete: {_names(incomplete)}")
        if unposed:
            self.notice(f"end of input: the {budget_s:g} s budget ran out before the final pose (with its "
                        f"covariance) of {len(unposed)} of {len(users)} users; their last published pose stands: "
                        f"{_names(unposed)}")

    def extra_diagnostics(self) -> dict[str, str]:
        out = {k: str(v) for k, v in self.graph.counts().items()}
        if self._no_survey:    # said once at start-up (node log, indoor-loc run), not only per rejected scan
            out["error"] = ("no radio map (radiomap ''): with wifi_source 'scan' a user starts at a scan WKNN "
                            "localises against the survey, so none can; set radiomap (an importer writes one)")
        for u, tr in self.graph.users.items():          # each user's current track
            out[f"user.{u}.step_length_m"] = f"{self.graph.step_len[tr.index]:.3f}"
            out[f"user.{u}.poses"] = str(len(tr.poses))
            out[f"user.{u}.scans_localised"] = str(tr.scans_localised)
            out[f"user.{u}.scans_unlocalised"] = str(tr.scans_unlocalised)
            out[f"user.{u}.scans_matched_to_users"] = str(tr.scans_from_users)
        for u, b in self.inputs_by_user.items():
            out[f"user.{u}.buffered"] = str(len(b.heap))
            out[f"user.{u}.dropped_late"] = str(b.dropped_late)
        for u, t in self.time.users.items():
            out[f"user.{u}.time_jumps"] = str(t.jumps)
            if self.params.wifi_source == "fix":
                out[f"user.{u}.fixes_waited_for"] = str(b.fixes_waited)
                out[f"user.{u}.fix_lag_max_s"] = f"{b.max_fix_lag_ns * 1e-9:.2f}"
                out[f"user.{u}.scans_given_up"] = str(b.scans_given_up)
                out[f"user.{u}.scans_waiting_for_fix"] = str(len(b.pending_scans))
        if self.params.wifi_source == "fix":
            bs = self.inputs_by_user.values()
            out["fix_wait.fixes_waited_for"] = str(sum(b.fixes_waited for b in bs))
            out["fix_wait.lag_max_s"] = f"{max((b.max_fix_lag_ns for b in bs), default=0) * 1e-9:.2f}"
            out["fix_wait.scans_given_up"] = str(sum(b.scans_given_up for b in bs))
            out["fix_wait.scans_waiting"] = str(sum(len(b.pending_scans) for b in bs))
        out.update(self.finish_report)
        if self.graph.last_solve is not None:
            s = self.graph.last_solve
            out["last_solve.poses"] = str(s.n_poses)
            out["last_solve.ms"] = f"{s.wall_s * 1e3:.1f}"
        return out
