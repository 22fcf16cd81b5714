"""How much an estimator believes a position it is told (``wifi/fix``, ``initialpose``): one rule
shared by ``pdr_kf_node`` and ``tll_pf`` (docs/recovery.md).

A message may be plausible -- inside every bound of :data:`indoor_loc.contract.BOUNDS` -- and still
claim a precision no such measurement has: a fix with a covariance of 1e-6 m² collapses a Kalman
filter's position covariance, so the true fixes after it hardly move the state (or fail its
innovation gate), and an initial pose with such a covariance collapses a particle cloud to a point.
An estimator therefore never takes a position as more precise than its source can be:

- :data:`FIX_SIGMA_MIN_M` (1.0 m): no WiFi fix is better than about a metre. The 2.4 GHz wavelength
  is 12 cm, but small-scale fading moves a received power by several dB within a wavelength, and
  one dB of RSSI is of the order of a metre at the distances of indoor access points; fingerprinting
  systems report median errors of 1.5-3 m at best. Our own matcher floors its fix covariance at the
  same value (``cov_floor_m`` of :class:`indoor_loc.wifi.powed_knn.PowedKnnParams`), so fixes of
  ``wifi_fix_node`` are never changed by it; only fixes claiming more are.
- :data:`POSE_SIGMA_MIN_M` (0.5 m): an initial pose is given by a person clicking on a map or by
  another localiser; RViz's *2D Pose Estimate* itself sends 0.5 m per axis (0.25 m²), the value
  ``initialpose`` messages without a covariance get (:mod:`msg_adapters.initial_pose`).

:func:`floor_cov` raises the smallest eigenvalues of a 2-D covariance to the floor (the ellipse's
orientation and its larger axis kept). :func:`check_pose_current` refuses an initial pose older than
the newest fix (``superseded_pose``), :func:`check_fix_timely` a fix that comes too long after the
odometry passed its stamp (``fix_too_late``).
"""
from __future__ import annotations

import numpy as np

from indoor_loc.errors import InvalidInputError

#: Smallest standard deviation (m, any direction) an estimator grants a WiFi fix.
FIX_SIGMA_MIN_M = 1.0
#: Smallest standard deviation (m, any direction) an estimator grants an initial pose.
POSE_SIGMA_MIN_M = 0.5


def floor_cov(cov: np.ndarray, sigma_min_m: float) -> tuple[np.ndarray, bool]:
    """``cov`` (2, 2) m² with every eigenvalue at least ``sigma_min_m²``; and whether it changed."""
    c = np.asarray(cov, dtype=float).reshape(2, 2)
    c = 0.5 * (c + c.T)
    lo = float(sigma_min_m) ** 2
    vals, vecs = np.linalg.eigh(c)
    if vals.min() >= lo:
        return c, False
    return (vecs * np.maximum(vals, lo)) @ vecs.T, True


def check_pose_current(stamp_ns: int, newest_fix_ns: int | None, newest_motion_ns: int | None = None,
                       max_ahead_s: float = 10.0) -> None:
    """Refuse an initial pose stamped before the newest fix the estimator has received
    (``superseded_pose``): that fix is later evidence of where the user is, and restarting at the
    older pose would throw it away and put a past position at the present (a pose that reaches a busy
    node seconds late, behind the fixes that followed it) -- or stamped more than ``max_ahead_s``
    after the newest odometry (``pose_ahead``): a pose from the stream's future, which the odometry
    and the fixes to come would all precede. A pose stamped 0 is a command for now."""
    if not stamp_ns:
        return
    if newest_fix_ns is not None and stamp_ns < newest_fix_ns:
        raise InvalidInputError("superseded_pose", f"initial pose stamped {stamp_ns} ns, "
                                                   f"{(newest_fix_ns - stamp_ns) * 1e-9:.3f} s before the newest "
                                                   "wifi/fix already received: superseded by it")
    if newest_motion_ns is not None and stamp_ns > newest_motion_ns + int(max_ahead_s * 1e9):
        raise InvalidInputError("pose_ahead", f"initial pose stamped {(stamp_ns - newest_motion_ns) * 1e-9:.3f} s "
                                              f"after the newest odometry, more than {max_ahead_s:g} s")


#: A fix stamped this long before the newest motion (odometry) an estimator applied is refused, s.
FIX_LATE_MAX_S = 5.0


def check_fix_timely(stamp_ns: int, newest_motion_ns: int | None, late_max_s: float) -> None:
    """Refuse a fix stamped more than ``late_max_s`` before the newest odometry already applied
    (``fix_too_late``): the estimator has walked on since, so the fix can no longer go at its place in
    time, and applied at the present it would pull the estimate back to where the user was (a walker
    covers 6 m in 5 s, several times a fix's error) -- a fix worked off late by a busy node, or
    replayed. Fixes up to ``late_max_s`` behind are applied at once (``late_fixes``)."""
    if newest_motion_ns is not None and stamp_ns < newest_motion_ns - int(late_max_s * 1e9):
        raise InvalidInputError("fix_too_late", f"wifi/fix stamped {(newest_motion_ns - stamp_ns) * 1e-9:.3f} s before "
                                                f"the newest odometry applied, more than {late_max_s:g} s")


#: Fastest a walker moves between two fixes, m/s (a brisk walk is 1.5-2 m/s; runners are not tracked).
WALK_SPEED_MAX_MPS = 2.0


def fixes_agree(a: tuple[int, np.ndarray, np.ndarray], b: tuple[int, np.ndarray, np.ndarray],
                gate: float, speed_max_mps: float = WALK_SPEED_MAX_MPS) -> bool:
    """Whether two fixes ``(stamp ns, xy (2,), cov (2, 2))`` can both be right: the squared Mahalanobis
    distance between them, under both covariances plus the walk possible between their stamps
    (``speed_max_mps`` times the interval, per axis), within ``gate``. A run of fixes refusing the
    filter restarts it only when the fixes agree with each other -- the filter has left the truth --
    and not when they are scattered (outliers, or hostile fixes far apart)."""
    dt = abs(b[0] - a[0]) * 1e-9
    S = np.asarray(a[2], float) + np.asarray(b[2], float) + (speed_max_mps * dt) ** 2 * np.eye(2)
    d = np.asarray(b[1], float) - np.asarray(a[1], float)
    return bool(d @ np.linalg.solve(S, d) <= gate)


#: Shortest interval between two initial poses obeyed as a person's commands, s. RViz's *2D Pose
#: Estimate* (and Foxglove's) is a press-drag-release gesture on the map -- the position, then the
#: heading -- which takes a person about half a second at the quickest; poses coming faster are a
#: program or a fault (a driver replaying its queue, a loop), not a person.
POSE_INTERVAL_MIN_S = 0.5


class CommandRate:
    """The rate bound on initial poses (``pose_burst``): a pose received less than ``min_interval_s``
    (the node's clock at reception) after the previous one received -- obeyed or not -- is refused,
    so a burst is refused as long as it lasts and a person's next click after a pause is obeyed.
    Checked before the pose touches anything (a refusal costs nothing: an estimator working off a
    burst of poses one re-initialisation at a time falls seconds behind its inputs). ``~/set_pose``
    requests are answered (``success``) and not bounded. A receive time
    of 0 (no clock) or before the previous one (the clock went back) is never a burst; the stages
    forget the previous pose when they reset a user for a jump in time (:meth:`reset`)."""

    def __init__(self, min_interval_s: float = POSE_INTERVAL_MIN_S) -> None:
        self.min_ns = int(min_interval_s * 1e9)
        self.last_ns: int | None = None         # the node's clock at the previous pose received
        self.refused = 0

    def reset(self) -> None:
        """A jump in time (a replay loop, the node's clock going back): the next pose is a first."""
        self.last_ns = None

    def check(self, recv_ns: int, answered: bool = False) -> None:
        """Refuse a pose received at ``recv_ns`` within a burst (``pose_burst``). ``answered``: a pose
        given through a request its caller gets an answer to (``~/set_pose``), a deliberate command
        whatever its rate: never refused, and the next topic pose is judged from it."""
        if not recv_ns:
            return
        if answered:
            self.last_ns = recv_ns
            return
        last, self.last_ns = self.last_ns, recv_ns
        if last is not None and 0 <= recv_ns - last < self.min_ns:
            self.refused += 1
            raise InvalidInputError("pose_burst", f"initial pose {(recv_ns - last) * 1e-9:.3f} s after the previous "
                                                  f"one, less than {self.min_ns * 1e-9:g} s: faster than a person "
                                                  "gives poses")
