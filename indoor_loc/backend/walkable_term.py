"""The floor plan as a factor of the back-end: a pose outside the walkable area costs its distance to it.

A floor's plan (the importer's layout, as :func:`indoor_loc.wifi.walkable.load_floor_plans` reads it:
``<floor>/map.yaml`` with ``z_m``, ``width_m``, ``height_m`` beside ``geojson_map.json``) is rasterised by
:func:`indoor_loc.graph.from_geojson.rasterise` (the outline minus shops and shafts is free) and turned
into the Euclidean distance from every cell to the nearest free cell (0 inside the walkable area). A
pose at ``p`` on that floor then gets the residual ``d(p) / σ`` (``GraphParams.walkable_std_m``), with
``d`` interpolated bilinearly and its gradient taken from the same four cells — so a track a biased
fix pulled into a shop is pulled back to the nearest corridor by as much as the PDR and the other fixes
allow, and a pose inside the walkable area feels nothing. Off the plan's raster the distance grows
with the distance to the raster (the gradient points back to it).

Pure numpy/scipy (no rclpy): :class:`WalkableField` is what :class:`indoor_loc.backend.graph.MultiUserGraph`
evaluates; :func:`load_walkable_fields` builds it from a floors directory.
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from indoor_loc.errors import ConfigError, MapError
from indoor_loc.wifi.walkable import Z_TOLERANCE_M, floor_plan_files

#: raster resolution of the distance field (m): finer than a mall's narrowest corridor (≈ 2 m)
RESOLUTION_M = 0.5


@dataclass(frozen=True)
class FloorDistance:
    """Distance (m) to the walkable area on one floor's raster: ``dist[r, c]`` at the cell whose centre
    is ``origin + (c, rows - 1 - r) / px_per_m`` (row 0 at the top, as the bitmap)."""
    dist: np.ndarray
    px_per_m: float
    origin_xy: tuple[float, float]

    def eval(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(d (N,) m, ∇d (N, 2)) at points xy (N, 2): bilinear inside the raster; outside it, the
        distance at the nearest raster point plus the distance to it."""
        xy = np.asarray(xy, float).reshape(-1, 2)
        h, w = self.dist.shape
        u = (xy[:, 0] - self.origin_xy[0]) * self.px_per_m            # column coordinate
        v = (h - 1) - (xy[:, 1] - self.origin_xy[1]) * self.px_per_m  # row coordinate
        uc, vc = np.clip(u, 0.0, w - 1.000001), np.clip(v, 0.0, h - 1.000001)
        c0, r0 = np.floor(uc).astype(int), np.floor(vc).astype(int)
        fu, fv = uc - c0, vc - r0
        d00, d01 = self.dist[r0, c0], self.dist[r0, c0 + 1]
        d10, d11 = self.dist[r0 + 1, c0], self.dist[r0 + 1, c0 + 1]
        d = (d00 * (1 - fu) * (1 - fv) + d01 * fu * (1 - fv) + d10 * (1 - fu) * fv + d11 * fu * fv)
        dd_du = ((d01 - d00) * (1 - fv) + (d11 - d10) * fv) * self.px_per_m     # per metre of x
        dd_dv = ((d10 - d00) * (1 - fu) + (d11 - d01) * fu) * self.px_per_m     # per metre of -y
        grad = np.column_stack([dd_du, -dd_dv])
        # beyond the raster: add the distance to it, its gradient pointing away from the raster
        ox, oy = (uc - u) / self.px_per_m, (v - vc) / self.px_per_m        # (raster point - p) in x, y
        off = np.hypot(ox, oy)
        out = off > 0
        if out.any():
            d = d + off
            grad[out] = grad[out] * 0.0 + np.column_stack([-ox[out], -oy[out]]) / off[out, None]
        return d, grad


def floor_distance(geojson: Path, extent_m: tuple[float, float], resolution_m: float = RESOLUTION_M) -> FloorDistance:
    """The distance field of one floor's GeoJSON plan stretched onto ``extent_m`` (W, H) m."""
    from scipy import ndimage

    from indoor_loc.graph.from_geojson import rasterise
    try:
        data = json.loads(Path(geojson).read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise MapError(f"{geojson}: not a readable GeoJSON file: {err}") from err
    plan = rasterise(data, resolution_m=resolution_m, extent_m=extent_m, margin_m=1.0, where=str(geojson))
    free = plan.grey > 127
    if not free.any():
        raise MapError(f"{geojson}: no walkable cell")
    dist = ndimage.distance_transform_edt(~free) / plan.px_per_m
    return FloorDistance(dist.astype(float), float(plan.px_per_m), (float(plan.origin_xy[0]), float(plan.origin_xy[1])))


class WalkableField:
    """Distance to the walkable area per floor (by floor height ``z_m``)."""

    def __init__(self, floors: dict[float, FloorDistance]) -> None:
        self.floors = dict(floors)
        self._z = np.array(sorted(self.floors), float)

    def floor_at(self, z: float) -> FloorDistance | None:
        """The plan of the floor at height ``z`` (None: no plan there)."""
        if not len(self._z) or not math.isfinite(z):
            return None
        i = int(np.argmin(np.abs(self._z - z)))
        return self.floors[float(self._z[i])] if abs(self._z[i] - z) <= Z_TOLERANCE_M else None

    def eval(self, xy: np.ndarray, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(d (N,), ∇d (N, 2)) of points xy (N, 2) on floors at heights z (N,); 0 where no plan."""
        xy = np.asarray(xy, float).reshape(-1, 2)
        z = np.asarray(z, float).reshape(-1)
        d = np.zeros(len(xy))
        g = np.zeros((len(xy), 2))
        for zk in np.unique(z):
            fl = self.floor_at(float(zk))
            if fl is None:
                continue
            m = z == zk
            d[m], g[m] = fl.eval(xy[m])
        return d, g


def load_walkable_fields(directory: str | Path, resolution_m: float = RESOLUTION_M) -> WalkableField:
    """The distance fields of the floor plans under ``directory`` (the importer's ``floors/``: one
    directory per floor with ``map.yaml`` and ``geojson_map.json``, or one floor's directory; read by
    :func:`indoor_loc.wifi.walkable.floor_plan_files`). ConfigError naming the path when there is no
    plan or one is unreadable."""
    floors: dict[float, FloorDistance] = {}
    for z, gj, size in floor_plan_files(directory):
        try:
            floors[z] = floor_distance(gj, size, resolution_m)
        except MapError as err:
            raise ConfigError(f"floor_plans: {err}") from err
    return WalkableField(floors)
