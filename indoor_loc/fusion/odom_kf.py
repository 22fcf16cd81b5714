"""The linear Kalman filter of :mod:`indoor_loc.fusion.linear_pdr` driven by a robot's odometry
increments (:mod:`indoor_loc.odometry.increments`) instead of footsteps.

The state stays ``x = [r1, r2, v1, v2]`` (position m, map frame; *travel vector*, the map-frame unit
direction of travel times the odometry's scale error). One increment of ``d`` metres whose heading
of travel changed by ``Δψ`` since the previous one first turns the travel vector, then moves along
it (the increment's chord has the new heading)::

    v_t = R(Δψ) v_(t-1) + w_v,       r_t = r_(t-1) + d · v_t + w_r

so ``F = [[I, d R(Δψ)], [0, R(Δψ)]]`` — still linear, so the filter and the RTS smoother of
linear_pdr apply unchanged. The process noise comes from the increment's own covariance: on the
position its along-track variance plus the cross-track spread of a heading error growing over the
increment (``d² var_Δψ / 3``), on the travel vector the heading variance (``|v| ≈ 1``) plus a slow
random walk of the scale (``scale_var_per_m · d``). No initial heading is needed: ``v`` starts at 0
with 1 per axis, and WiFi fixes make it observable, as for PDR.
"""
from __future__ import annotations

import math

import numpy as np

from indoor_loc.errors import InvalidInputError


def odom_transition(distance_m: float, dtravel_rad: float, var_along: float, var_yaw: float, *,
                    scale_var_per_m: float = 1e-5, q_floor: float = 1e-6) -> tuple[np.ndarray, np.ndarray]:
    """F (4, 4) and Q (4, 4) of one odometry increment (see the module doc); variances m², rad²."""
    if not (math.isfinite(distance_m) and math.isfinite(dtravel_rad) and distance_m >= 0
            and var_along >= 0 and var_yaw >= 0):
        raise InvalidInputError("bad_odom", f"odom_transition: expected finite distance >= 0, heading change and "
                                            f"variances >= 0, got {distance_m}, {dtravel_rad}, {var_along}, {var_yaw}")
    c, s = math.cos(dtravel_rad), math.sin(dtravel_rad)
    R = np.array([[c, -s], [s, c]])
    F = np.eye(4)
    F[:2, 2:] = distance_m * R
    F[2:, 2:] = R
    q_r = var_along + distance_m ** 2 * var_yaw / 3.0 + q_floor
    q_v = var_yaw + scale_var_per_m * distance_m + q_floor
    Q = np.diag([q_r, q_r, q_v, q_v])
    # the position also carries the travel-vector noise of this increment (r_t = r + d v_t)
    Q[:2, :2] += distance_m ** 2 * q_v * np.eye(2)
    Q[:2, 2:] = Q[2:, :2] = distance_m * q_v * np.eye(2)
    return F, Q
