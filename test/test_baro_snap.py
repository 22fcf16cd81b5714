"""The floor snapped to the barometric height during a transit (indoor_loc.baro.snap via FloorTrack):
on the new floor when the walker arrives (stairs, a lift over two storeys), not on a door's pressure
step, and the smoothed floor change dated to the middle of the height ramp."""
from __future__ import annotations

import numpy as np
import pytest

from indoor_loc.baro.snap import FloorSnapParams
from indoor_loc.baro.track import FloorTrack
from indoor_loc.errors import ConfigError
from indoor_loc.sim.baro import BaroSimParams, simulate_pressure

S = 10**9
FLOORS = [0.0, 3.5, 7.0]


def _track_run(knots_t, knots_h, duration, seed, *, snap=None, start_z=3.5, **kw):
    """Feed a FloorTrack one fix (the start floor) and the simulated pressure of the height profile;
    returns (sample stamps (K,) ns, z() after each sample (K,), the track)."""
    rng = np.random.default_rng(seed)
    d = simulate_pressure(np.array(knots_t, float), np.array(knots_h, float) + 1.1, duration, BaroSimParams(**kw), rng)
    tr = FloorTrack(floors_m=FLOORS, snap=snap)
    tr.fix(0, start_z, 0.0)
    z = np.empty(len(d.t_ns))
    for k, (t, p) in enumerate(zip(d.t_ns.tolist(), d.pressure_pa.tolist())):
        tr.baro(int(t), p)
        z[k] = tr.z()[0]
    return d.t_ns, z, tr


def _z_at(t_ns, z, t_s):
    return z[np.searchsorted(t_ns, int(t_s * S), side="right") - 1]


@pytest.mark.parametrize("seed", range(3))
def test_on_the_new_floor_when_arriving_by_stairs_and_by_a_two_storey_lift(seed):
    # floor 1; stairs up to floor 2 in 10 s (arrive 70 s); the lift down two storeys in 7 s (arrive 137 s)
    t_ns, z, tr = _track_run([0, 60, 70, 130, 137, 200], [3.5, 3.5, 7.0, 7.0, 0.0, 0.0], 200.0, seed,
                             spikes_per_min=0)
    assert _z_at(t_ns, z, 59.0) == 3.5
    assert _z_at(t_ns, z, 70.0) == 7.0 and _z_at(t_ns, z, 129.0) == 7.0
    assert _z_at(t_ns, z, 137.0) == 0.0 and _z_at(t_ns, z, 199.0) == 0.0
    assert 3.5 in z[(t_ns > 130 * S) & (t_ns < 137 * S)]            # through floor 1 on the way
    assert tr.detector.s.changes == 2 and tr.filter.floor == 0
    # without the snap the floor waits for the detector's report (hold_s after arrival)
    t_ns, z, _ = _track_run([0, 60, 70, 130, 137, 200], [3.5, 3.5, 7.0, 7.0, 0.0, 0.0], 200.0, seed,
                            spikes_per_min=0, snap=FloorSnapParams(enabled=False))
    assert _z_at(t_ns, z, 137.0) == 7.0


def _flips(z):
    return int(np.count_nonzero(np.diff(z) != 0))


def test_door_spikes_rarely_snap():
    # half an hour on floor 1 with a door every minute (twice the simulator's rate) moving the pressure
    # by 0.15-0.25 hPa (1.2-2.1 m, the simulator's strongest; with the noise and overlapping doors, at
    # times past the snapping height) for 0.5-3 s: at most one brief snap per half hour and seed, no
    # floor change
    kw = dict(spikes_per_min=1.0, spike_hpa=(0.15, 0.25), spike_s=(0.5, 3.0))
    flips = 0
    for seed in range(2):
        t_ns, z, tr = _track_run([0, 1800], [3.5, 3.5], 1800.0, seed, **kw)
        flips += _flips(z)
        assert tr.detector.s.changes == 0 and tr.filter.floor == 1 and z[-1] == 3.5
    assert flips <= 4
    # a snap at the midpoint between floors (no hysteresis) takes many more of them
    _, z, _ = _track_run([0, 1800], [3.5, 3.5], 1800.0, 0, **kw, snap=FloorSnapParams(hysteresis=0.0))
    assert _flips(z) >= 3 * max(flips, 1)


def test_smoothed_floor_change_is_dated_to_the_middle_of_the_ramp():
    # the lift: up one storey in 3.5 s, arriving at 63.5 s, reported about 4 s later
    t_ns, _, tr = _track_run([0, 60, 63.5, 140], [3.5, 3.5, 7.0, 7.0], 140.0, 1, spikes_per_min=0)
    (ev,) = tr.events
    assert ev.detect_ns > 66 * S
    zs = tr.z_at(np.array([55, 61, 63, 65, 100]) * S)
    assert zs.tolist() == [3.5, 3.5, 7.0, 7.0, 7.0]


def test_bad_snap_params_refused():
    with pytest.raises(ConfigError, match="hysteresis"):
        FloorSnapParams(hysteresis=0.6).validate()
    with pytest.raises(ConfigError, match="max_vertical_speed_mps"):
        FloorSnapParams(max_vertical_speed_mps=0.0).validate()


def test_the_newest_smoothed_pose_takes_the_snapped_floor_during_a_transit():
    # the lift from floor 1 to floor 2 (arriving at 63.5 s); before the detector reports it, a pose
    # stamped after the snap is on floor 2 in z_at (the back-end's newest pose) as in z()
    rng = np.random.default_rng(2)
    d = simulate_pressure(np.array([0, 60, 63.5, 140.0]), np.array([3.5, 3.5, 7.0, 7.0]) + 1.1, 140.0,
                          BaroSimParams(spikes_per_min=0), rng)
    tr = FloorTrack(floors_m=FLOORS)
    tr.fix(0, 3.5, 0.0)
    for t, p in zip(d.t_ns.tolist(), d.pressure_pa.tolist()):
        tr.baro(int(t), p)
        if t >= 64 * S:
            break
    assert tr.detector.in_transit and not tr.events and tr.z()[0] == 7.0
    assert tr.z_at(np.array([50 * S, 64 * S])).tolist() == [3.5, 7.0]


@pytest.mark.parametrize("seed", range(3))
def test_a_second_ride_soon_after_the_first_snaps_from_the_new_floor(seed):
    # the lift from floor 0 to 1 (arrive 63.5 s), 9 s out and back in, then on to floor 2 (arrive
    # 76 s): the first change is reported during the stop; the second ride's snap measures from the
    # new floor's height (it used to start from a base still following the old floor's, metres low)
    t_ns, z, tr = _track_run([0, 60, 63.5, 72.5, 76, 140], [0, 0, 3.5, 3.5, 7.0, 7.0], 140.0, seed,
                             start_z=0.0, spikes_per_min=0)
    assert _z_at(t_ns, z, 63.5) == 3.5 and _z_at(t_ns, z, 72.0) == 3.5
    assert _z_at(t_ns, z, 76.3) == 7.0 and _z_at(t_ns, z, 139.0) == 7.0
    assert tr.detector.s.changes == 2


def test_stairs_with_a_pause_snap_on_arrival():
    # stairs from floor 0: 2.1 m up, 7 s on a landing (the detector ends its transit as a small level
    # shift: 2.1 m < min_change_m), the last 1.4 m in 2.5 s (arrive 73.5 s; within 0.3 m of the floor
    # from 73 s). The snap is not over at the shift: it snaps at 0.7 storey on the last ramp (it used
    # to wait for a new transit 1 m above the landing: after the walker arrived). A noise-free
    # barometer, so the times are exact.
    quiet = dict(spikes_per_min=0, noise_hpa=0.0, quantum_hpa=0.0, drift_hpa_per_h=0.0, wave_hpa=0.0)
    t_ns, z, tr = _track_run([0, 60, 64, 71, 73.5, 140], [0, 0, 2.1, 2.1, 3.5, 3.5], 140.0, 0, start_z=0.0,
                             **quiet)
    assert tr.detector.s.level_shifts == 1 and tr.detector.s.changes == 1
    assert _z_at(t_ns, z, 70.9) == 0.0
    assert _z_at(t_ns, z, 73.0) == 3.5 and _z_at(t_ns, z, 139.0) == 3.5
