"""Map mismatch: the residual against an obviously-correct version, the map's own leave-one-out
residuals, online == batch, and wifi_fix_node warning when its scans stop fitting its map (APs moved
500 m) but not over whole simulated walks with the right map."""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from indoor_loc.errors import ConfigError
from indoor_loc.params import params_from_dict
from indoor_loc.pipeline.wifi_fix_stage import WifiFixParams, WifiFixStage
from indoor_loc.sim.building import sample_building
from indoor_loc.sim.rf import RssField, read_rss
from indoor_loc.sim.scenario import SimConfig, simulate
from indoor_loc.wifi.map_check import (MapCheck, MapCheckParams, MapCheckState, MapIndex, WindowStats, judge,
                                       map_reference, match_ratio, residual_limit, verdicts)
from indoor_loc.wifi.radiomap import add_fingerprints, empty_radiomap
from indoor_loc.wifi.types import RadioMap, WifiScan
from msg_adapters.diagnostics import diagnostics_from_msg, stage_diagnostics
from msg_adapters.wifi_scan import scan_to_msg

B = [f"02:00:00:00:00:{i:02x}" for i in range(8)]


def _scan(bssids, rssi, stamp_ns: int = 1) -> WifiScan:
    return WifiScan(stamp_ns, tuple(bssids), np.asarray(rssi, float), np.full(len(bssids), 2412.0))


def _random_map(rng: np.random.Generator, m: int = 40, a: int = 8) -> RadioMap:
    rss = rng.uniform(-95.0, -40.0, (m, a))
    rss[rng.random((m, a)) < 0.35] = np.nan
    return RadioMap(positions=rng.uniform(0, 30, (m, 2)), bssids=B[:a], rssi_dbm=rss, freq_mhz=np.full(a, 2412.0))


def _slow_residual(rm: RadioMap, scan: WifiScan, floor_dbm: float = -100.0, beta: float = math.e) -> float:
    """The Sørensen distance to every fingerprint, one AP at a time, in plain Python."""
    def pw(r: float) -> float:
        return 0.0 if not r > floor_dbm else ((r - floor_dbm) / -floor_dbm) ** beta
    x = {b: pw(r) for b, r in zip(scan.bssid, scan.rssi_dbm)}
    best = 1.0
    for row in np.asarray(rm.rssi_dbm, float):
        y = {b: pw(r) for b, r in zip(rm.bssids, row) if not math.isnan(r)}
        shared = sum(min(v, y[b]) for b, v in x.items() if b in y)
        if shared > 0:
            best = min(best, 1.0 - 2.0 * shared / (sum(x.values()) + sum(y.values())))
    return best


def test_residual_matches_the_plain_sorensen_distance_to_the_nearest_fingerprint():
    rng = np.random.default_rng(3)
    rm = _random_map(rng)
    index = MapIndex(rm, MapCheckParams())
    for _ in range(60):
        n = int(rng.integers(1, 8))
        bss = list(rng.choice(B[:6] + ["aa:00:00:00:00:01", "aa:00:00:00:00:02"], n, replace=False))
        scan = _scan(bss, rng.uniform(-99.0, -35.0, n))
        assert index.residual(scan) == pytest.approx(_slow_residual(rm, scan), abs=1e-12)
    row = np.asarray(rm.rssi_dbm)[5]
    heard = ~np.isnan(row)
    assert index.residual(_scan(np.array(B)[heard], row[heard])) == pytest.approx(0.0, abs=1e-12)   # its own scan
    assert index.residual(_scan(["aa:00:00:00:00:01"], [-40.0])) == 1.0                              # nothing shared


def test_a_strong_ap_unknown_to_the_map_is_a_reading_the_map_cannot_explain():
    rm = _random_map(np.random.default_rng(4))
    index = MapIndex(rm, MapCheckParams())
    row = np.asarray(rm.rssi_dbm)[0]
    heard = ~np.isnan(row)
    base = _scan(np.array(B)[heard], row[heard])
    more = _scan(list(np.array(B)[heard]) + ["aa:00:00:00:00:09"], list(row[heard]) + [-40.0])
    assert index.residual(more) > index.residual(base) + 0.1


def _ref(rm: RadioMap, p: MapCheckParams) -> np.ndarray:
    return map_reference(rm, p).residual


def test_leave_one_out_skips_the_same_survey_point_and_the_same_walk():
    rm = _random_map(np.random.default_rng(5), m=20)
    twin = add_fingerprints(rm, np.asarray(rm.positions), [_scan(np.array(B)[~np.isnan(r)], r[~np.isnan(r)])
                                                           for r in np.asarray(rm.rssi_dbm)], "survey")
    p = MapCheckParams()
    assert np.all(_ref(twin, dataclasses.replace(p, exclude_m=0.0)) < 1e-12)   # each meets its twin
    ref = _ref(twin, p)
    assert len(ref) == twin.n_scans and np.all(ref > 0.0)
    # two walks over the same points: a fingerprint is matched against the other walk only
    walks = dataclasses.replace(twin, source=["w1"] * 20 + ["w2"] * 20,
                                positions=np.asarray(twin.positions) + np.repeat([[0.0, 0.0], [0.3, 0.0]], 20, 0))
    assert np.all(_ref(walks, dataclasses.replace(p, exclude_m=0.0)) < 1e-12)
    one_walk = dataclasses.replace(walks, source=["w1"] * 40)
    assert np.all(_ref(one_walk, dataclasses.replace(p, exclude_m=0.0)) < 1e-12)
    assert np.all(_ref(one_walk, dataclasses.replace(p, exclude_m=0.5)) > 0.0)


def test_online_updates_equal_the_batch_and_a_saved_state_continues():
    rm = _random_map(np.random.default_rng(6))
    p = MapCheckParams(window=10, min_scans=4)
    rng = np.random.default_rng(7)
    mc = MapCheck(rm, p)
    # a stretch that fits, one that does not (declined, then far), one that fits again
    res = np.concatenate([rng.uniform(0, mc.map_q, 30), rng.uniform(0, mc.map_q, 15), np.full(15, 0.99),
                          rng.uniform(0, mc.map_q, 30)])
    dec = np.concatenate([rng.random(30) < 0.2, np.ones(15, bool), np.zeros(15, bool), rng.random(30) < 0.2])
    online = []
    for r, d in zip(res, dec):
        mc.update_residual(r, d)
        online.append(mc.state.mismatch)
    assert np.array_equal(verdicts(res, dec, mc.map_q, p), online)
    assert not any(online[:30]) and all(online[40:60]) and not online[-1] and mc.state.mismatches == 1
    # save after 45 scans, restore, run the rest == run all
    first = MapCheck(rm, p)
    for r, d in zip(res[:45], dec[:45]):
        first.update_residual(r, d)
    saved = first.state.copy()
    assert np.array_equal(verdicts(res[45:], dec[45:], mc.map_q, p, saved), online[45:])
    again = MapCheck(rm, p)
    again.state = saved
    for r, d in zip(res[45:], dec[45:]):
        again.update_residual(r, d)
    assert again.state.mismatch == mc.state.mismatch and np.array_equal(again.state.residual, mc.state.residual)


def test_judge_waits_for_min_scans_and_holds_a_mismatch_until_the_scans_fit_again():
    p = MapCheckParams(min_scans=8)
    q = 0.3
    limit = residual_limit(q, p)
    assert limit == pytest.approx(0.65)
    assert not judge(False, WindowStats(7, 1.0, 1.0), q, p)              # too few scans to say
    assert judge(False, WindowStats(8, 0.75, 0.1), q, p)                 # most declined
    assert judge(False, WindowStats(8, 0.0, limit + 0.01), q, p)         # far outside the map's own residuals
    assert not judge(False, WindowStats(8, 0.7, limit - 0.01), q, p)
    assert judge(True, WindowStats(8, 0.6, 0.1), q, p)                   # declined share not yet down
    assert judge(True, WindowStats(8, 0.0, q + 0.01), q, p)              # residual not yet back
    assert not judge(True, WindowStats(8, 0.5, q), q, p)
    assert judge(False, WindowStats(20, 0.8, math.nan), math.nan, p)     # no reference: declines still count
    assert not judge(False, WindowStats(20, 0.0, 0.99), math.nan, p)


@pytest.mark.parametrize("bad, match", [({"window": 0}, "window: expected >= 1"),
                                        ({"min_scans": 30}, r"min_scans: expected in \[1, window = 20\]"),
                                        ({"clear_declined_share": 0.9}, "clear_declined_share"),
                                        ({"residual_margin": 1.0}, "residual_margin"),
                                        ({"window": 2.5}, "window: expected int")])
def test_bad_parameters_are_refused(bad, match):
    with pytest.raises(ConfigError, match=match):
        params_from_dict(MapCheckParams, bad)


# -- the wifi_fix stage on a simulated building -------------------------------------------------------------
@pytest.fixture(scope="module")
def sim():
    """The sample building (with its AP events: one AP moved, one switched off), 3 walkers x 300 s."""
    building = sample_building()
    run = simulate(building, SimConfig(walkers=3, duration_s=300.0, seed=11))
    rm = add_fingerprints(empty_radiomap(), run.survey_xy, run.survey_scans, source="survey")
    return building, run, rm


def _moved_scans(building, run, shift_m: float, n: int) -> list[WifiScan]:
    """Scans along the walkers' routes from a field whose every AP stands ``shift_m`` further east; the
    readings a phone would get (most positions hear nothing there: those give no scan)."""
    aps = tuple(dataclasses.replace(a, xyz=(a.xyz[0] + shift_m, a.xyz[1], a.xyz[2]), move_at_s=None,
                                    move_to_xyz=None, off_at_s=None) for a in building.aps)
    fld = RssField(dataclasses.replace(building, aps=aps), run.config.rf, rng=np.random.default_rng(21))
    rng = np.random.default_rng(22)
    xyz = np.vstack([w.motion.xyz[::20] for w in run.walkers])
    floor = np.concatenate([w.motion.floor[::20] for w in run.walkers])
    val = read_rss(fld.mean_rss(xyz, floor), rng, fading_std_db=2.0, sensitivity_dbm=-90.0, slope_db=2.0)
    out = []
    for i in np.flatnonzero(np.isfinite(val).any(axis=1))[:n]:
        cols = np.flatnonzero(np.isfinite(val[i]))
        out.append(WifiScan(0, tuple(fld.bssids[j] for j in cols), val[i, cols],
                            np.array([fld.freq_mhz[j] for j in cols])))
    assert len(out) == n
    return out


def _feed(st: WifiFixStage, scans: list[WifiScan], t0_s: float) -> list[int]:
    """Process the scans one per 4 s; the diagnostics level after each."""
    levels = []
    for i, s in enumerate(scans):
        stamp = int((t0_s + 4.0 * i) * 1e9)
        st.process("wifi/scan", scan_to_msg(dataclasses.replace(s, stamp_ns=stamp)), stamp)
        status = diagnostics_from_msg(stage_diagnostics("/alice/wifi_fix_node", st, stamp))["/alice/wifi_fix_node"]
        levels.append(status.level)
    return levels


@pytest.mark.parametrize("config", [{"method": "wknn"}, {"method": "wknn", "fallback": "powed"}],
                         ids=["wknn", "wknn+powed"])
def test_scans_from_aps_moved_500_m_warn_within_min_scans_and_the_right_map_never_does(sim, config):
    building, run, rm = sim
    st = WifiFixStage(params_from_dict(WifiFixParams, config), radio_map=rm, namespace="/alice")
    walks = [s for w in run.walkers for s in w.scans]            # the three whole walks, one after the other
    assert len(walks) > 200
    levels = _feed(st, walks, 1.0)
    assert max(levels) == 0 and st.take_notices() == [], st.extra_diagnostics()
    diag = st.extra_diagnostics()
    assert diag["map_fit.state"] == "ok" and "warning" not in diag
    assert "map_fit.mismatches" not in diag and float(diag["map_fit.residual_p50"]) < float(diag["map_fit.residual_limit"])
    fixes_before = st.fixes

    # after a window of scans that fit: WARN once the moved scans are half the window (its median)
    window = st.params.map_check.window
    moved = _moved_scans(building, run, 500.0, window)
    levels = _feed(st, moved, 4.0 * len(walks) + 10.0)
    first = levels.index(1)
    assert first <= window // 2 and all(lv == 1 for lv in levels[first:]), levels   # WARN, and it stays
    notices = st.take_notices()
    assert len(notices) == 1 and "do not fit the radio map" in notices[0], notices   # said once
    diag = st.extra_diagnostics()
    assert diag["map_fit.state"] == "mismatch" and "do not fit the radio map" in diag["warning"]
    assert float(diag["map_fit.residual_p50"]) > 0.95 > float(diag["map_fit.residual_limit"])
    if "fallback" in config:        # the fallback positions nearly all of them: they are caught by their residual
        assert st.fixes - fixes_before >= 0.8 * len(moved) and float(diag["map_fit.declined_share"]) < 0.5
    else:                           # WKNN declines them: most of the window declined
        assert float(diag["map_fit.declined_share"]) > 0.7
    status = diagnostics_from_msg(stage_diagnostics("/alice/wifi_fix_node", st, 0))["/alice/wifi_fix_node"]
    assert status.message.startswith("the scans do not fit the radio map")

    # a node started on the wrong map says it at its min_scans-th scan
    fresh = WifiFixStage(params_from_dict(WifiFixParams, config), radio_map=rm, namespace="/alice")
    levels = _feed(fresh, moved, 1.0)
    assert levels.index(1) == fresh.params.map_check.min_scans - 1 and len(fresh.take_notices()) == 1, levels

    # scans that fit again: back to OK without a word
    levels = _feed(st, run.walkers[0].scans[:40], 4.0 * (len(walks) + 20) + 10.0)
    assert levels[-1] == 0 and st.extra_diagnostics()["map_fit.state"] == "ok" and st.take_notices() == []
    assert st.extra_diagnostics()["map_fit.mismatches"] == "1"


def test_a_new_map_gets_its_own_reference_and_the_check_can_be_off(sim):
    _, run, rm = sim
    st = WifiFixStage(params_from_dict(WifiFixParams, {"method": "wknn"}), radio_map=rm)
    first = st.map_check
    assert first is not None and first.radio_map is rm
    half = dataclasses.replace(rm, positions=np.asarray(rm.positions)[::2], rssi_dbm=np.asarray(rm.rssi_dbm)[::2],
                               scan_ids=None, stamps_ns=None, source=[], z_m=None)
    st.set_radio_map(half)
    _feed(st, run.walkers[0].scans[:3], 1.0)
    assert st.map_check is not first and st.map_check.radio_map is half
    assert len(st.map_check.reference.residual) == half.n_scans
    off = WifiFixStage(params_from_dict(WifiFixParams, {"method": "wknn", "map_check": {"enabled": False}}),
                       radio_map=rm)
    _feed(off, run.walkers[0].scans[:3], 1.0)
    assert off.map_check is None and not any(k.startswith("map_fit.") for k in off.extra_diagnostics())


def test_map_check_state_round_trips():
    st = MapCheckState.empty(5)
    st.declined[2] = True
    c = st.copy()
    c.declined[0] = True
    assert not st.declined[0] and c.declined[2] and c.count == st.count


def test_a_map_whose_positions_are_shuffled_is_suspect_from_the_start(sim):
    """Fingerprints paired with the wrong positions fit every scan: the map's own leave-one-out says it."""
    _, run, rm = sim
    right = MapCheck(rm)
    assert right.match_ratio < 0.3 and not right.map_suspect and right.describe_map() == ""
    perm = np.random.default_rng(8).permutation(rm.n_scans)
    wrong = dataclasses.replace(rm, positions=np.asarray(rm.positions)[perm], scan_ids=None, stamps_ns=None,
                                source=[], z_m=None)
    st = WifiFixStage(params_from_dict(WifiFixParams, {"method": "wknn"}), radio_map=wrong, namespace="/alice")
    assert st.map_check is not None and st.map_check.match_ratio > 0.7 and st.map_check.map_suspect
    notices = st.take_notices()
    assert len(notices) == 1 and "disagrees with itself" in notices[0], notices
    levels = _feed(st, run.walkers[0].scans[:10], 1.0)
    assert levels == [1] * 10 and st.take_notices() == []                 # a standing WARN, said once
    diag = st.extra_diagnostics()
    assert "disagrees with itself" in diag["warning"] and diag["map_fit.state"] == "ok"   # the scans do fit it
    assert float(diag["map_fit.map_match_ratio"]) > 0.7


def test_match_ratio_needs_enough_matches():
    from indoor_loc.wifi.map_check import MIN_MATCHES, Reference
    few = Reference(np.zeros(5), np.full(MIN_MATCHES - 1, 10.0), 10.0)
    assert math.isnan(match_ratio(few))
    enough = Reference(np.zeros(5), np.r_[np.full(MIN_MATCHES - 1, 2.0), 50.0], 10.0)
    assert match_ratio(enough) == pytest.approx(0.2)
