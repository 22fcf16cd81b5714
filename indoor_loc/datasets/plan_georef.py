"""Floor plans given as images with reference points -> plans in the map frame (pure numpy).

A competition ships a floor's plan as a bitmap and a few reference points: pixel (column ``u``, row
``v`` from the top-left corner, continuous: ``(0, 0)`` is the top-left corner of the top-left pixel) ↔
latitude/longitude. With the points in the ENU map frame (:mod:`indoor_loc.datasets.geodesy`) the
image-to-map transform is the similarity ``xy = s R(theta) p + t`` of the image frame ``p = (u, H - v)``
(x right, y up, pixel units), fitted in least squares (Umeyama 1991, no reflection) from two or more
points: ``s`` m/px, ``theta`` the angle of the image's x axis from east (counter-clockwise), ``t`` the
map position of the image's bottom-left corner. :func:`align_plan` resamples the image onto a grid
aligned with the map axes (nearest pixel, outside = white), so the nav2 ``map.yaml`` convention
(resolution, bottom-left origin, no rotation) and ``indoor-loc map from-image`` read it as it is.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from indoor_loc.errors import MapError


@dataclass(frozen=True)
class PlanRef:
    """The image -> map similarity of a plan (module doc) and the fit's RMS residual at its points, m."""
    scale_m_per_px: float
    theta_rad: float
    t: np.ndarray
    height_px: int
    rms_m: float

    def to_map(self, uv_px: np.ndarray) -> np.ndarray:
        """Map xy (N, 2) m of image points (N, 2) ``(u, v)`` px from the top-left corner."""
        uv = np.asarray(uv_px, float).reshape(-1, 2)
        p = np.column_stack([uv[:, 0], self.height_px - uv[:, 1]])
        c, s = math.cos(self.theta_rad), math.sin(self.theta_rad)
        return self.scale_m_per_px * p @ np.array([[c, s], [-s, c]]) + self.t


def fit_plan_ref(uv_px: np.ndarray, xy_m: np.ndarray, height_px: int) -> PlanRef:
    """Least-squares similarity from reference points: image ``(u, v)`` px (N, 2) -> map ``xy`` m (N, 2),
    N >= 2 with two distinct image points (MapError otherwise)."""
    uv = np.asarray(uv_px, float).reshape(-1, 2)
    xy = np.asarray(xy_m, float).reshape(-1, 2)
    if len(uv) != len(xy) or len(uv) < 2 or not (np.all(np.isfinite(uv)) and np.all(np.isfinite(xy))):
        raise MapError(f"floor plan: expected two or more finite reference points (pixel and position), got "
                       f"{len(uv)} pixels and {len(xy)} positions")
    p = np.column_stack([uv[:, 0], height_px - uv[:, 1]])
    pm, xm = p.mean(axis=0), xy.mean(axis=0)
    pc, xc = p - pm, xy - xm
    var = float((pc ** 2).sum())
    if var <= 1e-9 or float((xc ** 2).sum()) <= 1e-12:
        raise MapError("floor plan: the reference points coincide (in the image or on the map)")
    # complex form of the 2-D Umeyama fit: xc = a * pc with a = s e^{i theta}
    zp, zx = pc[:, 0] + 1j * pc[:, 1], xc[:, 0] + 1j * xc[:, 1]
    a = complex(np.sum(np.conj(zp) * zx) / var)
    s, theta = abs(a), math.atan2(a.imag, a.real)
    zt = complex(xm[0], xm[1]) - a * complex(pm[0], pm[1])
    ref = PlanRef(s, theta, np.array([zt.real, zt.imag]), int(height_px), 0.0)
    res = ref.to_map(uv) - xy
    return PlanRef(s, theta, ref.t, int(height_px), float(np.sqrt(np.mean(np.sum(res ** 2, axis=1)))))


def align_plan(grey: np.ndarray, ref: PlanRef, *, max_px: int = 40_000_000) -> tuple[np.ndarray, np.ndarray, float]:
    """The plan resampled onto a grid aligned with the map axes at the image's scale: (grey (H', W')
    uint8, bottom-left origin (2,) m, resolution m/px). An image already aligned (|theta| below half a
    pixel over its size) is returned as it is."""
    g = np.asarray(grey)
    h, w = g.shape[:2]
    s = ref.scale_m_per_px
    if abs(ref.theta_rad) * max(h, w) < 0.5:
        return g, ref.t.copy(), s
    corners = ref.to_map(np.array([[0, 0], [w, 0], [0, h], [w, h]], float))
    lo, hi = corners.min(axis=0), corners.max(axis=0)
    wo, ho = int(math.ceil((hi[0] - lo[0]) / s)), int(math.ceil((hi[1] - lo[1]) / s))
    if wo * ho > max_px:
        raise MapError(f"floor plan: the aligned image would be {wo} x {ho} pixels (more than {max_px})")
    cols, rows = np.meshgrid(np.arange(wo) + 0.5, np.arange(ho) + 0.5)
    xy = np.column_stack([lo[0] + cols.ravel() * s, lo[1] + (ho - rows.ravel()) * s])   # output pixel centres
    c, sn = math.cos(ref.theta_rad), math.sin(ref.theta_rad)
    p = (xy - ref.t) @ np.array([[c, -sn], [sn, c]]) / s            # R^-1 (xy - t) / s: image frame
    u, v = np.floor(p[:, 0]).astype(np.int64), np.floor(h - p[:, 1]).astype(np.int64)
    inside = (u >= 0) & (u < w) & (v >= 0) & (v < h)
    out = np.full(wo * ho, 255, np.uint8)
    out[inside] = g[v[inside], u[inside]]
    return out.reshape(ho, wo), lo, s
