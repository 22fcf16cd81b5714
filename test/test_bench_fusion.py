"""bench fusion's helpers: a --set variant reaches every key of its node and is cached apart; an
estimate is scored only where it spans (coverage), interpolated between its stamps."""
from __future__ import annotations

import numpy as np
import yaml

from indoor_loc.bench.fusion import _errors, effective_params, summarise, WalkScore, WKNN


def test_a_set_reaches_every_key_of_its_node_and_keys_the_cache(tmp_path):
    imp = tmp_path / "import"
    imp.mkdir()
    (imp / "params.yaml").write_text(yaml.safe_dump({
        "/**/tll_pf": {"ros__parameters": {"smooth_redrawn": "mixture"}},
        "/b1_x/tll_pf": {"ros__parameters": {"graph_file": "g.yaml"}},
        "/**/imu_node": {"ros__parameters": {"heading_source": "orientation"}}}))
    base, k0 = effective_params(imp, [], tmp_path / "w")
    again, k1 = effective_params(imp, [], tmp_path / "w")
    var, k2 = effective_params(imp, ["tll_pf.n_particles=500", "backend_node.pdr_info=[1, 1, 100]"], tmp_path / "w")
    assert k0 == k1 and base == again and k2 != k0
    doc = yaml.safe_load(var.read_text())
    assert doc["/b1_x/tll_pf"]["ros__parameters"] == {"graph_file": "g.yaml", "n_particles": 500}
    assert doc["/**/tll_pf"]["ros__parameters"]["n_particles"] == 500
    assert doc["/**/backend_node"]["ros__parameters"] == {"pdr_info": [1, 1, 100]}
    assert "n_particles" not in doc["/**/imu_node"]["ros__parameters"]


def test_an_estimate_is_scored_where_it_spans_only():
    s = 1_000_000_000
    at = np.array([0, 1, 2, 3]) * s
    truth = np.zeros((4, 2))
    e = _errors(np.array([1, 3]) * s, np.array([[0.0, 1.0], [0.0, 3.0]]), at, truth)
    assert np.isnan(e[0]) and np.allclose(e[1:], [1.0, 2.0, 3.0])
    sc = WalkScore("B1", "w", scans={"wifi/fix": e, WKNN: np.array([1.0, 1.0, np.nan, 1.0])})
    d = summarise([sc], "scans")
    assert d["wifi/fix"]["coverage"] == 0.75 and d["wifi/fix"]["mean"] == 2.0 and d[WKNN]["covered"] == 3
