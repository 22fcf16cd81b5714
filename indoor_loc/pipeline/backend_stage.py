"""BackendStage (``backend_node``): the multi-user factor-graph back-end, one instance for all users.

Inputs, from every user namespace (a multi-user stage, see :mod:`indoor_loc.pipeline.stage`):
``pdr/odom`` (one message per stepometer hop; per interval ``steps = |p_i − p_(i−1)| /
odom_step_length_m`` and ``Δψ = wrap(yaw_i − yaw_(i−1))``, the contract of ``imu_node``) and
``wifi/scan`` (and ``wifi/fix`` with ``wifi_source: fix``: the front end's fixes as position factors;
each pose's z is the floor height of the user's fix nearest to it in time, so a user changing floors
gets a path at the right heights).
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
odometry). A scan or fix stamped more than ``max_future_s`` ahead of the user's odometry is rejected
(``future_stamp``) rather than moving the clock. A jump back — the clock message more than
``time_jump_s`` before the clock, confirmed by the next one (a bag replayed in a loop, a simulation
restarted, a device clock reset), or ``/clock`` going back (:meth:`BackendStage.clock_jump`, called by
the node; no confirmation needed while the user's new pass may still be coming) — finishes the user's
track as when it leaves (kept in the graph as a finished user's; its scans stay in the map) and starts
the user afresh: ``backend/<user>/path`` restarts with the new track, a notice is logged (WARN) and
``time_jumps`` counted. A lone message that far back is a
straggler and takes the usual way (``too_late``). After a jump, a scan or fix stamped more than
``time_jump_s`` ahead of the user's clock but not after the clock before the jump is of the old track,
still in flight (a lagging fix): refused (``before_jump``), not put into the new track.

Method, insertion policy, solver and the bound on the graph's size: :mod:`indoor_loc.backend.graph`.
"""
from __future__ import annotations

import bisect
import dataclasses
import heapq
import math
import traceback
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from indoor_loc.params import field as pfield, require
from indoor_loc.backend.graph import GraphParams, MultiUserGraph
from indoor_loc.backend.wifi_map import survey_positions
from indoor_loc.contract import BACKEND_PATH, BACKEND_POSE, Qos
from indoor_loc.errors import InvalidInputError, InvalidMessageError
from msg_adapters.markers import points_markers
from msg_adapters.odom import odom_from_msg
from msg_adapters.path import path_to_msg
from msg_adapters.pose import fix_from_msg, pose_to_msg
from msg_adapters.wifi_scan import scan_from_msg
from indoor_loc.pipeline.stage import ORDERS, Output, Port, Stage
from indoor_loc.wifi.radiomap import load_radiomap, save_radiomap

NODE_NAME = "backend_node"
#: At most this many messages of one user are held while a jump back waits for its confirmation
#: (the user's next odometry, normally within a second); beyond, they take the usual way.
HELD_MAX = 1000

@dataclass(frozen=True)
class BackendParams(GraphParams):
    """Parameters of ``backend_node``: its own, and the graph's inherited from :class:`GraphParams`
    (same names, defaults and docs, declared once)."""
    radiomap: str = pfield("", "pre-surveyed radio map directory (fixed map scans); '' = none: with wifi_source "
                           "'scan' no user can start (a user starts at a scan localised against the survey), so "
                           "scans are rejected as 'no_survey'; with 'fix' the fixes place the users and only the "
                           "map's scan positions are read, for backend/wifi_map (all of it with save_map)")
    users: list = pfield([], "live: user namespaces to follow; [] = discover them from the ROS graph")
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
    max_future_s: float = pfield(60.0, "a scan or fix stamped more than this ahead of its user's newest pdr/odom is "
                                       "rejected ('future_stamp': a wrong stamp, or odometry stalled) instead of "
                                       "moving the user's clock, s")
    time_jump_s: float = pfield(2.0, "a user's pdr/odom (scans for a user without odometry) stamped more than this "
                                     "before its newest, the next one too, is a clock jump back (a replay loop, a "
                                     "sim-time restart, a clock reset): WARN, counted, the user starts afresh (its "
                                     "track so far kept as a finished user's); /clock going back this far "
                                     "(use_sim_time) restarts every user; > reorder_window_s; 0 = off, s")
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
        require(self.fix_wait_s >= 0, n, "fix_wait_s", ">= 0", self.fix_wait_s)
        require(self.max_future_s > 0, n, "max_future_s", "> 0", self.max_future_s)
        require(self.time_jump_s == 0 or self.time_jump_s > self.reorder_window_s, n, "time_jump_s",
                "0 (off) or > reorder_window_s (a message late within the window is not a jump)", self.time_jump_s)
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
    # waiting for fixes (wifi_source fix)
    fix_known_ns: int | None = None                    # newest wifi/fix stamp received
    pending_scans: list = field(default_factory=list)  # sorted stamps of scans whose fix has not come
    fixes_waited: int = 0                              # fixes more than reorder_window_s behind the odometry
    max_fix_lag_ns: int = 0                            # the largest such lag (stamp time), ns
    scans_given_up: int = 0                            # scans whose fix can no longer be used (graph past them)
    future_stamps: int = 0                             # scans/fixes rejected: more than max_future_s ahead
    time_jumps: int = 0                                # clock jumps back: the user started afresh
    floors: "_FloorRuns" = field(default_factory=lambda: _FloorRuns())
    held: list = field(default_factory=list)           # (topic, msg, stamp) held while a jump back is unconfirmed
    armed_at_ns: int | None = None                     # /clock went back to this: the next jump back needs no
                                                       # confirmation (until :meth:`BackendStage._disarm`)
    before_jump_ns: int | None = None                  # the clock before the user's last jump back (its old track's end)

    def clock_ns(self) -> int | None:
        """The user's clock: its newest odometry stamp, or for a user without odometry its newest scan
        (or fix) stamp."""
        return self.newest_odom_ns if self.newest_odom_ns is not None else self.newest_scan_ns

    def afresh(self) -> "_UserInput":
        """A new buffer for the user starting afresh, keeping its counters."""
        return _UserInput(dropped_late=self.dropped_late, fixes_waited=self.fixes_waited,
                          max_fix_lag_ns=self.max_fix_lag_ns, scans_given_up=self.scans_given_up,
                          future_stamps=self.future_stamps, time_jumps=self.time_jumps)


@dataclass
class _FloorRuns:
    """The floor heights of a user's fixes taken, as runs of equal z: ``(first stamp, last stamp, z)``.
    :meth:`z_at` gives each stamp the z of the fix nearest to it in time (a floor change is placed
    half-way between the last fix on the old floor and the first on the new one)."""
    first: list = field(default_factory=list)
    last: list = field(default_factory=list)
    z: list = field(default_factory=list)

    def add(self, stamp_ns: int, z: float) -> None:
        if self.z and self.z[-1] == z:
            self.last[-1] = max(self.last[-1], stamp_ns)
        else:
            self.first.append(stamp_ns)
            self.last.append(stamp_ns)
            self.z.append(float(z))

    def z_at(self, stamps_ns) -> np.ndarray:
        """z (m) at each of ``stamps_ns`` (0 before any fix)."""
        t = np.asarray(stamps_ns, np.int64)
        if not self.z:
            return np.zeros(t.shape)
        # boundaries half-way between one run's last fix and the next run's first
        mid = (np.asarray(self.last[:-1], np.float64) + np.asarray(self.first[1:], np.float64)) / 2
        return np.asarray(self.z)[np.searchsorted(mid, t.astype(np.float64), side="left")]

    def forget_before(self, stamp_ns: int) -> None:
        """Drop runs no stamp at or after ``stamp_ns`` can take z from (bounds memory with the graph)."""
        k = bisect.bisect_left(self.last, stamp_ns) - 1      # runs [0, k) end before the one ending before it
        if k > 0:
            del self.first[:k], self.last[:k], self.z[:k]


class BackendStage(Stage):
    """Multi-user factor-graph back-end: <user>/pdr/odom + <user>/wifi/scan -> backend/<user>/{pose,path}."""
    NODE_NAME = NODE_NAME
    PARAMS = BackendParams
    MULTI_USER = True

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
        self.graph = MultiUserGraph(params.graph_params(), survey)
        self._no_survey = params.wifi_source == "scan" and (survey is None or not survey.n_scans)
        self.inputs_by_user: dict[str, _UserInput] = {}
        self._seq = 0
        self._replaying = False
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
            why = ("a fix whose scan was given up after fix_wait_s, a duplicate or out of stamp order"
                   if kind == 1 and self.params.fix_wait_s > 0 else "later than reorder_window_s")
            raise InvalidMessageError("too_late", f"{user}: stamp {stamp} older than the graph's newest "
                                                  f"{b.taken_ns}: {why}")
        self._seq += 1
        heapq.heappush(b.heap, (stamp, kind, self._seq, payload))

    def _jump_guard(self, user: str, topic: str, msg: Any, stamp_ns: int, recv_ns: int) -> list[Output] | None:
        """Clock jumps back. A message of the user's clock (its ``pdr/odom``; ``wifi/scan`` for a user
        without odometry) stamped more than ``time_jump_s`` before the clock is held, and so is every
        later message that far back; the next clock message decides: also that far back, the jump is
        confirmed (:meth:`_start_afresh`, the held messages then go into the new track); back in step
        with the clock, the held ones were stragglers and take the usual way (a message older than the
        graph's newest is ``too_late``, counted) — one late or wrongly stamped message never restarts a
        user. Returns None when the message goes on as usual, else the outputs (nothing while held)."""
        p = self.params
        b = self._buffer(user)
        clock = b.clock_ns()
        if not p.time_jump_s or clock is None or self._replaying:
            return None
        is_clock = topic == "pdr/odom" or (topic == "wifi/scan" and b.newest_odom_ns is None)
        far_back = stamp_ns < clock - p.time_jump_s * 1e9
        self._disarm(b, clock, is_clock and not far_back, recv_ns)
        if far_back:
            if is_clock and b.armed_at_ns is not None:    # /clock said so already
                return self._start_afresh(user, clock, b.held + [(topic, msg, stamp_ns)], recv_ns, said=True)
            if is_clock and any(h[0] == topic for h in b.held):
                return self._start_afresh(user, clock, b.held + [(topic, msg, stamp_ns)], recv_ns)
            if is_clock or b.held:
                outs = self._replay(user, b, recv_ns) if len(b.held) >= HELD_MAX else []   # bounded
                b.held.append((topic, msg, stamp_ns))
                return outs
            return None                              # a straggler scan or fix: too_late as usual
        if is_clock and b.held:                      # in step again: the held ones were stragglers
            outs = self._replay(user, b, recv_ns)
            return outs + self._replay_one(user, topic, msg, recv_ns)
        return None

    def _replay(self, user: str, b: _UserInput, recv_ns: int) -> list[Output]:
        """Hand the user's held messages to their handlers the usual way (no jump check)."""
        held, b.held = b.held, []
        outs: list[Output] = []
        for topic, msg, _ in held:
            outs += self._replay_one(user, topic, msg, recv_ns)
        return outs

    def _replay_one(self, user: str, topic: str, msg: Any, recv_ns: int) -> list[Output]:
        handler = {"pdr/odom": self._on_odom, "wifi/scan": self._on_scan, "wifi/fix": self._on_fix}[topic]
        self._replaying = True
        try:
            return handler(msg, recv_ns, user)
        except InvalidInputError as err:             # counted under its reason, as Stage.process does
            self._reject(err.reason, f"{user}/{topic}: {err}")
            return []
        except Exception as err:  # noqa: BLE001 - as Stage.process: counted, and the other held messages go on
            self._reject("internal_error", f"{user}/{topic}: {type(err).__name__}: {err}\n"
                                           f"{traceback.format_exc(limit=4)}")
            return []
        finally:
            self._replaying = False

    def _start_afresh(self, user: str, clock_ns: int, held: list, recv_ns: int, said: bool = False) -> list[Output]:
        """The user's clock jumped back: its track so far is finished and the user starts afresh
        with the ``held`` messages (:meth:`_new_track`). A notice (WARN; unless ``said`` by the
        ``/clock`` one) and the count say so."""
        outs = self._new_track(user)
        b = self.inputs_by_user[user]
        b.held = held
        b.before_jump_ns = clock_ns
        first = held[0]
        if not said:
            self.notice(f"{user}: {first[0]} stamp jumped back {(clock_ns - first[2]) * 1e-9:.3f} s "
                        f"({clock_ns} -> {first[2]} ns: a replay loop, a sim-time restart or a clock reset): "
                        f"the user starts afresh, its track so far kept as a finished user's "
                        f"(jump {b.time_jumps} of this user)")
        return outs + self._replay(user, b, recv_ns)

    def _new_track(self, user: str) -> list[Output]:
        """Finish the user's track (everything buffered taken, window optimised, its path published,
        as when a user leaves; it stays in the graph as a finished user's track) and give the user a
        fresh input buffer (its counters kept, one more time jump) for a new track."""
        p = self.params
        held, self.inputs_by_user[user].held = self.inputs_by_user[user].held, []
        outs = self._release(user, everything=True)
        self.graph.finish_user(user)
        tr = self.graph.users.get(user)
        if tr is not None and tr.poses:
            if p.window_poses:
                self.graph.optimize_window(user)
            outs.append(self._path_output(user))
        self.graph.restart_user(user)
        b = self.inputs_by_user[user] = self.inputs_by_user[user].afresh()
        b.time_jumps += 1
        b.held = held
        return outs

    def clock_jump(self, back_ns: int, now_ns: int) -> list[Output]:
        """The node's clock (``/clock`` under ``use_sim_time``) went back by ``back_ns`` to ``now_ns``:
        every user whose clock is more than ``time_jump_s`` ahead of it starts afresh — at once if
        messages of its new pass are already held, else at its first one (no confirmation needed;
        messages of the old pass still in flight go into the old track). One notice names them."""
        p = self.params
        users = [u for u, b in self.inputs_by_user.items()
                 if p.time_jump_s and (b.clock_ns() or 0) > now_ns + p.time_jump_s * 1e9]
        if not users:
            return []
        self.notice(f"/clock jumped back {back_ns * 1e-9:.3f} s (a replay loop or a simulation restart): "
                    f"these users start afresh, their tracks so far kept as finished users': {', '.join(users)}")
        outs: list[Output] = []
        for user in users:
            b = self.inputs_by_user[user]
            if any(h[0] == "pdr/odom" or b.newest_odom_ns is None for h in b.held):
                outs += self._start_afresh(user, b.clock_ns() or 0, b.held, now_ns, said=True)
            else:
                b.armed_at_ns = now_ns
        return outs

    def _disarm(self, b: _UserInput, clock_ns: int, in_step: bool, recv_ns: int) -> None:
        """End the arming of a user by a ``/clock`` jump (:meth:`clock_jump`) once its new pass can no
        longer be on its way: a clock message in step with the user's old clock received more than
        ``time_jump_s`` of the new clock after the jump (the user goes on with its old clock — a
        message of the old pass still in flight comes sooner), or the new clock past the user's clock
        (a pass replayed on ``/clock`` would no longer be stamped that far back). A jump back then
        needs its confirmation as any other (:meth:`_jump_guard`), so a lone late message does not
        restart the user."""
        if b.armed_at_ns is None:
            return
        if recv_ns > clock_ns or (in_step and recv_ns > b.armed_at_ns + self.params.time_jump_s * 1e9):
            b.armed_at_ns = None

    def clock_jump_threshold_ns(self) -> int:
        return int(self.params.time_jump_s * 1e9)

    def _check_future(self, user: str, stamp_ns: int, what: str) -> _UserInput:
        """Refuse a scan or fix stamped more than ``max_future_s`` ahead of the user's odometry: it would
        move the user's clock (and give up every scan waiting for its fix) on one wrong stamp. Refuse
        too, after a jump back, one stamped more than ``time_jump_s`` ahead of the user's clock but not
        after the clock before the jump: a message of the old track still in flight (a fix the WiFi
        node sends seconds after its scan), which would set the new track's clock and fix wait to the
        old track's stamps and so drop the new track's fixes as too_late."""
        b = self._buffer(user)
        clock = b.clock_ns()
        if (b.before_jump_ns is not None and clock is not None
                and clock + self.params.time_jump_s * 1e9 < stamp_ns <= b.before_jump_ns):
            raise InvalidMessageError(
                "before_jump", f"{user}: {what} stamp {stamp_ns} is {(stamp_ns - clock) * 1e-9:.1f} s ahead of the "
                               f"user's clock since it jumped back from {b.before_jump_ns}: a message of the track "
                               f"before the jump still in flight (its wifi/fix lagging), not of the new one")
        if b.newest_odom_ns is not None and stamp_ns > b.newest_odom_ns + self.params.max_future_s * 1e9:
            b.future_stamps += 1
            raise InvalidMessageError(
                "future_stamp", f"{user}: {what} stamp {stamp_ns} is {(stamp_ns - b.newest_odom_ns) * 1e-9:.1f} s "
                                f"ahead of the user's odometry (newest {b.newest_odom_ns}), more than max_future_s "
                                f"({self.params.max_future_s:g} s): a wrong stamp, or the user's pdr/odom stalled")
        return b

    def _on_odom(self, msg, recv_ns: int, user: str) -> list[Output]:
        od = odom_from_msg(msg)
        jump = self._jump_guard(user, "pdr/odom", msg, od.stamp_ns, recv_ns)
        if jump is not None:
            return jump
        self._push(user, od.stamp_ns, 0, od)
        b = self._buffer(user)
        b.newest_odom_ns = od.stamp_ns if b.newest_odom_ns is None else max(b.newest_odom_ns, od.stamp_ns)
        return self._release(user)

    def _on_scan(self, msg, recv_ns: int, user: str) -> list[Output]:
        scan = scan_from_msg(msg)
        if self._no_survey:
            raise InvalidMessageError("no_survey", "no radio map (radiomap ''): a user starts at a scan WKNN "
                                                   "localises against the survey, so none can; set radiomap")
        jump = self._take_wifi(user, "wifi/scan", msg, scan.stamp_ns, recv_ns, 2, scan)
        if jump is not None:
            return jump
        b = self._buffer(user)
        if self.params.wifi_source == "fix" and self.params.fix_wait_s > 0 and (
                b.fix_known_ns is None or scan.stamp_ns > b.fix_known_ns):
            bisect.insort(b.pending_scans, scan.stamp_ns)       # its fix is still to come
        return self._release(user)

    def _on_fix(self, msg, recv_ns: int, user: str) -> list[Output]:
        """A front-end fix (``wifi_source: fix``); it sorts before its own scan (same stamp), so the
        scan attaches to the fix's pose. A fix has its scan's stamp: it moves the scans' wait mark too,
        so a user without odometry is not held back until it leaves."""
        fix = fix_from_msg(msg, frame_id=self.params.frame_id)
        jump = self._take_wifi(user, "wifi/fix", msg, fix.stamp_ns, recv_ns, 1, fix)
        if jump is not None:
            return jump
        b = self._buffer(user)
        if b.newest_odom_ns is not None:
            lag = b.newest_odom_ns - fix.stamp_ns
            if lag > self.params.reorder_window_s * 1e9:     # held for: the window alone would have lost it
                b.fixes_waited += 1
                b.max_fix_lag_ns = max(b.max_fix_lag_ns, lag)
        b.fix_known_ns = fix.stamp_ns if b.fix_known_ns is None else max(b.fix_known_ns, fix.stamp_ns)
        # this scan's fix, or a later one: every scan up to its stamp is settled (fixes come in stamp order)
        del b.pending_scans[:bisect.bisect_right(b.pending_scans, b.fix_known_ns)]
        return self._release(user)

    def _take_wifi(self, user: str, topic: str, msg, stamp_ns: int, recv_ns: int, order: int,
                   event) -> list[Output] | None:
        """A scan's or fix's way in: held if it belongs to a jump back (its outputs returned), refused
        if stamped too far ahead, else queued and the scans' wait mark moved to its stamp (None)."""
        jump = self._jump_guard(user, topic, msg, stamp_ns, recv_ns)
        if jump is not None:
            return jump
        self._check_future(user, stamp_ns, topic)
        self._push(user, stamp_ns, order, event)
        b = self._buffer(user)
        b.newest_scan_ns = stamp_ns if b.newest_scan_ns is None else max(b.newest_scan_ns, stamp_ns)
        return None

    def _release(self, user: str, *, everything: bool = False) -> list[Output]:
        """Take the user's due events into the graph, in stamp order; outputs for new poses."""
        b = self._buffer(user)
        p = self.params
        odom_mark = -math.inf if b.newest_odom_ns is None else b.newest_odom_ns - p.reorder_window_s * 1e9
        scan_mark = -math.inf if b.newest_scan_ns is None else b.newest_scan_ns - p.max_scan_wait_s * 1e9
        barrier = self._fix_barrier(b, everything)
        new_pose = False
        while b.heap:
            stamp, kind, _, payload = b.heap[0]
            if not (everything or stamp <= odom_mark or (kind >= 1 and stamp <= scan_mark)):
                break
            if barrier is not None and (stamp, kind) >= (barrier, 1):
                break                          # a scan's fix is still to come: it goes in before these
            heapq.heappop(b.heap)
            b.taken_ns = stamp
            if kind == 0:
                new_pose |= self._take_odom(user, b, payload)
            elif kind == 1:
                self.graph.add_fix(user, payload.stamp_ns, payload.xy, payload.cov)
                b.floors.add(payload.stamp_ns, payload.z)
                new_pose = True
            else:
                pose, _match = self.graph.add_scan(user, payload)
                new_pose |= pose is not None
        self._give_up(b, everything)
        outs: list[Output] = []
        if new_pose:
            outs.append(self._pose_output(user))
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
        stamp = int(self.graph.poses.stamp[i])
        msg = pose_to_msg(stamp, x[:2], float(x[2]), cov_xy, frame_id=self.params.frame_id,
                          yaw_var=yaw_var, z=float(self._buffer(user).floors.z_at([stamp])[0]))
        return (BACKEND_POSE.format(user=user), msg)

    def _path_output(self, user: str) -> Output:
        st, x = self.graph.trajectory(user)
        stamp = int(st[-1]) if len(st) else 0
        msg = path_to_msg(st, x[:, :2], x[:, 2], frame_id=self.params.frame_id, stamp_ns=stamp)
        floors = self._buffer(user).floors
        if len(st):
            floors.forget_before(int(st[0]))            # older poses have left the graph
        for ps, z in zip(msg.poses, floors.z_at(st).tolist()):   # each pose at the floor of its nearest fix
            ps.pose.position.z = z
        return (BACKEND_PATH.format(user=user), msg)

    def _map_output(self, stamp_ns: int) -> Output:
        xy = np.vstack([self._drawn_survey, self.graph.wifi_radio_map().positions])
        return ("backend/wifi_map", points_markers("wifi_map", xy, self.params.frame_id, stamp_ns, scale=0.25))

    def _started_users(self) -> list[str]:
        return [u for u, tr in self.graph.users.items() if tr.poses]

    def finish_user(self, user: str) -> list[Output]:
        """The user's input ended: take everything buffered, publish its path (window-optimised)."""
        if user not in self.inputs_by_user:
            return []
        self.inputs_by_user[user].armed_at_ns = None                 # its new pass did not come
        outs = self._replay(user, self.inputs_by_user[user], 0)     # an unconfirmed jump: stragglers
        outs += self._release(user, everything=True)
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
            outs += self._replay(user, self.inputs_by_user[user], 0)
            outs += self._release(user, everything=True)
        if not self.graph.poses.n:
            return outs
        self.graph.optimize()
        users = self._started_users()
        outs += [self._pose_output(u) for u in users]
        outs += [self._path_output(u) for u in users]
        # every track's newest pose: a user restarted by a jump back may not have a pose on its new track yet
        end = int(self.graph.poses.view("stamp").max())
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
        for u, tr in self.graph.users.items():          # each user's current track
            out[f"user.{u}.step_length_m"] = f"{self.graph.step_len[tr.index]:.3f}"
            out[f"user.{u}.poses"] = str(len(tr.poses))
            out[f"user.{u}.scans_localised"] = str(tr.scans_localised)
            out[f"user.{u}.scans_unlocalised"] = str(tr.scans_unlocalised)
            out[f"user.{u}.scans_matched_to_users"] = str(tr.scans_from_users)
        for u, b in self.inputs_by_user.items():
            out[f"user.{u}.buffered"] = str(len(b.heap))
            out[f"user.{u}.dropped_late"] = str(b.dropped_late)
            out[f"user.{u}.future_stamps"] = str(b.future_stamps)
            out[f"user.{u}.time_jumps"] = str(b.time_jumps)
            if self.params.wifi_source == "fix":
                out[f"user.{u}.fixes_waited_for"] = str(b.fixes_waited)
                out[f"user.{u}.fix_lag_max_s"] = f"{b.max_fix_lag_ns * 1e-9:.2f}"
                out[f"user.{u}.scans_given_up"] = str(b.scans_given_up)
                out[f"user.{u}.scans_waiting_for_fix"] = str(len(b.pending_scans))
        out["time_jumps"] = str(sum(b.time_jumps for b in self.inputs_by_user.values()))
        out["future_stamps"] = str(sum(b.future_stamps for b in self.inputs_by_user.values()))
        if self.params.wifi_source == "fix":
            bs = self.inputs_by_user.values()
            out["fix_wait.fixes_waited_for"] = str(sum(b.fixes_waited for b in bs))
            out["fix_wait.lag_max_s"] = f"{max((b.max_fix_lag_ns for b in bs), default=0) * 1e-9:.2f}"
            out["fix_wait.scans_given_up"] = str(sum(b.scans_given_up for b in bs))
            out["fix_wait.scans_waiting"] = str(sum(len(b.pending_scans) for b in bs))
        if self.graph.last_solve is not None:
            s = self.graph.last_solve
            out["last_solve.poses"] = str(s.n_poses)
            out["last_solve.ms"] = f"{s.wall_s * 1e3:.1f}"
        return out
