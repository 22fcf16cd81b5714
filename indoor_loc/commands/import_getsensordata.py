"""``indoor-loc import getsensordata LOG... OUT_DIR``: GetSensorData logs (IPIN tracks) -> bags + maps.

LOG: logfiles (``.txt``, ``.txt.gz``, ``.log``) or directories of them. Writes:

- ``OUT_DIR/<log name>.mcap`` — one bag per log, namespace ``/<log name>`` (topics in
  :mod:`indoor_loc.datasets.getsensordata_bags`);
- ``OUT_DIR/radiomap/`` — WiFi + BLE fingerprints (format v2: floor height ``z``, reading ages) from every
  scan of the **survey logs** at the position interpolated between ``POSI`` points (not between two
  points on different floors); BLE readings of the ``--ble-window-s`` before each WiFi scan join it as
  entries ``ble:<beacon id>`` (:mod:`indoor_loc.wifi.ble`). Survey logs: ``--survey`` (log names), else
  every log with two or more ``POSI`` points;
- ``OUT_DIR/map_origin.yaml`` — the map frame: ENU at ``--origin LAT,LON`` (default: the
  ``map_origin.yaml`` beside the logs, as ``indoor-loc bag to-getsensordata`` writes it, else the first
  ``POSI`` point of the first log that has one), floor id × ``--storey-height-m`` = z;
- with ``--floor-plans PLANS.yaml`` (floor plans given as images with reference points, pixel -> latitude,
  longitude: :mod:`indoor_loc.datasets.plan_georef`): ``OUT_DIR/floors/floor<id>/plan.png`` + ``map.yaml``
  (nav2 keys; the image resampled onto the map axes) and, with one floor, ``OUT_DIR/graph.yaml`` (its
  skeleton graph seeded at the radio map's scan positions) for ``tll_pf``;
- ``OUT_DIR/params.yaml`` — every node (imu_node, wifi_fix_node with the radio map and ``ble.enabled`` when
  the map holds beacons, pdr_kf_node, backend_node); ``OUT_DIR/import_report.md`` — per-log counts,
  clocks and what was odd.
"""
from __future__ import annotations

import argparse
import math
import shutil
from pathlib import Path

import numpy as np
import yaml

from indoor_loc.errors import ConfigError, DatasetError
from indoor_loc.output_paths import check_outputs
from indoor_loc.params import params_file_text

STOREY_HEIGHT_M = 4.0
BLE_WINDOW_S = 5.0
_SUFFIXES = (".txt", ".txt.gz", ".log", ".log.gz")


def add_arguments(sub) -> None:
    p = sub.add_parser("getsensordata", help="GetSensorData logfiles (IPIN competition smartphone tracks)",
                       description="Import GetSensorData logs into MCAP bags (one per log), a WiFi + BLE radio "
                                   "map from the logs' reference points, params.yaml and an import report")
    p.add_argument("logs", nargs="+", type=Path, metavar="LOG", help="logfiles or directories of them")
    p.add_argument("out_dir", type=Path, metavar="OUT_DIR", help="output directory (created)")
    p.add_argument("--origin", default="", help="map origin LAT,LON in degrees (default: the first POSI point)")
    p.add_argument("--storey-height-m", type=float, default=None,
                   help=f"z = floor id x this, m (default: map_origin.yaml beside the logs, else {STOREY_HEIGHT_M:g})")
    p.add_argument("--survey", default="", help="comma-separated log names that build the radio map "
                                                "(default: every log with two or more POSI points)")
    p.add_argument("--ble-window-s", type=float, default=BLE_WINDOW_S,
                   help=f"BLE readings this long before a WiFi scan join its fingerprint, s (default {BLE_WINDOW_S:g})")
    p.add_argument("--floor-plans", type=Path, default=None,
                   help="YAML list of floor plans given as images with reference points: {floor: ID, image: FILE "
                        "(relative to the YAML), points: [[u, v, lat, lon], ...]} (u, v: pixel column and row from "
                        "the top-left; two or more points); written to OUT_DIR/floors/, and with one floor the "
                        "building graph for tll_pf")
    p.add_argument("--overwrite", action="store_true",
                   help="replace bags, radiomap/, floors/, graph.yaml, params.yaml, map_origin.yaml and "
                        "import_report.md already in OUT_DIR")
    p.set_defaults(func=import_getsensordata)


def find_logs(paths: list[Path]) -> list[Path]:
    """Logfiles named or inside the named directories (sorted; ConfigError if none or missing)."""
    out: list[Path] = []
    for p in paths:
        if p.is_dir():
            out += sorted(f for f in p.iterdir() if f.is_file() and f.name.lower().endswith(_SUFFIXES))
        elif p.is_file():
            out.append(p)
        else:
            raise ConfigError(f"LOG {p} does not exist")
    if not out:
        raise ConfigError(f"no logfiles ({', '.join(_SUFFIXES)}) in {', '.join(map(str, paths))}")
    return out


def _origin_beside(inputs: list[Path]) -> dict:
    """``map_origin.yaml`` in the directory of the first LOG (as ``indoor-loc bag to-getsensordata``
    writes it), or {} when there is none or it is unreadable."""
    first = inputs[0] if inputs else None
    if first is None:
        return {}
    f = (first if first.is_dir() else first.parent) / "map_origin.yaml"
    try:
        d = yaml.safe_load(f.read_text()) if f.is_file() else None
        if isinstance(d, dict) and {"latitude_deg", "longitude_deg"} <= set(d):
            return {**d, "_file": str(f)}
    except (OSError, yaml.YAMLError):
        pass
    return {}


def parse_origin(text: str) -> tuple[float, float] | None:
    if not text.strip():
        return None
    try:
        lat, lon = (float(v) for v in text.split(","))
    except ValueError as err:
        raise ConfigError(f"--origin: expected LAT,LON in degrees, got {text!r}") from err
    if not (-90 <= lat <= 90 and -180 <= lon <= 180):
        raise ConfigError(f"--origin: latitude in [-90, 90] and longitude in [-180, 180], got {text!r}")
    return lat, lon


def import_getsensordata(args: argparse.Namespace) -> int:
    from indoor_loc.backend.graph import FIX_GRAPH_PARAMS
    from indoor_loc.datasets.getsensordata import ble_scans, read_log, wifi_scans
    from indoor_loc.datasets.getsensordata_bags import (log_name, log_namespace, positions_at, truth_of,
                                                        write_log_bag)
    from indoor_loc.wifi.ble import is_ble_key, merge_scans
    from indoor_loc.wifi.methods import recommended_params
    from indoor_loc.wifi.radiomap import add_fingerprints, empty_radiomap, save_radiomap

    paths = list(getattr(args, "paths", None) or [*args.logs, args.out_dir])
    if len(paths) < 2:
        raise ConfigError("expected LOG... OUT_DIR (at least one log and the output directory)")
    *inputs, out = paths
    beside = _origin_beside(inputs)
    h = args.storey_height_m if args.storey_height_m is not None else \
        float(beside.get("storey_height_m", STOREY_HEIGHT_M)) if beside else STOREY_HEIGHT_M
    if not (h > 0 and math.isfinite(h)):
        raise ConfigError(f"--storey-height-m: expected > 0, got {h}")
    if not 0 < args.ble_window_s <= 600:
        raise ConfigError(f"--ble-window-s: expected in (0, 600], got {args.ble_window_s}")
    logs = find_logs(inputs)
    out = Path(out).resolve()
    if out.exists() and not out.is_dir():
        raise ConfigError(f"OUT_DIR {out} exists and is not a directory")
    names = [log_name(p) for p in logs]
    nss = [log_namespace(p) for p in logs]
    if len(set(nss)) != len(nss):
        raise ConfigError(f"two logs give the same namespace: {sorted(n for n in nss if nss.count(n) > 1)}")
    survey_sel = {t.strip() for t in args.survey.split(",") if t.strip()}
    bad = survey_sel - set(names)
    if bad:
        raise ConfigError(f"--survey: no log(s) {sorted(bad)}; the logs are {names}")
    bags = [out / f"{ns.strip('/')}.mcap" for ns in nss]
    plans_spec = _read_plan_spec(args.floor_plans) if getattr(args, "floor_plans", None) else []
    check_outputs([*bags, out / "radiomap", out / "params.yaml", out / "map_origin.yaml", out / "import_report.md",
                   *([out / "floors", out / "graph.yaml"] if plans_spec else [])],
                  overwrite=args.overwrite, what="import getsensordata")
    origin = parse_origin(args.origin)
    origin_note = "--origin"
    if origin is None and beside:
        origin = (float(beside["latitude_deg"]), float(beside["longitude_deg"]))
        origin_note = f"{beside['_file']}"
    parsed = []
    skipped: list[str] = []
    for p in logs:
        try:
            parsed.append(read_log(p))
        except DatasetError as err:           # one unreadable log must not lose the others
            skipped.append(f"{p.name}: {err}")
    if not parsed:
        raise DatasetError("no log could be read: " + "; ".join(skipped))
    if origin is None:
        first = next((lg for lg in parsed if len(lg.posi)), None)
        origin = (float(first.posi.lat[0]), float(first.posi.lon[0])) if first is not None else (0.0, 0.0)
        origin_note = ("the first POSI point of " + first.path.name) if first is not None else \
            "no log has POSI points: (0, 0), positions are meaningless"
    out.mkdir(parents=True, exist_ok=True)
    rm = empty_radiomap()
    rows = []
    for log in parsed:
        name, ns = log_name(log.path), log_namespace(log.path)
        scans, dup = wifi_scans(log, source=name)
        bles = ble_scans(log, source=name)
        if dup:
            log.oddities.append(f"WIFI: {dup} BSSIDs repeated within a scan (kept the newest result)")
        tt, txy, _tz, tfl = truth_of(log, origin, h)
        survey = (name in survey_sel) if survey_sel else len(log.posi) >= 2
        in_map = 0
        if survey and scans:
            fused = merge_scans(scans, bles, args.ble_window_s)
            xy, fl, ok = positions_at([s.stamp_ns for s in fused], tt, txy, tfl)
            cross = int(np.sum(~ok & (np.array([s.stamp_ns for s in fused]) >= (tt[0] if len(tt) else 0))
                               & (np.array([s.stamp_ns for s in fused]) <= (tt[-1] if len(tt) else -1))))
            if cross:
                log.oddities.append(f"{cross} scans between POSI points on different floors: not in the radio map")
            keep = np.flatnonzero(ok)
            if len(keep):
                zs = fl[keep].astype(float) * h
                rm = add_fingerprints(rm, xy[keep], [fused[i] for i in keep], source=name, z_m=zs,
                                      floors={_floor_name(int(f)): float(f) * h for f in np.unique(fl[keep])})
            in_map = len(keep)
        bag = out / f"{ns.strip('/')}.mcap"
        counts = write_log_bag(log, bag, origin=origin, storey_height_m=h, namespace=ns, scans=scans, bles=bles)
        rows.append({"log": name, "ns": ns, "role": "survey" if survey else "test", "duration_s": log.duration_s,
                     "posi": len(log.posi), "floors": ",".join(str(f) for f in sorted(set(log.posi.floor.tolist()))),
                     "scans": len(scans), "in_map": in_map, "ble": len(bles),
                     "messages": sum(counts.values()), "lines": sum(log.counts.values()),
                     "oddities": len(log.oddities)})
    rm_dir = out / "radiomap"
    if rm.n_scans:
        save_radiomap(rm, rm_dir, created_by="indoor-loc import getsensordata", inputs=[str(p) for p in logs])
    elif rm_dir.exists():                    # --overwrite: an earlier import's map must not stay beside these
        shutil.rmtree(rm_dir)
    n_ble = sum(1 for b in rm.bssids if is_ble_key(b))
    (out / "map_origin.yaml").write_text(
        "# the map frame of these bags: ENU (x east, y north, z up) tangent to WGS84 at the origin, height 0;\n"
        "# z = floor id x storey_height_m\n"
        + yaml.safe_dump({"frame_id": "map", "latitude_deg": origin[0], "longitude_deg": origin[1],
                          "storey_height_m": h, "from": origin_note}, sort_keys=False))
    plan_rows, graph_file = write_floor_plans(plans_spec, origin, h, out, rm) if plans_spec else ([], None)
    has_ahrs = all("AHRS" in lg.sensors for lg in parsed)
    params: dict = {"imu_node": {"heading_source": "orientation" if has_ahrs else "auto"}, "pdr_kf_node": {}}
    if rm.n_scans:
        wifi = {"radiomap": str(rm_dir), **recommended_params(rm)}
        if n_ble:
            wifi["ble"] = {"enabled": True, "window_s": float(args.ble_window_s)}
        params["wifi_fix_node"] = wifi
        params["backend_node"] = {"radiomap": str(rm_dir), **FIX_GRAPH_PARAMS}
    if graph_file is not None:
        params["tll_pf"] = {"graph_file": str(graph_file)}
    (out / "params.yaml").write_text(params_file_text(params, header=(
        "Written by `indoor-loc import getsensordata`. Map frame: ENU at map_origin.yaml, z = floor id x "
        f"{h:g} m.\nimu_node: heading from the logged AHRS rotation vector (magnetic north) when every log has "
        "one, else its own filter.\nNo building graph is imported (tll_pf needs one: `indoor-loc map`).\n"
        "Keys /**/<node> reach the node in any namespace (ros2 run ... -r __ns:=/<log> --params-file).")))
    report = _report(parsed, rows, rm, n_ble, origin, origin_note, h, skipped) + _plans_note(plan_rows)
    (out / "import_report.md").write_text(report)
    print(_table(rows))
    if rm.n_scans:
        print(f"\nradio map: {rm_dir} ({rm.n_scans} scans, {rm.n_aps - n_ble} APs + {n_ble} beacons)")
    else:
        print("\nradio map: NONE (no survey log has scans between two POSI points)")
    print(f"origin:    {origin[0]:.8f}, {origin[1]:.8f} ({origin_note})")
    print(f"params:    {out / 'params.yaml'}\nreport:    {out / 'import_report.md'}")
    print(f"oddities:  {sum(len(lg.oddities) for lg in parsed)} (see the report)")
    if skipped:
        print(f"SKIPPED {len(skipped)} unreadable log(s): " + "; ".join(skipped))
    return 0


def _read_plan_spec(path: Path) -> list[dict]:
    """The ``--floor-plans`` YAML as a checked list of {floor, image (Path), points (N, 4)} (ConfigError)."""
    try:
        spec = yaml.safe_load(Path(path).read_text())
    except (OSError, yaml.YAMLError) as err:
        raise ConfigError(f"--floor-plans {path}: cannot read it: {err}") from err
    if not isinstance(spec, list) or not spec:
        raise ConfigError(f"--floor-plans {path}: expected a YAML list of {{floor, image, points}}")
    out = []
    for i, e in enumerate(spec):
        try:
            pts = np.asarray(e["points"], float)
            floor, image = int(e["floor"]), Path(path).parent / str(e["image"])
        except (KeyError, TypeError, ValueError) as err:
            raise ConfigError(f"--floor-plans {path}: entry {i}: expected floor (int), image and points "
                              f"[[u, v, lat, lon], ...]: {err}") from err
        if pts.ndim != 2 or pts.shape[1] != 4 or len(pts) < 2 or not np.all(np.isfinite(pts)):
            raise ConfigError(f"--floor-plans {path}: entry {i}: points must be two or more [u, v, lat, lon]")
        if not image.is_file():
            raise ConfigError(f"--floor-plans {path}: entry {i}: image {image} does not exist")
        out.append({"floor": floor, "image": image, "points": pts})
    if len({e["floor"] for e in out}) != len(out):
        raise ConfigError(f"--floor-plans {path}: a floor is given twice")
    return out


def write_floor_plans(spec: list[dict], origin: tuple[float, float], h: float, out: Path, rm) -> tuple[list[dict], Path | None]:
    """Each plan aligned with the map frame into ``OUT/floors/floor<id>/`` (``plan.png`` + nav2 ``map.yaml``
    with the floor and its z); with one floor, its skeleton graph (seeded at the radio map's scan positions)
    as ``OUT/graph.yaml``. Returns a report row per plan and the graph file (None: none)."""
    from PIL import Image

    from indoor_loc.datasets.geodesy import geodetic_to_enu
    from indoor_loc.datasets.plan_georef import align_plan, fit_plan_ref
    from indoor_loc.errors import MapError
    from indoor_loc.graph.from_image import read_plan
    rows, aligned = [], []
    for e in spec:
        grey = read_plan(e["image"])
        pts = e["points"]
        ref = fit_plan_ref(pts[:, :2], geodetic_to_enu(pts[:, 2], pts[:, 3], *origin), grey.shape[0])
        img, lo, res = align_plan(grey, ref)
        d = out / "floors" / _floor_name(e["floor"])
        d.mkdir(parents=True, exist_ok=True)
        Image.fromarray(img).save(d / "plan.png")
        meta = {"image": "plan.png", "resolution": float(res), "origin": [float(lo[0]), float(lo[1]), 0.0], "negate": 0,
                "occupied_thresh": 0.65, "free_thresh": 0.196, "mode": "trinary", "floor": int(e["floor"]),
                "z_m": float(e["floor"] * h), "frame_id": "map", "source": str(e["image"])}
        (d / "map.yaml").write_text("# floor plan in the map frame (nav2 map_server keys + floor and height)\n"
                                    + yaml.safe_dump(meta, sort_keys=False))
        rows.append({"floor": e["floor"], "image": e["image"].name, "points": len(pts), "m_per_px": res,
                     "rotation_deg": math.degrees(ref.theta_rad), "rms_m": ref.rms_m, "dir": d})
        aligned.append((img, lo, res, e["floor"]))
    graph_file = None
    if len(aligned) == 1 and rm.n_scans:
        from indoor_loc.graph.from_image import PlanParams, skeleton_graph
        from indoor_loc.graph.io import save_graph
        img, lo, res, floor = aligned[0]
        pp = PlanParams(px_per_m=1.0 / res, origin_x_m=float(lo[0]), origin_y_m=float(lo[1]))
        try:
            g = skeleton_graph(img, pp, seeds_xy=np.asarray(rm.positions, float))
            graph_file = save_graph(g, out / "graph.yaml", source={
                "tool": "indoor-loc import getsensordata", "image": rows[0]["image"], "px_per_m": pp.px_per_m,
                "origin_m": [pp.origin_x_m, pp.origin_y_m], "seeds": "radio map scan positions"})
        except MapError as err:
            rows[0]["graph"] = f"no graph: {err}"
    return rows, graph_file


def _plans_note(rows: list[dict]) -> str:
    if not rows:
        return ""
    lines = ["", "## Floor plans", "", "Aligned with the map frame from their reference points (least-squares "
             "similarity; RMS = the residual at the points).", "",
             "| floor | image | points | m/px | rotation deg | RMS m | written |", "|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['floor']} | {r['image']} | {r['points']} | {r['m_per_px']:.4f} | {r['rotation_deg']:.2f} | "
                     f"{r['rms_m']:.2f} | `{r['dir'].name}/`{'; ' + r['graph'] if 'graph' in r else ''} |")
    return "\n".join(lines) + "\n"


def _floor_name(floor_id: int) -> str:
    return f"floor{floor_id}"


_COLS = [("log", "log", "{}"), ("role", "role", "{}"), ("duration_s", "duration s", "{:.1f}"),
         ("posi", "POSI", "{}"), ("floors", "floors", "{}"), ("scans", "WiFi scans", "{}"),
         ("in_map", "in radio map", "{}"), ("ble", "BLE scans", "{}"), ("lines", "lines", "{}"),
         ("messages", "messages", "{}"), ("oddities", "oddities", "{}")]


def _table(rows: list[dict]) -> str:
    lines = ["| " + " | ".join(c[1] for c in _COLS) + " |", "|" + "---|" * len(_COLS)]
    for r in rows:
        lines.append("| " + " | ".join(f.format(r[k]) for k, _, f in _COLS) + " |")
    return "\n".join(lines)


def _report(parsed, rows, rm, n_ble, origin, origin_note, h, skipped) -> str:
    from indoor_loc.datasets.getsensordata import KNOWN_UNUSED
    lines = ["# GetSensorData import report", "",
             f"{len(parsed)} logs; map frame ENU at {origin[0]:.8f}, {origin[1]:.8f} ({origin_note}); z = floor id × "
             f"{h:g} m.", "",
             "Conventions: bag time = the header's creation date + AppTimestamp (ns). Inertial, magnetic, pressure "
             "and AHRS samples are stamped on their own sensor clock shifted onto the app clock by the least read "
             "delay (`offset` below); a WiFi scan = the WIFI lines of one AppTimestamp (age_ms = the scan's newest "
             "result time − the AP's); a BLE scan = the BLE4 lines of one AppTimestamp; ground_truth = the POSI "
             "points (linear in between is an assumption).", "",
             (f"Radio map: `radiomap/`, {rm.n_scans} scans, {rm.n_aps - n_ble} WiFi APs and {n_ble} BLE beacons "
              "(keys `ble:<id>`)." if rm.n_scans else "Radio map: **none** (no survey log has scans between two "
              "POSI points)."), "", "## Logs", "", _table(rows), "", "## Lines per type", "",
             "| log | " + " | ".join(_TYPES) + " | other |", "|---|" + "---|" * (len(_TYPES) + 1)]
    for lg in parsed:
        other = {k: v for k, v in lg.counts.items() if k not in _TYPES}
        lines.append(f"| {lg.path.name} | " + " | ".join(str(lg.counts.get(t, 0)) for t in _TYPES) + " | "
                     + (", ".join(f"{k} {v}" for k, v in sorted(other.items())) or "") + " |")
    lines += ["", f"Read and counted, not converted (no topic of the message contract): {', '.join(KNOWN_UNUSED)}.",
              "", "## Clocks", "",
              "Per sensor: samples, rate from the sensor clock, offset sensor → app clock, read delay (app time − "
              "aligned sensor time) median / 99th percentile, drift of the offset between the first and last "
              "third, and whether the sensor had to be stamped on the app clock.", "",
              "| log | sensor | samples | rate Hz | offset s | delay median ms | delay p99 ms | drift ppm | stamped on |",
              "|---|---|---|---|---|---|---|---|---|"]
    for lg in parsed:
        for typ, c in lg.clock.items():
            lines.append(f"| {lg.path.name} | {typ} | {int(c['samples'])} | {c['rate_hz']:.1f} | {c['offset_s']:.4f} | "
                         f"{c['read_delay_median_ms']:.1f} | {c['read_delay_p99_ms']:.1f} | "
                         f"{c.get('drift_ppm', float('nan')):.0f} | {'app clock' if c['app_clock'] else 'sensor clock'} |")
    lines += ["", f"## Oddities ({sum(len(lg.oddities) for lg in parsed)})", ""]
    for lg in parsed:
        lines += [f"- {lg.path.name}: {o}" for o in lg.oddities]
    if not any(lg.oddities for lg in parsed):
        lines.append("(none)")
    if skipped:
        lines += ["", "## Skipped (unreadable)", ""] + [f"- {s}" for s in skipped]
    return "\n".join(lines) + "\n"


_TYPES = ("ACCE", "GYRO", "MAGN", "PRES", "AHRS", "WIFI", "BLE4", "POSI")
