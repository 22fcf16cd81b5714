"""Graph particle filter core: exact propagation, resampling, constrained mean, updates, smoother."""
from __future__ import annotations

import numpy as np
import pytest

from indoor_loc.errors import ConfigError
from indoor_loc.graph import build_graph
from indoor_loc.graph.tll import TransitionParams, transition_table
from indoor_loc.pf.filter import (GraphParticleFilter, Particles, PfParams, constrained_mean, effective_sample_size,
                                  particle_xy, systematic_resample)
from indoor_loc.pf.tracker import GraphTracker


def corridor_l():
    # an L: 0 (0,0) -(10)- 1 (10,0) -(5)- 2 (10,5) -(5)- 3 (10,10)
    return build_graph([0, 1, 2, 3], np.array([[0, 0], [10, 0], [10, 5], [10, 10]], float), [(0, 1), (1, 2), (2, 3)])


def _pf(g, n=64, **kw):
    pf = GraphParticleFilter(g, transition_table(g, TransitionParams()), PfParams(n_particles=n, **kw))
    return pf


def _place(pf, link, pos, direction):
    n = len(link)
    pf.p = Particles(link=np.asarray(link, np.int32), pos=np.asarray(pos, float), direction=np.asarray(direction, np.int8),
                     speed=np.ones(n), mode=np.ones(n, np.int8), scale=np.ones(n), yaw_offset=np.zeros(n),
                     log_w=np.full(n, -np.log(n)))


@pytest.mark.parametrize("start, dist, want", [
    ((0, 2.0, 1), 3.0, (5.0, 0.0)),              # along the first link
    ((0, 2.0, 1), 12.0, (10.0, 4.0)),            # across node 1 onto link 1
    ((0, 2.0, 1), 16.5, (10.0, 8.5)),            # across nodes 1 and 2
    ((2, 1.0, -1), 7.0, (9.0, 0.0)),             # backwards from link 2 across 2 and 1
    ((0, 9.0, 1), 22.0, (9.0, 0.0)),             # to the dead end (node 3), U-turn, back past node 1
])
def test_zero_noise_propagation_is_exact_across_nodes(start, dist, want, rng):
    g = corridor_l()
    pf = _pf(g)
    link, pos, d = start
    _place(pf, [link] * 8, [pos] * 8, [d] * 8)
    pf._move(np.full(8, dist), rng, None)
    xy = particle_xy(g, pf.p)
    np.testing.assert_allclose(xy, np.tile(want, (8, 1)), atol=1e-9)


def test_distance_along_graph_is_preserved_on_a_branching_graph(rng):
    # a star: whatever link a particle takes, its along-graph distance from the start is exact
    g = build_graph(range(5), np.array([[0, 0], [10, 0], [20, 0], [10, 10], [10, -10]], float),
                    [(0, 1), (1, 2), (1, 3), (1, 4)])
    pf = _pf(g, n=500)
    _place(pf, np.zeros(500), np.full(500, 4.0), np.ones(500))
    pf._move(np.full(500, 9.0), rng, None)
    xy = particle_xy(g, pf.p)
    from_node1 = np.hypot(xy[:, 0] - 10, xy[:, 1])
    np.testing.assert_allclose(from_node1, 3.0, atol=1e-9)
    assert set(pf.p.link.tolist()) == {1, 2, 3}       # every branch taken, never back along link 0


def test_pdr_heading_chooses_the_branch(rng):
    g = build_graph(range(4), np.array([[0, 0], [10, 0], [20, 0], [10, 10]], float), [(0, 1), (1, 2), (1, 3)])
    pf = _pf(g, n=400, yaw_offset_sigma_rad=0.0, u_turn_prob=0.0)
    _place(pf, np.zeros(400), np.full(400, 9.0), np.ones(400))
    pf.predict_pdr(3.0, np.pi / 2, rng)               # walking north: the branch to node 3
    w = pf.p.weights
    assert w[pf.p.link == 2].sum() > 0.95


def test_systematic_resampling_indices_and_normalised_weights(rng):
    w = rng.random(1000)
    w /= w.sum()
    idx = systematic_resample(w, rng)
    assert idx.min() >= 0 and idx.max() < 1000 and len(idx) == 1000
    counts = np.bincount(idx, minlength=1000)
    assert np.all(np.abs(counts - 1000 * w) < 1.0 + 1e-9)     # systematic: within one of the expectation
    g = corridor_l()
    pf = _pf(g, n=300)
    pf.init_gaussian(np.array([5.0, 0.0]), np.eye(2), rng)
    pf.update_position(np.array([10.0, 3.0]), np.eye(2), rng)
    assert effective_sample_size(pf.p.log_w) < 150
    assert pf.maybe_resample(rng)
    assert np.exp(pf.p.log_w).sum() == pytest.approx(1.0)
    assert effective_sample_size(pf.p.log_w) == pytest.approx(300)


def test_constrained_mean_of_an_l_shaped_cloud_lands_on_a_link():
    g = corridor_l()
    # half the weight at (2, 0), half at (10, 8): the plain mean (6, 4) is off the graph
    xy = np.array([[2.0, 0.0], [10.0, 8.0]])
    w = np.array([0.5, 0.5])
    est, link, t = constrained_mean(g, xy, w)
    assert np.allclose(w @ xy, [6.0, 4.0])
    assert g.project(est[None, :])[2][0] < 1e-9
    # nearest link point to (6, 4): (10, 4) on link 1 (4 m) vs (6, 0) on link 0 (4 m): a tie; (10, 4) or (6, 0)
    assert link in (0, 1)
    assert np.hypot(*(est - [6.0, 4.0])) == pytest.approx(4.0)


def test_wifi_update_pulls_towards_fix_and_reinitialises_when_lost(rng):
    g = corridor_l()
    pf = _pf(g, n=500, yaw_offset_sigma_rad=0.0, init_sigma_extra_m=0.0)
    pf.init_gaussian(np.array([2.0, 0.0]), np.eye(2) * 0.25, rng)
    assert not pf.update_position(np.array([3.0, 0.0]), np.eye(2), rng)
    assert abs(pf.estimate()[0][0] - 2.5) < 1.5
    assert pf.update_position(np.array([10.0, 9.0]), np.eye(2) * 0.25, rng)      # far away: diverged
    assert pf.n_reinit == 1
    assert np.hypot(*(pf.estimate()[0] - [10.0, 9.0])) < 2.0


def test_speed_model_moves_within_speed_limits(rng):
    g = corridor_l()
    pf = _pf(g, n=2000, p_stop=0.0)
    pf.init_gaussian(np.array([1.0, 0.0]), np.eye(2) * 0.01, rng)
    before = particle_xy(g, pf.p)
    pf.predict_speed(2.0, rng)
    moved = np.hypot(*(particle_xy(g, pf.p) - before).T)
    assert moved.max() <= 2.0 * 1.8 * 1.0 + 3 * 0.5 * 2.0 ** 1.5     # v_max * dt plus 3 sigma of noise
    assert np.median(moved) > 0.3


def test_tracker_filters_a_walk_and_smoothed_poses_are_on_the_graph():
    g = corridor_l()
    tr = GraphTracker(g, transition_table(g, TransitionParams()), PfParams(n_particles=300, yaw_offset_sigma_rad=0.0),
                      rng=np.random.default_rng(3))
    truth = lambda s: np.array([s, 0.0]) if s <= 10 else np.array([10.0, s - 10])   # noqa: E731
    noise = np.random.default_rng(4)
    s, t = 0.0, 0
    tr.fix(t, truth(0.0), np.eye(2))
    tr.odom(t, 0.0, 0.0)
    ox, oy = 0.0, 0.0
    for k in range(1, 50):
        t += 320_000_000
        step = 0.36
        heading = 0.0 if s < 10 else np.pi / 2
        s += step
        ox, oy = ox + step * np.cos(heading), oy + step * np.sin(heading)
        tr.odom(t, ox, oy)
        if k % 12 == 0:
            tr.fix(t, truth(s) + noise.normal(0, 1.0, 2), np.eye(2))
    err = np.hypot(*(tr.estimates[-1].xy - truth(s)))
    assert err < 1.5
    sm = tr.smooth(20)
    assert len(sm) == len(tr.history)
    pts = np.array([e.xy for e in sm])
    assert g.project(pts)[2].max() < 1e-9


def test_params_validation():
    with pytest.raises(ConfigError, match="n_particles"):
        PfParams(n_particles=0).validate()
    with pytest.raises(ConfigError, match="v_min/v_max"):
        PfParams(v_min=2.0, v_max=1.0).validate()
