"""Measurements every estimator consumes (pure numpy): the WiFi :class:`Fix`, the PDR interval
:class:`PdrInterval` decoded from ``pdr/odom``, and the one :func:`wrap_angle`.

The linear Kalman filter, the particle filter, the graph back-end and the simulator all take these
types, so a measurement is decoded once, in one place, the same way for all of them.

``pdr/odom`` contract (written by :class:`indoor_loc.imu.pdr.Pdr`, one ``nav_msgs/Odometry`` per
stepometer hop, stamped at the hop's end): between two consecutive messages ``i-1`` and ``i``

- the step count is ``n_i = |p_i - p_(i-1)| / step_length_m`` (each hop is laid straight along its
  mean heading, so the chord is the walked distance ``d_i = |p_i - p_(i-1)|``);
- the heading change is ``dtheta_i = wrap(yaw_i - yaw_(i-1))``;
- the along-track variance of ``d_i`` is the growth of the position covariance along the chord,
  ``u^T (C_i - C_(i-1)) u`` with ``u`` the chord's unit vector (the producer adds exactly
  ``(step_length_rel_std * d_i)^2`` along the track), clipped at 0;
- the variance of ``dtheta_i`` is ``var(yaw_i) + var(yaw_(i-1))``: the two ends treated as
  independent, an upper bound (heading errors of a gyro-integrating filter are positively
  correlated over one hop, which makes the true variance of the difference smaller).

These are the inputs of the linear PDR state model (step count and heading change per interval) of
Raitoharju, Nurminen and Piché, "Kalman filter with a linear state model for PDR+WLAN positioning
and its application to assisting a particle filter", EURASIP J. Adv. Signal Process. 2015:33,
doi:10.1186/s13634-015-0216-z, Sec. 4, and the odometry edges of Nowicki and Skrzypczyński,
Sensors 19(1):157, 2019 (see ``docs/references.md``).
The first message of a stream opens the first interval and yields no interval itself.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, NamedTuple, TypeVar, overload

import numpy as np

from indoor_loc.errors import InvalidInputError

__all__ = ["Fix", "OdomPose", "PdrInterval", "PdrIntervalDecoder", "PdrIntervals", "pdr_intervals", "wrap_angle"]

_A = TypeVar("_A", bound=np.ndarray)


@overload
def wrap_angle(a: float) -> float: ...
@overload
def wrap_angle(a: _A) -> _A: ...
def wrap_angle(a: Any) -> Any:
    """Angle(s) wrapped to [-pi, pi), rad: a float for a float, an array of the same shape for an
    array (the same floor-modulo for both, so online and batch code agree to the bit)."""
    if isinstance(a, np.ndarray):
        return np.remainder(a + math.pi, 2.0 * math.pi) - math.pi
    return (a + math.pi) % (2.0 * math.pi) - math.pi


@dataclass(frozen=True)
class Fix:
    """A position estimate from one scan: ``xy`` (2,) metres in the map frame, ``cov`` (2, 2) m^2.

    ``ok`` is False when the method declined (too few shared APs, outlier rejection...), with
    ``reason`` saying why; ``info`` holds method-specific extras (matched map scans, weights...).
    ``z`` is the floor's height (m, the radio map's ``z_m``; 0 on a single-floor map) and ``z_var``
    its variance (m², from the floor probabilities; 0 when the floor is certain).
    """
    stamp_ns: int
    xy: np.ndarray
    cov: np.ndarray
    ok: bool = True
    reason: str = ""
    info: dict[str, Any] = field(default_factory=dict)
    z: float = 0.0
    z_var: float = 0.0


class OdomPose(NamedTuple):
    """A planar odometry pose as ``pdr/odom`` carries it: stamp_ns; x, y m and yaw rad (ENU, CCW from
    x) in ``frame_id``; cov (3, 3) of (x, y, yaw); speed m/s; yaw_rate rad/s; the frames ("" from the
    core, which does not know them)."""
    stamp_ns: int
    x: float
    y: float
    yaw: float
    cov: np.ndarray
    speed: float
    yaw_rate: float
    frame_id: str = ""
    child_frame_id: str = ""
    speed_var: float = 0.0          # variance of speed (twist.covariance[0]), m²/s²; 0 = not given
    yaw_rate_var: float = 0.0       # variance of yaw_rate (twist.covariance[35]), rad²/s²; 0 = not given


class PdrInterval(NamedTuple):
    """One PDR interval between two consecutive ``pdr/odom`` messages (see the module doc).

    t_start_ns, t_end_ns: stamps of the interval's ends, int ns; steps: step count (distance /
    nominal step length); distance_m: walked distance, m; dtheta: heading change, rad, in
    [-pi, pi); yaw: heading at the end, rad, in the odom frame; distance_var: along-track variance
    of ``distance_m``, m^2; dtheta_var: variance of ``dtheta``, rad^2 (an upper bound).
    """
    t_start_ns: int
    t_end_ns: int
    steps: float
    distance_m: float
    dtheta: float
    yaw: float
    distance_var: float
    dtheta_var: float


class PdrIntervals(NamedTuple):
    """Intervals as arrays, shape (N,) each; the fields of :class:`PdrInterval`."""
    t_start_ns: np.ndarray
    t_end_ns: np.ndarray
    steps: np.ndarray
    distance_m: np.ndarray
    dtheta: np.ndarray
    yaw: np.ndarray
    distance_var: np.ndarray
    dtheta_var: np.ndarray

    def __len__(self) -> int:
        return len(self.t_end_ns)

    def row(self, i: int) -> PdrInterval:
        return PdrInterval(int(self.t_start_ns[i]), int(self.t_end_ns[i]), float(self.steps[i]),
                           float(self.distance_m[i]), float(self.dtheta[i]), float(self.yaw[i]),
                           float(self.distance_var[i]), float(self.dtheta_var[i]))


def _check_step_length(step_length_m: float) -> float:
    if not (math.isfinite(step_length_m) and step_length_m > 0):
        raise InvalidInputError("step_length", f"expected step_length_m > 0, got {step_length_m!r}")
    return float(step_length_m)


def _along_var(dx: float, dy: float, d: float, dc: np.ndarray) -> float:
    """``u^T dC u`` for the chord (dx, dy) of length d; 0 for a zero-length chord."""
    if d <= 0.0:
        return 0.0
    ux, uy = dx / d, dy / d
    v = ux * ux * float(dc[0, 0]) + 2.0 * ux * uy * float(dc[0, 1]) + uy * uy * float(dc[1, 1])
    return max(v, 0.0)


class PdrIntervalDecoder:
    """Online decoder: feed successive odometry poses, get one :class:`PdrInterval` per pose after
    the first. Same numbers as :func:`pdr_intervals` on the whole arrays (tested)."""

    def __init__(self, step_length_m: float) -> None:
        self.step_length_m = _check_step_length(step_length_m)
        self._prev: tuple[int, float, float, float, np.ndarray] | None = None

    @property
    def last_stamp_ns(self) -> int | None:
        """Stamp of the last pose fed (None before the first)."""
        return self._prev[0] if self._prev is not None else None

    def reset(self) -> None:
        self._prev = None

    def update(self, stamp_ns: int, x: float, y: float, yaw: float, cov: np.ndarray) -> PdrInterval | None:
        """Pose at the end of a hop: ``x, y`` m, ``yaw`` rad, ``cov`` (3, 3) of (x, y, yaw).

        Raises :class:`InvalidInputError` (``"non_monotonic_stamp"``) when the stamp does not
        increase; the decoder is then unchanged."""
        prev = self._prev
        if prev is not None and stamp_ns <= prev[0]:
            raise InvalidInputError("non_monotonic_stamp", f"pdr/odom stamp {stamp_ns} <= previous {prev[0]}")
        cov = np.asarray(cov, dtype=float)
        self._prev = (int(stamp_ns), float(x), float(y), float(yaw), cov)
        if prev is None:
            return None
        dx, dy = float(x) - prev[1], float(y) - prev[2]
        d = math.hypot(dx, dy)
        return PdrInterval(prev[0], int(stamp_ns), d / self.step_length_m, d, wrap_angle(float(yaw) - prev[3]),
                           float(yaw), _along_var(dx, dy, d, cov[:2, :2] - prev[4][:2, :2]),
                           float(cov[2, 2]) + float(prev[4][2, 2]))


def pdr_intervals(stamps_ns: np.ndarray, xy: np.ndarray, yaw: np.ndarray, cov: np.ndarray | None = None, *,
                  step_length_m: float) -> PdrIntervals:
    """Batch decoder over N odometry poses: stamps (N,) int ns, xy (N, 2) m, yaw (N,) rad, cov
    (N, 3, 3) of (x, y, yaw) or None (variances 0) -> N-1 intervals (see the module doc)."""
    step = _check_step_length(step_length_m)
    t = np.asarray(stamps_ns, dtype=np.int64)
    xy = np.asarray(xy, dtype=float).reshape(-1, 2)
    yaw = np.asarray(yaw, dtype=float)
    n = len(t)
    if xy.shape[0] != n or yaw.shape != (n,):
        raise InvalidInputError("shape", f"expected stamps (N,), xy (N, 2), yaw (N,), got {t.shape}, "
                                         f"{xy.shape}, {yaw.shape}")
    if n > 1 and np.any(np.diff(t) <= 0):
        raise InvalidInputError("non_monotonic_stamp", "pdr/odom stamps must increase")
    c = np.zeros((n, 3, 3)) if cov is None else np.asarray(cov, dtype=float)
    if c.shape != (n, 3, 3):
        raise InvalidInputError("shape", f"expected cov (N, 3, 3), got {c.shape}")
    dxy = np.diff(xy, axis=0)
    d = np.hypot(dxy[:, 0], dxy[:, 1])
    dc = np.diff(c[:, :2, :2], axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        u = np.where(d[:, None] > 0, dxy / np.where(d > 0, d, 1.0)[:, None], 0.0)
    along = np.maximum(np.einsum("ni,nij,nj->n", u, dc, u), 0.0)
    return PdrIntervals(t[:-1].copy(), t[1:].copy(), d / step, d, wrap_angle(np.diff(yaw)), yaw[1:].copy(),
                        along, c[1:, 2, 2] + c[:-1, 2, 2])
