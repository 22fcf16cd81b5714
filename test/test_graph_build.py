"""Floor plan / GeoJSON -> building graph, and the ``indoor-loc map`` command."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from indoor_loc.errors import ConfigError, MapError
from indoor_loc.graph.from_geojson import EARTH_RADIUS_M, rasterise
from indoor_loc.graph.from_image import PlanParams, free_space, skeleton_graph
from indoor_loc.graph.io import load_graph

PUTMC = Path(__file__).resolve().parents[1] / ".." / "shared" / "datasets" / "putmc"
PPM = 10.0   # px per metre of the synthetic plans


def _plan(w_m: float, h_m: float) -> np.ndarray:
    return np.full((int(h_m * PPM), int(w_m * PPM)), 255, np.uint8)


def _box(img: np.ndarray, x0: float, y0: float, x1: float, y1: float, grey: int = 0) -> None:
    """Fill map rectangle [x0, x1] x [y0, y1] (m, y up) with ``grey``."""
    h = img.shape[0]
    img[h - int(round(y1 * PPM)):h - int(round(y0 * PPM)), int(round(x0 * PPM)):int(round(x1 * PPM))] = grey


def _building(img: np.ndarray, x0: float, y0: float, x1: float, y1: float, t: float = 0.2) -> None:
    _box(img, x0, y0, x1, y0 + t)
    _box(img, x0, y1 - t, x1, y1)
    _box(img, x0, y0, x0 + t, y1)
    _box(img, x1 - t, y0, x1, y1)


def _two_rooms(door_grey: int) -> np.ndarray:
    """Two 8 x 6 m rooms side by side; the wall between them has a 1 m door drawn in ``door_grey``."""
    img = _plan(20, 10)
    _building(img, 1, 1, 19, 9)
    _box(img, 9.9, 1, 10.1, 4)
    _box(img, 9.9, 5, 10.1, 9)
    _box(img, 9.9, 4, 10.0, 5, door_grey)         # the door leaf, drawn as a thin line
    return img


def test_light_door_line_is_passable_dark_wall_is_not():
    p = PlanParams(px_per_m=PPM, min_spur_m=0.5)
    g = skeleton_graph(_two_rooms(door_grey=200), p)
    x = g.node_xyz[:, 0]
    assert x.min() < 8 and x.max() > 12, "the graph spans both rooms through the light door"
    g2 = skeleton_graph(_two_rooms(door_grey=40), p)
    x2 = g2.node_xyz[:, 0]
    assert x2.max() < 10 or x2.min() > 10, "a dark stroke is a wall: one room only"


def test_strip_between_outer_wall_and_image_border_is_outside():
    # the building's top wall runs 1 m below the image border and has a 1.5 m window gap: the strip
    # above it is outside even though the closing over outer-wall gaps reaches the border
    img = _plan(20, 10)
    _building(img, 1, 1, 19, 9)
    _box(img, 9, 8.8, 10.5, 9, 255)
    p = PlanParams(px_per_m=PPM)
    free = free_space(img, p)
    assert not free[:int(1.0 * PPM)].any(), "no free pixel in the strip above the building"
    g = skeleton_graph(img, p)
    assert g.node_xyz[:, 1].max() < 9.0


def test_lonlat_shapes_are_projected_to_metres():
    lat0 = 30.0
    d = 0.001
    outline = [[120.0, lat0], [120.0 + d, lat0], [120.0 + d, lat0 + d], [120.0, lat0 + d], [120.0, lat0]]
    data = {"type": "FeatureCollection", "features": [
        {"type": "Feature", "properties": {}, "geometry": {"type": "Polygon", "coordinates": [outline]}}]}
    plan = rasterise(data, resolution_m=0.5, margin_m=0.0)
    assert plan.lonlat
    h, w = plan.grey.shape
    k_lat = np.radians(d) * EARTH_RADIUS_M
    assert abs((h - 1) * 0.5 - k_lat) <= 0.5
    assert abs((w - 1) * 0.5 - k_lat * np.cos(np.radians(lat0 + d / 2))) <= 0.5
    plan2 = rasterise(data, resolution_m=0.5, margin_m=0.0, extent_m=(40.0, 20.0))
    assert plan2.grey.shape == (41, 81)


def test_geojson_errors_name_the_feature():
    data = {"type": "FeatureCollection", "features": [
        {"type": "Feature", "properties": {}, "geometry": {"type": "LineString", "coordinates": [[0, 0], [5, 0]]}},
        {"type": "Feature", "properties": {}, "geometry": {"type": "LineString", "coordinates": [[1, 1]]}}]}
    with pytest.raises(MapError, match=r"features\[1\]"):
        rasterise(data)
    data["features"][1]["geometry"] = {"type": "Circle", "coordinates": [0, 0]}
    with pytest.raises(MapError, match=r"features\[1\].*Circle"):
        rasterise(data)
    with pytest.raises(MapError, match="FeatureCollection"):
        rasterise({"type": "Feature"})


def test_sample_building_walls_give_its_corridor():
    """Skeletonising the simulator building's walls recovers its authored corridor and doors."""
    from indoor_loc.sim.building import building_graph, sample_building, sample_building_path
    data = json.loads(sample_building_path().read_text())
    plan = rasterise(data, resolution_m=0.05, floor=0)
    g = skeleton_graph(plan.grey, plan.plan_params())
    b = sample_building()
    authored = building_graph(b)
    on0 = (authored.node_floor == 0) & np.isin(np.array(b.node_kind), ["corridor", "junction", "door"])
    d = g.project(authored.node_xyz[on0, :2])[2]
    assert on0.sum() >= 10
    assert np.percentile(d, 90) < 0.5 and d.max() < 1.5, d


def test_map_command_from_image_and_draw(tmp_path):
    from PIL import Image

    from indoor_loc.cli import main
    png = tmp_path / "plan.png"
    Image.fromarray(_two_rooms(200)).save(png)
    out = tmp_path / "g.yaml"
    assert main(["map", "from-image", str(png), "--px-per-m", str(PPM), "--origin", "5", "-2", "-o", str(out)]) == 0
    g = load_graph(out)
    assert g.node_xyz[:, 0].min() > 5 + 1 and g.node_xyz[:, 1].min() > -2 + 1
    assert "from-image" in out.read_text()
    assert main(["map", "from-image", str(png), "--px-per-m", str(PPM), "-o", str(out)]) == 2   # exists
    seeds = tmp_path / "seeds.csv"
    seeds.write_text("x,y\n8,5\n")
    assert main(["map", "from-image", str(png), "--px-per-m", str(PPM), "--grid", "0.5", "--seeds", str(seeds),
                 "-o", str(out), "--overwrite"]) == 0
    assert load_graph(out).n_links > 100
    pic = tmp_path / "g.png"
    assert main(["map", "draw", str(out), "-o", str(pic), "--plan", str(png), "--px-per-m", str(PPM),
                 "--width-in", "4"]) == 0
    assert pic.stat().st_size > 1000


def test_map_command_from_geojson_authored_graph(tmp_path):
    from indoor_loc.cli import main
    from indoor_loc.sim.building import sample_building_path
    out = tmp_path / "b.yaml"
    assert main(["map", "from-geojson", str(sample_building_path()), "-o", str(out)]) == 0
    g = load_graph(out)
    assert len(g.floors) == 2 and g.link_vertical.any()
    bad = tmp_path / "bad.geojson"
    bad.write_text("{not json")
    assert main(["map", "from-geojson", str(bad), "-o", str(tmp_path / "x.yaml")]) == 2


def test_read_points_rejects_bad_rows(tmp_path):
    from indoor_loc.commands.map import read_points
    f = tmp_path / "p.txt"
    f.write_text("# x y\n1 2\n3 oops\n")
    with pytest.raises(ConfigError, match=r"p.txt:3"):
        read_points(f)


@pytest.mark.skipif(not (PUTMC / "map.png").exists(), reason="PUTMC dataset not found at ../shared/datasets/putmc")
def test_putmc_graph_covers_every_true_route():
    """The graph made from PUTMC's map.png follows every walk's true route (before the door and
    outside fixes, parts of five walks lay up to 12.6 m off it)."""
    from indoor_loc.commands.map import route_points
    from indoor_loc.datasets.putmc import PUTMC_SCALE_PX_PER_M, Putmc
    from indoor_loc.graph.from_image import read_plan
    ds = Putmc(PUTMC)
    g = skeleton_graph(read_plan(ds.map_png()), PlanParams(px_per_m=PUTMC_SCALE_PX_PER_M),
                       seeds_xy=ds.survey_map().positions)
    d = g.project(route_points(np.concatenate([r.segments for r in ds.routes.values()])))[2]
    assert d.mean() < 0.4 and np.percentile(d, 95) < 1.0 and d.max() < 3.0, (d.mean(), d.max())
    assert g.node_xyz[:, 1].max() < 35.5, "nothing in the strip outside the north wall"


def test_bench_route_sampling_holds_the_latest_estimate():
    """The PF bench scores the route at the reference's sampling: a pose every ROUTE_SAMPLE_S and
    at every scan inside the trajectory, each the latest estimate at or before it."""
    from indoor_loc.bench.pf import ROUTE_SAMPLE_S, decimate, paper_sampling
    t = np.array([0, 1_000_000_000, 2_000_000_000, 4_000_000_000], np.int64)
    xy = np.array([[0.0, 0], [1, 0], [2, 0], [4, 0]])
    q, p = paper_sampling(t, xy, np.array([1_500_000_000, 9_000_000_000]))
    step = int(ROUTE_SAMPLE_S * 1e9)
    assert list(q) == sorted({0, step, 2 * step, 3 * step, 1_500_000_000})
    assert np.allclose(p[:, 0], [0, 1, 1, 2, 2])          # held, never interpolated ahead
    kept = decimate([(0, None), (4 * 10**9, None), (10 * 10**9, None), (12 * 10**9, None), (21 * 10**9, None)], 10.0)
    assert [k[0] for k in kept] == [0, 10 * 10**9, 21 * 10**9]


def test_map_learn_counts_the_choices_of_recorded_tracks(tmp_path):
    """A T-junction: tracks that always turn left at the junction move that row's probability
    towards left by the Dirichlet update (a = 10, 6 observations: (10 * 0.5 + 6) / 16)."""
    from indoor_loc.bag.writer import BagWriter
    from indoor_loc.cli import main
    from indoor_loc.graph.model import build_graph
    from indoor_loc.graph.io import save_graph
    from indoor_loc.graph.tll import (TransitionParams, load_transitions, slot_nodes, transition_table)
    from msg_adapters.path import path_to_msg

    # 0 --- 1 (junction) --- 2 ; 1 --- 3 to the north.  Walking 0 -> 1 -> 3 is a left turn.
    g = build_graph([0, 1, 2, 3], np.array([[0.0, 0], [10, 0], [20, 0], [10, 10]]), [(0, 1), (1, 2), (1, 3)])
    gf = save_graph(g, tmp_path / "t.graph.yaml")
    run = tmp_path / "run.mcap"
    xy = np.vstack([np.column_stack([np.linspace(0, 10, 21), np.zeros(21)]),
                    np.column_stack([np.full(20, 10.0), np.linspace(0.5, 10, 20)])])
    t = np.arange(len(xy), dtype=np.int64) * 500_000_000
    with BagWriter(run) as bag:
        for k in range(6):
            bag.write(f"/walk{k + 1:02d}/pf/path", path_to_msg(t, xy), int(t[-1]))
    out = tmp_path / "learned.npz"
    assert main(["map", "learn", str(gf), str(run), "-o", str(out)]) == 0
    learned = load_transitions(out, g, gf)
    prior = transition_table(g, TransitionParams(rule="tll"))
    owner = slot_nodes(g)
    link01 = int(np.flatnonzero((g.link_nodes == [0, 1]).all(axis=1))[0])
    link13 = int(np.flatnonzero((g.link_nodes == [1, 3]).all(axis=1))[0])
    s_in = int(np.flatnonzero((owner == 1) & (g.adj_link == link01))[0])
    j = int(np.flatnonzero((owner == 1) & (g.adj_link == link13))[0] - g.adj_ptr[1])
    assert np.isclose(learned.probs[s_in, j], (10 * prior.probs[s_in, j] + 6) / 16)
    assert np.allclose(learned.probs.sum(axis=1), 1.0)
    other = save_graph(build_graph([0, 1], np.array([[0.0, 0], [5, 0]]), [(0, 1)]), tmp_path / "o.graph.yaml")
    with pytest.raises(MapError, match="another graph"):
        load_transitions(out, g, other)
