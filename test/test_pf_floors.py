"""The particle filter on a three-floor graph: crossing a stairwell, riding a lift with the
barometer, the fix's floor as evidence, pf/pose z."""
from __future__ import annotations

import numpy as np
import pytest

from indoor_loc.graph.tll import TransitionParams, transition_table
from indoor_loc.pf.filter import PfParams
from indoor_loc.pf.floors import FloorGeometry
from indoor_loc.pf.tracker import GraphTracker
from indoor_loc.sim.baro import BaroSimParams, simulate_pressure
from indoor_loc.sim.building import building_graph, make_tower_building

B = make_tower_building()
G = building_graph(B)
TR = transition_table(G, TransitionParams())


def _node(kind: str, floor: int, x: float) -> int:
    idx = [i for i, k in enumerate(B.node_kind) if k == kind and B.node_floor[i] == floor]
    return min(idx, key=lambda i: abs(B.node_xyz[i, 0] - x))


def _walk(nodes: list[int], speed=1.2, lift_speed=1.0, dt=0.5):
    """(t (N,), xyz (N, 3)) along the nodes' shortest paths: walking on level links and stairs,
    standing in the lift (2 s at each end)."""
    path = [nodes[0]]
    for a, b in zip(nodes[:-1], nodes[1:]):
        path += B.shortest_path(a, b)[1:]
    t, pts = [0.0], [B.node_xyz[path[0]]]
    for a, b in zip(path[:-1], path[1:]):
        pa, pb = B.node_xyz[a], B.node_xyz[b]
        lift = np.hypot(*(pb - pa)[:2]) < 0.5
        if lift:
            t.append(t[-1] + 2.0)
            pts.append(pa)
        t.append(t[-1] + (abs(pb[2] - pa[2]) / lift_speed if lift else np.linalg.norm(pb - pa) / speed))
        pts.append(pb)
        if lift:
            t.append(t[-1] + 2.0)
            pts.append(pb)
    t, pts = np.array(t), np.array(pts)
    ts = np.arange(0.0, t[-1], dt)
    return ts, np.column_stack([np.interp(ts, t, pts[:, k]) for k in range(3)])


def _run(ts, xyz, *, fix_floor: bool | str, baro: bool, seed=0, fix_every=4):
    """fix_floor: every fix carries its floor (True), only the first (\"first\": the barometer is
    relative, something has to say where it starts) or none (False)."""
    rng = np.random.default_rng(seed)
    tr = GraphTracker(G, TR, PfParams(n_particles=600, yaw_offset_sigma_rad=0.2), rng=np.random.default_rng(seed))
    s = 10**9
    pres = simulate_pressure(ts, xyz[:, 2] + 1.1, ts[-1], BaroSimParams(spikes_per_min=0), rng) if baro else None
    k_baro = 0
    out = []
    for k, (t, p) in enumerate(zip(ts, xyz)):
        stamp = int(t * s)
        while pres is not None and k_baro < len(pres.t_ns) and pres.t_ns[k_baro] <= stamp:
            tr.baro(int(pres.t_ns[k_baro]), float(pres.pressure_pa[k_baro]))
            k_baro += 1
        if k % fix_every == 0:
            z = float(p[2]) if fix_floor is True or (fix_floor == "first" and k == 0) else None
            est = tr.fix(stamp, p[:2] + rng.normal(0, 1.0, 2), np.eye(2) * 2.0,
                         z=None if z is None else float(FloorGeometry(G).fz[np.argmin(abs(FloorGeometry(G).fz - z))]))
        else:
            est = tr.odom(stamp, float(p[0]), float(p[1]))
        if est is not None:
            out.append((t, est))
    return out


def _floor_error(ts, xyz, out, settle_s=8.0):
    """Fraction of estimates (on a floor, more than settle_s after reaching it) on the wrong floor."""
    fz = np.array([f.height_m for f in G.floors])
    true = np.argmin(abs(xyz[:, 2:3] - fz[None]), axis=1)
    on_floor = np.abs(xyz[:, 2] - fz[true]) < 0.05
    last_change = np.maximum.accumulate(np.where(np.r_[True, np.diff(true) != 0], ts, 0.0))
    wrong = []
    for t, est in out:
        k = min(np.searchsorted(ts, t), len(ts) - 1)
        if on_floor[k] and t - last_change[k] > settle_s:
            wrong.append(est.floor != true[k])
    return float(np.mean(wrong)), len(wrong)


def test_pf_crosses_the_stairwell_with_the_fixes_floors():
    ts, xyz = _walk([_node("junction", 0, 20), _node("junction", 1, 28), _node("junction", 2, 12)])
    assert xyz[-1, 2] == pytest.approx(7.0)
    out = _run(ts, xyz, fix_floor=True, baro=False)
    err, n = _floor_error(ts, xyz, out)
    assert n > 50 and err < 0.05
    last = out[-1][1]
    assert last.floor == 2 and last.z == pytest.approx(7.0) and np.hypot(*(last.xy - xyz[-1, :2])) < 4.0


def test_pf_crosses_the_stairwell_with_the_barometer_and_no_fix_floors():
    ts, xyz = _walk([_node("junction", 0, 20), _node("junction", 1, 28), _node("junction", 0, 36)])
    for seed in range(3):
        assert _floor_error(ts, xyz, _run(ts, xyz, fix_floor="first", baro=True, seed=seed))[0] < 0.05


def test_pf_rides_the_lift_with_the_barometer():
    ts, xyz = _walk([_node("junction", 0, 4), _node("junction", 2, 12), _node("junction", 1, 4)])
    for seed in range(2):
        with_baro = _floor_error(ts, xyz, _run(ts, xyz, fix_floor="first", baro=True, seed=seed))[0]
        without = _floor_error(ts, xyz, _run(ts, xyz, fix_floor="first", baro=False, seed=seed))[0]
        assert with_baro < 0.05 and without > 0.3


def test_a_fix_on_another_floor_weighs_against_a_particle():
    fg = FloorGeometry(G)
    k, w = fg.fix_floor(3.5, 0.0, 0.05)
    assert k == 1 and w == 0.05
    ll = fg.fix_log_likelihood(np.array([0, 1, 2]), k, w)
    assert ll[1] > ll[0] == ll[2]
    assert fg.fix_floor(3.5, 3.0, 0.05)[1] > 0.2          # an unsure floor detector weighs less
    assert fg.fix_floor(1.75, 0.0, 0.05) is None           # between floors: not a floor


def _cloud_on_floor_0(seed: int = 0) -> GraphTracker:
    """A filter whose cloud is on floor 0 around x = 25 m, more than shaft_reach_m from the stairwell
    (x = 41 m) and the lift (x = -1.5 m)."""
    tr = GraphTracker(G, TR, PfParams(n_particles=600), rng=np.random.default_rng(seed))
    tr.pf.init_gaussian(np.array([25.0, 10.0]), np.eye(2) * 4.0, np.random.default_rng(seed), floor=0,
                        inflate=False)
    return tr


def test_a_barometer_floor_change_redraws_the_cloud_far_from_every_shaft_at_the_shafts():
    from indoor_loc.pf.floors import PfFloorParams, baro_floor_to
    tr = _cloud_on_floor_0()
    xy0 = tr.pf.xy()
    assert np.hypot(xy0[:, 0] - 41.0, xy0[:, 1] - 7.0).min() > 10.0 and np.abs(xy0[:, 0] + 1.5).min() > 10.0
    moved = baro_floor_to(tr.pf, 1, PfFloorParams())
    assert moved == len(xy0)
    k, z, _ = tr.pf.estimate_floor()
    assert k == 1 and z == pytest.approx(3.5)
    xy = tr.pf.xy()
    # each particle went to its nearest shaft; the cloud's weight follows the distance of the jump
    near_stairs = np.abs(xy[:, 0] - 41.0) < 3.0
    assert near_stairs.any() and (~near_stairs).any()
    w = tr.pf.p.weights
    assert w[near_stairs].sum() > w[~near_stairs].sum()     # the cloud at x ~ 25 m is nearer the stairs
    # off (shaft_reset_sigma_m 0, as before): the far particles stayed on floor 0
    tr = _cloud_on_floor_0()
    assert baro_floor_to(tr.pf, 1, PfFloorParams(shaft_reset_sigma_m=0.0)) == 0
    assert tr.pf.estimate_floor()[0] == 0
