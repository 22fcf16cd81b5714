"""Floor plans as the walkable area (indoor_loc.wifi.walkable) and the wifi_fix stage's ``floor_plans``."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml

from indoor_loc.errors import ConfigError
from indoor_loc.params import params_from_dict
from indoor_loc.pipeline.wifi_fix_stage import WifiFixParams, WifiFixStage
from indoor_loc.wifi.powed_knn import PowedKnn
from indoor_loc.wifi.radiomap import add_fingerprints, empty_radiomap
from indoor_loc.wifi.types import WifiScan
from indoor_loc.wifi.walkable import load_floor_plans

SIZE = (30.0, 20.0)


def _poly(x0, y0, x1, y1):
    return {"type": "Feature", "properties": {},
            "geometry": {"type": "Polygon", "coordinates": [[[x0, y0], [x1, y0], [x1, y1], [x0, y1], [x0, y0]]]}}


def _write_floor(root: Path, name: str, z: float, *, shop=(10.0, 5.0, 20.0, 15.0), geojson=True) -> Path:
    """A floor in the importer's layout: the outline (the plan's bounding box, 300 x 200 plan units
    stretched onto 30 x 20 m) with one shop in it."""
    d = root / name
    d.mkdir(parents=True)
    (d / "map.yaml").write_text(yaml.safe_dump({"floor": name, "z_m": z, "width_m": SIZE[0], "height_m": SIZE[1],
                                                "frame_id": "map"}))
    if geojson:
        feats = [_poly(0, 0, 300, 200), _poly(*(10 * v for v in shop))]
        (d / "geojson_map.json").write_text(json.dumps({"type": "FeatureCollection", "features": feats}))
    return d


def test_floor_plans_give_each_floor_its_free_space(tmp_path):
    _write_floor(tmp_path, "F1", 0.0)
    _write_floor(tmp_path, "F2", 5.0, shop=(2.0, 2.0, 8.0, 8.0))
    _write_floor(tmp_path, "F3", 10.0, geojson=False)            # an image-only floor: no plan, skipped
    walkable, used = load_floor_plans(tmp_path)
    assert sorted(used) == [0.0, 5.0]
    pts = np.array([[5.0, 10.0], [15.0, 10.0], [5.0, 5.0], [28.0, 18.0], [-5.0, 10.0], [15.0, 30.0]])
    np.testing.assert_array_equal(walkable(pts, 0.0), [True, False, True, True, False, False])   # shop in the middle
    np.testing.assert_array_equal(walkable(pts, 5.0), [True, True, False, True, False, False])   # shop at (2..8, 2..8)
    assert not walkable(pts, 10.0).any()                          # no plan for that floor: nothing added there
    one, used1 = load_floor_plans(tmp_path / "F2")                # a single floor's directory
    assert list(used1) == [5.0]
    np.testing.assert_array_equal(one(pts, 5.0), walkable(pts, 5.0))


def test_bad_floor_plans_are_a_config_error_naming_the_path(tmp_path):
    with pytest.raises(ConfigError, match="nowhere"):
        load_floor_plans(tmp_path / "nowhere")
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(ConfigError, match="no floor plan"):
        load_floor_plans(empty)
    d = _write_floor(tmp_path / "a", "F1", 0.0)
    (d / "geojson_map.json").write_text("{not json")
    with pytest.raises(ConfigError, match="geojson_map.json"):
        load_floor_plans(tmp_path / "a")
    d = _write_floor(tmp_path / "b", "F1", 0.0)
    (d / "map.yaml").write_text(yaml.safe_dump({"floor": "F1", "width_m": 30.0, "height_m": 20.0}))
    with pytest.raises(ConfigError, match="map.yaml"):
        load_floor_plans(tmp_path / "b")
    _write_floor(tmp_path / "c", "F1", 0.0)
    _write_floor(tmp_path / "c", "F1b", 0.0)
    with pytest.raises(ConfigError, match="second plan"):
        load_floor_plans(tmp_path / "c")
    with pytest.raises(ConfigError, match="nowhere"):             # the node fails at start-up
        WifiFixStage(params_from_dict(WifiFixParams, {"floor_plans": str(tmp_path / "nowhere")}))


def test_the_stage_bounds_the_extrapolating_grid_by_the_plan(tmp_path):
    """With floor_plans and powed.field_weight > 0 the grid reaches field_reach_m from the survey inside
    the plan's free space only; without plans it keeps the default reach."""
    rng = np.random.default_rng(3)
    ap = rng.uniform([0, 0], SIZE, (12, 2))
    bssids = [f"02:00:00:00:03:{i:02x}" for i in range(len(ap))]
    xs = np.arange(1.0, 29.0, 1.0)
    pts = np.column_stack([xs, np.full(len(xs), 2.0)])           # one survey walk along y = 2 m
    d = np.sqrt(((pts[:, None] - ap[None]) ** 2).sum(-1) + 1.0)
    rss = -35 - 30 * np.log10(d) + rng.normal(0, 2, d.shape)
    scans = [WifiScan(i, tuple(bssids), r, np.full(len(ap), 2437.0)) for i, r in enumerate(rss)]
    rm = add_fingerprints(empty_radiomap(), pts, scans, "walk0", z_m=0.0, floors={"F1": 0.0})
    _write_floor(tmp_path / "floors", "F1", 0.0)
    base = {"method": "powed", "powed": {"field_weight": 0.05, "cov_calibration": False}}
    plain = WifiFixStage(params_from_dict(WifiFixParams, base), radio_map=rm)
    st = WifiFixStage(params_from_dict(WifiFixParams, {**base, "floor_plans": str(tmp_path / "floors")}),
                      radio_map=rm)
    assert isinstance(st.positioner, PowedKnn) and st.positioner.walkable is st.walkable
    assert st.extra_diagnostics()["floor_plans"] == "1"
    far = lambda g: np.abs(g[:, 1] - 2.0) > 2.5                   # noqa: E731  beyond the default 2 m reach
    g_plain, g_plan = plain.positioner._grid_pos, st.positioner._grid_pos
    assert not far(g_plain).any()
    assert far(g_plan).sum() > 50                                 # the field extends where people can be ...
    assert st.walkable is not None
    assert st.walkable(g_plan[far(g_plan)], 0.0).all()            # ... and only there
    assert (np.abs(g_plan[far(g_plan), 1] - 2.0) <= 10.0 + 1e-9).all()
    assert not ((g_plan[:, 0] > 11) & (g_plan[:, 0] < 19) & (g_plan[:, 1] > 6) & (g_plan[:, 1] < 14)).any()
