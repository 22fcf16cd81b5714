"""Barometer core: pressure -> height, the floor-change detector on synthetic profiles (stairs, lift,
weather drift, door spikes) and the floor HMM."""
from __future__ import annotations

import numpy as np
import pytest

from indoor_loc.baro.detector import BaroParams, FloorChangeDetector, detect_floor_changes
from indoor_loc.baro.floors import FloorFilter
from indoor_loc.baro.height import height_change_m, metres_per_hpa, pressure_at_height_pa
from indoor_loc.errors import ConfigError
from indoor_loc.sim.baro import BaroSimParams, simulate_pressure


def test_height_of_pressure_known_values():
    # ICAO standard atmosphere: 1000 m above sea level the pressure is 898.75 hPa
    assert float(height_change_m(89875.0)) == pytest.approx(1000.0, abs=1.0)
    assert float(height_change_m(101325.0)) == 0.0
    assert metres_per_hpa() == pytest.approx(8.3, abs=0.05)
    h = np.array([-10.0, 0.0, 3.5, 17.5])
    np.testing.assert_allclose(height_change_m(pressure_at_height_pa(h, 98000.0), 98000.0), h, atol=1e-9)


def _profile(knots_t, knots_h, duration, seed, **kw):
    rng = np.random.default_rng(seed)
    return simulate_pressure(np.array(knots_t, float), np.array(knots_h, float), duration, BaroSimParams(**kw), rng)


def test_stairs_and_lift_are_floor_changes_detected_within_5_s():
    # flat, stairs up one storey in 12 s, flat, lift down two storeys in 6 s, flat
    for seed in range(5):
        d = _profile([0, 60, 72, 132, 138, 200], [0, 0, 3.5, 3.5, -3.5, -3.5], 200.0, seed, spikes_per_min=0)
        ev, _ = detect_floor_changes(d.t_ns, d.pressure_pa)
        assert len(ev) == 2, ev
        assert ev[0].dh_m == pytest.approx(3.5, abs=0.8) and ev[1].dh_m == pytest.approx(-7.0, abs=0.8)
        assert ev[0].detect_ns * 1e-9 - 72 <= 5.0 and ev[1].detect_ns * 1e-9 - 138 <= 5.0
        assert 55 <= ev[0].start_ns * 1e-9 <= 72 and 128 <= ev[1].start_ns * 1e-9 <= 138


def test_thirty_minutes_of_weather_drift_and_door_spikes_no_false_change():
    for seed, duration in ((0, 1800.0), (1, 600.0)):
        d = _profile([0, duration], [1.1, 1.1], duration, seed, spikes_per_min=1.0, drift_hpa_per_h=1.2)
        assert len(d.spikes) > duration / 120
        ev, h = detect_floor_changes(d.t_ns, d.pressure_pa)
        assert ev == []
        assert abs(h[-1]) > duration / 600   # the drift is there: metres of apparent height


def test_spikes_do_not_hide_a_lift_ride():
    d = _profile([0, 100, 104, 200], [0, 0, 3.5, 3.5], 200.0, 3, spikes_per_min=3.0)
    ev, _ = detect_floor_changes(d.t_ns, d.pressure_pa)
    assert [round(e.dh_m / 3.5) for e in ev] == [1]


def test_online_state_save_restore_equals_one_run():
    d = _profile([0, 60, 66, 120], [0, 0, 7.0, 7.0], 120.0, 1)
    ev_all, _ = detect_floor_changes(d.t_ns, d.pressure_pa)
    a = FloorChangeDetector()
    out = []
    k = len(d.t_ns) // 2
    for t, p in zip(d.t_ns[:k], d.pressure_pa[:k]):
        out += a.update(int(t), float(p))
    b = FloorChangeDetector(BaroParams(), a.state())
    for t, p in zip(d.t_ns[k:], d.pressure_pa[k:]):
        out += b.update(int(t), float(p))
    assert out == ev_all and len(out) == 1


def test_bad_params_refused():
    with pytest.raises(ConfigError, match="min_change_m"):
        BaroParams(min_change_m=0.5, band_m=1.0).validate()


def test_floor_filter_changes_on_evidence_only():
    f = FloorFilter([0.0, 3.5, 7.0])
    s = 10**9
    f.fix(1 * s, 0.0)
    assert f.floor == 0
    f.fix(3 * s, 3.5)                       # one fix on another floor: not enough
    assert f.floor == 0
    f.fix(5 * s, 3.5)
    f.fix(7 * s, 3.5)                       # consistent fixes: changed
    assert f.floor == 1
    # with a barometer: a floor change moves it at once, fixes on another floor do not
    from indoor_loc.baro.detector import FloorChange
    f.baro_sample(8 * s)
    f.baro_event(FloorChange(8 * s, 9 * s, 9 * s, 3.3))
    assert f.floor == 2
    for k in range(10, 13):                 # as many as changed it without the barometer
        f.baro_sample(k * s)
        f.fix(k * s, 0.0)
    assert f.floor == 2
    # smoothing puts the change before the fixes that confirmed it
    z = f.z_at(np.array([4 * s, 6 * s]))
    assert z[0] == 3.5


def test_a_two_storey_ride_measured_short_leaves_no_mass_on_the_start_floor():
    """A descent of two storeys over a pause, reported as one change of 6.1 m (1.74 storeys of
    3.5 m: the detector merges the flights), from floor 2 with a little mass on floor 1 (fixes during
    the pause): the floor below both, not the start floor (the old plausibility mixing kept 22 % on
    floor 2 and the next wrong fix nearly flipped the floor)."""
    from indoor_loc.baro.detector import FloorChange
    s = 10**9
    f = FloorFilter([0.0, 3.5, 7.0])
    f.fix(1 * s, 7.0)
    f.baro_sample(2 * s)
    f.p = np.array([0.0, 0.174, 0.826])
    f.baro_event(FloorChange(2 * s, 14 * s, 18 * s, -6.08))
    assert f.floor == 0 and f.p[0] > 0.85 and f.p[2] < 0.05, f.p
    # a change of no storey stays where it was (nothing explains it better than staying)
    g = FloorFilter([0.0, 3.5, 7.0])
    g.fix(1 * s, 0.0)
    g.baro_sample(2 * s)
    g.baro_event(FloorChange(2 * s, 4 * s, 8 * s, 0.9))
    assert g.floor == 0 and g.p[0] > 0.75, g.p

def test_floor_filter_learns_floors_from_fixes():
    f = FloorFilter()
    for k in range(5):
        f.fix(k * 10**9, 4.0)
    assert f.floor_z.tolist() == [4.0] and f.z() == (4.0, 0.0)
    for k in range(5, 10):
        f.fix(k * 10**9, 0.0, 0.1)
    assert f.floor_z.tolist() == [0.0, 4.0] and f.z()[0] == 0.0


def test_a_fix_arriving_after_a_barometer_change_it_precedes_is_taken_before_it():
    """The back-end takes fixes through its reorder window and the pressure at once: a fix on the
    middle floor stamped just before a two-storey change reported from it used to count as evidence
    for the floor after the change (and the next wrong fix moved the pose back up a floor). Taken in
    arrival order it now gives what stamp order gives."""
    from indoor_loc.baro.detector import FloorChange
    from indoor_loc.baro.track import FloorTrack
    s = 10**9
    ev = FloorChange(107 * s, 118 * s, 122 * s, -6.08)

    def feed(order):
        tr = FloorTrack(floors_m=[0.0, 3.5, 7.0])
        f = tr.filter
        for kind, t, v in order:
            f.baro_sample(t)
            if kind == "fix":
                tr.fix(t, v, 1.0)
            else:
                f.baro_event(v)
        return f
    fixes = [("fix", k * s, 7.0) for k in (90, 94, 98, 102)] + [("fix", k * s, 3.5) for k in (110, 114, 118, 121)]
    after = [("fix", 125 * s, 3.5), ("fix", 129 * s, 0.0)]
    ordered = feed(fixes + [("event", 122 * s, ev)] + after)
    late = feed(fixes[:-1] + [("event", 122 * s, ev)] + [fixes[-1]] + after)   # the 121 s fix after the change
    assert np.allclose(late.p, ordered.p) and late.floor == ordered.floor == 0
    assert late.late_fixes == 1
    assert [h[0] for h in late.history] == [h[0] for h in ordered.history]
    assert np.array_equal(late.z_at(np.array([124 * s, 126 * s, 130 * s])),
                          ordered.z_at(np.array([124 * s, 126 * s, 130 * s])))
