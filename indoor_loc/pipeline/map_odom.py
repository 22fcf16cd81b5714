"""The ``map -> <user>/odom`` correction every estimator publishes for tf users (as nav2_amcl does).

A robot's (or walker's) odometry gives ``T_odom_base(t)``, the pose of ``<user>/base_link`` in
``<user>/odom``; an estimator gives ``T_map_base(t)``, the same body in ``map``. The correction is

    T_map_odom = T_map_base(t) · T_odom_base(t)^-1

taken at the estimate's stamp ``t``, with the odometry pose at that very stamp: the motion input's
poses are buffered (:class:`OdomTrack`) and interpolated between the two that bracket ``t``; an
estimate ahead of the newest odometry waits for the next odometry message (a robot's odometry comes
at tens of Hz, so a few tens of ms; nav2_amcl waits for tf the same way). A tf user then gets
``map -> odom -> base_link`` = the estimate at ``t`` and, between estimates, the estimate carried forward by the odometry.

The yaw of the correction is ``yaw_est - yaw_odom``; an estimate whose yaw is unknown (variance
at least :data:`YAW_UNKNOWN_VAR`, e.g. a fix-only Kalman estimate) keeps the previous correction's
rotation (0 before any), so its position still composes exactly.

One mechanism for every stage: a stage declares :class:`MapOdomSpec` (its motion topics, its pose
output, the correction's topic) as ``Stage.MAP_ODOM`` and the base class (``pipeline/stage.py``)
feeds a :class:`MapOdom` with every accepted motion message and every pose output, and appends the
correction to the outputs (one per call and user: the newest). The node broadcasts it on ``/tf``
(``nodes/tf_out.py``). The math here is plain numpy; messages go through ``msg_adapters``.
"""
from __future__ import annotations

import bisect
import math
from collections import deque
from dataclasses import dataclass
from typing import Any

from indoor_loc.errors import InvalidInputError
from msg_adapters.odom import odom_from_msg
from msg_adapters.pose_cdr import PoseCdr
from msg_adapters.tf import pose_yaw_var, transform_to_msg

#: An estimate's yaw variance (rad²) from which its yaw is taken as unknown (pi² : a uniform heading).
YAW_UNKNOWN_VAR = math.pi ** 2
#: Odometry poses kept per user (a robot's 50 Hz odometry: 40 s; a walker's hops: minutes).
ODOM_BUFFER = 2000


def wrap(a: float) -> float:
    """An angle in [-pi, pi)."""
    return (a + math.pi) % (2.0 * math.pi) - math.pi


def compose(a: tuple[float, float, float], b: tuple[float, float, float]) -> tuple[float, float, float]:
    """``a · b`` of planar poses ``(x, y, yaw)``."""
    c, s = math.cos(a[2]), math.sin(a[2])
    return (a[0] + c * b[0] - s * b[1], a[1] + s * b[0] + c * b[1], wrap(a[2] + b[2]))


def inverse(a: tuple[float, float, float]) -> tuple[float, float, float]:
    """``a^-1`` of a planar pose."""
    c, s = math.cos(a[2]), math.sin(a[2])
    return (-(c * a[0] + s * a[1]), s * a[0] - c * a[1], wrap(-a[2]))


def correction(map_base: tuple[float, float, float], odom_base: tuple[float, float, float],
               yaw: float | None = None) -> tuple[float, float, float]:
    """``T_map_odom = T_map_base · T_odom_base^-1``; with ``yaw`` given, the correction's rotation is
    that one and its translation makes the positions agree (``map_base``'s yaw is then not used)."""
    if yaw is None:
        return compose(map_base, inverse(odom_base))
    c, s = math.cos(yaw), math.sin(yaw)
    return (map_base[0] - (c * odom_base[0] - s * odom_base[1]),
            map_base[1] - (s * odom_base[0] + c * odom_base[1]), wrap(yaw))


class OdomTrack:
    """One user's odometry poses in stamp order (bounded), interpolated at any stamp."""

    def __init__(self, maxlen: int = ODOM_BUFFER) -> None:
        self.stamps: deque[int] = deque(maxlen=maxlen)
        self.poses: deque[tuple[float, float, float]] = deque(maxlen=maxlen)
        self.frame = ""

    def add(self, stamp_ns: int, pose: tuple[float, float, float], frame: str) -> None:
        self.frame = frame
        if not self.stamps or stamp_ns > self.stamps[-1]:
            self.stamps.append(stamp_ns)
            self.poses.append(pose)
            return
        i = bisect.bisect_left(self.stamps, stamp_ns)     # late (a stage whose stamp order is ANY)
        if self.stamps[i] == stamp_ns:
            self.poses[i] = pose
            return
        if len(self.stamps) == self.stamps.maxlen:
            if i == 0:
                return                                    # older than everything kept
            self.stamps.popleft()
            self.poses.popleft()
            i -= 1
        self.stamps.insert(i, stamp_ns)
        self.poses.insert(i, pose)

    def at(self, stamp_ns: int) -> tuple[float, float, float] | None:
        """The pose at ``stamp_ns``: linear between the bracketing poses (yaw along the shorter arc),
        the first/last one outside them; None before any."""
        if not self.stamps:
            return None
        i = bisect.bisect_left(self.stamps, stamp_ns)
        if i == 0:
            return self.poses[0]
        if i >= len(self.stamps):
            return self.poses[-1]
        t0, t1 = self.stamps[i - 1], self.stamps[i]
        a, b = self.poses[i - 1], self.poses[i]
        f = (stamp_ns - t0) / (t1 - t0)
        return (a[0] + f * (b[0] - a[0]), a[1] + f * (b[1] - a[1]), wrap(a[2] + f * wrap(b[2] - a[2])))


@dataclass(frozen=True)
class MapOdomSpec:
    """What a stage's correction is made of: its motion input topics (``nav_msgs/Odometry``), its
    pose output (``geometry_msgs/PoseWithCovarianceStamped``; ``{user}`` for a multi-user stage) and
    the topic of the correction (``geometry_msgs/TransformStamped``, latched)."""
    motion: tuple[str, ...]
    estimate: str
    out: str


@dataclass
class _UserCorrection:
    track: OdomTrack
    yaw: float = 0.0            # rotation of the latest correction (kept when an estimate's yaw is unknown)
    #: the newest estimate whose stamp the odometry has not reached yet: (stamp_ns, frame, pose, yaw var)
    pending: tuple[int, str, tuple[float, float, float], float] | None = None


class MapOdom:
    """Per-user odometry tracks and corrections of one stage (see the module doc)."""

    def __init__(self, spec: MapOdomSpec) -> None:
        self.spec = spec
        self.users: dict[str, _UserCorrection] = {}
        self.published = 0
        #: (message, its OdomPose) of the motion message being handled (:meth:`decoded`)
        self._decoded: tuple[Any, Any] | None = None

    def _user(self, user: str) -> _UserCorrection:
        u = self.users.get(user)
        if u is None:
            u = self.users[user] = _UserCorrection(OdomTrack())
        return u

    def reset(self, user: str) -> None:
        self.users.pop(user, None)

    def decoded(self, msg: Any, od: Any) -> None:
        """The stage's handler has decoded motion message ``msg`` into ``od`` (an ``OdomPose``):
        :meth:`motion` takes its pose and frame from it instead of decoding the message again."""
        self._decoded = (msg, od)

    def motion(self, user: str, msg: Any) -> None:
        """An accepted motion message (already validated by the stage's handler)."""
        done, self._decoded = self._decoded, None
        if done is not None and done[0] is msg:
            od = done[1]
        else:
            od = odom_from_msg(msg, unknown_cov=True)     # a robot driver's -1: the stage took it
        self._user(user).track.add(od.stamp_ns, (od.x, od.y, od.yaw), od.frame_id)

    def corrections(self, user: str, outs: list[tuple[str, Any]]) -> list[tuple[str, Any]]:
        """The correction for the newest estimate among ``outs`` and the one waiting: at once when the
        odometry has reached its stamp, else when it does (an estimate ahead of the odometry, e.g. a fix
        applied before the next odometry message, waits for it rather than use a stale odometry pose)."""
        topic = self.spec.estimate.format(user=user)
        cands = []
        for t, m in outs:
            if t == topic:
                try:
                    # an estimate packed to CDR (msg_adapters/pose_cdr.py) carries what it holds
                    cands.append(m.estimate if isinstance(m, PoseCdr) else pose_yaw_var(m))
                except InvalidInputError:
                    continue                          # the stage's own output: nothing to correct from
        u = self._user(user) if cands else self.users.get(user)
        if u is None:
            return []
        if u.pending is not None:
            cands.append(u.pending)
            u.pending = None
        if not cands:
            return []
        stamp_ns, frame, est, yaw_var = max(cands, key=lambda c: c[0])
        if not u.track.stamps or stamp_ns > u.track.stamps[-1]:
            u.pending = (stamp_ns, frame, est, yaw_var)
            return []
        odom = u.track.at(stamp_ns)
        assert odom is not None
        yaw = u.yaw if yaw_var >= YAW_UNKNOWN_VAR or not math.isfinite(est[2]) else None
        x, y, u.yaw = correction(est, odom, yaw)
        self.published += 1
        return [(self.spec.out.format(user=user),
                 transform_to_msg(stamp_ns, frame, u.track.frame, x, y, u.yaw))]
