"""Small quaternion and angle helpers; quaternions scalar-first (w, x, y, z), Hamilton product.

A quaternion ``q`` "device→ENU" rotates device-frame vectors into the ENU frame:
``v_enu = R(q) v_dev`` with ``R(q) = quat_to_rotmat(q)``. Functions accept one quaternion, shape
(4,), or a stack, shape (N, 4), and return the same leading shape.
"""
from __future__ import annotations

import math
from typing import Sequence

import numpy as np

from indoor_loc.errors import InvalidInputError


def qmul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product ``a ⊗ b`` of (…, 4) arrays (w x y z)."""
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    w1, x1, y1, z1 = np.moveaxis(a, -1, 0)
    w2, x2, y2, z2 = np.moveaxis(b, -1, 0)
    return np.stack([
        w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
        w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
        w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
        w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
    ], axis=-1)


def qconj(q: np.ndarray) -> np.ndarray:
    """Conjugate (the inverse of a unit quaternion), (…, 4)."""
    return np.asarray(q, dtype=float) * np.array([1.0, -1.0, -1.0, -1.0])


def qnormalize(q: np.ndarray) -> np.ndarray:
    """Unit quaternion(s) of the same shape; raises ValueError on a zero or non-finite norm."""
    q = np.asarray(q, dtype=float)
    n = np.linalg.norm(q, axis=-1, keepdims=True)
    if not np.all(np.isfinite(n)) or np.any(n == 0.0):
        raise InvalidInputError("bad_quaternion", "quaternion with zero or non-finite norm")
    return q / n


def quat_from_rotvec(v: np.ndarray) -> np.ndarray:
    """Exponential map: rotation vector (…, 3) in rad → unit quaternion (…, 4)."""
    v = np.asarray(v, dtype=float)
    angle = np.linalg.norm(v, axis=-1, keepdims=True)
    half = 0.5 * angle
    # sin(a/2)/a → 1/2 for a → 0 (series avoids 0/0)
    k = np.where(angle > 1e-9, np.sin(half) / np.where(angle > 1e-9, angle, 1.0), 0.5 - angle**2 / 48.0)
    return np.concatenate([np.cos(half), k * v], axis=-1)


def quat_to_rotmat(q: np.ndarray) -> np.ndarray:
    """Rotation matrix (…, 3, 3) of unit quaternion(s) (…, 4): ``v_out = R v_in``."""
    w, x, y, z = np.moveaxis(np.asarray(q, dtype=float), -1, 0)
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], axis=-2)


def quat_rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Rotate vector(s) ``v`` (…, 3) by ``q`` (…, 4): ``R(q) v``."""
    return np.einsum("...ij,...j->...i", quat_to_rotmat(q), np.asarray(v, dtype=float))


def yaw_xyzw(q: Sequence[float] | np.ndarray) -> float:
    """Yaw (ZYX Euler, CCW from world x), rad, of one quaternion in ROS order x, y, z, w.
    Plain floats: this runs once per IMU sample, where numpy's per-call overhead is 5x the math."""
    x, y, z, w = (float(v) for v in q)
    return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def quat_yaw(q: np.ndarray) -> np.ndarray:
    """Heading (yaw, rad, counter-clockwise from ENU east) of device→ENU quaternion(s): the angle of
    the device x axis projected on the horizontal plane (ZYX Euler yaw)."""
    w, x, y, z = np.moveaxis(np.asarray(q, dtype=float), -1, 0)
    return np.arctan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def quat_to_rpy(q: np.ndarray) -> np.ndarray:
    """ZYX Euler angles (roll, pitch, yaw) in rad, (…, 3), of device→ENU quaternion(s)."""
    w, x, y, z = np.moveaxis(np.asarray(q, dtype=float), -1, 0)
    roll = np.arctan2(2.0 * (w * x + y * z), 1.0 - 2.0 * (x * x + y * y))
    pitch = np.arcsin(np.clip(2.0 * (w * y - z * x), -1.0, 1.0))
    return np.stack([roll, pitch, quat_yaw(q)], axis=-1)


def quat_from_two_vectors(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Shortest-arc unit quaternion rotating direction ``a`` (3,) onto direction ``b`` (3,)."""
    a = np.asarray(a, dtype=float) / np.linalg.norm(a)
    b = np.asarray(b, dtype=float) / np.linalg.norm(b)
    c = float(np.dot(a, b))
    if c < -1.0 + 1e-12:  # opposite: any perpendicular axis, 180°
        axis = np.cross(a, [1.0, 0.0, 0.0])
        if np.linalg.norm(axis) < 1e-6:
            axis = np.cross(a, [0.0, 1.0, 0.0])
        axis /= np.linalg.norm(axis)
        return np.array([0.0, *axis])
    q = np.array([1.0 + c, *np.cross(a, b)])
    return q / np.linalg.norm(q)


def heading_inclination_error(q_est: np.ndarray, q_ref: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """BROAD error metric (Laidig et al., Data 6(7), 2021): ``q_err = q_est ⊗ q_ref⁻¹`` with both
    normalised; heading error ``2·atan(|z/w|)``, inclination error
    ``2·acos(clip(sqrt(w² + z²), 0, 1))``, both in rad, shape (N,). NaN where a reference is NaN."""
    qe = np.asarray(q_est, dtype=float)
    qr = np.asarray(q_ref, dtype=float)
    qe = qe / np.linalg.norm(qe, axis=-1, keepdims=True)
    qr = qr / np.linalg.norm(qr, axis=-1, keepdims=True)
    e = qmul(qe, qconj(qr))
    w, z = e[..., 0], e[..., 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        heading = 2.0 * np.arctan(np.abs(z / w))
    incl = 2.0 * np.arccos(np.clip(np.sqrt(w * w + z * z), 0.0, 1.0))
    return heading, incl
