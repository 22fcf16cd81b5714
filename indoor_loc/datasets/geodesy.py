"""WGS84 latitude/longitude <-> a local East-North-Up frame (pure numpy).

The map frame of an imported GetSensorData log is ENU (REP 103: x east, y north, z up) tangent to the
ellipsoid at an origin (a given latitude/longitude or the first reference point), height 0. Points go
geodetic -> ECEF -> ENU exactly (no flat-earth shortcut: over a few hundred metres both agree to
millimetres, but the exact form also holds for a campus); the inverse uses Bowring's closed form for the
latitude, exact to well under a millimetre at ground level.
"""
from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike

#: WGS84 semi-major axis (m) and flattening
WGS84_A = 6378137.0
WGS84_F = 1.0 / 298.257223563
_E2 = WGS84_F * (2.0 - WGS84_F)
_B = WGS84_A * (1.0 - WGS84_F)
_EP2 = (WGS84_A ** 2 - _B ** 2) / _B ** 2


def _ecef(lat_deg: np.ndarray, lon_deg: np.ndarray, h_m: np.ndarray) -> np.ndarray:
    lat, lon = np.radians(lat_deg), np.radians(lon_deg)
    n = WGS84_A / np.sqrt(1.0 - _E2 * np.sin(lat) ** 2)
    return np.stack([(n + h_m) * np.cos(lat) * np.cos(lon), (n + h_m) * np.cos(lat) * np.sin(lon),
                     (n * (1.0 - _E2) + h_m) * np.sin(lat)], axis=-1)


def _rotation(lat0_deg: float, lon0_deg: float) -> np.ndarray:
    """ECEF -> ENU rotation (rows: east, north, up) at the origin."""
    la, lo = math.radians(lat0_deg), math.radians(lon0_deg)
    return np.array([[-math.sin(lo), math.cos(lo), 0.0],
                     [-math.sin(la) * math.cos(lo), -math.sin(la) * math.sin(lo), math.cos(la)],
                     [math.cos(la) * math.cos(lo), math.cos(la) * math.sin(lo), math.sin(la)]])


def check_origin(lat0_deg: float, lon0_deg: float) -> None:
    """ValueError unless the origin is a finite latitude in [-90, 90] and longitude in [-180, 180]."""
    if not (math.isfinite(lat0_deg) and math.isfinite(lon0_deg) and -90 <= lat0_deg <= 90
            and -180 <= lon0_deg <= 180):
        raise ValueError(f"expected an origin latitude in [-90, 90] and longitude in [-180, 180] deg, "
                         f"got ({lat0_deg}, {lon0_deg})")


def geodetic_to_enu(lat_deg: ArrayLike, lon_deg: ArrayLike, lat0_deg: float, lon0_deg: float) -> np.ndarray:
    """(N, 2) east, north in metres of points (N,) deg relative to the origin (both at height 0)."""
    check_origin(lat0_deg, lon0_deg)
    lat = np.asarray(lat_deg, float).reshape(-1)
    lon = np.asarray(lon_deg, float).reshape(-1)
    d = _ecef(lat, lon, np.zeros_like(lat)) - _ecef(np.array(lat0_deg), np.array(lon0_deg), np.array(0.0))
    enu = d @ _rotation(lat0_deg, lon0_deg).T
    return enu[:, :2]


def enu_to_geodetic(xy_m: ArrayLike, lat0_deg: float, lon0_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """(lat (N,), lon (N,)) deg of ENU points (N, 2) m at height 0 in the origin's tangent plane (the
    inverse of :func:`geodetic_to_enu` for points on the ellipsoid: the tangent-plane height that puts
    them there is solved for, two fixed-point steps suffice at building scale)."""
    check_origin(lat0_deg, lon0_deg)
    xy = np.asarray(xy_m, float).reshape(-1, 2)
    r = _rotation(lat0_deg, lon0_deg)
    o = _ecef(np.array(lat0_deg), np.array(lon0_deg), np.array(0.0))
    up = np.zeros(len(xy))
    lat = lon = np.zeros(len(xy))
    for _ in range(3):          # the up coordinate of a point at ellipsoid height 0 (the curvature drop)
        p = o + np.column_stack([xy, up]) @ r
        lat, lon, h = _ecef_to_geodetic(p)
        up = up - h
    return lat, lon


def _ecef_to_geodetic(p: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    lon = np.arctan2(y, x)
    q = np.hypot(x, y)
    th = np.arctan2(z * WGS84_A, q * _B)
    lat = np.arctan2(z + _EP2 * _B * np.sin(th) ** 3, q - _E2 * WGS84_A * np.cos(th) ** 3)
    n = WGS84_A / np.sqrt(1.0 - _E2 * np.sin(lat) ** 2)
    h = q / np.cos(lat) - n
    return np.degrees(lat), np.degrees(lon), h
