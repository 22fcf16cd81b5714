"""Total link lengths and transition tables on hand-made graphs with hand-computed values."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import dijkstra

from indoor_loc.errors import ConfigError
from indoor_loc.graph import build_graph, save_graph
from indoor_loc.graph.tll import (TransitionParams, cache_path, cached_transitions, count_choices,
                                  dirichlet_update, learn_transitions, total_link_lengths, transition_table)


def t_junction():
    # 0 -(4)- 1 -(6)- 2, and 1 -(3)- 3
    return build_graph([0, 1, 2, 3], np.array([[0, 0], [4, 0], [10, 0], [4, 3]], float), [(0, 1), (1, 2), (1, 3)])


def loop_with_tail():
    # rectangle 0(0,0) 1(2,0) 2(10,0) 3(10,4) 4(0,4), tail 3 - 5(14,4)
    xy = np.array([[0, 0], [2, 0], [10, 0], [10, 4], [0, 4], [14, 4]], float)
    return build_graph(range(6), xy, [(0, 1), (1, 2), (2, 3), (3, 4), (4, 0), (3, 5)])


def row(g, tr, node, link):
    """Transition probabilities arriving at ``node`` over ``link``: {leaving link: p}."""
    s = next(s for s in range(g.adj_ptr[node], g.adj_ptr[node + 1]) if g.adj_link[s] == link)
    return {int(g.adj_link[g.adj_ptr[node] + j]): float(p) for j, p in enumerate(tr.probs[s]) if p > 0}


def test_t_junction_tll_by_hand():
    g = t_junction()
    np.testing.assert_allclose(total_link_lengths(g, 40.0), [[13, 4], [6, 13], [3, 13]])
    tr = transition_table(g, TransitionParams(p_min=0.0, p_max=1.0))
    assert row(g, tr, 1, 0) == pytest.approx({1: 6 / 9, 2: 3 / 9})
    assert row(g, tr, 1, 1) == pytest.approx({0: 4 / 7, 2: 3 / 7})
    assert row(g, tr, 1, 2) == pytest.approx({0: 0.4, 1: 0.6})


def test_l_max_cut_by_hand():
    g = t_junction()
    # from node 0 only 5 m: link 0 (4 m) + 1 m into each branch; from node 3: 3 + 2 + 2
    np.testing.assert_allclose(total_link_lengths(g, 5.0), [[6, 4], [5, 5], [3, 7]])


def test_loop_partial_links_by_hand():
    g = loop_with_tail()
    tll = total_link_lengths(g, 40.0)
    # from node 1: shortest paths meet on link 3-4 at 2 m from node 3 (d3 = 12 via 2, d4 = 6 via 0)
    assert tll[0, 1] == pytest.approx(2 + 4 + 8)          # link 0-1 seen from node 1
    assert tll[1, 0] == pytest.approx(8 + 4 + 2 + 4)      # link 1-2 seen from node 1 (+ the tail)
    tll10 = total_link_lengths(g, 10.0)
    assert tll10[0, 1] == pytest.approx(2 + 4 + 4)        # 3-4 cut at l_MAX = 10 m from node 1
    assert tll10[1, 0] == pytest.approx(8 + 2)            # 2-3 cut
    # every TLL row of a node sums to all link length within l_MAX; 40 m covers the whole graph
    assert tll[0, 1] + tll[1, 0] == pytest.approx(g.link_len.sum())


def test_dead_end_u_turn_and_rows_sum_to_one():
    g = loop_with_tail()
    for rule in ("tll", "uniform", "angle"):
        tr = transition_table(g, TransitionParams(rule=rule))
        np.testing.assert_allclose(tr.probs.sum(axis=1), 1.0)
        assert row(g, tr, 5, 5) == {5: 1.0}                    # dead end: back along the same link
        assert np.all(tr.cdf[:, -1] == 1.0)
        # never back along the arriving link where there is a choice
        assert 1 not in row(g, tr, 1, 1)


def test_uniform_and_angle_rules():
    g = t_junction()
    uni = transition_table(g, TransitionParams(rule="uniform"))
    assert row(g, uni, 1, 0) == pytest.approx({1: 0.5, 2: 0.5})
    ang = transition_table(g, TransitionParams(rule="angle", p_min=0.0, p_max=1.0))
    # arriving eastwards at node 1: straight on (1 + cos 0 = 2) vs left (1 + cos 90° = 1)
    assert row(g, ang, 1, 0) == pytest.approx({1: 2 / 3, 2: 1 / 3})


def test_clamping_to_p_min():
    # a 0.5 m stub beside a long corridor gets a tiny TLL share; p_min lifts it
    g = build_graph([0, 1, 2, 3], np.array([[0, 0], [30, 0], [60, 0], [30, 0.5]], float), [(0, 1), (1, 2), (1, 3)])
    raw = row(g, transition_table(g, TransitionParams(p_min=0.0, p_max=1.0)), 1, 0)
    assert raw[2] < 0.05
    clamped = row(g, transition_table(g, TransitionParams(p_min=0.05)), 1, 0)
    assert clamped[2] == pytest.approx(0.05) and sum(clamped.values()) == pytest.approx(1.0)


def _oracle_tll(g, l_max, pieces=200):
    """Slow, obvious version: subdivide every link into short pieces, run Dijkstra on the fine
    graph and credit each piece (inside l_MAX) to the first original link of its shortest path."""
    m = g.n_nodes
    rows, cols, w, piece_link = [], [], [], []
    nid = m
    for li, (a, b) in enumerate(g.link_nodes):
        chain = [a] + list(range(nid, nid + pieces - 1)) + [b]
        nid += pieces - 1
        for u, v in zip(chain[:-1], chain[1:]):
            rows.append(u)
            cols.append(v)
            w.append(g.link_len[li] / pieces)
            piece_link.append(li)
    n = nid
    mat = csr_matrix((w, (rows, cols)), shape=(n, n))
    rows, cols, w = np.array(rows), np.array(cols), np.array(w)
    piece_link = np.array(piece_link)
    out = np.zeros((g.n_links, 2))
    dist, pred = dijkstra(mat, directed=False, indices=np.arange(m), return_predecessors=True)
    for k in range(m):
        # first original link on the path to each fine node
        first = np.full(n, -1)
        order = np.argsort(dist[k])
        edge_of = {}
        for e, (u, v) in enumerate(zip(rows, cols)):
            edge_of[(u, v)] = e
            edge_of[(v, u)] = e
        for x in order:
            p = pred[k, x]
            if p < 0:
                continue
            first[x] = piece_link[edge_of[(p, x)]] if p == k else first[p]
        for e, (u, v) in enumerate(zip(rows, cols)):
            far = u if dist[k, u] > dist[k, v] else v
            if dist[k, far] <= l_max + 1e-9 and first[far] >= 0:
                bl = first[far]
                out[bl, int(g.link_nodes[bl, 1] == k)] += w[e]
    return out


@pytest.mark.parametrize("seed", [1, 2])
def test_tll_matches_subdivided_dijkstra_oracle(seed):
    rng = np.random.default_rng(seed)
    xy = rng.uniform(0, 30, (9, 2))
    # a spanning path plus random chords: connected, loops, several junctions
    links = {(i, i + 1) for i in range(8)} | {tuple(sorted(rng.choice(9, 2, replace=False))) for _ in range(5)}
    g = build_graph(range(9), xy, sorted(links))
    for l_max in (15.0, 40.0):
        got = total_link_lengths(g, l_max, chunk=4)
        want = _oracle_tll(g, l_max)
        # the oracle's pieces are at most 30*1.42/200 ~ 0.2 m long
        np.testing.assert_allclose(got, want, atol=0.5)


def test_dirichlet_update_and_learning():
    np.testing.assert_allclose(dirichlet_update(np.array([0.5, 0.5]), np.array([3, 1]), a=4.0), [5 / 8, 3 / 8])
    with pytest.raises(ConfigError, match="a > 0"):
        dirichlet_update(np.array([1.0]), np.array([1.0]), a=0.0)
    g = t_junction()
    prior = transition_table(g, TransitionParams(p_min=0.0, p_max=1.0))
    counts = count_choices(g, [np.array([0, 0, 2]), np.array([0, 2]), np.array([0, 1])])
    post = learn_transitions(g, prior, [np.array([0, 0, 2]), np.array([0, 2]), np.array([0, 1])], a=3.0)
    # arriving at 1 over link 0: prior (2/3, 1/3), observed 1 x link 1, 2 x link 2
    assert counts.sum() == 3
    assert row(g, post, 1, 0) == pytest.approx({1: (3 * 2 / 3 + 1) / 6, 2: (3 * 1 / 3 + 2) / 6})
    np.testing.assert_allclose(post.probs.sum(axis=1), 1.0)


def test_cache_beside_the_map(tmp_path):
    g = loop_with_tail()
    f = save_graph(g, tmp_path / "g.graph.yaml")
    params = TransitionParams()
    tr, hit = cached_transitions(g, f, params)
    assert not hit and cache_path(f).exists()
    tr2, hit2 = cached_transitions(g, f, params)
    assert hit2 and np.array_equal(tr.probs, tr2.probs)
    _, hit3 = cached_transitions(g, f, TransitionParams(l_max_m=20.0))   # other parameters: recomputed
    assert not hit3
    f.write_text(f.read_text() + "# edited\n")                          # edited map: recomputed
    _, hit4 = cached_transitions(g, f, TransitionParams(l_max_m=20.0))
    assert not hit4


def test_params_validation():
    with pytest.raises(ConfigError, match="rule"):
        TransitionParams(rule="bogus").validate()
    with pytest.raises(ConfigError, match="p_min"):
        TransitionParams(p_min=0.6).validate()
