"""The back-end's walkable factor (indoor_loc/backend/walkable_term.py): the distance field of a floor
plan, its place in the graph's Jacobian, a track biased into a shop pulled back to the corridor, and
backend_node's ``floor_plans`` over the stage."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml

from indoor_loc.backend.graph import FIX_GRAPH_PARAMS, GraphParams, MultiUserGraph
from indoor_loc.backend.walkable_term import load_walkable_fields
from indoor_loc.errors import ConfigError

SEC = 1_000_000_000
SIZE = (40.0, 20.0)       # m; the plan is drawn in tenths of a metre and stretched onto it


def _poly(x0, y0, x1, y1):
    return {"type": "Feature", "properties": {},
            "geometry": {"type": "Polygon", "coordinates": [[[x0, y0], [x1, y0], [x1, y1], [x0, y1], [x0, y0]]]}}


def _floor(root: Path, name: str = "B1", z: float = -5.0) -> Path:
    """A 40 x 20 m floor whose only walkable space is the corridor y < 6 m (a shop fills y 6..20)."""
    d = root / name
    d.mkdir(parents=True)
    (d / "map.yaml").write_text(yaml.safe_dump({"floor": name, "z_m": z, "width_m": SIZE[0], "height_m": SIZE[1]}))
    feats = [_poly(0, 0, 400, 200), _poly(0, 60, 400, 200)]
    (d / "geojson_map.json").write_text(json.dumps({"type": "FeatureCollection", "features": feats}))
    return root


def test_distance_field_is_zero_in_the_corridor_and_grows_into_the_shop(tmp_path):
    f = load_walkable_fields(_floor(tmp_path))
    d, g = f.eval(np.array([[20.0, 3.0], [20.0, 10.0], [20.0, 16.0], [20.0, 30.0]]), np.full(4, -5.0))
    assert d[0] == 0
    assert d[1] == pytest.approx(4.0, abs=0.6) and d[2] == pytest.approx(10.0, abs=0.6)
    assert d[3] > d[2]                                        # beyond the raster it keeps growing
    assert g[1, 1] == pytest.approx(1.0, abs=0.05)            # the way out of the shop is -y
    d_other, _ = f.eval(np.array([[20.0, 10.0]]), np.array([0.0]))
    assert d_other[0] == 0                                    # no plan for that floor: no cost
    with pytest.raises(ConfigError, match="no floor plan"):
        load_walkable_fields(_empty(tmp_path))


def _empty(root: Path) -> Path:
    d = root / "empty"
    d.mkdir()
    return d


def _biased_walk(g: MultiUserGraph, bias_y: float, rng, *, whole: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """A user walking along the corridor's y = 3 m (a step of the prior's 0.65 m every 0.5 s), a fix every
    2 s biased by ``bias_y`` into the shop; returns its optimised (stamps, poses)."""
    g.set_floor("u", -5.0)
    t = 0
    x = 2.0
    for k in range(60):
        t0, t = t, t + SEC // 2
        x += 0.65
        g.add_hop("u", t0, t, 1.0, 0.0)
        if k % 4 == 3:
            fx = np.array([x + rng.normal(0, 1.0), 3.0 + bias_y + rng.normal(0, 1.0)])
            g.add_fix("u", t, fx, np.eye(2) * 4.0)
    if whole:
        g.optimize()
    st, xs = g.trajectory("u")
    return st, xs


def test_a_track_biased_into_a_shop_is_pulled_back_to_the_corridor(tmp_path):
    field = load_walkable_fields(_floor(tmp_path))
    res = {}
    for std in (0.0, 0.5):
        g = MultiUserGraph(GraphParams(**{**FIX_GRAPH_PARAMS, "walkable_std_m": std, "window_poses": 0}), None, field)
        _, xs = _biased_walk(g, 6.0, np.random.default_rng(4))
        res[std] = np.abs(xs[:, 1] - 3.0).mean()
    assert res[0.0] > 5.0                                     # the fixes' bias, whole
    assert res[0.5] < 4.0                                     # at the corridor's edge (y = 6) or inside


def test_walkable_jacobian_matches_numerical_derivatives(tmp_path):
    field = load_walkable_fields(_floor(tmp_path))
    rng = np.random.default_rng(5)
    g = MultiUserGraph(GraphParams(**{**FIX_GRAPH_PARAMS, "walkable_std_m": 0.7, "window_poses": 0}), None, field)
    _biased_walk(g, 6.0, rng)
    g.poses.x[:g.poses.n] += rng.normal(0, 0.5, (g.poses.n, 3))
    fun, jac, z0, _, n = g.problem(np.arange(g.poses.n))
    J = jac(z0).toarray()
    h = 1e-6
    for c in rng.choice(len(z0), 40, replace=False):
        d = np.zeros_like(z0)
        d[c] = h
        np.testing.assert_allclose(J[:, c], (fun(z0 + d) - fun(z0 - d)) / (2 * h), atol=2e-4)
    assert len(fun(z0)) > 3 * g.pdr.n + 2 * g.wifi.n + 3 * g.gauge.n + g.poses.n - 1   # a row per pose


def test_the_live_windows_take_the_walkable_factor_only_when_asked(tmp_path):
    """walkable_live False (the default): the window optimisations at each fix (backend/<u>/pose) leave the
    plan out, the whole-graph one (the paths) takes it; True: the windows take it too."""
    field = load_walkable_fields(_floor(tmp_path))
    last_y = {}
    for live in (False, True):
        g = MultiUserGraph(GraphParams(**{**FIX_GRAPH_PARAMS, "walkable_std_m": 0.5, "walkable_live": live,
                                          "window_poses": 30}), None, field)
        _, xs = _biased_walk(g, 6.0, np.random.default_rng(4), whole=False)
        last_y[live] = float(np.abs(xs[:, 1] - 3.0).mean())
    assert last_y[False] > 5.0 and last_y[True] < 4.0
