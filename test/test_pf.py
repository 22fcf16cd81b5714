"""Graph particle filter core: exact propagation, resampling, constrained mean, updates, smoother."""
from __future__ import annotations

import numpy as np
import pytest

from indoor_loc.errors import ConfigError
from indoor_loc.graph import build_graph
from indoor_loc.graph.tll import TransitionParams, transition_table
from indoor_loc.pf.filter import (GraphParticleFilter, LinkIndex, Particles, PfParams, constrained_mean,
                                  effective_sample_size, kld_bound, normalise_log, particle_xy, systematic_resample)
from indoor_loc.pf.tracker import GraphTracker, MonitorParams


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
    pf = _pf(g, n=400, yaw_offset_sigma_rad=0.0, u_turn_prob=0.0, heading_sigma_rad=0.35)   # an accurate heading
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


# ----------------------------------------------------------------------------------------------
# divergence monitoring, adaptive particle count, projection
# ----------------------------------------------------------------------------------------------
def ladder():
    # two parallel 40 m corridors (y = 0 and y = 10) joined at both ends
    xy = np.array([[0, 0], [20, 0], [40, 0], [0, 10], [20, 10], [40, 10]], float)
    return build_graph(range(6), xy, [(0, 1), (1, 2), (3, 4), (4, 5), (0, 3), (2, 5)])


def _diverged_walk(monitor_enabled):
    g = ladder()
    pp = PfParams(n_particles=400, yaw_offset_sigma_rad=0.0, inject_fraction=0.0, reinit_mahalanobis2=1e12,
                  heading_sigma_rad=0.35)                         # the synthetic PDR heading is exact
    tr = GraphTracker(g, transition_table(g, TransitionParams()), pp, rng=np.random.default_rng(5),
                      monitor=MonitorParams(enabled=monitor_enabled))
    noise = np.random.default_rng(6)
    t = 0
    tr.odom(t, 0.0, 0.0, 0.0)
    tr.reset_at(t, np.array([3.0, 10.0]), np.eye(2) * 0.25)      # a wrong initial pose: the other corridor
    x = 3.0
    for k in range(1, 61):                                        # 30 s eastwards at 1 m/s
        t += 500_000_000
        x += 0.5
        tr.odom(t, x - 3.0, 0.0, 0.0)
        if k % 2 == 0:
            tr.fix(t, np.array([x, 0.0]) + noise.normal(0, 0.7, 2), np.eye(2) * 0.5)
    return tr, np.hypot(*(tr.estimates[-1].xy - [x, 0.0]))


def test_kf_monitor_reinitialises_a_diverged_filter_around_the_kf():
    tr, err = _diverged_walk(True)
    assert tr.monitor.reinits >= 1
    assert err < 2.0
    tr_off, err_off = _diverged_walk(False)                        # the same walk unmonitored stays lost
    assert tr_off.monitor.reinits == 0
    assert err_off > 8.0


def test_kf_monitor_leaves_an_agreeing_filter_alone():
    g = corridor_l()
    tr = GraphTracker(g, transition_table(g, TransitionParams()), PfParams(n_particles=300, yaw_offset_sigma_rad=0.0),
                      rng=np.random.default_rng(3))
    noise = np.random.default_rng(4)
    t, s = 0, 0.0
    tr.fix(t, np.array([0.0, 0.0]), np.eye(2))
    tr.odom(t, 0.0, 0.0, 0.0)
    for k in range(1, 28):
        t += 320_000_000
        s += 0.36
        tr.odom(t, s, 0.0, 0.0)
        if k % 3 == 0:
            tr.fix(t, np.array([s, 0.0]) + noise.normal(0, 0.7, 2), np.eye(2))
    assert tr.kf is not None and tr.kf.state.n_updates >= 3
    assert np.isfinite(tr.monitor.last_deviance)
    assert tr.monitor.reinits == 0


def test_particle_count_rule_follows_the_covariance_volume():
    g = ladder()
    pf = _pf(g, n=1000, adaptive=True, n_min=50, n_max=100_000, init_sigma_extra_m=0.0, count_ref_sigma_m=5.0)
    assert pf.count_for(np.eye(2) * 25.0) == 1000                  # the reference prior
    assert pf.count_for(np.eye(2) * 100.0) == 4000                 # twice the std per axis: 4x the area
    assert pf.count_for(np.diag([25.0, 100.0])) == 2000
    assert pf.count_for(np.eye(2) * 1e-4) == 50                    # clamped to n_min
    assert _pf(g, n=1000).count_for(np.eye(2) * 100.0) == 1000     # not adaptive: fixed count


def test_kld_converged_cloud_uses_fewer_particles_than_a_spread_one(rng):
    g = ladder()
    pf = _pf(g, n=3000, adaptive=True, n_min=50, n_max=5000, kld_bin_m=1.0)
    pf.init_uniform(rng)
    pf.p.log_w[:] = normalise_log(np.log(np.linspace(0.5, 1.0, len(pf.p))))   # unequal: N_eff below threshold?
    pf.p.log_w[0] += 5.0
    pf.p.log_w = normalise_log(pf.p.log_w)
    assert pf.maybe_resample(rng)
    n_spread = len(pf.p)
    # a converged cloud: every particle within 2 m on one link
    pf.p.link[:] = 0
    pf.p.pos[:] = 5.0 + 2.0 * rng.random(len(pf.p))
    pf.p.log_w[:] = -50.0
    pf.p.log_w[:10] = 0.0
    pf.p.log_w = normalise_log(pf.p.log_w)
    assert pf.maybe_resample(rng)
    n_conv = len(pf.p)
    assert n_conv < n_spread / 5
    assert 50 <= n_conv and n_spread <= 5000
    k = len(np.unique(np.floor(pf.p.pos)))                         # occupied 1 m bins of the kept set
    assert k <= 3
    assert n_conv >= max(50, kld_bound(np.array([k]), 0.05, 2.326)[0])
    assert np.isclose(np.exp(pf.p.log_w).sum(), 1.0)


def test_link_index_projection_matches_the_exhaustive_one(rng):
    g = ladder()
    ix = LinkIndex(g)
    pts = rng.uniform([-5, -5], [45, 15], (500, 2))
    link, pos = ix.project(pts)
    _, _, d_exact = g.project(pts)
    d = np.hypot(*(ix.xy(link, pos) - pts).T)
    assert np.all(d <= d_exact + 0.25 + 1e-9)                     # half the sample spacing
    assert np.all((pos >= 0) & (pos <= g.link_len[link] + 1e-9))


def test_perf_command_prints_one_row_per_count(capsys):
    from indoor_loc.pf.perf import grid_graph, main
    assert main(["--counts", "50,100", "--reps", "3"]) == 0
    rows = [ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("| 50 ") or ln.startswith("| 100 ")]
    assert len(rows) == 2
    assert grid_graph(3, 2.0).n_links == 12


def test_adaptive_tracker_shrinks_its_cloud_and_still_smooths_on_the_graph():
    g = corridor_l()
    pp = PfParams(n_particles=2000, adaptive=True, n_min=100, n_max=3000, yaw_offset_sigma_rad=0.0)
    tr = GraphTracker(g, transition_table(g, TransitionParams()), pp, rng=np.random.default_rng(3))
    truth = lambda s: np.array([s, 0.0]) if s <= 10 else np.array([10.0, s - 10])   # noqa: E731
    noise = np.random.default_rng(4)
    s, t, ox, oy = 0.0, 0, 0.0, 0.0
    tr.fix(t, truth(0.0), np.eye(2))
    n0 = len(tr.pf.p)
    assert n0 == 400                                   # 2000 * sqrt(det((1 + 2^2) I)) / 5^2
    tr.odom(t, 0.0, 0.0)
    for k in range(1, 50):
        t += 320_000_000
        h = 0.0 if s < 10 else np.pi / 2
        s += 0.36
        ox, oy = ox + 0.36 * np.cos(h), oy + 0.36 * np.sin(h)
        tr.odom(t, ox, oy)
        if k % 6 == 0:
            tr.fix(t, truth(s) + noise.normal(0, 1.0, 2), np.eye(2))
    assert tr.pf.n_resample >= 1 and len(tr.pf.p) < n0
    assert np.hypot(*(tr.estimates[-1].xy - truth(s))) < 1.5
    sm = tr.smooth(20)
    assert g.project(np.array([e.xy for e in sm]))[2].max() < 1e-9


def test_fix_density_gaussian_and_student_t_integrate_to_one_and_t_has_heavier_tails():
    g = corridor_l()
    S = np.array([[2.0, 0.3], [0.3, 1.0]])
    xs = np.linspace(-60, 60, 1201)
    X, Y = np.meshgrid(xs, xs)
    d = np.column_stack([X.ravel(), Y.ravel()])
    m2 = np.einsum("ni,ij,nj->n", d, np.linalg.inv(S), d)
    cell = (xs[1] - xs[0]) ** 2
    gauss = _pf(g, fix_dof=0.0)._fix_log_density(m2, S)
    t = _pf(g, fix_dof=5.0)._fix_log_density(m2, S)
    assert np.exp(gauss).sum() * cell == pytest.approx(1.0, abs=1e-6)
    assert np.exp(t).sum() * cell == pytest.approx(1.0, abs=2e-3)          # tails beyond 60 m carry ~1e-3
    # Gaussian: exactly the bivariate normal density
    want = -0.5 * m2 - 0.5 * np.log(np.linalg.det(2 * np.pi * S))
    np.testing.assert_allclose(gauss, want, atol=1e-12)
    # 5 sigma away the t density is far above the Gaussian's (in two dimensions both peak at 1 / (2 pi sqrt det S))
    at = np.array([0.0, 25.0])
    lt, lg = _pf(g, fix_dof=5.0)._fix_log_density(at, S), _pf(g, fix_dof=0.0)._fix_log_density(at, S)
    assert lt[0] == pytest.approx(lg[0])
    assert lt[1] > lg[1] + 5


def test_redrawn_particles_carry_the_inject_mass_and_the_others_keep_their_relative_weights(rng):
    g = corridor_l()
    pf = _pf(g, n=100, inject_mass=0.05)
    _place(pf, np.zeros(100), np.linspace(0, 10, 100), np.ones(100))
    w = rng.random(100)
    pf.p.log_w = normalise_log(np.log(w))
    idx = pf.inject(np.full(10, 2, np.int32), np.full(10, 0.5), rng)
    assert set(idx.tolist()) == set(np.argsort(w)[:10].tolist())           # the lowest weights are redrawn
    wn = pf.p.weights
    assert wn[idx].sum() == pytest.approx(0.05)
    kept = np.setdiff1d(np.arange(100), idx)
    np.testing.assert_allclose(wn[kept] / wn[kept].sum(), w[kept] / w[kept].sum(), rtol=1e-12)
    np.testing.assert_allclose(particle_xy(g, pf.p)[idx], np.tile([10.0, 7.5], (10, 1)))


def test_one_outlying_fix_moves_the_estimate_only_as_far_as_the_inject_mass_allows(rng):
    # a walker standing at (3, 0) on a long corridor; the WiFi matcher's wrong match puts one fix 9 m
    # along the corridor. With a small prior mass for the redrawn particles the estimate stays and
    # only fixes that keep agreeing on the new place move it; with the default it follows at once.
    g = build_graph([0, 1], np.array([[0, 0], [40, 0]], float), [(0, 1)])
    cov = np.eye(2) * 4.0

    def settled(mass):
        pf = _pf(g, n=1000, yaw_offset_sigma_rad=0.0, inject_mass=mass)
        pf.init_gaussian(np.array([3.0, 0.0]), cov, rng)
        for _ in range(5):
            pf.update_position(np.array([3.0, 0.0]), cov, rng)
            pf.maybe_resample(rng)
        pf.update_position(np.array([12.0, 0.0]), cov, rng)
        return pf

    pf = settled(1e-4)
    assert abs(pf.estimate()[0][0] - 3.0) < 1.0
    for _ in range(4):
        pf.maybe_resample(rng)
        pf.update_position(np.array([12.0, 0.0]), cov, rng)
    assert abs(pf.estimate()[0][0] - 12.0) < 1.5
    assert settled(PfParams().inject_mass).estimate()[0][0] > 8.0


def _walk_with_a_wrong_fix_run_at_the_end():
    # a walker goes east at 1 m/s along a 100 m corridor; the WiFi fixes are right (1.5 m) but report
    # a broad covariance (8 m, as a fingerprint matcher in a large open hall does), and the last
    # three are 25 m behind him (a wrong match that persists), so the causal filter follows them there
    g = build_graph(range(11), np.array([[10.0 * i, 0.0] for i in range(11)]), [(i, i + 1) for i in range(10)])
    tr = GraphTracker(g, transition_table(g, TransitionParams()), PfParams(n_particles=500, yaw_offset_sigma_rad=0.0),
                      rng=np.random.default_rng(11))
    noise = np.random.default_rng(12)
    cov = np.eye(2) * 64.0
    t, x = 0, 20.0
    truth = {}
    tr.fixes = {}                                                   # stamp -> fix mean, for the checks
    tr.odom(t, 0.0, 0.0, 0.0)
    for k in range(1, 121):                                         # 60 s, a PDR hop every 0.5 s
        t += 500_000_000
        x += 0.5
        tr.odom(t, x - 20.0, 0.0, 0.0)
        truth[t] = x
        if k % 4 == 0:
            off = -25.0 if k > 108 else 0.0
            tr.fixes[t] = np.array([x + off, 0.0]) + noise.normal(0, 1.5, 2)
            tr.fix(t, tr.fixes[t], cov)
    return tr, truth


def test_mixture_smoother_does_not_chain_the_past_to_particles_redrawn_at_a_wrong_fix():
    # with the filter's own transition at a fix (mixture), a particle redrawn far from every
    # particle (sensor resetting at a wrong fix) takes its predecessor from the filter's weights
    # instead of the nearest particle, which drags the smoothed past towards the wrong fixes
    tr, truth = _walk_with_a_wrong_fix_run_at_the_end()
    assert abs(tr.estimates[-1].xy[0] - (max(truth.values()) - 25.0)) < 6.0      # the causal filter followed them
    before = [t for t in truth if 5e9 <= t < 54e9]                                # before the wrong fixes

    def err(ests):
        xy = {e.stamp_ns: e.xy for e in ests}
        return np.mean([np.hypot(*(xy[t] - [truth[t], 0.0])) for t in before])

    assert err(tr.estimates) < 1.0
    chained, mixed = err(tr.smooth(50)), err(tr.smooth(50, redrawn="mixture"))
    assert mixed < 1.5, mixed
    assert mixed < chained - 1.0, (mixed, chained)                               # the default chains: 4.1 m
    with pytest.raises(ValueError):
        tr.smooth(5, redrawn="nearest")


def test_redrawn_draw_densities_follow_the_particles_through_resampling():
    # the smoother's mixture needs, per particle of a fix step's (resampled) set, the density q it
    # was drawn from: -inf for the particles the motion model brought there, the Gaussian draw
    # density (fix covariance + init_sigma_extra_m²) at its position for the redrawn ones
    tr, _ = _walk_with_a_wrong_fix_run_at_the_end()
    draw = np.eye(2) * 64.0 + tr.pf.params.init_sigma_extra_m ** 2 * np.eye(2)
    steps = [h for seg in tr.segments + [tr.history] for h in seg if h.redrawn_log_q is not None]
    assert len(steps) == len(tr.fixes) - 1 and tr.pf.n_resample > 0           # the first fix initialises
    resampled = 0
    for h in steps:
        q = h.redrawn_log_q
        fin = np.isfinite(q)
        assert q.shape == (len(h.xy),) and 0 < fin.sum() < len(q) and np.all(q[~fin] == -np.inf)
        d = h.xy[fin] - tr.fixes[h.stamp_ns]
        want = (-0.5 * np.einsum("ij,jk,ik->i", d, np.linalg.inv(draw), d) - np.log(2 * np.pi)
                - 0.5 * np.log(np.linalg.det(draw)))
        np.testing.assert_allclose(q[fin], want, atol=1e-9)
        resampled += np.all(h.log_w == h.log_w[0])        # equal weights: this fix's set was resampled
    assert resampled > 0                                  # the index carry-over was exercised
