"""GeoJSON floor shapes -> a floor-plan bitmap, for :func:`indoor_loc.graph.from_image.skeleton_graph`.

Two kinds of GeoJSON are read (RFC 7946 structure):

- **Wall lines**: LineString / MultiLineString features are wall strokes (``kind: wall`` when
  features carry a ``kind``, as the simulator's building file does; its rooms, nodes, links and
  access points are not walls). Door gaps are the gaps between the strokes.
- **Area shapes** (venue maps such as the Microsoft indoor-location competition's): the
  Polygon/MultiPolygon of largest area is the floor's outline (walkable), every other polygon an
  obstacle (a shop, a shaft), filled as wall.

Coordinates are map metres, or longitude/latitude degrees (every coordinate within ±180/±90 and
the whole spread under 0.1°), which are projected to local metres east/north of the shapes'
south-west corner (equirectangular, WGS 84 mean radius; under 1 mm error per 100 m at these
extents). ``extent_m = (W, H)`` instead stretches the bounding box of the shapes onto
``[0, W] x [0, H]``, the convention of datasets that publish the floor's size in metres beside
the image (the competition's ``floor_info.json``).

The bitmap is white (255) free space and black (0) walls/obstacles, with ``margin_m`` of white
around the shapes; :func:`plan_params` gives the matching scale and origin.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any, Mapping

import numpy as np
from scipy import ndimage

from indoor_loc.errors import MapError
from indoor_loc.graph.from_image import PlanParams

EARTH_RADIUS_M = 6_371_008.8   #: WGS 84 mean radius (m)


@dataclass(frozen=True)
class GeoPlan:
    """A rasterised GeoJSON floor: ``grey (H, W) uint8`` and the map position of its bottom-left corner."""
    grey: np.ndarray
    px_per_m: float
    origin_xy: tuple[float, float]
    lonlat: bool
    n_walls: int
    n_areas: int

    def plan_params(self, base: PlanParams | None = None) -> PlanParams:
        """``base`` (default :class:`PlanParams`) with this bitmap's scale and origin."""
        return replace(base or PlanParams(), px_per_m=self.px_per_m, origin_x_m=self.origin_xy[0],
                       origin_y_m=self.origin_xy[1])


def _rings(geom: Mapping[str, Any], where: str) -> tuple[list[np.ndarray], list[list[np.ndarray]]]:
    """(lines, polygons) of a geometry; a polygon is its list of rings (outer first)."""
    t = geom.get("type")
    c: Any = geom.get("coordinates")
    if c is None and t not in ("Point", "MultiPoint"):
        raise MapError(f"{where}: {t} without coordinates")
    try:
        if t == "LineString":
            return [np.asarray(c, float)[:, :2]], []
        if t == "MultiLineString":
            return [np.asarray(l, float)[:, :2] for l in c], []
        if t == "Polygon":
            return [], [[np.asarray(r, float)[:, :2] for r in c]]
        if t == "MultiPolygon":
            return [], [[np.asarray(r, float)[:, :2] for r in poly] for poly in c]
        if t in ("Point", "MultiPoint"):
            return [], []
    except (TypeError, ValueError, IndexError) as err:
        raise MapError(f"{where}: bad {t} coordinates ({err})") from err
    raise MapError(f"{where}: unsupported geometry type {t!r}")


def _area(ring: np.ndarray) -> float:
    x, y = ring[:, 0], ring[:, 1]
    return 0.5 * abs(float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))))


def rasterise(data: Mapping[str, Any], *, resolution_m: float = 0.05, floor: int | None = None,
              extent_m: tuple[float, float] | None = None, margin_m: float = 1.0,
              wall_width_m: float = 0.1, where: str = "geojson") -> GeoPlan:
    """Draw the walls and obstacles of a GeoJSON FeatureCollection (see the module docstring).

    ``floor``: keep only features whose ``floor`` property equals it (features without one are
    kept). Raises :class:`MapError` naming the offending feature."""
    from skimage.draw import line as draw_line
    from skimage.draw import polygon as draw_polygon

    if not resolution_m > 0:
        raise MapError(f"{where}: resolution_m must be > 0, got {resolution_m!r}")
    if not isinstance(data, Mapping) or data.get("type") != "FeatureCollection":
        raise MapError(f"{where}: expected a GeoJSON FeatureCollection")
    feats = data.get("features")
    if not isinstance(feats, list) or not feats:
        raise MapError(f"{where}: 'features' must be a non-empty list")
    lines: list[np.ndarray] = []
    polys: list[list[np.ndarray]] = []
    for k, ft in enumerate(feats):
        w = f"{where}: features[{k}]"
        if not isinstance(ft, Mapping) or not isinstance(ft.get("geometry"), Mapping):
            raise MapError(f"{w}: a Feature needs a geometry")
        props = ft.get("properties") or {}
        if floor is not None and "floor" in props and int(props["floor"]) != floor:
            continue
        kind = props.get("kind")
        ls, ps = _rings(ft["geometry"], w)
        if kind is not None and kind != "wall":
            ls = []                                     # only walls are strokes
        if kind is not None:
            ps = []                                     # a wall-line building: rooms are not obstacles
        for r in ls + [r for p in ps for r in p]:
            if r.ndim != 2 or len(r) < 2 or not np.isfinite(r).all():
                raise MapError(f"{w}: a line or ring needs >= 2 finite [x, y] points")
        lines += ls
        polys += ps
    if not lines and not polys:
        raise MapError(f"{where}: no wall lines or area polygons" + (f" on floor {floor}" if floor is not None else ""))
    allpts = np.vstack(lines + [r for p in polys for r in p])
    lo, hi = allpts.min(axis=0), allpts.max(axis=0)
    lonlat = bool(np.all(np.abs(allpts[:, 0]) <= 180) and np.all(np.abs(allpts[:, 1]) <= 90)
                  and np.all(hi - lo < 0.1))
    if extent_m is not None:
        if not (extent_m[0] > 0 and extent_m[1] > 0):
            raise MapError(f"{where}: extent must be two positive sizes in metres, got {extent_m!r}")
        span = np.maximum(hi - lo, 1e-12)
        scale = np.asarray(extent_m, float) / span

        def to_m(p: np.ndarray) -> np.ndarray:
            return (p - lo) * scale
    elif lonlat:
        k_lat = math.radians(1.0) * EARTH_RADIUS_M
        k_lon = k_lat * math.cos(math.radians(0.5 * (lo[1] + hi[1])))

        def to_m(p: np.ndarray) -> np.ndarray:
            return (p - lo) * np.array([k_lon, k_lat])
    else:
        def to_m(p: np.ndarray) -> np.ndarray:
            return p
    lines = [to_m(l) for l in lines]
    polys = [[to_m(r) for r in p] for p in polys]
    lo_m, hi_m = to_m(lo), to_m(hi)
    ppm = 1.0 / resolution_m
    origin = lo_m - margin_m
    w_px = int(math.ceil((hi_m[0] - origin[0] + margin_m) * ppm)) + 1
    h_px = int(math.ceil((hi_m[1] - origin[1] + margin_m) * ppm)) + 1
    if w_px * h_px > 200_000_000:
        raise MapError(f"{where}: {w_px}x{h_px} px at {resolution_m} m/px is too large; use a coarser resolution")

    def px(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return h_px - 1 - (p[:, 1] - origin[1]) * ppm, (p[:, 0] - origin[0]) * ppm   # rows, cols

    wall = np.zeros((h_px, w_px), bool)
    if polys:
        areas = [_area(p[0]) for p in polys]
        big = max(areas)
        outline = np.zeros_like(wall)
        for p, a in zip(polys, areas):
            target = outline if a >= 0.999 * big else wall
            for j, ring in enumerate(p):
                r, c = px(ring)
                rr, cc = draw_polygon(r, c, shape=wall.shape)  # type: ignore[no-untyped-call]
                target[rr, cc] = j == 0                  # holes (inner rings) are cut back out
        wall |= ~outline
    for l in lines:
        r, c = px(l)
        for k in range(len(l) - 1):
            rr, cc = draw_line(int(round(r[k])), int(round(c[k])),  # type: ignore[no-untyped-call]
                               int(round(r[k + 1])), int(round(c[k + 1])))
            ok = (rr >= 0) & (rr < h_px) & (cc >= 0) & (cc < w_px)
            wall[rr[ok], cc[ok]] = True
    if lines and wall_width_m * ppm > 1.5:
        wall = ndimage.distance_transform_edt(~wall) <= 0.5 * wall_width_m * ppm
    grey = np.where(wall, 0, 255).astype(np.uint8)
    return GeoPlan(grey, ppm, (float(origin[0]), float(origin[1])), lonlat, len(lines), len(polys))
