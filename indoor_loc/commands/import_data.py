"""``indoor-loc import DATASET ...``: convert a dataset into MCAP bags + params.yaml.

One subparser per dataset (``putmc``; ``ms-indoor``: :mod:`indoor_loc.commands.import_ms_indoor`;
``getsensordata``: :mod:`indoor_loc.commands.import_getsensordata`); each
adds its own arguments and a ``func``.

``indoor-loc import putmc DATASET_DIR OUT_DIR [--walks 1,2,7] [--keep-stale]`` writes
``OUT_DIR/walkNN.mcap`` (namespace ``/walkNN``; topics in :mod:`indoor_loc.datasets.putmc_bags`),
``OUT_DIR/radiomap/`` (the 114-scan survey map), ``OUT_DIR/params.yaml`` (imu_node with the
phone's orientation as heading; wifi_fix_node with that radio map and WKNN) and
``OUT_DIR/import_report.md`` (per-walk counts, durations, oddities), and prints the summary.
"""
from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np

from indoor_loc.backend.putmc_events import PUTMC_GRAPH_PARAMS
from indoor_loc.errors import ConfigError, DatasetError
from indoor_loc.wifi.methods import recommended_params
from indoor_loc.output_paths import check_outputs
from indoor_loc.params import params_file_text
from indoor_loc.wifi.radiomap import save_radiomap


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="dataset", metavar="DATASET", required=True)
    p = sub.add_parser("putmc", help="PUTMC (multi-user graph paper, Xperia Z3, 24 walks)",
                       description="Import PUTMC walks into MCAP bags (one per walk) + radio map + params.yaml")
    p.add_argument("dataset_dir", type=Path, help="the putmc/ directory (GT/, PUTMC_Floor3_Xperia_*/, map.png)")
    p.add_argument("out_dir", type=Path, help="output directory (created)")
    p.add_argument("--walks", default="", help="comma-separated walk numbers (default: all), e.g. 1,2,7")
    p.add_argument("--keep-stale", action="store_true",
                   help="keep the stale samples recorded before the start gap (default: drop them)")
    p.add_argument("--map-yaw-deg", type=float, default=None,
                   help="yaw added to the phone's ENU orientation to align it with the map frame, deg "
                        "(default: the dataset estimate, about 7.8; 0 = raw Android ENU)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--overwrite", action="store_true",
                   help="replace walk bags, radiomap/, params.yaml and import_report.md already in OUT_DIR")
    p.set_defaults(func=import_putmc)
    from indoor_loc.commands import import_ms_indoor
    import_ms_indoor.add_arguments(sub)
    from indoor_loc.commands import import_getsensordata
    import_getsensordata.add_arguments(sub)


def main(args: argparse.Namespace) -> int:
    return int(args.func(args) or 0)


def parse_walks(text: str, available: list[int]) -> list[int]:
    """``"1,2,7"`` -> [1, 2, 7] (empty -> all available); unknown numbers raise ConfigError."""
    if not text.strip():
        return list(available)
    try:
        walks = sorted({int(t) for t in text.split(",") if t.strip()})
    except ValueError as err:
        raise ConfigError(f"--walks: expected comma-separated integers, got {text!r}") from err
    bad = [w for w in walks if w not in available]
    if bad:
        raise ConfigError(f"--walks: no walk(s) {bad}; the dataset has {available}")
    return walks


def import_putmc(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from indoor_loc.datasets.putmc import PUTMC_MAP_YAW_RAD, Putmc, estimate_map_yaw
    from indoor_loc.datasets.putmc_bags import walk_bag_counts, write_walk_bag

    ds = Putmc(args.dataset_dir)
    walks = parse_walks(args.walks, ds.walk_numbers)
    map_yaw = PUTMC_MAP_YAW_RAD if args.map_yaw_deg is None else math.radians(args.map_yaw_deg)
    out = Path(args.out_dir).resolve()
    if out.exists() and not out.is_dir():
        raise ConfigError(f"OUT_DIR {out} exists and is not a directory")
    check_outputs([out / f"walk{n:02d}.mcap" for n in walks]
                  + [out / "radiomap", out / "params.yaml", out / "import_report.md"],
                  overwrite=args.overwrite, what=f"import into {out}")
    out.mkdir(parents=True, exist_ok=True)

    survey = ds.survey_map()
    rm_dir = out / "radiomap"
    save_radiomap(survey, rm_dir)

    graph_file = putmc_graph(ds, survey, out)

    parsed = []
    for n in walks:
        parsed.append(ds.walk(n, keep_stale=args.keep_stale))
    total = sum(sum(walk_bag_counts(w).values()) for w in parsed)
    rows = []
    with tqdm(total=total, unit="msg", desc="import putmc", disable=args.no_progress) as bar:
        for w in parsed:
            bar.set_postfix_str(w.name)
            bag = out / f"{w.name}.mcap"
            counts = write_walk_bag(w, ds.routes[w.walk], bag, map_yaw_rad=map_yaw, progress=bar.update)
            bar.update(sum(counts.values()) - len(w.acc_t))   # IMU messages were counted as written
            rows.append(_row(w, ds.routes[w.walk].length_m, counts))

    params = {"imu_node": {"heading_source": "orientation", "step_length_m": 0.65},
              "wifi_fix_node": {"radiomap": str(rm_dir), **recommended_params(survey)},
              # Nowicki & Skrzypczyński 2019's joint + step-length configuration: walks one after another
              # (1…24), each matching the survey and all earlier walks' scans; information from measured
              # noise and a Huber kernel on the WKNN hyperedges (see PUTMC_GRAPH_PARAMS)
              "backend_node": {"radiomap": str(rm_dir), "offline_order": "sequential", **PUTMC_GRAPH_PARAMS},
              "tll_pf": {"graph_file": str(graph_file)}}
    (out / "params.yaml").write_text(params_file_text(params, header=(
        "Written by `indoor-loc import putmc`. imu/data carries the phone's orientation rotated into the\n"
        f"map frame (map yaw {math.degrees(map_yaw):.2f} deg), so the PDR heading is its yaw (offset 0).\n"
        "Keys /**/<node> reach the node in any namespace (ros2 run ... -r __ns:=/walkNN --params-file).")))
    oddities = ds.oddities + [o for w in parsed for o in w.oddities]
    try:
        yaw_est, yaw_per = estimate_map_yaw(parsed)
        yaw_note = (f"Heading check: walking direction − phone yaw (Android ENU) over these walks = "
                    f"{math.degrees(yaw_est):.1f}° pooled, per walk "
                    f"{math.degrees(min(yaw_per.values())):.0f}…{math.degrees(max(yaw_per.values())):.0f}° "
                    f"(applied: {math.degrees(map_yaw):.2f}°; indoor magnetic disturbance makes it wander)")
    except DatasetError as err:
        yaw_note = f"Heading check: {err}."
    report = _report(args, rows, oddities, survey, map_yaw, yaw_note)
    (out / "import_report.md").write_text(report)
    print(_table(rows))
    print(f"\nradio map: {rm_dir} ({survey.n_scans} scans, {survey.n_aps} APs)")
    print(f"params:    {out / 'params.yaml'}\nreport:    {out / 'import_report.md'}")
    print(f"\noddities ({len(oddities)}):")
    for o in oddities:
        print(f"  walk {o.walk:2d}  {o.kind:24s} {o.detail}")
    return 0


def putmc_graph(ds, survey, out: Path) -> Path:
    """The floor's building graph from ``map.png`` (skeleton of the free space inside the building
    envelope, seeded at the survey scan positions; the plan's light strokes — door leaves, glazing —
    are passable, see :mod:`indoor_loc.graph.from_image`), written to ``OUT/graph.yaml``."""
    from indoor_loc.datasets.putmc import PUTMC_SCALE_PX_PER_M
    from indoor_loc.graph.from_image import PlanParams, read_plan, skeleton_graph
    from indoor_loc.graph.io import save_graph

    params = PlanParams(px_per_m=PUTMC_SCALE_PX_PER_M)
    g = skeleton_graph(read_plan(ds.map_png()), params, seeds_xy=survey.positions)
    path = save_graph(g, out / "graph.yaml", source={
        "tool": "indoor-loc import putmc", "image": "map.png", "px_per_m": PUTMC_SCALE_PX_PER_M,
        "wall_threshold": params.wall_threshold, "clearance_m": params.clearance_m,
        "envelope_gap_m": params.envelope_gap_m, "seeds": "survey scan positions"})
    print(f"graph:     {path} ({g.n_nodes} nodes, {g.n_links} links, {g.link_len.sum():.0f} m)")
    return path


def _row(w, gt_len_m: float, counts: dict[str, int]) -> dict:
    st = w.scan_t
    aps = np.mean([len(s) for s in w.scans]) if w.scans else float("nan")
    return {
        "walk": w.walk, "folder": w.folder,
        "acc_raw": w.raw_counts["acc"], "acc_dropped": w.dropped["acc"],
        "orient_raw": w.raw_counts["orient"], "orient_dropped": w.dropped["orient"],
        "scans": len(w.scans), "scans_dropped": w.dropped["wifi"], "aps_per_scan": float(aps),
        "imu_msgs": counts.get(f"/{w.name}/imu/data", 0), "scan_msgs": counts.get(f"/{w.name}/wifi/scan", 0),
        "duration_s": (w.end_ns - w.start_ns) * 1e-9,
        "wifi_span_s": float((st[-1] - st[0]) * 1e-9) if len(st) > 1 else 0.0,
        "gt_len_m": gt_len_m, "n_oddities": len(w.oddities),
    }


_COLS = [("walk", "walk", "{}"), ("folder", "folder", "{}"), ("acc_raw", "acc lines", "{}"),
         ("acc_dropped", "acc dropped (stale)", "{}"), ("orient_raw", "orient lines", "{}"),
         ("orient_dropped", "orient dropped (stale)", "{}"), ("scans", "scans", "{}"),
         ("aps_per_scan", "AP/scan", "{:.1f}"),
         ("imu_msgs", "imu/data msgs", "{}"), ("scan_msgs", "wifi/scan msgs", "{}"),
         ("duration_s", "duration s", "{:.1f}"), ("wifi_span_s", "1st→last scan s", "{:.1f}"),
         ("gt_len_m", "GT length m", "{:.1f}"), ("n_oddities", "oddities", "{}")]


def _table(rows: list[dict]) -> str:
    """Markdown table of the per-walk rows plus a total line."""
    head = "| " + " | ".join(c[1] for c in _COLS) + " |"
    lines = [head, "|" + "---|" * len(_COLS)]
    for r in rows:
        lines.append("| " + " | ".join(fmt.format(r[k]) for k, _, fmt in _COLS) + " |")
    tot = {k: ("" if k in ("folder", "aps_per_scan", "walk") else fmt.format(sum(r[k] for r in rows)))
           for k, _, fmt in _COLS}
    tot["walk"] = "**total**"
    lines.append("| " + " | ".join(tot[k] for k, _, _ in _COLS) + " |")
    return "\n".join(lines)


def _report(args, rows, oddities, survey, map_yaw, yaw_note) -> str:
    from indoor_loc.datasets.putmc import PUTMC_Y0
    lines = [
        "# PUTMC import report", "",
        f"Dataset: `{Path(args.dataset_dir).resolve()}`; walks: {', '.join(str(r['walk']) for r in rows)}; "
        f"stale samples {'kept' if args.keep_stale else 'dropped'}.", "",
        "Conventions: time = the phone's boot clock in int ns, as in the files (bag log time = header "
        f"stamp). Map frame ENU: x = x_img, y = {PUTMC_Y0:.4f} m − y_img (map.png bottom-left at (0, 0)). "
        f"imu/data orientation = Android rotation vector (device→ENU) rotated by {math.degrees(map_yaw):.2f}° "
        "about z into the map frame; yaw variance = headingAcc²; no gyroscope (angular_velocity_covariance[0] = "
        "−1). ground_truth = time-stamped true scan positions (nav_msgs/Path); ground_truth/route = GT route "
        "LINE_LIST (MarkerArray); both latched, written once at the walk's first stamp.", "",
        f"Radio map: `radiomap/`, {survey.n_scans} survey scans, {survey.n_aps} APs.", "", yaw_note, "",
        "## Walks", "", _table(rows), "",
        "Counts: `acc lines`/`orient lines` are the raw file lines; `imu/data msgs` = acc lines − acc dropped "
        "(one message per accelerometer sample).", "",
        f"## Oddities ({len(oddities)})", "",
    ]
    lines += [f"- walk {o.walk}: **{o.kind}** — {o.detail}" for o in oddities] or ["(none)"]
    return "\n".join(lines) + "\n"
