"""``indoor-loc import ms-indoor SITE_DIR OUT_DIR``: a Microsoft indoor-location site -> bags + maps.

Writes, for the selected floors (``--floors B1,F3``; default all) and walks (``--walks ID,…``, ids
or unique id prefixes; default all):

- ``OUT_DIR/<floor>/<trace id>.mcap`` — one bag per walk (topics in
  :mod:`indoor_loc.datasets.ms_indoor_bags`);
- ``OUT_DIR/radiomap/`` — one multi-floor radio map (format v2: per-scan floor height ``z``,
  per-reading ``age_ms``) from every scan of the **survey walks** inside their waypoint span, at
  the position interpolated between waypoints. Survey walks: ``--survey-walks ID,…`` (the user's),
  else the documented interleaved split (per floor, ids sorted, in every block of five the 1st,
  3rd and 5th are survey walks, the 2nd and 4th test walks);
- ``OUT_DIR/floors/<floor>/`` — ``floor_image.png``, ``geojson_map.json`` (both already in the map
  frame: metres, x right, y up, origin at the plan's bottom-left corner) and ``map.yaml`` (a nav2
  map_server description of the image: resolution m/px, origin [0, 0, 0], plus the floor's z);
- ``OUT_DIR/split.yaml`` — survey and test walks per floor; ``OUT_DIR/params.yaml`` — every node
  (imu_node heading from the rotation vector; wifi_fix_node with the radio map, the
  recommended method and, where GeoJSON plans exist, ``floor_plans`` = ``OUT_DIR/floors`` with powed
  k-NN's path-loss field turned on; backend_node on the front end's fixes; pdr_kf_node's step
  length; tll_pf on its walk's floor graph, one ``/<floor>_<id>/tll_pf`` key per walk on a site of
  several floors; and, when the heading offset is set, the spread of the survey walks' offsets as
  every estimator's initial-heading prior: ``pdr_kf_node.heading_prior_std_rad``,
  ``tll_pf.yaw_offset_sigma_rad``, ``backend_node.gauge_std_rad``; with the plans the back-end's
  walkable factor and per-walk fix bias, ``backend_node.walkable_std_m``/``fix_bias_std_m``);
- ``OUT_DIR/floors/<floor>/graph.yaml`` — the floor's link graph from its GeoJSON plan
  (:mod:`indoor_loc.graph.floor_plan`: the skeleton of the walkable space reaching the survey
  waypoints, at the floor's height);
  ``OUT_DIR/import_report.md`` — per-walk counts and what was odd.

Floor heights: ``z = storey index × --storey-height-m`` (default 5 m). The index comes from the floor's
name (:func:`indoor_loc.datasets.ms_indoor.floor_levels`: B1 → −1, F1/1F/L1/G → 0, F3 → 2, M → 0.5,
LG<n>, then B<n>, then P<n> stacking below ground), ``--floor-levels NAME=LEVEL,...`` overriding it; a
name of no known convention gets the next index above the highest floor, named in the report's
"Floors" table. Walks with fewer than two waypoints have no truth: they are written and positioned but take no
part in the split (role ``no truth``) and build no map. A floor without ``floor_info.json`` takes its
extent from its GeoJSON plan's lon/lat extent; a plan that cannot be placed or drawn is not copied
(the report says why), so the nodes never load it.
"""
from __future__ import annotations

import argparse
import json
import shutil
from pathlib import Path

import numpy as np
import yaml

from indoor_loc.backend.graph import FIX_GRAPH_PARAMS
from indoor_loc.errors import ConfigError, DatasetError
from indoor_loc.output_paths import check_outputs
from indoor_loc.pipeline.imu_stage import ImuStageParams
from indoor_loc.params import params_file_text
from indoor_loc.wifi.methods import recommended_params
from indoor_loc.wifi.radiomap import add_fingerprints, empty_radiomap, save_radiomap


NO_MAP = ("no survey scan lies inside a waypoint span (walks with fewer than two waypoints cannot build a map): "
          "no radiomap/ and no wifi_fix_node in params.yaml; position these walks against a radio map built "
          "elsewhere")


def add_arguments(sub) -> None:
    p = sub.add_parser("ms-indoor", help="Microsoft Indoor Location Competition 2.0 site (trace .txt/.txt.gz)",
                       description="Import a Microsoft indoor-location site into MCAP bags (one per walk), a "
                                   "multi-floor radio map, floor plans, params.yaml and an import report")
    p.add_argument("dataset_dir", type=Path, help="the site directory (<floor>/path_data_files/, floor_info.json…)")
    p.add_argument("out_dir", type=Path, help="output directory (created)")
    p.add_argument("--floors", default="", help="comma-separated floor names (default: all), e.g. B1,F3")
    p.add_argument("--walks", default="", help="comma-separated trace ids or unique prefixes (default: all)")
    p.add_argument("--survey-walks", default="",
                   help="trace ids (or prefixes) that build the radio map (default: the interleaved split)")
    p.add_argument("--storey-height-m", type=float, default=5.0, help="floor height per storey, m (default 5)")
    p.add_argument("--metadata", type=Path, default=None,
                   help="directory with the floors' plan files (<floor>/floor_info.json…) when the site's "
                        "floor directories hold only traces (default: ../../metadata/<site> for a site "
                        "directory .../train/<site>, the competition's Kaggle layout, if it exists)")
    p.add_argument("--floor-levels", default="",
                   help="storey index per floor, NAME=LEVEL,... (0 = ground, e.g. G=0,M=0.5,P1=-2); default: "
                        "from the floor names' conventions (the import report says which rule set each)")
    p.add_argument("--ble-window-s", type=float, default=0.0,
                   help="> 0: the BLE readings of this many seconds before each survey scan join its fingerprint as "
                        "'ble:<id>' entries and wifi_fix_node takes ble/scan (ble.enabled); default 0: WiFi only (on "
                        "ms_site2 BLE changed no floor's error: `indoor-loc bench ble`)")
    p.add_argument("--overwrite", action="store_true",
                   help="replace bags, radiomap/, params.yaml, split.yaml and import_report.md already in OUT_DIR")
    p.set_defaults(func=import_ms_indoor)


def _select(text: str, ids: list[str], what: str) -> list[str]:
    if not text.strip():
        return list(ids)
    out = []
    for tok in (t.strip() for t in text.split(",")):
        if not tok:
            continue
        hit = [i for i in ids if i == tok] or [i for i in ids if i.startswith(tok)]
        if len(hit) != 1:
            raise ConfigError(f"{what}: {tok!r} matches {len(hit)} of the {len(ids)} walks (need exactly one)")
        out.append(hit[0])
    return sorted(set(out))


def import_ms_indoor(args: argparse.Namespace) -> int:
    from indoor_loc.datasets.ms_indoor import (has_truth_span, heading_offsets, parse_floor_levels, read_site,
                                               read_trace, scans_with_truth, split_map_test, trace_id_of)
    from indoor_loc.datasets.ms_indoor_bags import trace_bag_counts, walk_namespace, write_trace_bag

    if not (args.storey_height_m > 0):
        raise ConfigError(f"--storey-height-m: expected > 0, got {args.storey_height_m}")
    from indoor_loc.wifi.ble import merge_scans
    ble_window = float(getattr(args, "ble_window_s", 0.0) or 0.0)
    if not 0 <= ble_window <= 600:
        raise ConfigError(f"--ble-window-s: expected in [0, 600], got {ble_window}")
    site = read_site(args.dataset_dir, levels=parse_floor_levels(getattr(args, "floor_levels", "") or ""),
                     metadata=getattr(args, "metadata", None))
    floors = site.floors
    names = [f.name for f in floors]
    if args.floors.strip():
        want = [t.strip() for t in args.floors.split(",") if t.strip()]
        bad = [w for w in want if w not in names]
        if bad:
            raise ConfigError(f"--floors: no floor(s) {bad}; the site has {names}")
        floors = [f for f in floors if f.name in want]
    out = Path(args.out_dir).resolve()
    src = Path(args.dataset_dir).resolve()
    if out == src or src in out.parents:
        raise ConfigError(f"OUT_DIR {out} is inside the dataset directory {src}: refusing to write there")
    if out.exists() and not out.is_dir():
        raise ConfigError(f"OUT_DIR {out} exists and is not a directory")
    all_ids = {f.name: [trace_id_of(p) for p in f.trace_files] for f in floors}
    flat = sorted(i for v in all_ids.values() for i in v)
    walks = set(_select(args.walks, flat, "--walks"))
    user_survey = set(_select(args.survey_walks, flat, "--survey-walks")) if args.survey_walks.strip() else None
    bag_of = {i: out / f.name / f"{i}.mcap" for f in floors for i in all_ids[f.name] if i in walks}
    check_outputs([*bag_of.values(), out / "radiomap", out / "params.yaml", out / "split.yaml",
                   out / "import_report.md"], overwrite=args.overwrite, what="import ms-indoor")
    out.mkdir(parents=True, exist_ok=True)             # only once the options are known to be good

    rm = empty_radiomap()
    rows, oddities, split = [], [], {}
    dropped: dict[str, int] = {}
    floor_rows: list[dict] = []
    skipped: list[str] = []
    heading: dict[str, list] = {}
    seeds: dict[str, list] = {}                       # floor -> survey waypoints (where the graph must reach)
    survey_heading: list[np.ndarray] = []             # (walking direction - phone yaw) on the survey walks
    floor_z = {f.name: f.z_m(args.storey_height_m) for f in floors}
    for fl in floors:
        ids = all_ids[fl.name]
        truth = {trace_id_of(p): has_truth_span(p) for p in fl.trace_files}
        no_truth = [i for i in ids if not truth[i]]
        if user_survey is None:
            survey, test = split_map_test([i for i in ids if truth[i]])
        else:
            survey = [i for i in ids if i in user_survey]
            test = [i for i in ids if i not in user_survey and truth[i]]
            oddities += [f"{i}: a survey walk with fewer than two waypoints: it cannot build the radio map"
                         for i in survey if not truth[i]]
        split[fl.name] = {"z_m": floor_z[fl.name], "survey": survey, "test": test}
        if no_truth:
            split[fl.name]["no_truth"] = [i for i in no_truth if i not in survey]
        plan_note = _write_floor_plan(fl, out / "floors" / fl.name, floor_z[fl.name])
        floor_rows.append({"floor": fl.name, "level": fl.level, "z": floor_z[fl.name], "rule": fl.level_rule,
                           "walks": len(ids), "no_truth": len(no_truth),
                           "notes": list(fl.notes) + ([plan_note] if plan_note else [])})
        for p in fl.trace_files:
            tid = trace_id_of(p)
            if tid not in walks and tid not in survey:
                continue
            try:
                tr = read_trace(p)
            except DatasetError as err:          # one unreadable walk must not lose the others
                oddities.append(f"{tid}: SKIPPED, unreadable: {err}")
                skipped.append(tid)
                continue
            if tr.floor and tr.floor != fl.name:
                oddities.append(f"{tid}: header FloorName {tr.floor!r} but stored under {fl.name}")
            oddities += [f"{tid}: {o}" for o in tr.oddities if not o.startswith("rows not used")]
            for k, v in tr.dropped.items():
                dropped[k] = dropped.get(k, 0) + v
            if len(tr.waypoint_xy) and np.isfinite(fl.width_m):
                wx, wy = tr.waypoint_xy[:, 0], tr.waypoint_xy[:, 1]
                off = int(np.sum((wx < 0) | (wx > fl.width_m) | (wy < 0) | (wy > fl.height_m)))
                if off:
                    oddities.append(f"{tid}: {off} of {len(wx)} waypoints outside the floor's extent "
                                    f"[0, {fl.width_m:.1f}] × [0, {fl.height_m:.1f}] m")
            if tid in survey:
                survey_heading.append(heading_offsets(tr))
                if len(tr.waypoint_xy):
                    seeds.setdefault(fl.name, []).append(tr.waypoint_xy[:, :2])
                sc, xy = scans_with_truth(tr)
                if sc and ble_window > 0:
                    sc = merge_scans(sc, tr.ble, ble_window)
                if sc:
                    rm = add_fingerprints(rm, xy, sc, source=f"{fl.name}/{tid}", z_m=floor_z[fl.name],
                                          floors={fl.name: floor_z[fl.name]})
            if tid not in walks:
                continue
            heading.setdefault(fl.name, []).append(heading_offsets(tr))
            bag = bag_of[tid]
            bag.parent.mkdir(parents=True, exist_ok=True)
            counts = write_trace_bag(tr, bag, z_m=floor_z[fl.name], floor=fl.name)
            sc, _ = scans_with_truth(tr)
            rel = trace_bag_counts(tr)
            rows.append({"floor": fl.name, "walk": tid, "ns": walk_namespace(tr, fl.name), "role":
                         "survey" if tid in survey else "test" if truth[tid] else "no truth", "device": tr.device,
                         "duration_s": (tr.end_ns - tr.start_ns) * 1e-9, "waypoints": len(tr.waypoint_t),
                         "scans": len(tr.scans), "scans_in_span": len(sc),
                         "aps_per_scan": float(np.mean([len(s) for s in tr.scans])) if tr.scans else 0.0,
                         "messages": sum(counts.values()), "imu_raw": rel["imu/data_raw"],
                         "unused_rows": sum(v for k, v in tr.row_counts.items()
                                            if k not in ("TYPE_WIFI", "TYPE_WAYPOINT") and not k.startswith("TYPE_ACC")
                                            and not k.startswith("TYPE_GYR") and not k.startswith("TYPE_MAG")
                                            and k != "TYPE_ROTATION_VECTOR")})
    rm_dir = out / "radiomap"
    if rm.n_scans:
        save_radiomap(rm, rm_dir, created_by="indoor-loc import ms-indoor", inputs=[str(src)])
    elif rm_dir.exists():                    # --overwrite: an earlier import's map must not stay beside these
        shutil.rmtree(rm_dir)
    (out / "split.yaml").write_text("# survey walks build radiomap/; test walks are positioned against it\n"
                                    + yaml.safe_dump(split, sort_keys=False))
    offset = _heading_offset(heading)
    imu_params = {"heading_source": "orientation"}
    if offset is not None:
        imu_params["heading_offset_rad"] = round(offset, 4)
    # the floor plans bound powed k-NN's extrapolating radio map (a site without any GeoJSON plan: none)
    plans = out / "floors"
    has_plan = any((plans / f.name / "geojson_map.json").exists() for f in floors)
    params: dict = {"imu_node": imu_params,
                    # the PDR Kalman filter counts steps as distance / the imu_node's step length
                    "pdr_kf_node": {"step_length_m": ImuStageParams().step_length_m}}
    graphs = _floor_graphs(floors, plans, seeds, floor_z, oddities)
    prior_sd = heading_prior_std(survey_heading) if offset is not None else None
    if prior_sd is not None:   # the odometry's yaw is the map heading up to this: every estimator starts on it
        params["pdr_kf_node"].update({"heading_prior_std_rad": prior_sd, **KF_CALIBRATED_HEADING})
    walk_keys = _pf_walk_keys(rows, graphs)
    pf_heading = {"yaw_offset_sigma_rad": prior_sd} if prior_sd is not None else {}
    if len(graphs) == 1 or (graphs and not walk_keys):
        params["tll_pf"] = {"graph_file": str(next(iter(graphs.values()))), **PF_MALL_PARAMS, **pf_heading}
    elif graphs:
        params["tll_pf"] = {**PF_MALL_PARAMS, **pf_heading}
    if rm.n_scans:
        params["wifi_fix_node"] = {"radiomap": str(rm_dir), **recommended_params(rm, str(plans) if has_plan else "")}
        if ble_window > 0 and any(b.startswith("ble:") for b in rm.bssids):
            params["wifi_fix_node"]["ble"] = {"enabled": True, "window_s": ble_window}
        # the back-end on the front end's fixes (see FIX_GRAPH_PARAMS); without this it has no survey
        params["backend_node"] = {"radiomap": str(rm_dir), **FIX_GRAPH_PARAMS}
        if prior_sd is not None:
            params["backend_node"].update({"gauge_std_rad": prior_sd, **BACKEND_CALIBRATED_HEADING})
        if has_plan:           # the floor plans as the back-end's walkable factor
            params["backend_node"].update({"floor_plans": str(plans), **BACKEND_WALKABLE})
    (out / "params.yaml").write_text(params_file_text(params, header=(
        "Written by `indoor-loc import ms-indoor`. imu/data carries Android's rotation vector (device->ENU,\n"
        "magnetic north); the map frame is the floor plans' (x right, y up), z = floor height.\n"
        "heading_offset_rad: walking direction in the map frame minus the phone's yaw, from the waypoints\n"
        "(import_report.md, 'Heading check'); absent when the walks show no constant offset.\n"
        "Keys /**/<node> reach the node in any namespace (ros2 run ... -r __ns:=/<floor>_<id> --params-file);\n"
        "/<floor>_<id>/tll_pf keys give each imported walk its floor's graph (floors/<floor>/graph.yaml)."))
        + _walk_keys_text(walk_keys))
    heading_note = _heading_note(heading)
    (out / "import_report.md").write_text(_report(src, rows, oddities, rm, floor_z, args.storey_height_m)
                                          + "\n" + _floors_note(floor_rows, site.ignored, dropped, site.metadata)
                                          + "\n" + heading_note + "\n")
    print(_table(rows))
    if rm.n_scans:
        print(f"\nradio map: {rm_dir} ({rm.n_scans} scans, {rm.n_aps} APs, floors "
              + ", ".join(f"{k} z={v:g} m" for k, v in rm.floors.items()) + ")")
    else:
        print(f"\nradio map: NONE — {NO_MAP}")
    print(f"params:    {out / 'params.yaml'}\nsplit:     {out / 'split.yaml'}\nreport:    {out / 'import_report.md'}")
    print(f"oddities:  {len(oddities)} (see the report)")
    for r in floor_rows:
        if r["rule"].startswith("fallback"):
            print(f"floor {r['floor']}: level {r['level']:g} by fallback ({r['rule'][10:]}); "
                  "set it with --floor-levels NAME=LEVEL")
    if skipped:
        print(f"SKIPPED {len(skipped)} unreadable walk(s): {', '.join(skipped)} (see the report)")
    return 0


#: ``tll_pf`` on a mall's imported site: the smoother takes a redrawn particle's predecessor from
#: the filter's weights (``mixture``), as the fixes are broad and sometimes far off (docs/backend.md,
#: "On a mall").
PF_MALL_PARAMS = {"smooth_redrawn": "mixture"}


def _floor_graphs(floors, plans: Path, seeds: dict[str, list], floor_z: dict[str, float],
                  oddities: list[str]) -> dict[str, Path]:
    """``floors/<floor>/graph.yaml`` for every floor whose GeoJSON plan was copied: the plan's
    skeleton (:func:`indoor_loc.graph.floor_plan.floor_plan_graph`) reaching the survey waypoints.
    A plan that gives no graph is named in the report; that floor's walks then get no tll_pf graph."""
    from indoor_loc.errors import MapError
    from indoor_loc.graph.floor_plan import floor_plan_graph
    from indoor_loc.graph.io import save_graph
    out: dict[str, Path] = {}
    for fl in floors:
        gj = plans / fl.name / "geojson_map.json"
        if not gj.exists():
            continue
        pts = np.vstack(seeds[fl.name]) if seeds.get(fl.name) else None
        try:
            g = floor_plan_graph(gj, extent_m=(fl.width_m, fl.height_m), floor=fl.name, z_m=floor_z[fl.name],
                                 seeds_xy=pts)
        except MapError as err:
            oddities.append(f"floor {fl.name}: no link graph from its plan: {err}")
            continue
        out[fl.name] = save_graph(g, plans / fl.name / "graph.yaml", source={
            "tool": "indoor-loc import ms-indoor", "geojson": "geojson_map.json", "floor": fl.name,
            "extent_m": [fl.width_m, fl.height_m], "seeds": "survey waypoints"})
        print(f"graph {fl.name}: {out[fl.name]} ({g.n_nodes} nodes, {g.n_links} links, {g.link_len.sum():.0f} m)")
    return out


def _pf_walk_keys(rows: list[dict], graphs: dict[str, Path]) -> dict[str, dict]:
    """``/<floor>_<id>/tll_pf`` -> its floor's graph, for every walk written on a floor with a graph
    (a site of several floors: one ``/**/tll_pf`` graph cannot fit them all)."""
    if len(graphs) < 2:
        return {}
    return {f"{r['ns']}/tll_pf": {"graph_file": str(graphs[r["floor"]])} for r in rows if r["floor"] in graphs}


def _walk_keys_text(keys: dict[str, dict]) -> str:
    if not keys:
        return ""
    return yaml.safe_dump({k: {"ros__parameters": v} for k, v in keys.items()}, sort_keys=False)


#: With a calibrated absolute heading (the rotation vector's yaw + the site's offset) the heading
#: changes of pdr/odom drift far less than a gyro-only heading (PUTMC's, where the defaults were set):
#: the Kalman filter's heading random walk per footstep and the back-end's heading information per
#: PDR edge say so. Chosen on ms_site2's B1 and F7 (bench fusion; F3 and F8 checked once). The
#: back-end's PDR position information (25 per edge, σ 0.2 m, was the paper's 1) and heading 400: the
#: PDR track's shape after one rotation and scale fitted to the truth is within 1–2.4 m of it on B1's
#: walks, so the smoothed path should follow it rather than every fix (B1, first 16 test walks).
KF_CALIBRATED_HEADING = {"sigma_dtheta_rad": 0.05}
BACKEND_CALIBRATED_HEADING = {"pdr_info": [25.0, 25.0, 400.0]}
#: The back-end's walkable factor where the site has floor plans: a pose 1 m outside the walkable area
#: costs as much as a 1 σ PDR error (indoor_loc/backend/walkable_term.py). Chosen on ms_site2's B1
#: (bench fusion, the first 16 test walks); F3, F7 and F8 checked once. With it, the fixes' error shared
#: along a walk (``fix_bias_std_m``: one bias per track with this prior std, m): radio-map error is
#: spatially correlated, so whole walks' fixes sit metres off together (docs/fusion.md, round 3); the
#: plan can then move a whole track at the cost of one prior. Chosen on ms_site2's B1 and F7 (3 m against
#: 1.5 and 8), F3 and F8 checked once.
BACKEND_WALKABLE = {"walkable_std_m": 1.0, "fix_bias_std_m": 3.0}

#: The smallest heading prior std the importer writes (rad, ≈ 3°): a phone's rotation-vector yaw is
#: never better, however well a few survey walks agree.
MIN_HEADING_STD_RAD = 0.05


def heading_prior_std(parts: list[np.ndarray]) -> float | None:
    """How far the calibrated odometry heading may be off the walking direction, rad: the circular
    standard deviation ``sqrt(-2 ln R)`` of (walking direction − phone yaw) over the **survey** walks'
    waypoint pairs (R their resultant length; no test walk's truth enters), at least
    :data:`MIN_HEADING_STD_RAD`. None without pairs."""
    d = np.concatenate([x for x in parts if len(x)]) if any(len(x) for x in parts) else np.zeros(0)
    if len(d) == 0:
        return None
    r = float(abs(np.mean(np.exp(1j * d))))
    return round(max(float(np.sqrt(-2.0 * np.log(min(max(r, 1e-9), 1.0)))), MIN_HEADING_STD_RAD), 2)


def _heading_offset(heading: dict[str, list]) -> float | None:
    """Site-wide circular mean of (walking direction − phone yaw), rad, or None if R < 0.5."""
    parts = [d for v in heading.values() for d in v if len(d)]
    if not parts:
        return None
    c = np.mean(np.exp(1j * np.concatenate(parts)))
    return float(np.angle(c)) if abs(c) >= 0.5 else None


def _heading_note(heading: dict[str, list]) -> str:
    """Per floor: circular mean and resultant length R of (walking direction − phone yaw)."""
    import math
    off = _heading_offset(heading)
    lines = ["## Heading check", "",
             "Walking direction between waypoints (map frame) minus the rotation vector's yaw, per floor: "
             "circular mean and resultant length R (1 = one constant offset, 0 = none). The site-wide mean "
             "becomes imu_node's `heading_offset_rad` (ms_site2: about +90°, a phone carried along its +y "
             "axis on plans nearly aligned with magnetic north) unless R < 0.5: "
             + (f"**{math.degrees(off):.1f}° set**." if off is not None else "**none set**."), ""]
    for name, parts in heading.items():
        d = np.concatenate(parts) if parts else np.zeros(0)
        if len(d) == 0:
            lines.append(f"- {name}: no pair of waypoints 2 m apart")
            continue
        c = np.mean(np.exp(1j * d))
        lines.append(f"- {name}: {len(d)} waypoint pairs, mean {math.degrees(float(np.angle(c))):.1f}°, "
                     f"R = {abs(c):.2f}")
    return "\n".join(lines)


def _write_floor_plan(fl, d: Path, z_m: float) -> str:
    """The floor's plan in the map frame (image, GeoJSON, map.yaml); returns a note when its GeoJSON
    is not copied (no extent to place it, or it cannot be drawn), so no node ever loads it."""
    from indoor_loc.errors import MapError
    from indoor_loc.wifi.walkable import plan_walkable
    d.mkdir(parents=True, exist_ok=True)
    img = fl.plans / "floor_image.png"
    gj = fl.plans / "geojson_map.json"
    meta = {"floor": fl.name, "z_m": z_m, "width_m": fl.width_m, "height_m": fl.height_m, "frame_id": "map"}
    if img.exists():
        shutil.copyfile(img, d / "floor_image.png")
        w_px = _png_width(img)
        if w_px and np.isfinite(fl.width_m):
            meta.update({"image": "floor_image.png", "resolution": fl.width_m / w_px,
                         "origin": [0.0, 0.0, 0.0], "negate": 0, "occupied_thresh": 0.65, "free_thresh": 0.196,
                         "mode": "trinary"})
    note = ""
    if gj.exists():
        if not np.isfinite(fl.width_m):
            note = "GeoJSON plan not used: the floor's extent is unknown"
        else:
            try:
                plan_walkable(gj, (fl.width_m, fl.height_m))
                shutil.copyfile(gj, d / "geojson_map.json")
            except MapError as err:
                note = f"GeoJSON plan not used: {err}"
    (d / "map.yaml").write_text("# floor plan in the map frame (nav2 map_server keys + floor height)\n"
                                + yaml.safe_dump(meta, sort_keys=False))
    return note


def _png_width(path: Path) -> int:
    head = path.read_bytes()[:24]
    if head[:8] != b"\x89PNG\r\n\x1a\n":
        return 0
    return int.from_bytes(head[16:20], "big")


_COLS = [("floor", "floor", "{}"), ("walk", "walk", "{}"), ("role", "role", "{}"), ("device", "device", "{}"),
         ("duration_s", "duration s", "{:.1f}"), ("waypoints", "waypoints", "{}"), ("scans", "scans", "{}"),
         ("scans_in_span", "scans in waypoint span", "{}"), ("aps_per_scan", "AP/scan", "{:.0f}"),
         ("imu_raw", "imu/data_raw", "{}"), ("messages", "messages", "{}"), ("unused_rows", "rows not used", "{}")]


def _table(rows: list[dict]) -> str:
    lines = ["| " + " | ".join(c[1] for c in _COLS) + " |", "|" + "---|" * len(_COLS)]
    for r in rows:
        lines.append("| " + " | ".join(f.format(r[k]) for k, _, f in _COLS) + " |")
    return "\n".join(lines)


def _report(src, rows, oddities, rm, floor_z, storey) -> str:
    lines = ["# Microsoft indoor-location import report", "",
             f"Site: `{src}`; {len(rows)} walks written; storey height {storey:g} m "
             f"({', '.join(f'{k}: z = {v:g} m' for k, v in floor_z.items())}).", "",
             "Conventions: time = Unix time in int ns (bag log time = header stamp). Map frame: the floor plans' "
             "metres, x right, y up, origin at the plan's bottom-left; ground_truth = the waypoints (linear in "
             "between), z = floor height. WiFi: readings with last_seen before the scan time are cached results, "
             "age_ms = scan time − last_seen; a BSSID listed twice in a scan keeps its most recent reading. Rows "
             "not used: Bluetooth (TYPE_BLUE/BLU4), TYPE_DIST*, accuracy changes; iBeacons (TYPE_BEACON) go to "
             "ble/scan.", "",
             (f"Radio map: `radiomap/`, {rm.n_scans} scans, {rm.n_aps} APs (survey walks in `split.yaml`)."
              if rm.n_scans else f"Radio map: **none** — {NO_MAP}"), "",
             "## Walks", "", _table(rows), "", f"## Oddities ({len(oddities)})", ""]
    lines += [f"- {o}" for o in oddities] or ["(none)"]
    return "\n".join(lines) + "\n"


def _floors_note(floor_rows: list[dict], ignored: tuple[str, ...], dropped: dict[str, int],
                 metadata: Path | None = None) -> str:
    """The report's floor table (level, how it was decided, walks without truth, what was odd) and
    the site's dropped rows by reason."""
    lines = ["## Floors", "", "Storey index (0 = ground; z = index × storey height) from the floor's name, "
             "or `--floor-levels`; a `fallback` index is a guess: set it with `--floor-levels NAME=LEVEL`.", "",
             "| floor | index | z m | from | walks | without a waypoint span | notes |", "|---|---|---|---|---|---|---|"]
    for r in floor_rows:
        lines.append(f"| {r['floor']} | {r['level']:g} | {r['z']:g} | {r['rule']} | {r['walks']} | {r['no_truth']} | "
                     + ("; ".join(r["notes"]) or "") + " |")
    if ignored:
        lines += ["", "Not floors (no path_data_files/, trace or plan file), ignored: " + ", ".join(ignored)]
    if metadata is not None:
        lines += ["", f"Plan files of floors that hold none: from `{metadata}/<floor>/`."]
    lines += ["", "Rows dropped over the walks read, by reason: "
              + (", ".join(f"{k} {v}" for k, v in sorted(dropped.items())) or "none")]
    return "\n".join(lines) + "\n"


def geojson_bounds(path: Path) -> tuple[float, float, float, float]:
    """(xmin, ymin, xmax, ymax) of every coordinate in a GeoJSON file (a frame sanity check)."""
    pts: list[tuple[float, float]] = []

    def walk(o):
        if isinstance(o, (list, tuple)) and len(o) >= 2 and all(isinstance(v, (int, float)) for v in o[:2]):
            pts.append((float(o[0]), float(o[1])))
        elif isinstance(o, (list, tuple)):
            for v in o:
                walk(v)
        elif isinstance(o, dict):
            for v in o.values():
                walk(v)
    walk(json.loads(Path(path).read_text()))
    a = np.array(pts)
    return float(a[:, 0].min()), float(a[:, 1].min()), float(a[:, 0].max()), float(a[:, 1].max())
