"""Where people can be on each floor, from floor plans: the walkable area that bounds the extrapolating
radio map (:mod:`indoor_loc.wifi.radio_field`, ``PowedKnn.walkable``).

A floor's plan is a GeoJSON FeatureCollection (the Microsoft Indoor Location Competition 2.0 format's
``geojson_map.json``): the largest polygon is the floor's outline, the others (shops, shafts) are
obstacles. It is drawn with :func:`indoor_loc.graph.from_geojson.rasterise`, its shapes' bounding box
stretched onto the floor's size in metres (the format's ``floor_info.json`` ``map_info.width/height``),
and the free space is what is walkable.

``indoor-loc import ms-indoor`` writes ``OUT_DIR/floors/<floor>/`` with ``geojson_map.json`` and
``map.yaml`` (``z_m``, ``width_m``, ``height_m``, ...); :func:`load_floor_plans` reads such a directory
(one subdirectory per floor, or a single floor's directory) and matches each plan to the radio map's
floor by its height ``z_m``.
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import yaml

from indoor_loc.errors import ConfigError, MapError
from indoor_loc.wifi.radio_field import Walkable

#: the grid resolution of a rasterised plan (m): finer than the radio map's grid (1 m)
PLAN_RESOLUTION_M = 0.5
#: floor heights closer than this are the same floor (m)
Z_TOLERANCE_M = 0.01


def plan_walkable(geojson: Path, extent_m: tuple[float, float], resolution_m: float = PLAN_RESOLUTION_M
                  ) -> Walkable | None:
    """Where people can be on a floor, from its GeoJSON plan stretched onto the floor's size
    ``extent_m`` (W, H) m: the free space of :func:`indoor_loc.graph.from_geojson.rasterise` (the outline
    minus shops and shafts). None without a plan file. On ms_site2 it holds 97-100 % of every floor's
    survey and test positions. An unreadable plan raises :class:`MapError` naming the file."""
    from indoor_loc.graph.from_geojson import rasterise
    if not geojson.is_file():
        return None
    try:
        data = json.loads(geojson.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise MapError(f"{geojson}: not a readable GeoJSON file: {err}") from err
    plan = rasterise(data, resolution_m=resolution_m, extent_m=extent_m, margin_m=1.0, where=str(geojson))
    free = plan.grey > 127
    h, w = free.shape

    def walkable(xy: np.ndarray, z: float) -> np.ndarray:
        c = np.round((xy[:, 0] - plan.origin_xy[0]) * plan.px_per_m).astype(int)
        r = np.round(h - 1 - (xy[:, 1] - plan.origin_xy[1]) * plan.px_per_m).astype(int)
        inside = (r >= 0) & (r < h) & (c >= 0) & (c < w)
        out = np.zeros(len(xy), bool)
        out[inside] = free[r[inside], c[inside]]
        return out
    return walkable


def floors_walkable(plans: dict[float, Walkable]) -> Walkable:
    """One walkable area over floors: the plan of the floor at height z (nothing walkable on a floor
    without a plan, so the grid there keeps its default reach)."""
    heights = np.array(sorted(plans), float)

    def walkable(xy: np.ndarray, z: float) -> np.ndarray:
        if len(heights):
            i = int(np.argmin(np.abs(heights - z)))
            if abs(heights[i] - z) <= Z_TOLERANCE_M:
                return plans[float(heights[i])](xy, z)
        return np.zeros(len(xy), bool)
    return walkable


def floor_plan_files(directory: str | Path) -> list[tuple[float, Path, tuple[float, float]]]:
    """The floor plans under ``directory`` in the importer's layout (each floor a directory with
    ``map.yaml`` giving ``z_m``, ``width_m``, ``height_m`` and its ``geojson_map.json``, or one floor's
    directory): ``(z_m, geojson path, (width_m, height_m))`` per floor. A floor directory without a
    GeoJSON plan is skipped. Raises :class:`ConfigError` naming the path when the directory holds no
    plan, a ``map.yaml`` is unreadable or malformed, or two plans claim the same floor height."""
    root = Path(directory).expanduser()
    if not root.is_dir():
        raise ConfigError(f"floor_plans: {root} is not a directory (expected the importer's floors/ directory)")
    metas = [root / "map.yaml"] if (root / "map.yaml").is_file() else sorted(root.glob("*/map.yaml"))
    found: list[tuple[float, Path, tuple[float, float]]] = []
    for meta_path in metas:
        gj = meta_path.parent / "geojson_map.json"
        if not gj.is_file():
            continue
        try:
            meta = yaml.safe_load(meta_path.read_text()) or {}
            z, w, h = (float(meta[k]) for k in ("z_m", "width_m", "height_m"))
        except (OSError, yaml.YAMLError, KeyError, TypeError, ValueError) as err:
            raise ConfigError(f"floor_plans: {meta_path}: expected a mapping with numbers z_m, width_m, "
                              f"height_m: {type(err).__name__}: {err}") from err
        if not (math.isfinite(z) and w > 0 and h > 0 and math.isfinite(w) and math.isfinite(h)):
            raise ConfigError(f"floor_plans: {meta_path}: z_m finite and width_m, height_m > 0 expected, "
                              f"got {z}, {w}, {h}")
        if any(abs(z - z0) <= Z_TOLERANCE_M for z0, _, _ in found):
            raise ConfigError(f"floor_plans: {meta_path}: a second plan for the floor at z = {z:g} m")
        found.append((z, gj, (w, h)))
    if not found:
        raise ConfigError(f"floor_plans: no floor plan (*/map.yaml with geojson_map.json) under {root}")
    return found


def load_floor_plans(directory: str | Path) -> tuple[Walkable, dict[float, str]]:
    """The walkable area of the floor plans under ``directory`` (:func:`floor_plan_files`) and the
    plans used ({z_m: geojson path}). Raises :class:`ConfigError` naming the path when the directory
    holds no plan or a plan is unreadable, malformed, or two plans claim the same floor height."""
    plans: dict[float, Walkable] = {}
    used: dict[float, str] = {}
    for z, gj, size in floor_plan_files(directory):
        try:
            walk = plan_walkable(gj, size)
        except MapError as err:
            raise ConfigError(f"floor_plans: {err}") from err
        assert walk is not None
        plans[z] = walk
        used[z] = str(gj)
    return floors_walkable(plans), used
