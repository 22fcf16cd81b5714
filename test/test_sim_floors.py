"""The three-floor simulated office: stairs and a lift on the graph, walkers changing floors and
riding the lift, the barometer they carry, and the multi-floor run's files."""
from __future__ import annotations

import numpy as np

from indoor_loc.baro.height import height_change_m
from indoor_loc.sim.baro import BaroSimParams
from indoor_loc.sim.building import building_graph, make_tower_building, validate_building
from indoor_loc.sim.scenario import SimConfig, simulate


def test_tower_graph_has_stairs_and_a_lift_as_vertical_links():
    b = make_tower_building()
    validate_building(b)
    g = building_graph(b)
    assert b.n_floors == 3 and [f.height_m for f in g.floors] == [0.0, 3.5, 7.0]
    vert = np.flatnonzero(g.link_vertical)
    plan = np.hypot(*(g.node_xyz[g.link_nodes[vert, 1], :2] - g.node_xyz[g.link_nodes[vert, 0], :2]).T)
    assert len(vert) == 4 and sorted(np.round(plan, 1).tolist()) == [0.0, 0.0, 6.0, 6.0]   # 2 lift, 2 flights
    assert np.all(g.link_tll_len[vert] > g.link_len[vert])          # the TLL length rule of vertical links


def test_walkers_change_floors_by_stairs_and_lift_and_carry_a_barometer():
    b = make_tower_building()
    run = simulate(b, SimConfig(walkers=1, duration_s=300.0, seed=5, change_floors=True, baro=BaroSimParams(spikes_per_min=0)))
    w = run.walkers[0]
    kinds = [b.node_kind[n] for n in w.plan.node_seq]
    assert "lift" in kinds and "stairs" in kinds
    assert np.count_nonzero(np.diff(w.motion.floor)) >= 2
    # the barometer follows the device height (relative to its first sample), within noise and drift
    assert w.baro is not None and len(w.baro.t_ns) > 2500
    h = height_change_m(w.baro.pressure_pa, w.baro.pressure_pa[:20].mean())
    true = np.interp(w.baro.t_ns, w.motion.t_ns, w.motion.xyz[:, 2]) - w.motion.xyz[0, 2]
    err = np.convolve(h - true, np.ones(50) / 50, mode="valid")
    assert np.abs(err).max() < 2.5           # weather: 1 hPa/h trend + a 0.15 hPa wave, under 0.3 hPa in 5 min
    on_floor_one = np.abs(true - 3.5) < 0.1
    assert on_floor_one.any() and abs(np.median(h[on_floor_one]) - 3.5) < 1.0


def test_without_change_floors_walkers_stay_on_the_start_floor_and_runs_are_unchanged():
    b = make_tower_building()
    a = simulate(b, SimConfig(walkers=1, duration_s=60.0, seed=2))
    c = simulate(b, SimConfig(walkers=1, duration_s=60.0, seed=2, baro=BaroSimParams()))
    assert set(a.walkers[0].motion.floor.tolist()) == {0}
    np.testing.assert_array_equal(a.walkers[0].imu.acc, c.walkers[0].imu.acc)   # the barometer draws last
    assert a.walkers[0].baro is None and c.walkers[0].baro is not None
