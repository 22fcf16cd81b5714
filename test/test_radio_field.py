"""The extrapolating radio map (indoor_loc.wifi.radio_field) and its hook in the powed k-NN grid."""
from __future__ import annotations

import dataclasses

import numpy as np

from indoor_loc.wifi.powed_knn import PowedKnn
from indoor_loc.wifi.powed_repr import sorensen, powed
from indoor_loc.wifi.powed_knn_params import PowedKnnParams
from indoor_loc.wifi.radio_field import detect_level, expected_powed, pathloss_prior, view_scale
from indoor_loc.wifi.radiomap import add_fingerprints, empty_radiomap
from indoor_loc.wifi.types import WifiScan
from grid_readings import assert_grid_equals

SIZE = (60.0, 40.0)
FLOOR, BETA = -100.0, np.e


def _field(rng, n_aps):
    """Log-distance APs over the floor: P = p0 - 10 n log10(d), p0 in [-40, -30] dBm, n in [2.5, 3.5]."""
    ap = np.column_stack([rng.uniform(0, SIZE[0], n_aps), rng.uniform(0, SIZE[1], n_aps)])
    p0 = rng.uniform(-40, -30, n_aps)
    n = rng.uniform(2.5, 3.5, n_aps)

    def rss(xy, noise_db):
        d = np.sqrt(((xy[:, None, :] - ap[None]) ** 2).sum(-1) + 1.0)
        r = p0[None] - 10 * n[None] * np.log10(d) + rng.normal(0, noise_db, (len(xy), n_aps))
        r[r < -95] = np.nan
        return np.clip(r, -120, 0)
    return rss


def _scans(rows, bssids):
    out = []
    for i, row in enumerate(rows):
        c = np.flatnonzero(~np.isnan(row))
        out.append(WifiScan(stamp_ns=i, bssid=tuple(bssids[j] for j in c), rssi_dbm=row[c].copy(),
                            freq_mhz=np.full(len(c), 2437.0)))
    return out


def _survey(rng, n_aps=40, noise_db=4.0, ys=(5.0, 14.0)):
    """Survey walks along y = ys (a scan every metre, one walk each): the north of the floor is never surveyed."""
    rss = _field(rng, n_aps)
    bssids = [f"02:00:00:00:02:{i:02x}" for i in range(n_aps)]
    xs = np.arange(1.0, SIZE[0], 1.0)
    rm = empty_radiomap()
    for j, y in enumerate(ys):
        pts = np.column_stack([xs, np.full(len(xs), y)])
        rm = add_fingerprints(rm, pts, _scans(rss(pts, noise_db), bssids), f"walk{j}")
    return rm, rss, bssids


def test_expected_powed_is_the_mean_over_the_reading_distribution():
    """E[powed(R)], R ~ N(mu, sigma^2), against a seeded Monte Carlo mean; sigma -> 0 gives powed(mu);
    far below the detection floor the expectation is 0."""
    rng = np.random.default_rng(3)
    mu = np.array([-95.0, -85.0, -70.0, -50.0])
    sig = np.array([6.0, 8.0, 4.0, 2.0])
    mc = powed(mu[None] + sig[None] * rng.standard_normal((200_000, 4)), FLOOR, BETA).mean(axis=0)
    np.testing.assert_allclose(expected_powed(mu, sig, FLOOR, BETA), mc, rtol=0.02, atol=1e-6)
    np.testing.assert_allclose(expected_powed(mu, np.full(4, 1e-9), FLOOR, BETA), powed(mu, FLOOR, BETA), rtol=1e-9)
    assert expected_powed(np.array([-160.0]), np.array([3.0]), FLOOR, BETA)[0] == 0.0


def test_pathloss_prior_predicts_the_unsurveyed_part_of_a_log_distance_field():
    """Far from the survey walks (y >= 24 m, 10 m or more from them) the path-loss prior predicts the
    expected powed values of a log-distance field much better than copying the nearest survey scan
    (what kernel regression does there). Measured (seed 11): 0.25 against 0.90 summed absolute error."""
    rng = np.random.default_rng(11)
    rm, rss, _ = _survey(rng)
    gx, gy = np.meshgrid(np.arange(2.0, SIZE[0], 4.0), np.arange(24.0, SIZE[1], 4.0))
    g = np.column_stack([gx.ravel(), gy.ravel()])
    prior = pathloss_prior(rm, g, np.zeros(len(g)), floor_dbm=FLOOR, beta=BETA).toarray()
    truth = np.mean([powed(rss(g, 4.0), FLOOR, BETA) for _ in range(40)], axis=0)
    nearest = powed(rm.rssi_dbm, FLOOR, BETA)[np.argmin(np.linalg.norm(g[:, None] - rm.positions[None], axis=2),
                                                         axis=1)]
    err_prior = np.abs(prior - truth).sum(axis=1).mean()
    err_nearest = np.abs(nearest - truth).sum(axis=1).mean()
    assert err_prior < 0.6 * err_nearest, (err_prior, err_nearest)
    assert prior.shape == (len(g), rm.n_aps) and np.all(prior >= 0)


def test_view_scale_maps_raw_values_to_a_view():
    raw = np.array([[0.2, 0.0, 0.0], [0.4, 0.1, 0.0]])
    w = np.array([2.0, 0.5, 3.0])
    np.testing.assert_allclose(view_scale(raw * w, raw), [2.0, 0.5, 0.0])


def test_the_field_locates_users_where_the_survey_did_not_go():
    """Users in the unsurveyed north (y in [24, 34] m, 10-20 m from the survey walks): a grid that reaches
    20 m and carries the path-loss prior (field_weight 0.05) locates them better than the same grid by
    kernel regression alone (which copies the nearest scans) and than the default 2 m grid. Measured (seed 4):
    2.4 m against 9.8 m and 15.8 m mean."""
    rng = np.random.default_rng(4)
    rm, rss, bssids = _survey(rng)
    pts = np.column_stack([rng.uniform(4, SIZE[0] - 4, 80), rng.uniform(24, 34, 80)])
    scans = _scans(rss(pts, 4.0), bssids)
    err = {}
    for label, params in (("field", {"field_weight": 0.05, "smooth_reach_m": 20.0}),
                          ("kernel", {"smooth_reach_m": 20.0}), ("default", {})):
        fixes = PowedKnn(PowedKnnParams(cov_calibration=False, smooth_views="grid", **params)).fit(rm).locate_many(scans)
        assert all(f.ok for f in fixes)
        err[label] = float(np.mean([np.hypot(*(f.xy - p)) for f, p in zip(fixes, pts)]))
    assert err["field"] < 0.8 * min(err["kernel"], err["default"]), err


def test_the_calibration_folds_refit_the_prior_without_the_left_out_walk():
    """The grid of a calibration fold is the kernel regression of the kept scans plus the path-loss prior
    fitted on the kept scans only (a prior fitted on every scan would leak the left-out walk into its own
    cross-validation and make the ellipses too small)."""
    rm, _, _ = _survey(np.random.default_rng(6), ys=(5.0, 14.0, 23.0))
    lam = 0.05
    pos = PowedKnn(PowedKnnParams(cov_calibration=False, age_tau_ms=0.0, field_weight=lam,
                                  smooth_reach_m=6.0)).fit(rm)
    h = pos.params.smooth_m
    keep = np.array(rm.source) != "walk1"
    readings, sums, rows = pos._smoothed(keep)
    g = pos._grid_pos[rows]
    d = np.linalg.norm(g[:, None, :] - rm.positions[keep][None], axis=2)
    w = np.exp(-0.5 * (d / h) ** 2) * (d <= 3 * h)
    prior = pathloss_prior(rm, g, np.zeros(len(g)), floor_dbm=FLOOR, beta=BETA, keep=keep,
                           detect_dbm=detect_level(rm)).toarray() * pos._w
    leaky = pathloss_prior(rm, g, np.zeros(len(g)), floor_dbm=FLOOR, beta=BETA).toarray() * pos._w
    expect = (w @ pos._vals[0][keep] + lam * prior) / (w.sum(axis=1) + lam)[:, None]
    assert_grid_equals(readings[0], sums[0], expect)
    assert np.abs(prior - leaky).max() > 1e-3                 # the left-out walk does move the models


def test_a_walkable_area_bounds_where_the_field_extends():
    """With a walkable area (a floor plan) the grid reaches field_reach_m from the map scans inside it only,
    smooth_reach_m elsewhere; without one, smooth_reach_m everywhere. The users in the unsurveyed north are
    then located as well as with the unbounded grid of the previous test."""
    rng = np.random.default_rng(4)
    rm, rss, bssids = _survey(rng)

    def north(xy, z):
        return xy[:, 1] >= 20.0
    params = PowedKnnParams(cov_calibration=False, smooth_views="grid", field_weight=0.05, field_reach_m=20.0)
    pos = PowedKnn(params, walkable=north).fit(rm)
    d = np.linalg.norm(pos._grid_pos[:, None] - rm.positions[None], axis=2).min(axis=1)
    inside = north(pos._grid_pos, 0.0)
    assert np.all(d[~inside] <= params.smooth_reach_m + 1e-9) and np.all(d[inside] <= 20.0 + 1e-9)
    assert inside.sum() > 0 and d[inside].max() > 10.0
    plain = PowedKnn(params).fit(rm)
    assert len(plain._grid_pos) < len(pos._grid_pos)
    d_plain = np.linalg.norm(plain._grid_pos[:, None] - rm.positions[None], axis=2).min(axis=1)
    assert np.all(d_plain <= params.smooth_reach_m + 1e-9)
    pts = np.column_stack([rng.uniform(4, SIZE[0] - 4, 80), rng.uniform(24, 34, 80)])
    scans = _scans(rss(pts, 4.0), bssids)
    err = [float(np.mean([np.hypot(*(f.xy - p)) for f, p in zip(m.locate_many(scans), pts)])) for m in (pos, plain)]
    assert err[0] < 0.5 * err[1], err


def test_a_fold_refits_only_the_aps_its_left_out_walk_heard():
    """A calibration fold's prior equals a prior fitted on the kept scans alone, though the fold refits
    only the APs the left-out walk heard (each AP's model depends on its own readings only)."""
    rm, _, _ = _survey(np.random.default_rng(7), ys=(5.0, 14.0, 23.0))
    walk1 = np.array(rm.source) == "walk1"
    unheard = np.arange(0, len(rm.bssids), 2)
    rss = np.array(rm.rssi_dbm, float)
    rss[np.ix_(walk1, unheard)] = np.nan                     # walk1 heard the odd APs only
    rm = dataclasses.replace(rm, rssi_dbm=rss)
    pos = PowedKnn(PowedKnnParams(cov_calibration=False, age_tau_ms=0.0, field_weight=0.05,
                                  smooth_reach_m=6.0)).fit(rm)
    rows = np.arange(len(pos._grid_pos))
    scale = pos._prior_scale[0]
    got = pos._field_prior(~walk1, rows).toarray() * scale
    refit = pathloss_prior(rm, pos._grid_pos, pos._grid_z, floor_dbm=FLOOR, beta=BETA, keep=~walk1,
                           detect_dbm=detect_level(rm)).toarray() * scale
    np.testing.assert_allclose(got, refit, atol=1e-12)
    full = pos._field_prior(np.ones(len(walk1), bool), rows).toarray() * scale
    np.testing.assert_array_equal(got[:, unheard], full[:, unheard])     # kept, not refitted
    assert np.abs(got - full).max() > 1e-3                                # the heard APs were refitted


def _two_floors(seed):
    """Survey walks on two floors 4 m apart (the same building shape, independent APs per floor)."""
    rng = np.random.default_rng(seed)
    rm = empty_radiomap()
    xs = np.arange(1.0, SIZE[0], 1.0)
    for f, z in enumerate((0.0, 4.0)):
        rss = _field(rng, 30)
        bssids = [f"02:00:00:00:0{f + 3}:{i:02x}" for i in range(30)]
        for j, y in enumerate((5.0, 14.0)):
            pts = np.column_stack([xs, np.full(len(xs), y)])
            rm = add_fingerprints(rm, pts, _scans(rss(pts, 4.0), bssids), f"f{f}walk{j}", z_m=z)
    return rm


def _dense(readings, n_rows, n_aps):
    out = np.zeros((n_rows, n_aps))
    for col in range(n_aps):
        r, v, _ = readings.gather(np.array([col]))
        out[r, col] = v
    return out


def test_the_prior_is_the_same_whatever_the_order_of_the_grid_points():
    """The prior is assembled as CSR block by block; grid points of several floors in any order get the
    values they have in floor order, bit for bit."""
    rm = _two_floors(11)
    pos = PowedKnn(PowedKnnParams(cov_calibration=False, field_weight=0.05, smooth_reach_m=6.0)).fit(rm)
    g, gz = pos._grid_pos, pos._grid_z
    assert len(np.unique(gz)) == 2 and np.all(np.diff(gz) >= 0)
    ordered = pathloss_prior(rm, g, gz, floor_dbm=FLOOR, beta=BETA)
    perm = np.random.default_rng(1).permutation(len(g))
    mixed = pathloss_prior(rm, g[perm], gz[perm], floor_dbm=FLOOR, beta=BETA)
    assert ordered.nnz > 0 and mixed.has_sorted_indices
    np.testing.assert_array_equal(mixed.toarray(), ordered.toarray()[perm])


def test_the_grid_interpolated_per_floor_equals_the_whole_grid():
    """The fit and the calibration folds interpolate the grid one floor at a time; every floor's points
    get the values (and, in the fit's views, the distances) of the whole grid interpolated at once."""
    rm = _two_floors(12)
    pos = PowedKnn(PowedKnnParams(cov_calibration=False, field_weight=0.05, smooth_reach_m=6.0)).fit(rm)
    n_aps = len(rm.bssids)
    src = np.array(rm.source)
    for keep in (np.ones(rm.n_scans, bool), src != "f1walk0"):
        readings, sums, rows = pos._smoothed(keep)
        whole = [_dense(r, len(rows), n_aps) for r in readings]
        covered = np.zeros(len(rows), bool)
        for zf in (0.0, 4.0):
            rd, sm, part = pos._smoothed(keep, zf)
            at = np.searchsorted(rows, part)
            assert np.array_equal(rows[at], part) and np.all(pos._grid_z[part] == zf)
            covered[at] = True
            for j in range(len(readings)):
                np.testing.assert_array_equal(_dense(rd[j], len(part), n_aps), whole[j][at])
                np.testing.assert_array_equal(sm[j], sums[j][at])
        assert covered.all()
    # the fit's views, kept per floor, give each grid point the distance to the whole grid's values
    view = next(j for j, v in enumerate(pos._views) if v.grid)
    whole_rd, whole_sums, rows = pos._smoothed(np.ones(rm.n_scans, bool))
    assert len(rows) == len(pos._grid_pos) and len(pos._views[view].parts) == 2
    c = np.arange(0, n_aps, 3)
    q = np.random.default_rng(2).uniform(0.01, 0.5, len(c))
    d = pos._dist_cols(c, q, view)
    vals = pos._views[view].values
    expect = sorensen(c, q, whole_rd[vals], whole_sums[vals], len(rows))
    np.testing.assert_array_equal(d[pos._n_map:], expect)
    assert np.all(d[:pos._n_map] == 1.0) and np.any(expect < 1.0)


def test_bench_by_gap_bands_scans_by_their_distance_to_the_survey():
    from indoor_loc.bench.wifi_ms import by_gap
    rm = add_fingerprints(empty_radiomap(), np.array([[0.0, 0.0], [10.0, 0.0]]),
                          _scans(np.array([[-50.0], [-60.0]]), ["a"]), "s")
    truth = np.array([[1.0, 0.0], [10.0, 2.0], [5.0, 5.0], [10.0, 20.0], [10.0, 30.0]])   # gaps 1, 2, 7.07, 20, 30
    ok = np.array([True, True, True, True, False])
    e = np.array([1.0, 3.0, 4.0, 12.0, np.nan])
    ref_ok = np.ones(5, bool)
    ref_e = np.array([2.0, 2.0, 8.0, 24.0, 5.0])
    bands = by_gap(truth, rm, (ok, e, e, ref_ok, ref_e))
    assert [b["range"] for b in bands] == ["0-3", "3-10", ">10"]
    assert [b["scans"] for b in bands] == [2, 1, 1]                    # the last scan: ours gave no fix
    assert bands[0]["mean"] == 2.0 and bands[0]["ref_mean"] == 2.0 and bands[0]["ratio"] == 1.0
    assert bands[1]["ratio"] == 0.5 and bands[2]["ratio"] == 0.5


def test_map_scan_estimates_weigh_by_the_grid_estimates_share_on_the_survey():
    """Users in the unsurveyed north (10-20 m from the survey walks), grid extrapolated 20 m into a walkable
    area, the default 'both' views: the estimates against the map scans can only say "on the survey", so they
    weigh by the share of the grid estimate's weight within smooth_reach_m of a map scan. Averaged with equal
    weights they pull the users halfway back to the walks. Measured (seed 4): 2.2 m against 8.6 m mean.
    Where the grid has no point beyond smooth_reach_m (no walkable area), every fix is unchanged."""
    rng = np.random.default_rng(4)
    rm, rss, bssids = _survey(rng)
    pts = np.column_stack([rng.uniform(4, SIZE[0] - 4, 80), rng.uniform(24, 34, 80)])
    scans = _scans(rss(pts, 4.0), bssids)

    def everywhere(xy, z):
        return np.ones(len(xy), bool)
    err, fixes = {}, {}
    for share in (True, False):
        params = PowedKnnParams(cov_calibration=False, field_weight=0.05, field_reach_m=20.0, field_survey_share=share)
        fx = PowedKnn(params, walkable=everywhere).fit(rm).locate_many(scans)
        err[share] = float(np.mean([np.hypot(*(f.xy - p)) for f, p in zip(fx, pts)]))
        fixes[share] = PowedKnn(params).fit(rm).locate_many(scans)
    assert err[True] < 0.5 * err[False], err
    assert max(float(np.abs(a.xy - b.xy).max()) for a, b in zip(fixes[True], fixes[False])) == 0.0


def test_a_calibration_fold_judges_the_survey_without_its_left_out_walk():
    """The off-survey flags a calibration fold uses are those of the kept walks only: a grid point next to
    the left-out walk alone is beyond the survey for that fold (else the fold would see its own walk)."""
    rm, _, _ = _survey(np.random.default_rng(6), ys=(5.0, 14.0, 23.0))

    def everywhere(xy, z):
        return np.ones(len(xy), bool)
    pos = PowedKnn(PowedKnnParams(cov_calibration=False, field_weight=0.05, field_reach_m=12.0),
                   walkable=everywhere).fit(rm)
    keep = np.array(rm.source) != "walk1"
    off = pos._off_survey(keep)
    d = np.linalg.norm(pos._grid_pos[:, None] - rm.positions[keep][None], axis=2).min(axis=1)
    np.testing.assert_array_equal(off[pos._n_map:], d > pos.params.smooth_reach_m + 1e-9)
    assert not off[:pos._n_map].any()
    near_walk1 = (np.abs(pos._grid_pos[:, 1] - 14.0) <= 1.0) & (pos._grid_pos[:, 0] >= 1.0) & (pos._grid_pos[:, 0] <= 59.0)
    assert near_walk1.sum() > 50 and off[pos._n_map:][near_walk1].all()
    assert not pos._off[pos._n_map:][near_walk1].any()
