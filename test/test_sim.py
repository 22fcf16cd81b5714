"""Simulator: building + graph validation, exact IMU synthesis, cadence, RSS model, seeds, bags."""
from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from indoor_loc.errors import MapError
from indoor_loc.imu.stepometer import stepometer_batch, total_steps
from indoor_loc.sim.building import (building_from_geojson, building_graph, building_to_geojson, make_sample_building,
                                     sample_building, sample_building_path, validate_building)
from indoor_loc.sim.rf import RfParams, RssField, count_crossings
from indoor_loc.sim.scenario import SimConfig, simulate
from indoor_loc.sim.walker import (GRAVITY_M_S2, ImuParams, WalkerParams, ideal_imu, make_plan, sample_motion,
                                   synthesize_imu)


@pytest.fixture(scope="module")
def building():
    return sample_building()


# ------------------------------------------------------------------------------------- building
def test_shipped_building_is_the_generated_one_and_small(building):
    assert sample_building_path().stat().st_size < 300_000
    gen = make_sample_building()
    assert json.loads(sample_building_path().read_text()) == json.loads(json.dumps(building_to_geojson(gen)))
    assert building.n_floors == 2 and len(building.aps) == 7
    assert {"corridor", "junction", "door", "room", "stairs"} <= set(building.node_kind)


def test_sample_graph_passes_map_validation_and_reaches_both_floors(building, tmp_path):
    validate_building(building)
    from indoor_loc.graph import load_graph, save_graph
    g = load_graph(save_graph(building_graph(building), tmp_path / "graph.yaml"))   # the map tools' checks
    assert g.n_nodes == len(building.node_xyz) and g.n_links == len(building.link_nodes)
    assert int(g.link_vertical.sum()) == 1 and len(g.floors) == 2 and len(g.rooms) == 20
    stairs = [i for i, k in enumerate(building.node_kind) if k == "stairs"]
    path = building.shortest_path(0, int(np.flatnonzero(building.node_floor == 1)[0]))
    assert any(n in stairs for n in path)
    assert building.node_floor[path[0]] == 0 and building.node_floor[path[-1]] == 1


@pytest.mark.parametrize("breakage, match", [
    (lambda d: d["features"].append({"type": "Feature", "geometry": {"type": "LineString", "coordinates": [[0, 0], [1, 1]]},
                                     "properties": {"kind": "link", "nodes": [3, 3], "floor": 0}}), "self-loop"),
    (lambda d: d["features"].__setitem__(slice(None), [f for f in d["features"]
                                                       if not (f["properties"]["kind"] == "link"
                                                               and f["properties"]["nodes"] == [2, 3])]),
     "disconnected"),
    (lambda d: d["indoor_loc"].__setitem__("version", 99), "v1"),
    (lambda d: d["features"][0]["properties"].__setitem__("kind", "door_handle"), "unknown kind"),
])
def test_bad_building_files_are_refused(building, breakage, match):
    data = building_to_geojson(building)
    # the link 2-3 exists (a door -> room link) so removing it disconnects a room
    assert any(f["properties"].get("nodes") == [2, 3] for f in data["features"])
    breakage(data)
    with pytest.raises(MapError, match=match):
        building_from_geojson(data)


def test_floor_plan_image_draws_the_walls_where_they_are(building, tmp_path):
    import yaml
    from PIL import Image

    from indoor_loc.sim.building import floor_plan_image, save_floor_plans
    img, (x0, y0) = floor_plan_image(building, 0, resolution_m=0.05)
    h = img.shape[0]

    def px(x, y):
        return img[int(round(h - 1 - (y - y0) / 0.05)), int(round((x - x0) / 0.05))]
    assert px(20.0, 0.0) == 0 and px(8.0, 4.0) == 0          # outer wall, a room partition
    assert px(20.0, 4.0) == 254 and px(20.0, 10.0) == 254     # a room, the corridor
    assert px(12.0, 8.8) == 254                               # the door gap in the corridor wall
    meta = yaml.safe_load(save_floor_plans(building, tmp_path)[1].read_text())
    assert meta["resolution"] == 0.05 and meta["origin"][:2] == [round(x0, 6), round(y0, 6)]
    assert Image.open(tmp_path / meta["image"]).size == (img.shape[1], img.shape[0])
    with pytest.raises(MapError, match="no floor 2"):
        floor_plan_image(building, 2)


# ------------------------------------------------------------------------------------------ IMU
def _walk(building, seed, **kw):
    rng = np.random.default_rng(seed)
    wp = WalkerParams(**kw)
    plan = make_plan(building, wp, 60.0, rng, floors=(0,))
    return wp, sample_motion(plan, wp, 100.0, 60.0, building.floor_z), rng


def test_noise_free_imu_integrates_back_to_the_true_path(building):
    """Strapdown (gyro -> attitude, specific force -> world, minus gravity, twice integrated) of the
    noise-free IMU stays within 1 mm of the true device path over 60 s with stops and U-turns."""
    _, m, _ = _walk(building, 5, uturn_prob=0.5)
    acc, gyro = ideal_imu(m)
    dt = 0.01
    rot, p = m.rot[0], m.xyz[0].copy()
    v = (m.xyz[1] - m.xyz[0]) / dt
    err = 0.0
    for i in range(len(acc) - 1):
        if i > 0:
            v = v + (rot.apply(acc[i]) - [0.0, 0.0, GRAVITY_M_S2]) * dt
        p = p + v * dt
        rot = rot * Rotation.from_rotvec(gyro[i] * dt)
        err = max(err, float(np.linalg.norm(p - m.xyz[i + 1])))
    assert err < 1e-3
    path_len = np.sum(np.linalg.norm(np.diff(m.body_xyz[:, :2], axis=0), axis=1))
    assert path_len > 30.0                       # it did walk
    # at rest the accelerometer reads gravity along the device's up axis
    still = np.flatnonzero(m.walk < 1e-6)
    assert len(still) and np.allclose(np.linalg.norm(acc[still], axis=1), GRAVITY_M_S2, atol=1e-2)


@pytest.mark.parametrize("cadence", [1.5, 1.8, 2.1])
def test_stepometer_counts_the_simulated_steps(building, cadence):
    """Continuous walking (no stops): the FFT stepometer on the noisy IMU counts the true steps
    within 2 % and finds the given cadence within 2 %."""
    wp, m, rng = _walk(building, 3, cadence_hz=cadence, uturn_prob=0.0, stop_s=(0.0, 0.01),
                        start_still_s=(0.0, 0.01))
    imu = synthesize_imu(m, building, ImuParams(), rng)
    hops = stepometer_batch(imu.t_ns, imu.acc)
    true_steps = m.steps[-1]
    assert abs(total_steps(hops) - true_steps) / true_steps < 0.02
    f = np.median([h.freq_hz for h in hops if h.walking])
    assert abs(f - cadence) / cadence < 0.02


def test_magnetometer_is_the_earth_field_away_from_disturbances(building):
    _, m, rng = _walk(building, 9)
    p = ImuParams(mag_noise_t=0.0, mag_bias_std_t=0.0)
    imu = synthesize_imu(m, building, p, rng)
    assert np.median(np.diff(imu.mag_t_ns)) == pytest.approx(1e9 / p.mag_rate_hz, abs=1)
    norm = np.linalg.norm(imu.mag_t, axis=1)
    # most of the walk is far from the four disturbances: the norm is the Earth field there
    assert np.median(norm) == pytest.approx(p.earth_field_t, rel=1e-3)


# ------------------------------------------------------------------------------------------ RSS
def test_rss_follows_the_log_distance_wall_model(building):
    rf = RfParams(shadow_std_db=0.0, bssid_offset_std_db=0.0)
    fld = RssField(building, rf, rng=np.random.default_rng(0))
    j = fld.bssids.index(building.aps[5].bssids[0])      # F1-AP3: 2.4 GHz, at the east end of floor 1
    ap = np.array(building.aps[5].xyz)
    # along the corridor (line of sight, same floor): exactly P1 - 10 n log10 d
    xs = np.linspace(2.0, 38.0, 10)
    rx = np.column_stack([xs, np.full(10, 10.0), np.full(10, ap[2])])
    got = fld.mean_rss(rx, np.ones(10, int))[:, j]
    d = np.linalg.norm(rx - ap, axis=1)
    assert np.allclose(got, rf.p1_24_dbm - 10 * rf.n_24 * np.log10(d), atol=1e-9)
    # one floor down: minus the floor attenuation
    got0 = fld.mean_rss(rx - [0, 0, 3.5], np.zeros(10, int))[:, j]
    d0 = np.linalg.norm(rx - [0, 0, 3.5] - ap, axis=1)
    assert np.allclose(got0, rf.p1_24_dbm - 10 * rf.n_24 * np.log10(d0) - rf.floor_db, atol=1e-9)
    # inside a room across one wall from the corridor: one wall's attenuation more
    room = np.array([[20.0, 4.0, ap[2]]])
    w = count_crossings(room[:, :2], ap[None, :2], building.walls[building.wall_floor == 1])[0]
    assert w >= 1
    expect = rf.p1_24_dbm - 10 * rf.n_24 * np.log10(np.linalg.norm(room[0] - ap)) - w * rf.wall_24_db
    assert fld.mean_rss(room, [1])[0, j] == pytest.approx(expect)


def test_shadowing_has_the_stated_spread_and_correlation(building):
    fld = RssField(building, RfParams(), rng=np.random.default_rng(1))
    rng = np.random.default_rng(2)
    xy = rng.uniform([0, 0], [40, 20], (4000, 2))
    s = fld.shadowing(xy)
    assert np.std(s) == pytest.approx(RfParams().shadow_std_db, rel=0.25)
    near = fld.shadowing(xy + [0.2, 0.0])
    far = fld.shadowing(xy + [15.0, 0.0])
    r_near = np.corrcoef(s.ravel(), near.ravel())[0, 1]
    r_far = np.corrcoef(s.ravel(), far.ravel())[0, 1]
    assert r_near > 0.95 and abs(r_far) < 0.2


def test_ap_events_switch_off_and_move(building):
    run = simulate(building, SimConfig(walkers=2, duration_s=90.0, seed=4))
    off = set(building.aps[2].bssids)          # F0-AP3 off at 60 s
    for w in run.walkers:
        for s in w.scans:
            if s.stamp_ns * 1e-9 - 2.0 > building.aps[2].off_at_s:   # every reading after the switch-off
                assert not off & set(s.bssid)
    fld = run.field
    moved = [fld.bssids.index(b) for b in building.aps[4].bssids]
    before = fld.mean_rss([[28.0, 16.0, 4.6]], [1], 0.0)[0, moved]
    after = fld.mean_rss([[28.0, 16.0, 4.6]], [1], 50.0)[0, moved]
    assert np.all(after > before + 5.0)        # it moved into this room


# ------------------------------------------------------------------------------------ scenario
def test_same_seed_same_run_other_seed_other_run(building):
    cfg = SimConfig(walkers=2, duration_s=30.0, seed=11)
    a, b = simulate(building, cfg), simulate(building, cfg)
    c = simulate(building, dataclasses.replace(cfg, seed=12))
    for wa, wb in zip(a.walkers, b.walkers):
        assert np.array_equal(wa.imu.acc, wb.imu.acc) and np.array_equal(wa.imu.mag_t, wb.imu.mag_t)
        assert [s.bssid for s in wa.scans] == [s.bssid for s in wb.scans]
        assert all(np.array_equal(x.rssi_dbm, y.rssi_dbm) for x, y in zip(wa.scans, wb.scans))
    assert not np.array_equal(a.walkers[0].imu.acc, c.walkers[0].imu.acc)


def test_scans_are_periodic_with_latency_and_miss_weak_aps(building):
    run = simulate(building, SimConfig(walkers=1, duration_s=60.0, seed=3))
    w = run.walkers[0]
    t = np.array([s.stamp_ns for s in w.scans]) * 1e-9
    assert np.all(np.abs(np.diff(t) - 4.0) <= 0.5 + 1e-9)
    ages = np.concatenate([s.age_ms for s in w.scans])
    assert ages.min() >= 0 and ages.max() <= 2000 and ages.max() > 1000
    counts = [len(s) for s in w.scans]
    assert max(counts) < len(run.field.bssids)            # never every BSSID: weak ones are missed
    assert all(np.all(s.rssi_dbm <= -1) and np.all(s.rssi_dbm >= -119) for s in w.scans)
    # multi-BSSID: several BSSIDs of one radio heard together
    heard = set(w.scans[0].bssid)
    assert any(sum(b in heard for b in ap.bssids) >= 2 for ap in building.aps)


# ------------------------------------------------------------------------------------ end to end
def test_sim_core_is_free_of_ros():
    import ast
    from pathlib import Path

    import indoor_loc.sim as sim
    bad = []
    for name in ("building", "rf", "walker", "scenario"):
        tree = ast.parse((Path(sim.__file__).parent / f"{name}.py").read_text())
        for node in ast.walk(tree):
            mods = [a.name for a in node.names] if isinstance(node, ast.Import) else \
                [node.module] if isinstance(node, ast.ImportFrom) and node.module else []
            bad += [f"{name}: {m}" for m in mods if m.split(".")[0] == "rclpy" or m.split(".")[0].endswith("_msgs")
                    or m.startswith(("indoor_loc.bag", "msg_adapters", "indoor_loc.nodes"))]
    assert not bad


def test_written_run_replays_through_the_nodes_with_truth(tmp_path):
    """``indoor-loc sim`` output drives ``indoor-loc run`` unedited (params.yaml, radio map), and the
    WiFi fixes land near the truth (the survey is of the same building)."""
    from indoor_loc.bag import bag_topics
    from indoor_loc.commands.eval import evaluate, trajectories_from_bags, truth_from_import
    from indoor_loc.pipeline.offline import run_offline
    from indoor_loc.commands.sim import generate
    from indoor_loc.wifi.radiomap import load_radiomap

    paths = generate(tmp_path / "sim", SimConfig(walkers=2, duration_s=40.0, seed=2), quiet=True)
    topics = bag_topics([paths["bag"]])
    for w in ("alice", "bob"):
        for rel in ("imu/data_raw", "imu/mag", "wifi/scan", "ground_truth", "ground_truth/route"):
            assert f"/{w}/{rel}" in topics
    assert topics["/alice/imu/data_raw"][1] == 4001
    assert load_radiomap(paths["radiomap"]).n_scans > 100
    run = tmp_path / "run.mcap"
    summary = run_offline([paths["bag"]], run, nodes=["imu", "wifi", "pdr_kf"], params=paths["params"])
    assert all(kv.get("rejected.total", "0") == "0" for kv in summary.per_stage.values())
    truths = truth_from_import(tmp_path / "sim")
    scores, _ = evaluate(trajectories_from_bags([run], "wifi/fix"), truths)
    assert {s.name for s in scores} >= {"alice", "bob"}
    assert scores[-1].scan_m.mean < 3.0        # time-aligned error of WKNN on the survey of this building


# ------------------------------------------------------------------------------------ failure paths
@pytest.mark.parametrize("argv, match", [
    (["--walkers", "0"], "walkers: expected 1..8"),
    (["--duration", "3"], "duration_s: expected >= 10"),
    (["--imu-hz", "5"], "rate_hz: expected 20..1000"),
    (["--scan-period", "1"], "period_s > sweep_s"),
])
def test_sim_command_refuses_bad_options(tmp_path, capsys, argv, match):
    from indoor_loc.cli import main
    assert main(["sim", str(tmp_path / "out"), *argv]) == 2
    assert match in capsys.readouterr().err
    assert not (tmp_path / "out").exists()           # nothing half-written


def test_sim_command_refuses_a_missing_or_foreign_building(tmp_path, capsys):
    from indoor_loc.cli import main
    assert main(["sim", str(tmp_path / "out"), "--building", str(tmp_path / "none.geojson")]) == 2
    assert "cannot read building file" in capsys.readouterr().err
    (tmp_path / "fc.geojson").write_text(json.dumps({"type": "FeatureCollection", "features": []}))
    assert main(["sim", str(tmp_path / "out"), "--building", str(tmp_path / "fc.geojson")]) == 2
    assert "not a building GeoJSON" in capsys.readouterr().err


def test_putmc_demo_without_the_dataset_says_where_it_looked(tmp_path, capsys):
    from indoor_loc.cli import main
    assert main(["demo", "--dataset", "putmc", "--data", str(tmp_path), "--out", str(tmp_path / "o")]) == 2
    assert "PUTMC dataset not found" in capsys.readouterr().err


def test_sim_command_refuses_an_earlier_run_unless_overwrite(tmp_path, capsys):
    from indoor_loc.cli import main
    out = tmp_path / "out"
    out.mkdir()
    (out / "params.yaml").write_text("earlier run\n")
    (out / "notes.txt").write_text("the user's own file\n")
    assert main(["sim", str(out), "--walkers", "1", "--duration", "10"]) == 2
    err = capsys.readouterr().err
    assert "params.yaml" in err and "--overwrite" in err
    assert (out / "params.yaml").read_text() == "earlier run\n"      # nothing replaced
    assert not (out / "sim.mcap").exists()
    assert main(["sim", str(out), "--walkers", "1", "--duration", "10", "--overwrite"]) == 0
    assert (out / "sim.mcap").is_file() and "earlier run" not in (out / "params.yaml").read_text()
    assert (out / "notes.txt").read_text() == "the user's own file\n"   # other files are left alone
    (tmp_path / "file").write_text("x")
    assert main(["sim", str(tmp_path / "file")]) == 2
    assert "not a directory" in capsys.readouterr().err
