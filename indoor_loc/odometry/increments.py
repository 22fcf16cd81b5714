"""Robot odometry as increments: the relative motion between consecutive poses of a robot's
``nav_msgs/Odometry``, decimated, with its covariance (pure numpy; no ROS).

A robot's odometry (wheel encoders, visual-inertial odometry) integrates its motion into a pose in
its own ``odom`` frame that drifts without bound. The estimators never use that absolute pose:
they take the *increment* between two poses, ``δ = p_(k-1)^-1 ⊕ p_k`` in SE(2) — forward and
leftward motion (m) in the robot's frame at the increment's start, and the heading change (rad) —
and lay it down in their own frame (the particle filter by each particle's odom→map heading
offset, the Kalman filter by its direction-of-travel vector, the back-end by its poses' headings).

Decimation. Odometry comes at any rate (10–200 Hz); the estimators want one increment per
meaningful motion: an increment closes when the robot has travelled ``min_distance_m``, or turned
``min_angle_rad``, or ``max_interval_s`` has passed since it began (so a standing robot still
reports "no motion" about once a second, which keeps the estimators' clocks going). Composition
of the raw increments is exact (SE(2)), so decimation loses nothing but the path's shape inside
one increment. :meth:`IncrementAccumulator.flush` closes the open increment early (a WiFi fix must
be applied at its place in time).

Direction of travel. The estimators model motion *along a direction of travel* (a walker's
footsteps); a differential-drive robot may reverse. Each increment reports ``distance_m >= 0`` along
its chord, and ``travel_rad``: the chord's heading in the increment frame (the first pose's yaw taken
as 0, the heading changes summed), so a reversing robot travels along ``yaw + π``. ``dtravel_rad``
is the change of that heading from the previous increment (wrapped); while the robot turns in place
the heading of travel follows its yaw.

Covariance (``covariance``): the increment's (forward, left, heading) covariance in the frame of its
start pose, m² and rad².

- ``message``: from the growth of the odometry's own pose covariance, ``R^T (Σ_k − Σ_(k−1)) R``
  (R the start pose's rotation), clipped to be positive semi-definite — right for an odometry that
  integrates its own uncertainty (robot_localization's EKF in the ``odom`` frame, most VIO);
- ``model``: a documented model, variances growing linearly with the motion (a random walk per
  metre and per radian, the continuous form of the odometry motion model of Thrun, Burgard & Fox,
  *Probabilistic Robotics*, §5.4, whose ``alpha1..4`` nav2_amcl uses; linear rather than quadratic
  in the motion so that the sum over decimated increments does not depend on the decimation)::

      var_forward = trans_var_per_m · d + trans_var_per_rad · |Δθ|
      var_left    = lateral_var_per_m · d
      var_heading = rot_var_per_rad · |Δθ| + rot_var_per_m · d

  plus ``var_floor`` on each; the default is a good differential-drive robot on a hard floor
  (5 cm per √(10 m) … see the fields);
- ``auto`` (default): ``message`` when the odometry's pose covariance grew over the increment (its
  translation and heading variances both increased), else ``model`` — a driver that fills zeros,
  −1 ("unknown", REP 103 / sensor_msgs practice) or a constant covariance (diff_drive_controller's
  ``pose_covariance_diagonal``) says nothing about the increment, so the model is used.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from indoor_loc import params as P
from indoor_loc.errors import InvalidInputError
from indoor_loc.measurements import wrap_angle

COVARIANCE_SOURCES = ("auto", "message", "model")


@dataclass(frozen=True)
class OdomIncrementParams:
    """Decimation of a robot's odometry into increments and its covariance model (module doc)."""
    min_distance_m: float = P.field(0.5, "close an increment once the robot has travelled this far, m")
    min_angle_rad: float = P.field(0.3, "... or turned this much, rad")
    max_interval_s: float = P.field(1.0, "... or this much stamp time has passed since it began, s")
    covariance: str = P.field("auto", "increment covariance: auto (the message's when its pose covariance "
                                      "grows, else the model), message or model")
    trans_var_per_m: float = P.field(2.5e-4, "model: forward variance per metre travelled, m²/m (1.6 cm per √m)")
    trans_var_per_rad: float = P.field(1e-4, "model: forward variance per radian turned, m²/rad")
    lateral_var_per_m: float = P.field(2.5e-4, "model: leftward variance per metre travelled, m²/m")
    rot_var_per_rad: float = P.field(4e-4, "model: heading variance per radian turned, rad²/rad (2 % of a turn)")
    rot_var_per_m: float = P.field(1e-4, "model: heading variance per metre travelled, rad²/m (0.6 deg per √m)")
    var_floor: float = P.field(1e-6, "added to each variance of every increment (m², rad²)")

    def validate(self) -> None:
        n = type(self).__name__
        P.require(self.min_distance_m > 0, n, "min_distance_m", "> 0", self.min_distance_m)
        P.require(self.min_angle_rad > 0, n, "min_angle_rad", "> 0", self.min_angle_rad)
        P.require(self.max_interval_s > 0, n, "max_interval_s", "> 0", self.max_interval_s)
        P.require(self.covariance in COVARIANCE_SOURCES, n, "covariance", f"one of {COVARIANCE_SOURCES}",
                  self.covariance)
        for name in ("trans_var_per_m", "trans_var_per_rad", "lateral_var_per_m", "rot_var_per_rad",
                     "rot_var_per_m"):
            P.require(getattr(self, name) >= 0, n, name, ">= 0", getattr(self, name))
        P.require(self.var_floor > 0, n, "var_floor", "> 0", self.var_floor)


@dataclass(frozen=True)
class OdomIncrement:
    """The motion between two odometry poses (see the module doc).

    t_start_ns, t_end_ns: stamps of the poses, int ns; dx_m, dy_m: forward and leftward motion in the
    start pose's frame, m; dyaw_rad: heading change, rad; distance_m: chord length, m; travel_rad: the
    chord's heading in the increment frame, rad (wrapped); dtravel_rad: its change from the previous
    increment, rad (wrapped; 0 for the stream's first); reverse: the robot moved backwards; cov:
    (3, 3) covariance of (dx, dy, dyaw), m² / rad²; from_message: cov is the message's (else the model's)."""
    t_start_ns: int
    t_end_ns: int
    dx_m: float
    dy_m: float
    dyaw_rad: float
    distance_m: float
    travel_rad: float
    dtravel_rad: float
    reverse: bool
    cov: np.ndarray
    from_message: bool

    @property
    def var_along(self) -> float:
        """Variance of the distance along the chord, m²."""
        if self.distance_m <= 1e-9:
            return float(self.cov[0, 0])
        u = np.array([self.dx_m, self.dy_m]) / self.distance_m
        return float(u @ self.cov[:2, :2] @ u)

    @property
    def var_yaw(self) -> float:
        """Variance of the heading change, rad²."""
        return float(self.cov[2, 2])


def relative_pose(x0: float, y0: float, yaw0: float, x1: float, y1: float, yaw1: float) -> tuple[float, float, float]:
    """``p0^-1 ⊕ p1`` in SE(2): (forward m, leftward m, heading change rad) of pose 1 seen from pose 0."""
    c, s = math.cos(yaw0), math.sin(yaw0)
    dx, dy = x1 - x0, y1 - y0
    return c * dx + s * dy, -s * dx + c * dy, wrap_angle(yaw1 - yaw0)


def compose(x: float, y: float, yaw: float, dx: float, dy: float, dyaw: float) -> tuple[float, float, float]:
    """``p ⊕ δ`` in SE(2): the pose reached from (x, y, yaw) by the relative motion (dx, dy, dyaw)."""
    c, s = math.cos(yaw), math.sin(yaw)
    return x + c * dx - s * dy, y + s * dx + c * dy, wrap_angle(yaw + dyaw)


def model_cov(p: OdomIncrementParams, distance_m: float, dyaw_rad: float) -> np.ndarray:
    """The model covariance (3, 3) of an increment of ``distance_m`` and heading change ``dyaw_rad``."""
    d, r = abs(distance_m), abs(dyaw_rad)
    return np.diag([p.trans_var_per_m * d + p.trans_var_per_rad * r + p.var_floor,
                    p.lateral_var_per_m * d + p.var_floor,
                    p.rot_var_per_rad * r + p.rot_var_per_m * d + p.var_floor])


def message_cov(yaw0: float, cov0: np.ndarray, cov1: np.ndarray) -> np.ndarray | None:
    """The covariance an odometry's pose covariance growth ``cov1 − cov0`` (x, y, yaw in the odom
    frame) gives an increment starting at heading ``yaw0``, in its start frame; None when it did not
    grow (translation trace and yaw variance both must increase)."""
    d = np.asarray(cov1, float) - np.asarray(cov0, float)
    if not (d[0, 0] + d[1, 1] > 0 and d[2, 2] > 0):
        return None
    c, s = math.cos(yaw0), math.sin(yaw0)
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    m = R.T @ (0.5 * (d + d.T)) @ R
    w, v = np.linalg.eigh(m)
    return (v * np.maximum(w, 0.0)) @ v.T


class IncrementAccumulator:
    """Online decimator: feed every odometry pose (:meth:`update`), get an :class:`OdomIncrement`
    when one closes. :meth:`flush` closes the open one now. The same increments as
    :func:`odometry_increments` on the whole arrays (tested). ``state`` can be saved (it is plain)."""

    def __init__(self, params: OdomIncrementParams | None = None) -> None:
        self.params = params or OdomIncrementParams()
        self.params.validate()
        self.reset()

    def reset(self) -> None:
        #: the increment's start pose (stamp, x, y, yaw, cov) in the odom frame
        self._start: tuple[int, float, float, float, np.ndarray] | None = None
        self._last: tuple[int, float, float, float, np.ndarray] | None = None
        self._turned = 0.0                # |heading change| summed over the raw increments, rad
        self._travelled = 0.0             # path length over the raw increments, m
        self.yaw = 0.0                    # the robot's heading in the increment frame at the start pose
        self._travel: float | None = None  # heading of travel of the previous increment
        self._reverse = False

    @property
    def last_stamp_ns(self) -> int | None:
        return self._last[0] if self._last is not None else None

    def update(self, stamp_ns: int, x: float, y: float, yaw: float, cov: np.ndarray | None = None) -> OdomIncrement | None:
        """One odometry pose (odom frame: m, m, rad; ``cov`` (3, 3) of x, y, yaw or None = unknown).
        Raises ``InvalidInputError("non_monotonic_stamp")`` (nothing changes) unless the stamp increases."""
        c = np.zeros((3, 3)) if cov is None else np.asarray(cov, float)
        if self._last is not None and stamp_ns <= self._last[0]:
            raise InvalidInputError("non_monotonic_stamp", f"odom stamp {stamp_ns} <= previous {self._last[0]}")
        pose = (int(stamp_ns), float(x), float(y), float(yaw), c)
        if self._start is None:
            self._start = self._last = pose
            return None
        last = self._last
        assert last is not None
        fx, fy, fth = relative_pose(last[1], last[2], last[3], x, y, yaw)
        self._travelled += math.hypot(fx, fy)
        self._turned += abs(fth)
        self._last = pose
        p = self.params
        if (self._travelled >= p.min_distance_m or self._turned >= p.min_angle_rad
                or (stamp_ns - self._start[0]) * 1e-9 >= p.max_interval_s):
            return self.flush()
        return None

    def flush(self) -> OdomIncrement | None:
        """Close the open increment at the last pose fed (None when no motion time has passed)."""
        s, e = self._start, self._last
        if s is None or e is None or e[0] == s[0]:
            return None
        p = self.params
        dx, dy, dyaw = relative_pose(s[1], s[2], s[3], e[1], e[2], e[3])
        dist = math.hypot(dx, dy)
        cov = None
        if p.covariance != "model":
            cov = message_cov(s[3], s[4], e[4])
        from_msg = cov is not None
        if cov is None:
            cov = model_cov(p, max(dist, self._travelled), max(self._turned, abs(dyaw)))
        else:
            cov = cov + p.var_floor * np.eye(3)
        if dist > 1e-6:
            self._reverse = dx < 0.0
            travel = wrap_angle(self.yaw + math.atan2(dy, dx))
        else:       # turning in place: travel follows the yaw (backwards after a reverse)
            travel = wrap_angle(self.yaw + dyaw + (math.pi if self._reverse else 0.0))
        dtravel = 0.0 if self._travel is None else wrap_angle(travel - self._travel)
        inc = OdomIncrement(s[0], e[0], dx, dy, dyaw, dist, travel, dtravel, self._reverse, cov, from_msg)
        self._travel = travel
        self.yaw = wrap_angle(self.yaw + dyaw)
        self._start = e
        self._turned = self._travelled = 0.0
        return inc


def odometry_increments(stamps_ns: np.ndarray, xy: np.ndarray, yaw: np.ndarray, cov: np.ndarray | None = None,
                        params: OdomIncrementParams | None = None) -> list[OdomIncrement]:
    """Batch: the increments of a whole odometry stream, stamps (N,) int ns, xy (N, 2) m, yaw (N,)
    rad, cov (N, 3, 3) or None; the last open increment is flushed."""
    t = np.asarray(stamps_ns, np.int64)
    xy = np.asarray(xy, float).reshape(-1, 2)
    yaw = np.asarray(yaw, float)
    if xy.shape[0] != len(t) or yaw.shape != t.shape:
        raise InvalidInputError("shape", f"expected stamps (N,), xy (N, 2), yaw (N,), got {t.shape}, {xy.shape}, "
                                         f"{yaw.shape}")
    acc = IncrementAccumulator(params)
    out: list[OdomIncrement] = []
    for i in range(len(t)):
        inc = acc.update(int(t[i]), float(xy[i, 0]), float(xy[i, 1]), float(yaw[i]),
                         None if cov is None else cov[i])
        if inc is not None:
            out.append(inc)
    last = acc.flush()
    if last is not None:
        out.append(last)
    return out


def integrate(increments: list[OdomIncrement], x0: float = 0.0, y0: float = 0.0, yaw0: float = 0.0) -> np.ndarray:
    """Dead reckoning: the poses (K + 1, 3) the increments lead to from (x0, y0, yaw0)."""
    out = [(x0, y0, wrap_angle(yaw0))]
    for inc in increments:
        out.append(compose(*out[-1], inc.dx_m, inc.dy_m, inc.dyaw_rad))
    return np.array(out, float)
