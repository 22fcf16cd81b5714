"""Building-graph file format v1: round trip, arrays, CSR adjacency, projection, every MapError."""
from __future__ import annotations

import copy

import numpy as np
import pytest

from indoor_loc.errors import MapError
from indoor_loc.graph import build_graph, graph_from_dict, graph_to_dict, load_graph, save_graph


def t_junction_doc() -> dict:
    # 10 -- 11 -- 12 along x, with 13 above 11
    return {"format": "indoor_loc.graph", "version": 1, "frame_id": "map",
            "nodes": [[10, 0.0, 0.0], [11, 4.0, 0.0], [12, 10.0, 0.0], [13, 4.0, 3.0]],
            "links": [[10, 11], [11, 12], [11, 13]],
            "rooms": {"office": [12]}}


def two_floor_doc() -> dict:
    return {"format": "indoor_loc.graph", "version": 1,
            "floors": [{"id": 0, "name": "G", "height_m": 0.0}, {"id": 1, "name": "1", "height_m": 3.5}],
            "nodes": [[0, 0.0, 0.0, 0], [1, 5.0, 0.0, 0], [2, 5.0, 0.0, 1], [3, 5.0, 8.0, 1]],
            "links": [[0, 1], [2, 3]],
            "vertical_links": [{"nodes": [1, 2], "length_m": 6.0, "tll_length_m": 30.0}]}


def test_arrays_and_csr_adjacency():
    g = graph_from_dict(t_junction_doc())
    assert g.node_xyz.shape == (4, 3) and g.link_nodes.shape == (3, 2)
    np.testing.assert_allclose(g.link_len, [4.0, 6.0, 3.0])
    np.testing.assert_array_equal(g.degree, [1, 3, 1, 1])
    k = g.index_of(11)
    sl = slice(g.adj_ptr[k], g.adj_ptr[k + 1])
    assert sorted(g.adj_link[sl].tolist()) == [0, 1, 2]
    assert sorted(g.node_ids[g.adj_node[sl]].tolist()) == [10, 12, 13]
    # the adjacency's end index says which end of the link touches the node
    for lk, end in zip(g.adj_link[sl], g.adj_end[sl]):
        assert g.link_nodes[lk, end] == k
    assert g.rooms == {"office": (g.index_of(12),)}
    assert not g.node_xyz.flags.writeable


def test_round_trip_file(tmp_path):
    for doc in (t_junction_doc(), two_floor_doc()):
        g = graph_from_dict(doc)
        p = save_graph(g, tmp_path / "g.graph.yaml", source={"tool": "test"})
        h = load_graph(p)
        np.testing.assert_array_equal(g.node_ids, h.node_ids)
        np.testing.assert_array_equal(g.node_xyz, h.node_xyz)
        np.testing.assert_array_equal(g.link_nodes, h.link_nodes)
        np.testing.assert_array_equal(g.link_len, h.link_len)
        np.testing.assert_array_equal(g.link_tll_len, h.link_tll_len)
        np.testing.assert_array_equal(g.link_vertical, h.link_vertical)
        assert graph_to_dict(h)["nodes"] == graph_to_dict(g)["nodes"]


def test_vertical_link_lengths_and_heights():
    g = graph_from_dict(two_floor_doc())
    np.testing.assert_allclose(g.node_xyz[:, 2], [0, 0, 3.5, 3.5])
    np.testing.assert_array_equal(g.link_vertical, [False, False, True])
    np.testing.assert_allclose(g.link_len, [5.0, 8.0, 6.0])
    np.testing.assert_allclose(g.link_tll_len, [5.0, 8.0, 30.0])


def test_project_clamps_to_ends_and_picks_nearest():
    g = graph_from_dict(t_junction_doc())
    link, t, d = g.project(np.array([[2.0, 0.5], [4.2, 2.0], [11.0, 1.0], [-1.0, 0.0]]))
    assert link.tolist() == [0, 2, 1, 0]
    np.testing.assert_allclose(t, [0.5, 2 / 3, 1.0, 0.0])
    np.testing.assert_allclose(d, [0.5, 0.2, np.sqrt(2.0), 1.0])
    np.testing.assert_allclose(g.point_at(link, t), [[2, 0], [4, 2], [10, 0], [0, 0]])


def _broken(edit) -> dict:
    doc = copy.deepcopy(t_junction_doc())
    edit(doc)
    return doc


@pytest.mark.parametrize("edit, match", [
    (lambda d: d.update(format="nope"), "format must be"),
    (lambda d: d.update(version=2), "version 2 is not supported"),
    (lambda d: d.update(extra=1), r"unknown key\(s\) \['extra'\]"),
    (lambda d: d.update(nodes=[]), "'nodes' must be a non-empty list"),
    (lambda d: d["nodes"].append([14, 1.0]), r"nodes\[4\] must be \[id, x, y\]"),
    (lambda d: d["nodes"].append([11, 1.0, 1.0]), "duplicate node id 11"),
    (lambda d: d["nodes"].append([-3, 1.0, 1.0]), "node id -3 is negative"),
    (lambda d: d["nodes"].__setitem__(0, [10, float("nan"), 0.0]), "node 10 has a non-finite coordinate"),
    (lambda d: d["nodes"].__setitem__(0, [10, "x", 0.0]), r"nodes\[0\]"),
    (lambda d: d["links"].append([11, 99]), r"link #3 \(11, 99\) names unknown node 99 \(dangling link\)"),
    (lambda d: d["links"].append([12, 12]), r"link #3 \(12, 12\) is a self-loop"),
    (lambda d: d["links"].append([12, 11]), r"link #3 \(12, 11\) duplicates link #1"),
    (lambda d: d["links"].append([1, 2, 3]), r"links\[3\] must be \[node_id, node_id\]"),
    (lambda d: (d["nodes"].append([14, 4.0, 3.0]), d["links"].append([13, 14])), r"link #3 \(13, 14\) has zero length"),
    (lambda d: d["nodes"].append([14, 50.0, 50.0]), "node 14 is on no link"),
    (lambda d: (d["nodes"].extend([[14, 50.0, 50.0], [15, 51.0, 50.0]]), d["links"].append([14, 15])),
     "2 disconnected parts; the smallest \\(2 nodes\\) contains node 14"),
    (lambda d: d["nodes"].append([14, 1.0, 1.0, 7]), "node 14 is on floor 7, which is not in the floor table"),
    (lambda d: d.update(rooms={"lab": [99]}), "room 'lab' names unknown node 99"),
    (lambda d: d.update(vertical_links=[{"nodes": [10, 13], "length_m": 3.0}]),
     r"vertical link #3 \(10, 13\) joins two nodes of one floor"),
    (lambda d: d.update(vertical_links=[{"nodes": [10]}]), r"vertical_links\[0\] must be"),
])
def test_every_validation_error(edit, match):
    with pytest.raises(MapError, match=match):
        graph_from_dict(_broken(edit))


def test_cross_floor_link_must_be_vertical_and_positive():
    doc = two_floor_doc()
    doc["links"].append([0, 3])
    with pytest.raises(MapError, match=r"link #2 \(0, 3\) joins two floors but is not declared vertical"):
        graph_from_dict(doc)
    doc = two_floor_doc()
    doc["vertical_links"][0]["length_m"] = 0.0
    with pytest.raises(MapError, match=r"vertical link #2 \(1, 2\) needs length_m > 0"):
        graph_from_dict(doc)


def test_load_names_the_file(tmp_path):
    p = tmp_path / "bad.graph.yaml"
    p.write_text("format: indoor_loc.graph\nversion: 1\nnodes: [[0, 0, 0], [1, 1, 0]]\nlinks: [[0, 5]]\n")
    with pytest.raises(MapError, match="bad.graph.yaml: link #0 \\(0, 5\\) names unknown node 5"):
        load_graph(p)
    with pytest.raises(MapError, match="cannot read graph file"):
        load_graph(tmp_path / "missing.yaml")
    p.write_text("format: [unclosed\n")
    with pytest.raises(MapError, match="cannot read graph file"):
        load_graph(p)


def test_build_graph_allows_disconnected_on_request():
    g = build_graph([0, 1, 2, 3], np.array([[0, 0], [1, 0], [5, 5], [6, 5]], float), [(0, 1), (2, 3)],
                    allow_disconnected=True)
    assert g.n_links == 2
