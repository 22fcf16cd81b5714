"""Pedestrian dead reckoning: stepometer hops × step length along the heading (Nowicki & Skrzypczyński 2019, Sec. 3).

Per stepometer hop ``i`` (``[t_start, t_end)``, ``n_i`` steps) and the heading ``ψ_i`` at the hop's
end, the position advances by ``d_i = l_s n_i`` metres along the **mean heading of the interval**
``ψ̄_i = ψ_(i-1) + wrap(ψ_i − ψ_(i-1))/2`` (the PDR edge ``e_p`` of Nowicki & Skrzypczyński 2019):
``x_i = x_(i-1) + d_i cos ψ̄_i``, ``y_i = y_(i-1) + d_i sin ψ̄_i``.

``pdr/odom`` contract (one nav_msgs/Odometry per stepometer hop, stamped at the hop's end, frame
``<user>/odom`` → ``<user>/base_link``); consumers decode it with :mod:`indoor_loc.measurements`
(:class:`~indoor_loc.measurements.PdrInterval`), which recovers per interval

- the step count ``n_i = |p_i − p_(i-1)| / step_length_m`` (each segment is laid straight along the
  mean heading, so the chord is exactly the walked distance; the odom origin (0, 0) is the start
  of the first hop, so the first message's steps are ``|p_0| / step_length_m``), and
- the heading change ``Δψ_i = wrap(ψ_i − ψ_(i-1))`` from the pose yaws;
- ``twist.linear.x`` = walking speed ``d_i / (t_end − t_start)`` m/s, ``twist.angular.z`` = yaw rate
  ``Δψ_i / (t_end − t_start)`` rad/s;
- the (x, y, yaw) covariance: yaw variance = the heading source's variance at the hop's end
  (``unknown_yaw_var`` = 1e6 rad² when there is no heading: accelerometer only); the position block
  accumulates, per hop, an along-track variance ``(step_length_rel_std · d_i)²`` and a cross-track
  variance ``d_i² · min(σ_ψ², 1)`` rotated into x, y (hops treated as independent), so it grows with
  the distance walked and with the heading uncertainty.
- step confidence: a hop the stepometer is unsure of (a moving but not periodic window, see
  :class:`indoor_loc.imu.stepometer_types.StepHop`) carries a count standard deviation ``σ_n`` (steps);
  it adds ``(step_length_m · σ_n)²`` to that hop's along-track variance (so the decoded interval's
  ``distance_var`` carries it), and ``twist.covariance[0]`` (variance of ``twist.linear.x``) is the
  hop's walking-speed variance ``((step_length_rel_std · d_i)² + (step_length_m · σ_n)²) / Δt²``
  (m²/s²): a consumer recovers the count's standard deviation as
  ``σ_n = sqrt(var_v Δt² − (step_length_rel_std · d_i)²) / step_length_m``. A confident hop has
  ``σ_n = 0``.

Without a heading the yaw is held at its last value (0 at the start) and the track is a straight
line whose length is still the walked distance.
"""
from __future__ import annotations

import bisect
import dataclasses
import math
from collections import deque
from dataclasses import dataclass, field as dc_field

import numpy as np
from numpy.typing import ArrayLike

from indoor_loc.measurements import OdomPose, wrap_angle
from indoor_loc.params import field, require

#: Yaw variance meaning "heading unknown", rad².
UNKNOWN_YAW_VAR = 1e6


@dataclass(frozen=True)
class PdrParams:
    """Parameters of :class:`Pdr`."""
    step_length_m: float = field(0.65, "nominal step length l_s, m (paper default 0.65)")
    step_length_rel_std: float = field(0.1, "relative standard deviation of the walked distance per hop "
                                            "(step length x count), 1")
    unknown_yaw_var: float = field(UNKNOWN_YAW_VAR, "yaw variance published when the heading is unknown, rad²")

    def validate(self) -> None:
        n = type(self).__name__
        require(self.step_length_m > 0, n, "step_length_m", "> 0", self.step_length_m)
        require(self.step_length_rel_std >= 0, n, "step_length_rel_std", ">= 0", self.step_length_rel_std)
        require(self.unknown_yaw_var > 0, n, "unknown_yaw_var", "> 0", self.unknown_yaw_var)


@dataclass
class PdrState:
    stamp_ns: int | None = None
    x: float = 0.0
    y: float = 0.0
    yaw: float = 0.0
    cov: np.ndarray = dc_field(default_factory=lambda: np.zeros((3, 3)))
    total_steps: float = 0.0
    distance_m: float = 0.0

    def copy(self) -> "PdrState":
        return dataclasses.replace(self, cov=self.cov.copy())


class Pdr:
    """Online PDR integrator (see the module docstring for the ``pdr/odom`` contract)."""

    def __init__(self, params: PdrParams | None = None) -> None:
        self.params = params if params is not None else PdrParams()
        self.params.validate()
        self._st = PdrState()
        self._st.cov[2, 2] = self.params.unknown_yaw_var

    def state(self) -> PdrState:
        return self._st.copy()

    def set_state(self, state: PdrState) -> None:
        self._st = state.copy()

    def update(self, t_start_ns: int, t_end_ns: int, steps: float, yaw: float | None,
               yaw_var: float | None = None, steps_std: float = 0.0) -> OdomPose:
        """Integrate one hop. ``yaw`` rad at the hop's end (None = unknown: the last yaw is held),
        ``yaw_var`` rad² (None with a known yaw = 0), ``steps_std`` the count's standard deviation
        (steps; 0 = a confident count)."""
        st = self._st
        p = self.params
        if yaw is None or not math.isfinite(yaw):
            yaw_new, var = st.yaw, p.unknown_yaw_var
        else:
            yaw_new = wrap_angle(float(yaw))
            var = 0.0 if yaw_var is None else min(float(yaw_var), p.unknown_yaw_var)
        dpsi = wrap_angle(yaw_new - st.yaw) if st.stamp_ns is not None else 0.0
        mean = st.yaw + 0.5 * dpsi if st.stamp_ns is not None else yaw_new
        d = max(0.0, float(steps)) * p.step_length_m
        c, s = math.cos(mean), math.sin(mean)
        st.x += d * c
        st.y += d * s
        # heading uncertainty of the segment: the larger of the two ends' variances
        seg_var = max(var, float(st.cov[2, 2]) if st.stamp_ns is not None else var)
        n_std = float(steps_std) if math.isfinite(steps_std) and steps_std > 0 else 0.0
        q_along = (p.step_length_rel_std * d) ** 2 + (p.step_length_m * n_std) ** 2
        q_cross = d * d * min(seg_var, 1.0)
        rot = np.array([[c, -s], [s, c]])
        st.cov[:2, :2] += rot @ np.diag([q_along, q_cross]) @ rot.T
        prev_var = float(st.cov[2, 2]) if st.stamp_ns is not None else var
        st.cov[2, 2] = var
        dt = max(1e-9, (int(t_end_ns) - int(t_start_ns)) * 1e-9)
        st.yaw = yaw_new
        st.stamp_ns = int(t_end_ns)
        st.total_steps += max(0.0, float(steps))
        st.distance_m += d
        # yaw rate = the heading change over the hop: the two ends' heading variances add (their errors
        # are treated as independent -- an upper bound for a slowly drifting heading); an unknown end
        # leaves the rate unknown (the unknown-yaw variance, like the pose's yaw)
        ends = var + prev_var
        rate_var = p.unknown_yaw_var if ends >= p.unknown_yaw_var else min(ends / (dt * dt), p.unknown_yaw_var)
        return OdomPose(st.stamp_ns, st.x, st.y, st.yaw, st.cov.copy(), d / dt, dpsi / dt,
                        speed_var=q_along / (dt * dt), yaw_rate_var=rate_var)


def pdr_batch(t_start_ns: ArrayLike, t_end_ns: ArrayLike, steps: ArrayLike, yaw: ArrayLike,
              yaw_var: ArrayLike | None = None, params: PdrParams | None = None) -> list[OdomPose]:
    """Integrate whole arrays of hops (N,) (``yaw`` NaN = unknown). Same as :meth:`Pdr.update` in a loop."""
    pdr = Pdr(params)
    n_ = np.asarray(steps, float)
    yv = np.zeros(len(n_)) if yaw_var is None else np.asarray(yaw_var, float)
    return [pdr.update(int(a), int(b), float(n), None if not np.isfinite(y) else float(y), float(v))
            for a, b, n, y, v in zip(np.asarray(t_start_ns, np.int64), np.asarray(t_end_ns, np.int64), n_,
                                     np.asarray(yaw, float), yv)]


class HeadingHistory:
    """Recent headings ``(stamp_ns, yaw rad, var rad²)`` for looking up the heading at a hop's end,
    which lags the newest sample by the stepometer latency. Linear interpolation of the unwrapped
    yaw; outside the stored span the nearest sample is used. Keeps ``horizon_s`` of history."""

    def __init__(self, horizon_s: float = 10.0) -> None:
        self.horizon_ns = int(horizon_s * 1e9)
        self._t: deque[int] = deque()
        self._yaw: deque[float] = deque()      # unwrapped
        self._var: deque[float] = deque()

    def __len__(self) -> int:
        return len(self._t)

    def add(self, stamp_ns: int, yaw: float, var: float) -> None:
        if self._t and stamp_ns <= self._t[-1]:
            return
        y = float(yaw)
        if self._yaw:
            y = self._yaw[-1] + wrap_angle(y - self._yaw[-1])
        self._t.append(int(stamp_ns))
        self._yaw.append(y)
        self._var.append(float(var))
        while len(self._t) > 2 and self._t[0] < stamp_ns - self.horizon_ns:
            self._t.popleft()
            self._yaw.popleft()
            self._var.popleft()

    def add_many(self, stamps_ns: list[int], yaw: list[float], var: list[float]) -> None:
        """:meth:`add` for each sample in order (same values and state)."""
        ts, ys, vs = self._t, self._yaw, self._var
        pi, two_pi = math.pi, 2.0 * math.pi
        last_t = ts[-1] if ts else None
        last_y = ys[-1] if ys else None
        for t, y, v in zip(stamps_ns, yaw, var):
            if last_t is not None and t <= last_t:
                continue
            y = float(y)
            if last_y is not None:
                y = last_y + ((y - last_y + pi) % two_pi - pi)      # wrap_angle, inline
            last_t, last_y = int(t), y
            ts.append(last_t)
            ys.append(y)
            vs.append(float(v))
        if ts:
            last = ts[-1]
            while len(ts) > 2 and ts[0] < last - self.horizon_ns:
                ts.popleft()
                ys.popleft()
                vs.popleft()

    def at(self, stamp_ns: int) -> tuple[float, float] | None:
        """(yaw wrapped, var) at ``stamp_ns`` or None when empty."""
        if not self._t:
            return None
        t = self._t
        i = bisect.bisect_left(t, stamp_ns)        # as np.searchsorted (side left), without a copy
        if i <= 0:
            return wrap_angle(self._yaw[0]), self._var[0]
        if i >= len(t):
            return wrap_angle(self._yaw[-1]), self._var[-1]
        w = (stamp_ns - t[i - 1]) / float(t[i] - t[i - 1])
        y = self._yaw[i - 1] + w * (self._yaw[i] - self._yaw[i - 1])
        return wrap_angle(y), max(self._var[i - 1], self._var[i])
