"""MultiUserGraph: assembled Jacobian vs numerical derivatives, insertion policy, joint vs separate
on a two-user synthetic building, bounding, the evolving map saved and loaded."""
from __future__ import annotations


import numpy as np
import pytest

from backend_synth import SEC, corridor_walk, feed, scan_at, survey
from indoor_loc.backend.graph import FIX_GRAPH_PARAMS, GraphParams, MultiUserGraph
from indoor_loc.errors import ConfigError
from indoor_loc.wifi.radiomap import load_radiomap, save_radiomap


def _err(graph, walk) -> np.ndarray:
    st, x = graph.trajectory(walk.name)
    return np.linalg.norm(x[:, :2] - walk.true_xy_at(st), axis=1)


@pytest.mark.parametrize("robust", ["none", "cauchy"])
def test_assembled_jacobian_matches_numerical_derivatives(robust):
    rng = np.random.default_rng(3)
    g = MultiUserGraph(GraphParams(window_poses=0, robust_kernel=robust, robust_threshold_m=0.5,
                                   wknn={"shared_threshold": 0.75, "shared_strict": False}), survey(0, 24, rng))
    a = corridor_walk("a", 2, 40, 0, rng, scan_period_s=1.0)
    b = corridor_walk("b", 38, 26, 100 * SEC, rng)
    feed(g, a)
    feed(g, b)
    g.poses.x[:g.poses.n] += rng.normal(0, 0.5, (g.poses.n, 3))      # away from the optimum
    assert g.wifi.n > 5 and np.any(g.wifi.view("refs") >= 0)             # b matched a's scans (joint)
    var = np.arange(g.poses.n)
    fun, jac, z0, _, _ = g.problem(var)
    h = 1e-6
    J = jac(z0).toarray()
    cols = rng.choice(len(z0), 40, replace=False)
    for c in cols:
        d = np.zeros_like(z0)
        d[c] = h
        np.testing.assert_allclose(J[:, c], (fun(z0 + d) - fun(z0 - d)) / (2 * h), atol=2e-5)


@pytest.mark.parametrize("robust,from_fix", [("none", False), ("huber", False), ("none", True)])
def test_jacobian_pattern_holds_every_nonzero(robust, from_fix):
    """The sparse Jacobian stores only entries the factor models can make non-zero: every column
    against central differences, and the stored pattern against the non-zeros it leaves out."""
    rng = np.random.default_rng(8)
    g = MultiUserGraph(GraphParams(window_poses=0, robust_kernel=robust, robust_threshold_m=0.3,
                                   wifi_info_from_fix=from_fix,
                                   wknn={"shared_threshold": 0.75, "shared_strict": False}), survey(0, 24, rng))
    feed(g, corridor_walk("a", 2, 40, 0, rng, scan_period_s=1.0))
    feed(g, corridor_walk("b", 38, 26, 100 * SEC, rng))
    g.poses.x[:g.poses.n] += rng.normal(0, 0.5, (g.poses.n, 3))
    if from_fix:      # a fix's information has a full Cholesky factor (upper triangular Lᵀ)
        g.wifi.view("sqrt_info")[:] = np.triu(rng.uniform(0.5, 3.0, (g.wifi.n, 2, 2)))
    fun, jac, z0, _, _ = g.problem(np.arange(g.poses.n))
    J = jac(z0)
    h = 1e-6
    num = np.stack([(fun(z0 + d) - fun(z0 - d)) / (2 * h) for d in h * np.eye(len(z0))], axis=1)
    np.testing.assert_allclose(J.toarray(), num, atol=2e-5)
    stored = np.zeros(J.shape, bool)
    stored[np.repeat(np.arange(J.shape[0]), np.diff(J.indptr)), J.indices] = True
    assert np.all(np.abs(num[~stored]) < 1e-7)                # nothing left out is non-zero
    assert np.mean(J.data == 0) < 0.05                          # and the pattern is tight (was ~45 % zeros)


def test_insertion_policy():
    rng = np.random.default_rng(5)
    p = GraphParams(window_poses=0, pose_period_s=1.28, min_scan_move_m=0.3)
    g = MultiUserGraph(p, survey(0, 60, rng))
    # hops before the first localised scan add nothing
    assert g.add_hop("u", 0, 320_000_000, 0.6, 0.0) is None and g.poses.n == 0
    i, m = g.add_scan("u", scan_at(400_000_000, np.array([1.0, 0.0]), rng))
    assert i == 0 and m is not None and g.poses.n == 1                    # first pose at the WKNN position:
    np.testing.assert_allclose(g.poses.x[0, :2], m.fix.xy)
    np.testing.assert_allclose(m.fix.xy, m.weights @ g.map.positions(m.refs, g.poses.x[:0, :2]))
    assert np.linalg.norm(m.fix.xy - [1.0, 0.0]) < 2.0                    # the matched survey scans' mean
    # standing still: a scan right after attaches to the same pose
    i2, _ = g.add_scan("u", scan_at(500_000_000, np.array([1.0, 0.0]), rng))
    assert i2 == 0 and g.poses.n == 1 and g.wifi.n == 2
    # walking: a pose every 1.28 s of hops (4 hops of 0.32 s)
    added = [g.add_hop("u", t - 320_000_000, t, 0.6, 0.0) for t in range(720_000_000, 2_100_000_000, 320_000_000)]
    assert sum(a is not None for a in added) == 1 and g.poses.n == 2      # at 1.68 s = first pose + 1.28 s
    # a scan after some walking gets its own pose, initialised at its WKNN fix, with a PDR edge to the last
    i3, m3 = g.add_scan("u", scan_at(2_300_000_000, np.array([3.0, 0.0]), rng))
    assert i3 == 2 and g.pdr.n == 2
    np.testing.assert_allclose(g.poses.x[2, :2], m3.fix.xy)
    assert np.linalg.norm(m3.fix.xy - [3.0, 0.0]) < 2.0
    # the motion from the last hop (2.0 s) to the scan is extrapolated and taken off the next hop:
    # every step counted after the start is in exactly one edge (or still accumulating)
    g.add_hop("u", 2_000_000_000, 2_320_000_000, 0.6, 0.0)
    g.add_hop("u", 2_320_000_000, 2_640_000_000, 0.6, 0.0)
    assert g.pdr.view("steps").sum() + g.users["u"].acc_steps == pytest.approx(7 * 0.6, abs=1e-9)
    with pytest.raises(ValueError, match="older"):
        g.add_hop("u", 0, 1_000_000_000, 0.6, 0.0)


def test_joint_optimisation_helps_the_user_outside_the_survey():
    """The survey covers x in [0, 24] only; APs are heard within ~6 m and WKNN needs 75 % of the APs
    shared both ways, so only scans over the survey are localised against it. User a walks 2 -> 58
    scanning every second: localised at the start, PDR carries it on, and its scans join the map at
    its poses. User b then walks 56 -> 30, outside the survey: on its own (separate) it is never
    localised; jointly it matches a's scans from its first scan on and is placed where it really is."""
    wknn = {"shared_threshold": 0.75, "shared_strict": False}
    out = {}
    for joint in (False, True):
        rng = np.random.default_rng(11)
        g = MultiUserGraph(GraphParams(joint=joint, window_poses=0, wknn=wknn), survey(0, 24, rng))
        a = corridor_walk("a", 2, 58, 0, rng, step_len=0.65, scan_period_s=1.0)
        b = corridor_walk("b", 56, 30, 100 * SEC, rng, step_len=0.65)
        feed(g, a)
        feed(g, b)
        g.optimize(max_iterations=50)
        st, _ = g.trajectory("b")
        span = (st[-1] - st[0]) / (b.truth_t[-1] - b.truth_t[0]) if len(st) else 0.0
        out[joint] = (_err(g, a), _err(g, b), span, g.users["b"].scans_from_users)
    assert np.mean(out[False][0]) < 1.0 and np.mean(out[True][0]) < 1.0      # a is fine either way
    assert out[False][2] == 0.0                       # separately b is never localised
    assert out[True][2] > 0.85 and out[True][3] >= 4  # jointly from its first scan, via a's scans
    assert np.mean(out[True][1]) < 1.0


def test_step_length_is_estimated():
    rng = np.random.default_rng(2)
    g = MultiUserGraph(GraphParams(window_poses=0), survey(0, 60, rng))
    w = corridor_walk("tall", 2, 58, 0, rng, step_len=0.75)
    feed(g, w)
    g.optimize(max_iterations=50)
    # the prior (0.65 m, information 200) pulls back; the data moves it well towards 0.75 m
    assert 0.69 < g.step_len[0] < 0.77
    g2 = MultiUserGraph(GraphParams(window_poses=0, estimate_step_length=False), survey(0, 60, rng))
    feed(g2, w)
    g2.optimize()
    assert g2.step_len[0] == 0.65


def test_window_optimisation_matches_batch_closely():
    rng = np.random.default_rng(8)
    walk = corridor_walk("u", 2, 58, 0, rng)
    live = MultiUserGraph(GraphParams(window_poses=30), survey(0, 60, np.random.default_rng(1)))
    batch = MultiUserGraph(GraphParams(window_poses=0), survey(0, 60, np.random.default_rng(1)))
    feed(live, walk)
    feed(batch, walk)
    live.optimize()
    batch.optimize()
    assert np.max(np.abs(live.poses.view("x")[:, :2] - batch.poses.view("x")[:, :2])) < 0.05


def test_graph_stays_bounded():
    rng = np.random.default_rng(4)
    g = MultiUserGraph(GraphParams(window_poses=10, max_active_poses=40, max_map_rows=8), survey(0, 60, rng))
    feed(g, corridor_walk("a", 2, 58, 0, rng))
    g.finish_user("a")
    feed(g, corridor_walk("b", 58, 2, 100 * SEC, rng))
    assert g.poses.n > 60 and g.poses.n - g.n_frozen == 40
    assert not g.poses.frozen[g.users["b"].poses[-1]]                  # the active user's newest poses stay free
    assert g.map.n_user_rows == 8 and g.map.dropped_rows > 0
    assert g.map.n_user_rows == np.count_nonzero(g.map.user[:g.map.n] >= 0)   # the running count is the rows'
    rep = g.optimize()
    assert rep.n_poses == 40


def test_evolving_map_save_and_load(tmp_path):
    rng = np.random.default_rng(6)
    wknn = {"shared_threshold": 0.75, "shared_strict": False}
    g = MultiUserGraph(GraphParams(window_poses=0, wknn=wknn), survey(0, 24, rng))
    walk = corridor_walk("a", 2, 40, 0, rng, step_len=0.65, scan_period_s=1.0)
    feed(g, walk)
    g.optimize()
    rm = g.wifi_radio_map()
    n_survey = 2 * 13
    assert rm.n_scans == n_survey + g.map.n_user_rows and set(rm.source[n_survey:]) == {"a"}
    path = save_radiomap(rm, tmp_path / "grown")
    back = load_radiomap(path)
    np.testing.assert_allclose(back.positions, rm.positions, atol=1e-6)
    assert back.source == rm.source
    # a later session starts from the grown map: a user beyond the survey is now localised
    g2 = MultiUserGraph(GraphParams(window_poses=0, joint=False, wknn=wknn), back)
    later = corridor_walk("b", 40, 26, 0, rng, scan_period_s=2.0)
    feed(g2, later)
    g2.optimize()
    learnt = g2.wifi.view("refs")[g2.wifi.view("refs") < -n_survey]     # fixed rows beyond the survey's
    assert g2.users["b"].scans_localised > 0 and len(learnt) > 0
    assert np.mean(_err(g2, later)) < 3.0


def test_bad_parameters_are_refused():
    with pytest.raises(ConfigError, match="robust_kernel"):
        GraphParams(robust_kernel="tukey").validate()
    with pytest.raises(ConfigError, match="pdr_info"):
        GraphParams(pdr_info=[1.0, 1.0]).validate()
    with pytest.raises(ConfigError, match="k: expected an integer"):
        GraphParams(wknn={"k": 0}).validate()


def test_reused_wknn_index_gives_the_same_matches_as_a_fresh_one():
    """The evolving map reuses its fitted WKNN index while a query's candidate rows are unchanged:
    two users' scans interleaved (merged order) and a row cap that drops rows match exactly as with
    an index fitted afresh for every query."""
    from indoor_loc.backend.graph import BackendWknnParams
    from indoor_loc.backend.wifi_map import EvolvingMap

    rng = np.random.default_rng(7)
    cached, fresh = (EvolvingMap(BackendWknnParams(), max_rows=6) for _ in range(2))
    s = survey(0, 30, rng, spacing=4.0)
    cached.add_fixed(s)
    fresh.add_fixed(s)
    n_user_matches = 0
    pose_xy = rng.uniform(0, 30, (30, 2))                  # the user rows' (pose i's) current positions
    for i in range(30):
        user = i % 3 if i < 20 else 0                      # interleaved, then one user alone
        scan = scan_at(i * SEC, np.array([rng.uniform(0, 30), 0.0]), rng)
        fresh._fitted = None
        a = cached.match(scan, user=user, joint=True, pose_xy=pose_xy)
        b = fresh.match(scan, user=user, joint=True, pose_xy=pose_xy)
        assert (a is None) == (b is None)
        if a is not None:
            assert np.array_equal(a.refs, b.refs) and np.allclose(a.weights, b.weights)
            np.testing.assert_allclose(a.fix.xy, a.weights @ cached.positions(a.refs, pose_xy))
            n_user_matches += a.n_from_users > 0
        cached.add_scan(scan, i, user)
        fresh.add_scan(scan, i, user)
    assert n_user_matches > 0 and cached.dropped_rows > 0


def test_long_run_stays_flat():
    """Thirty users one after another along the corridor (about 1500 poses in all) with small caps:
    what the graph holds stops growing once the caps are reached — poses, edges, map rows and
    pinned fixed positions — while later users still match the scans of dropped poses (pinned in
    the map), and the newest user is still localised."""
    rng = np.random.default_rng(11)
    p = GraphParams(window_poses=10, max_active_poses=60, max_user_poses=40, max_frozen_poses=30, max_map_rows=50)
    g = MultiUserGraph(p, survey(0, 30, rng, spacing=6.0))
    sizes = []
    for u in range(30):
        x0, x1 = (2.0, 58.0) if u % 2 == 0 else (58.0, 2.0)
        walk = corridor_walk(f"u{u:02d}", x0, x1, u * 100 * SEC, rng)
        feed(g, walk)
        g.finish_user(walk.name)
        c = g.counts()
        sizes.append((c["poses"], c["pdr_edges"], c["wifi_edges"], c["map_rows"], len(g.map.fixed_xy)))
    sizes = np.array(sizes)
    assert g.n_dropped > 1000                                            # ~ 50 poses per walk
    cap = p.max_active_poses + p.max_frozen_poses + 30                   # + a kept frozen pose per user
    assert sizes[:, 0].max() <= cap and sizes[:, 1].max() <= cap
    assert np.all(sizes[10:].max(axis=0) <= sizes[:10].max(axis=0) * 1.5 + 5)   # flat after warm-up
    assert sizes[:, 3].max() <= g.map.n_loaded_fixed + 50                # survey rows + capped user rows
    assert sizes[:, 4].max() <= g.map.n_loaded_fixed + 50 + 4 * sizes[:, 2].max()   # survey + pinned rows + refs
    assert g.users["u29"].scans_from_users > 0
    g.optimize()
    assert np.median(_err(g, walk)) < 3.0


def test_dropping_frozen_poses_changes_no_estimate():
    """Dropped poses were constants already: the same users with the same freezing, once keeping
    every frozen pose and once dropping them at once, give the same trajectories (the pinned map
    positions and the rewritten hyperedges are the same constants)."""
    runs = []
    for max_frozen in (100000, 0):
        rng = np.random.default_rng(5)
        g = MultiUserGraph(GraphParams(window_poses=10, max_active_poses=50, max_user_poses=30,
                                       max_frozen_poses=max_frozen), survey(0, 30, rng, spacing=6.0))
        walks = [corridor_walk(f"u{u}", 2.0, 58.0, u * 20 * SEC, rng, y=0.5 * u) for u in range(4)]
        for w in walks:
            feed(g, w)
            g.finish_user(w.name)
        g.optimize()
        runs.append((g, [g.trajectory(w.name) for w in walks]))
    (keep, tk), (drop, td) = runs
    assert keep.n_dropped == 0 and drop.n_dropped > 100
    assert drop.counts()["wifi_edges"] < keep.counts()["wifi_edges"]
    n_compared = 0
    for (sk, xk), (sd, xd) in zip(tk, td):           # the first users' poses are all gone when dropped
        common, ik, id_ = np.intersect1d(sk, sd, return_indices=True)
        assert len(common) == len(sd)
        assert np.allclose(xk[ik], xd[id_], atol=1e-6)
        n_compared += len(common)
    assert n_compared >= 30


def test_a_solved_graph_is_freed_without_the_cycle_collector():
    """The last solve's Jacobian (kept for covariances) holds no reference back to its graph, so a
    dropped graph is freed at once (many short-lived graphs, as in the reduced-map bench, would
    otherwise pile up until the cyclic GC ran); the covariance still comes from the last solve."""
    import gc
    import weakref

    def solved():
        rng = np.random.default_rng(5)
        g = MultiUserGraph(GraphParams(window_poses=0), survey(0, 24, rng))
        feed(g, corridor_walk("a", 2, 22, 0, rng, scan_period_s=1.0))
        assert g.optimize() is not None
        return g

    g = solved()
    pose = g.users["a"].poses[len(g.users["a"].poses) // 2]
    cov = g.marginal_cov(pose)
    assert cov is not None and cov.shape == (3, 3) and np.all(np.linalg.eigvalsh(0.5 * (cov + cov.T)) > 0)
    np.testing.assert_array_equal(g.marginal_cov(pose), cov)       # J evaluated once, reused
    g = solved()                                                    # no covariance asked: J not evaluated
    ref = weakref.ref(g)
    enabled = gc.isenabled()
    gc.disable()
    try:
        del g
        assert ref() is None
    finally:
        if enabled:
            gc.enable()


def test_front_end_fixes_as_position_factors():
    """``wifi_source: fix``: the front end's fixes (truth + 2 m noise, one wild one) are position
    factors with their covariance; the PDR-linked trajectory beats the fixes, the user starts at its
    first fix, and (separate users) scans neither match the survey nor add poses."""
    rng = np.random.default_rng(4)
    g = MultiUserGraph(GraphParams(window_poses=10, wifi_source="fix", joint=False, wifi_info=1.0,
                                   robust_kernel="huber", robust_threshold_m=1.345), survey(0, 60, rng))
    w = corridor_walk("u", 2, 50, 0, rng, scan_period_s=2.0)
    fix_err = []
    for stamp, kind, payload in w.events:
        if kind == 0:
            g.add_hop("u", *payload)
            continue
        noise = rng.normal(0, 2.0, 2) + (np.array([0.0, 25.0]) if len(fix_err) == 5 else 0.0)
        fix_err.append(np.linalg.norm(noise))
        i = g.add_fix("u", stamp, w.true_xy_at([stamp])[0] + noise, 4.0 * np.eye(2))
        assert (i == 0) if len(fix_err) == 1 else (i == g.users["u"].poses[-1])
        n_after_fix = g.poses.n
        assert g.add_scan("u", payload) == (None, None) and g.poses.n == n_after_fix
    g.optimize(max_iterations=30)
    assert g.wifi.n == len(fix_err) and np.all(g.wifi.view("refs") < 0)
    e = _err(g, w)
    assert np.mean(e) < 0.6 * np.mean(fix_err) and np.max(e) < 5.0            # the wild fix is bounded
    with pytest.raises(ConfigError, match="wifi_source"):
        GraphParams(wifi_source="both").validate()
    # a bad fix is refused before anything changes (a NaN pose or a factor without an inverse
    # would poison every later solve)
    g2 = MultiUserGraph(GraphParams(**FIX_GRAPH_PARAMS), None)
    for xy, cov in [([np.nan, 0.0], np.eye(2)), ([0.0, 0.0], np.zeros((2, 2))),
                    ([0.0, 0.0], np.array([[1.0, 2.0], [2.0, 1.0]])), ([0.0, 0.0], np.diag([np.inf, 1.0]))]:
        with pytest.raises(ValueError, match="not finite / positive definite"):
            g2.add_fix("u", SEC, np.array(xy), cov)
    assert g2.poses.n == 0 and g2.wifi.n == 0 and not g2.users
