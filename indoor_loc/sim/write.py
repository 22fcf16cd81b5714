"""Write a :class:`~indoor_loc.sim.scenario.SimRun` like the importers write a dataset.

``OUT/sim.mcap`` — one bag, one namespace per walker (``/alice``, ``/bob`` …), log time = header
stamp (bag time starts at :data:`~indoor_loc.sim.scenario.T0_NS`):

- ``imu/data_raw`` (sensor_msgs/Imu, frame ``<walker>/imu_link``): accelerometer + gyroscope,
  no orientation (REP 145), at ``imu.rate_hz``;
- ``imu/mag`` (sensor_msgs/MagneticField, tesla) at ``imu.mag_rate_hz`` on its own time grid;
- ``wifi/scan`` (schema wifi_scan.v1, source ``sim``, per-AP ``age_ms``);
- ``baro/pressure`` (sensor_msgs/FluidPressure, Pa, frame ``<walker>/imu_link``) when the run
  simulates a barometer (``SimConfig.baro``);
- ``ground_truth`` (nav_msgs/Path, latched, written once at the start): the device's true plan
  position and walking heading at ``truth_hz``; ``ground_truth/route`` (MarkerArray, latched):
  the graph links the walker walked, as LINE_LIST;
- ``/map/graph`` (MarkerArray, latched): the building's links, nodes and walls.

``OUT/radiomap/`` the survey (radio map format v1), ``OUT/building.geojson`` the building (walls,
rooms, APs, graph), ``OUT/graph.yaml`` its link graph in the map format of :mod:`indoor_loc.graph`,
``OUT/floor_plans/floor<k>.png|yaml`` an occupancy image per floor (nav2 map_server format),
``OUT/truth/<walker>.csv`` dense truth (stamp_ns, x, y, z, floor, heading, steps — the cumulative
true step count), ``OUT/params.yaml`` configuring every node for this run
(``/**/node_name:`` keys, so it applies in any namespace, live and offline), ``OUT/scenario.yaml``
(seed, walkers, their step length and cadence, AP events).
"""
from __future__ import annotations

import copy

import csv
from pathlib import Path

import numpy as np
import yaml

from indoor_loc.bag import BagWriter
from indoor_loc.bag.schemas import qos_dict
from indoor_loc.contract import join_ns
from indoor_loc.graph import save_graph
from indoor_loc.sim.building import Building, building_graph, save_building, save_floor_plans
from indoor_loc.sim.scenario import T0_NS, SimRun, SimWalker
from indoor_loc.wifi.radiomap import add_fingerprints, empty_radiomap, save_radiomap
from indoor_loc.sim.robot_write import robot_message, robot_node_params, robot_scenario, robot_streams

LATCHED = [qos_dict(reliability="reliable", durability="transient_local", depth=1)]
GRAPH_TOPIC = "/map/graph"
TRUTH_HZ = 5.0


#: Stream kind of a barometer (robot_write's robots use 3 and 4).
BARO = 5


def building_markers(building: Building, stamp_ns: int):
    """MarkerArray of the building: links (LINE_LIST, ns map/graph/links), nodes (SPHERE_LIST) and
    walls (LINE_LIST, ns map/walls), at the floors' heights."""
    from geometry_msgs.msg import Point
    from visualization_msgs.msg import Marker

    from msg_adapters.markers import graph_markers

    arr = graph_markers(building.node_xyz[:, :2], building.link_nodes, "map", stamp_ns, ns="map/graph")
    for mk in arr.markers:              # put links and nodes at their real heights
        if mk.ns == "map/graph/links" and mk.points:
            z = building.node_xyz[building.link_nodes.reshape(-1), 2]
            for p, zz in zip(mk.points, z.tolist()):
                p.z = zz
        elif mk.ns == "map/graph/nodes" and mk.points:
            for p, zz in zip(mk.points, building.node_xyz[:, 2].tolist()):
                p.z = zz
    walls = Marker()
    walls.header.frame_id = "map"
    walls.header.stamp = arr.markers[0].header.stamp
    walls.ns, walls.id, walls.type, walls.action = "map/walls", 0, Marker.LINE_LIST, Marker.ADD
    walls.pose.orientation.w = 1.0
    walls.scale.x = 0.15
    walls.color.r, walls.color.g, walls.color.b, walls.color.a = 0.5, 0.5, 0.55, 1.0
    for (a, b), f in zip(building.walls.tolist(), building.wall_floor.tolist()):
        z = float(building.floor_z[f])
        walls.points += [Point(x=a[0], y=a[1], z=z), Point(x=b[0], y=b[1], z=z)]
    arr.markers.append(walls)
    return arr


def truth_samples(w: SimWalker, hz: float = TRUTH_HZ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(stamps_ns relative, xy (N, 2), heading (N,)) of the device at ``hz``."""
    step = max(1, int(round(1e9 / hz / float(w.motion.t_ns[1] - w.motion.t_ns[0]))))
    idx = np.arange(0, len(w.motion.t_ns), step)
    return w.motion.t_ns[idx], w.motion.xyz[idx, :2], w.motion.heading[idx]


def route_segments(building: Building, w: SimWalker) -> np.ndarray:
    """(L, 2, 2) plan segments of the graph links the walker walked (each link once)."""
    seq = w.plan.node_seq
    pairs = sorted({tuple(sorted(p)) for p in zip(seq[:-1], seq[1:]) if p[0] != p[1]})
    xy = building.node_xyz[:, :2]
    return np.array([[xy[a], xy[b]] for a, b in pairs], float).reshape(-1, 2, 2)


def write_bag(run: SimRun, path: str | Path, *, t0_ns: int = T0_NS, progress=None,
              robot_imu: bool = True) -> dict[str, int]:
    from msg_adapters.imu import imu_to_msg, mag_to_msg
    from msg_adapters.markers import graph_markers
    from msg_adapters.path import path_to_msg
    from msg_adapters.pressure import pressure_to_msg
    from msg_adapters.wifi_scan import scan_to_msg
    from indoor_loc.wifi.types import WifiScan

    b = run.building
    baro = run.config.baro
    pressure_var_pa2 = 0.0 if baro is None else (baro.noise_hpa * 100.0) ** 2
    with BagWriter(path) as bag:
        bag.add_topic(GRAPH_TOPIC, "visualization_msgs/msg/MarkerArray", qos_profiles=LATCHED)
        bag.write(GRAPH_TOPIC, building_markers(b, t0_ns), t0_ns)
        streams = []
        for w in list(run.walkers) + list(run.robots):
            ns = f"/{w.name}"
            t_gt, t_route = join_ns(ns, "ground_truth"), join_ns(ns, "ground_truth/route")
            bag.add_topic(t_gt, "nav_msgs/msg/Path", qos_profiles=LATCHED)
            bag.add_topic(t_route, "visualization_msgs/msg/MarkerArray", qos_profiles=LATCHED)
            ts, xy, hd = truth_samples(w)
            bag.write(t_gt, path_to_msg(ts + t0_ns, xy, hd, frame_id="map", stamp_ns=t0_ns), t0_ns)
            seg = route_segments(b, w)
            nodes = seg.reshape(-1, 2)
            bag.write(t_route, graph_markers(nodes, np.arange(len(nodes)).reshape(-1, 2), "map", t0_ns,
                                             ns="ground_truth/route"), t0_ns)
            frame = f"{w.name}/imu_link"
            if not any(w is r for r in run.robots):     # a robot's odom and imu: robot_streams
                streams.append((w.imu.t_ns + t0_ns, 0, w, join_ns(ns, "imu/data_raw"), frame))
                streams.append((w.imu.mag_t_ns + t0_ns, 1, w, join_ns(ns, "imu/mag"), frame))
            streams.append((np.array([s.stamp_ns for s in w.scans], np.int64) + t0_ns, 2, w,
                            join_ns(ns, "wifi/scan"), frame))
            baro = getattr(w, "baro", None)
            if baro is not None:
                streams.append((baro.t_ns + t0_ns, BARO, w, join_ns(ns, "baro/pressure"), frame))
        streams += [st for st in robot_streams(run.robots, t0_ns) if robot_imu or st[1] != 4]
        # merge every stream in stamp order (ties: IMU, magnetometer, scans; then walker order)
        keys = np.concatenate([s[0] for s in streams])
        which = np.concatenate([np.full(len(s[0]), k) for k, s in enumerate(streams)])
        index = np.concatenate([np.arange(len(s[0])) for s in streams])
        order = np.lexsort((which, keys))
        done = 0
        for o in order:
            stamps, kind, w, topic, frame = streams[which[o]]
            i = int(index[o])
            t = int(stamps[i])
            if kind == 0:
                msg = imu_to_msg(t, frame, w.imu.acc[i], w.imu.gyro[i])
            elif kind == 1:
                msg = mag_to_msg(t, frame, w.imu.mag_t[i])
            elif kind == BARO:
                msg = pressure_to_msg(t, frame, float(w.baro.pressure_pa[i]), pressure_var_pa2)
            elif kind >= 3:
                msg = robot_message(kind, w, i, t)
            else:
                s = w.scans[i]
                msg = scan_to_msg(WifiScan(t, s.bssid, s.rssi_dbm, s.freq_mhz, s.ssid, s.age_ms,
                                           f"{w.name}/wifi_link", "sim"))
            bag.write(topic, msg, t)
            done += 1
            if progress is not None and done % 5000 == 0:
                progress(5000)
        if progress is not None:
            progress(done % 5000)
        return dict(bag.topic_counts())


def write_truth_csv(w: SimWalker, path: Path, t0_ns: int = T0_NS) -> None:
    m = w.motion
    step = max(1, int(round(0.1e9 / float(m.t_ns[1] - m.t_ns[0]))))       # 10 Hz
    with open(path, "w", newline="") as fh:
        wr = csv.writer(fh, lineterminator="\n")
        wr.writerow(("stamp_ns", "x", "y", "z", "floor", "heading", "steps"))
        for i in range(0, len(m.t_ns), step):
            wr.writerow((int(m.t_ns[i] + t0_ns), f"{m.xyz[i, 0]:.4f}", f"{m.xyz[i, 1]:.4f}", f"{m.xyz[i, 2]:.4f}",
                         int(m.floor[i]), f"{m.heading[i]:.5f}", f"{m.steps[i]:.3f}"))


def node_params(run: SimRun, radiomap_dir: Path, graph_file: Path) -> dict:
    """The params.yaml of a simulated run: every node, ``/**/node_name`` keys (any namespace)."""
    if multi_floor(run):
        # floors: the powed method detects the floor of every fix (the map's scans carry their floor's height)
        flat = node_params_flat(run, radiomap_dir, graph_file)
        backend = {**flat["/**/backend_node"]["ros__parameters"], "wifi_source": "fix"}   # the fixes carry the floors
        return {**flat, "/**/wifi_fix_node": {"ros__parameters": {"radiomap": str(radiomap_dir), "method": "powed"}},
                "/**/backend_node": {"ros__parameters": backend}}
    return node_params_flat(run, radiomap_dir, graph_file)


def multi_floor(run: SimRun) -> bool:
    """A run whose walkers change floors, or any run in a building of more than two floors (the tower:
    a walker staying on floor 1 too): its radio map carries the floors and the fixes detect them."""
    return run.building.n_floors > 1 and (bool(run.config.change_floors) or run.building.n_floors > 2)


def node_params_flat(run: SimRun, radiomap_dir: Path, graph_file: Path) -> dict:
    """:func:`node_params` of a run on one floor."""
    mean_step = float(run.config.step_length_m[0])
    # a multi-floor building's floor heights (the radio map's floors) for the Kalman filter and the
    # back-end (tll_pf has them from the graph): the barometer snaps to a floor no fix named yet
    fz = [float(z) for z in run.building.floor_z]
    floors = {"floors": {"heights_m": fz}} if len(fz) > 1 else {}

    def floors_copy() -> dict:            # one mapping per node: yaml would alias a shared one (rcl refuses)
        return copy.deepcopy(floors)
    return {
        "/**/imu_node": {"ros__parameters": {
            "heading_source": "aekf",         # imu/data_raw + imu/mag: the AEKF gives the heading
            "step_length_m": round(mean_step, 3),
            "heading_offset_rad": 0.0}},      # the device's x axis points forward (REP 103)
        "/**/wifi_fix_node": {"ros__parameters": {"radiomap": str(radiomap_dir), "method": "wknn"}},
        "/**/pdr_kf_node": {"ros__parameters": {"step_length_m": round(mean_step, 3), **floors_copy()}},
        # the particle filter on the building graph (its TLL table is cached beside graph.yaml)
        "/**/tll_pf": {"ros__parameters": {"graph_file": str(graph_file)}},
        # the multi-user back-end (one node for every walker): the same survey, imu_node's step length
        "/**/backend_node": {"ros__parameters": {"radiomap": str(radiomap_dir),
                                                 "odom_step_length_m": round(mean_step, 3),
                                                 "path_period_s": 10.0, **floors_copy(),
                                                 # walkers and robots: each user's own motion topic
                                                 **({"motion_source": "any"} if run.robots else {})}},
    } | robot_node_params(run.robots)


def write_run(run: SimRun, out_dir: str | Path, *, progress=None) -> dict[str, Path]:
    """Write everything (see module doc); returns the paths by role."""
    out = Path(out_dir).resolve()
    out.mkdir(parents=True, exist_ok=True)
    if multi_floor(run):
        fz = run.building.floor_z
        rm = add_fingerprints(empty_radiomap(), run.survey_xy, run.survey_scans, source="survey",
                              z_m=fz[run.survey_floor], floors={f"F{k}": float(z) for k, z in enumerate(fz)})
    else:
        rm = add_fingerprints(empty_radiomap(), run.survey_xy, run.survey_scans, source="survey")
    rm_dir = save_radiomap(rm, out / "radiomap", created_by="indoor-loc sim")
    geo = save_building(run.building, out / "building.geojson")
    plans = save_floor_plans(run.building, out / "floor_plans")
    graph = save_graph(building_graph(run.building), out / "graph.yaml",
                       source={"tool": "indoor-loc sim", "building": run.building.name})
    (out / "truth").mkdir(exist_ok=True)
    for stale in (out / "truth").glob("*.csv"):      # a previous run's walkers
        stale.unlink()
    for w in list(run.walkers) + list(run.robots):
        write_truth_csv(w, out / "truth" / f"{w.name}.csv")
    params = node_params(run, rm_dir, graph)
    (out / "params.yaml").write_text(
        "# Written by `indoor-loc sim`: configures every node for this simulated run (any namespace).\n"
        "# imu/data_raw + imu/mag feed the AEKF; the step length is the population mean (each walker's\n"
        "# own is in scenario.yaml, which the estimators do not know).\n"
        + yaml.safe_dump(params, sort_keys=False))
    cfg = run.config
    scenario = {
        "seed": cfg.seed, "duration_s": cfg.duration_s, "t0_ns": T0_NS, "building": run.building.name,
        "imu_rate_hz": cfg.imu.rate_hz, "mag_rate_hz": cfg.imu.mag_rate_hz, "scan_period_s": cfg.scanner.period_s,
        "walkers": [{"name": w.name, "step_length_m": round(w.params.step_length_m, 4),
                     "cadence_hz": round(w.params.cadence_hz, 4), "steps": round(float(w.motion.steps[-1]), 2),
                     "scans": len(w.scans), "route_nodes": [int(n) for n in w.plan.node_seq]} for w in run.walkers],
        "ap_events": [{"ap": ap.name, **({"off_at_s": ap.off_at_s} if ap.off_at_s is not None else {}),
                       **({"move_at_s": ap.move_at_s, "move_to_xyz": list(ap.move_to_xyz)}
                          if ap.move_at_s is not None else {})}
                      for ap in run.building.aps if ap.off_at_s is not None or ap.move_at_s is not None],
        "survey": {"scans": rm.n_scans, "aps": rm.n_aps, "spacing_m": cfg.survey_spacing_m},
    }
    if run.robots:
        scenario["robots"] = robot_scenario(run.robots)
    (out / "scenario.yaml").write_text(yaml.safe_dump(scenario, sort_keys=False))
    bag = out / "sim.mcap"
    write_bag(run, bag, progress=progress)
    return {"bag": bag, "radiomap": rm_dir, "building": geo, "graph": graph, "floor_plans": plans[0].parent, "params": out / "params.yaml",
            "scenario": out / "scenario.yaml", "truth": out / "truth"}
