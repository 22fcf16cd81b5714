"""A floor's link graph from its GeoJSON plan (venue shapes: outline + obstacle polygons).

The importers' one recipe, so every floor of every imported site gets a graph the same way:
rasterise the plan (:func:`indoor_loc.graph.from_geojson.rasterise`, stretched onto the floor's
published extent when it has one) at ``resolution_m``, keep the free space reachable from
``seeds_xy`` (the survey walks' positions: pockets nobody can walk into are dropped) and take its
skeleton (:func:`indoor_loc.graph.from_image.skeleton_graph`). The graph is placed at the floor's
height ``z_m`` (a one-floor graph; ``floor`` names it).
"""
from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np

from indoor_loc.errors import MapError
from indoor_loc.graph.from_geojson import rasterise
from indoor_loc.graph.from_image import PlanParams, skeleton_graph
from indoor_loc.graph.model import BuildingGraph, Floor

#: Raster resolution of a plan for its graph (m/px): fine enough for 2 m wide mall corridors, small
#: enough that a 300 × 400 m floor skeletonises in a few seconds.
PLAN_RESOLUTION_M = 0.2


def floor_plan_graph(geojson: str | Path, *, extent_m: tuple[float, float] | None, floor: str = "0",
                     z_m: float = 0.0, seeds_xy: np.ndarray | None = None,
                     resolution_m: float = PLAN_RESOLUTION_M, plan: PlanParams | None = None) -> BuildingGraph:
    """The graph of one floor's GeoJSON plan (see the module docstring); MapError if the plan
    cannot be read, drawn or gives no free space around the seeds."""
    path = Path(geojson)
    try:
        data = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as err:
        raise MapError(f"cannot read GeoJSON {path}: {err}") from err
    raster = rasterise(data, resolution_m=resolution_m, extent_m=extent_m, where=str(path))
    seeds = None if seeds_xy is None or not len(seeds_xy) else np.asarray(seeds_xy, float)[:, :2]
    g = skeleton_graph(raster.grey, raster.plan_params(plan), seeds_xy=seeds)
    return replace(g, floors=(Floor(int(g.floors[0].id), str(floor), float(z_m)),),
                   node_xyz=np.column_stack([g.node_xyz[:, :2], np.full(g.n_nodes, float(z_m))]))
