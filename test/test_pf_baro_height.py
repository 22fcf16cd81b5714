"""The barometer's evidence on the particles during a transit (issue #28): a re-initialisation
around a far fix on the barometer's floor, and the particles' heights weighed against the barometric
height while the detector has not yet ended the transit."""
from __future__ import annotations

import numpy as np
import pytest

from indoor_loc.baro.detector import FloorChangeDetector
from indoor_loc.baro.height import pressure_at_height_pa
from indoor_loc.graph.tll import TransitionParams, transition_table
from indoor_loc.pf.filter import PfParams
from indoor_loc.pf.floors import PfFloorParams, baro_height, baro_height_sigma
from indoor_loc.pf.tracker import GraphTracker
from indoor_loc.sim.building import building_graph, make_tower_building

B = make_tower_building()
G = building_graph(B)
TR = transition_table(G, TransitionParams())
S = 10**9
P0 = 101325.0


def _at_the_lift_on_floor_1(seed: int = 0, **floor_kw) -> GraphTracker:
    """A walker who has just ridden the lift to floor 1 (x = -1.5 m, y = 10 m): the cloud there, the
    barometer reporting."""
    tr = GraphTracker(G, TR, PfParams(n_particles=600), rng=np.random.default_rng(seed),
                      floors=PfFloorParams(**floor_kw))
    tr.pf.init_gaussian(np.array([-1.0, 10.0]), np.eye(2) * 0.5, np.random.default_rng(seed), floor=1, inflate=False)
    for k in range(20):                               # 2 s of pressure at a standstill
        tr.baro(k * S // 10, float(pressure_at_height_pa(3.5, P0)))
    assert tr.pf.estimate_floor()[0] == 1
    return tr


def test_a_re_initialisation_around_a_far_fix_goes_on_the_barometers_floor():
    # A fix 10 m from every particle re-initialises half of them around it (the filter has
    # "diverged"); the fix says floor 0 (WiFi lags a lift ride), the barometer is reporting. The
    # redrawn particles go on the floor the barometer vouches for, as sensor-resetting ones do;
    # before, they went on the fix's floor and pf/pose showed floor 0 for ~2-4 s after the ride.
    for seed in range(3):
        tr = _at_the_lift_on_floor_1(seed)
        n_reinit = tr.pf.n_reinit
        est = tr.fix(2 * S, np.array([9.0, 10.0]), np.eye(2) * 1.0, z=0.0)
        assert tr.pf.n_reinit == n_reinit + 1               # the re-initialisation did happen
        assert est.floor == 1 and est.z == pytest.approx(3.5)
        fl = tr.pf.floors.floor_of(tr.pf.p.link, tr.pf.p.pos)
        assert (fl == 1).all()


def test_without_a_barometer_a_re_initialisation_follows_the_fixs_floor():
    tr = GraphTracker(G, TR, PfParams(n_particles=600), rng=np.random.default_rng(0))
    tr.pf.init_gaussian(np.array([-1.0, 10.0]), np.eye(2) * 0.5, np.random.default_rng(0), floor=1, inflate=False)
    tr.fix(2 * S, np.array([9.0, 10.0]), np.eye(2) * 1.0, z=0.0)
    fl = tr.pf.floors.floor_of(tr.pf.p.link, tr.pf.p.pos)
    assert (fl == 0).sum() > 200                             # the redrawn half, on the fix's floor


def _stair_link() -> int:
    """The east stairwell's flight from floor 0 to floor 1."""
    for link in np.flatnonzero(G.link_vertical):
        fa, fb = G.node_floor[G.link_nodes[link]]
        kinds = {B.node_kind[int(n)] for n in G.link_nodes[link]}
        if {int(fa), int(fb)} == {0, 1} and kinds == {"stairs"}:
            return int(link)
    raise AssertionError("no flight 0-1")


def test_particles_heights_are_weighed_against_the_barometric_height():
    tr = GraphTracker(G, TR, PfParams(n_particles=400), rng=np.random.default_rng(0))
    p, fg = tr.pf, tr.pf.floors
    tr.pf.init_gaussian(np.array([41.0, 10.0]), np.eye(2) * 0.5, np.random.default_rng(0), floor=1, inflate=False)
    link = _stair_link()
    n = len(p.p.link)
    p.p.link[: n // 2] = link                                   # half on the flight, at 0.2 .. 0.9 of its length
    p.p.pos[: n // 2] = np.linspace(0.2, 0.9, n // 2) * G.link_len[link]
    z = fg.z_of(p.p.link, p.p.pos)
    w0 = p.p.weights.copy()
    log_l = baro_height(p, 3.5, 0.4, PfFloorParams())            # the walker is up: at the top
    w = p.p.weights
    top = np.abs(z - 3.5) < 0.1
    assert top.any() and (w[top] / w0[top]).min() > 10 * (w[~top] / w0[~top]).max() * 0.05
    # weights fall with the height's distance, never below baro_floor_wrong (the level gate's)
    order = np.argsort(np.abs(z - 3.5))
    assert np.all(np.diff(log_l[order]) <= 1e-12)
    assert log_l.min() == pytest.approx(np.log(PfFloorParams().baro_floor_wrong))


def test_the_height_sigma_comes_from_the_detectors_noise_lag_and_drift():
    det = FloorChangeDetector()
    for k in range(30):                                           # 3 s level at 10 Hz
        det.update(k * S // 10, float(pressure_at_height_pa(0.0, P0)))
    still = baro_height_sigma(det, 0)
    n = len(det.s.raw)
    assert still == pytest.approx(np.hypot(1.25 * det.params.noise_m / np.sqrt(n),
                                           det.params.drift_m_per_s * 2.9), rel=1e-6)
    for k in range(30, 60):                                       # climbing at 0.5 m/s
        det.update(k * S // 10, float(pressure_at_height_pa(0.5 * (k - 30) / 10, P0)))
    assert baro_height_sigma(det, 3 * S) > 0.5 * det.params.smooth_s * 0.4    # the median's lag


def test_particles_walking_back_down_the_stairs_lose_weight_before_the_change_is_reported():
    # Carol arrives upstairs; the detector reports the change ~4 s later (hold_s). Particles that
    # took the flight back down meanwhile are weighed by their heights against the barometer's.
    def run(on: bool) -> float:
        tr = GraphTracker(G, TR, PfParams(n_particles=400), rng=np.random.default_rng(1),
                          floors=PfFloorParams(baro_height=on))
        h = np.r_[np.zeros(100), np.linspace(0, 3.5, 80), np.full(15, 3.5)]    # 10 s level, 8 s up, 1.5 s at the top
        tr.pf.init_gaussian(np.array([41.0, 10.0]), np.eye(2) * 0.5, np.random.default_rng(1), floor=0, inflate=False)
        tr.fix(0, np.array([41.0, 10.0]), np.eye(2) * 0.5, z=0.0)          # where the walk starts
        link = _stair_link()
        for k, hk in enumerate(h[1:], start=1):
            if k == 180:                                          # at the top: half the cloud walked back down
                p = tr.pf.p
                n = len(p.link)
                p.link[:], p.pos[: n // 2] = link, 0.3 * G.link_len[link]
                top_end = 1 if G.node_floor[G.link_nodes[link, 1]] == 1 else 0
                p.pos[n // 2:] = G.link_len[link] if top_end else 0.0
            tr.baro(k * S // 10, float(pressure_at_height_pa(hk + 1.1, P0)))
        assert tr.baro_det.in_transit                              # not yet reported
        p = tr.pf.p
        return float(p.weights[tr.pf.floors.floor_of(p.link, p.pos) == 1].sum())
    assert run(True) > 0.9 and run(False) < 0.6


def _heights_seen(h: np.ndarray) -> list:
    """FloorTrack fed heights ``h`` (m, 10 Hz) from floor 0: the snap's height_z at each sample."""
    from indoor_loc.baro.track import FloorTrack
    ft = FloorTrack(floors_m=[0.0, 3.5, 7.0])
    ft.fix(0, 0.0, 0.01)
    out = []
    for k, hk in enumerate(h):
        ft.baro(S + k * S // 10, float(pressure_at_height_pa(hk + 1.1, P0)))
        out.append(ft.snap.height_z)
    return out


def test_a_door_spike_gives_no_height_a_walker_on_the_stairs_does():
    # a door: the pressure steps by 1.6 m of height (0.19 hPa) within 0.3 s, holds 3 s, comes back
    door = np.r_[np.zeros(100), np.linspace(0, 1.6, 4), np.full(30, 1.6), np.linspace(1.6, 0, 4), np.zeros(50)]
    assert all(z is None for z in _heights_seen(door))
    # stairs: 0.4 m/s up; the height is there once the floor is snapped (0.7 storey), to the top
    stairs = np.r_[np.zeros(100), np.linspace(0, 3.5, 88), np.full(10, 3.5)]
    seen = _heights_seen(stairs)
    first = next(k for k, z in enumerate(seen) if z is not None)
    assert 100 + 55 < first < 100 + 88                         # (2.45 m at 0.4 m/s: 6.1 s, plus the median)
    assert all(z is not None for z in seen[first:])
    assert seen[-1] == pytest.approx(3.5, abs=0.3)
