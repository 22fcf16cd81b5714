"""``indoor-loc radiomap build|fit|info``: make and inspect radio maps (format: :mod:`indoor_loc.wifi.radiomap`).

``indoor-loc radiomap build BAG... --out DIR [--topic-scan wifi/scan] [--topic-truth ground_truth]
[--putmc DATASET_DIR] [--method wknn] [--floor-plans PLANS_DIR] [--overwrite]``

- From bags: every ``wifi/scan`` becomes a fingerprint at the ground-truth position linearly
  interpolated at the scan's stamp, the truth being the time-stamped ``nav_msgs/Path`` on
  ``ground_truth`` *in the same namespace* (``/walk07/wifi/scan`` pairs with
  ``/walk07/ground_truth``; all Path messages of a namespace are merged). Scans outside the path's
  time span, namespaces without truth and invalid scans are skipped and counted. The fingerprint's
  ``source`` is the namespace (``walk07``) or, without one, the bag's file stem.
- ``--putmc DATASET_DIR``: the PUTMC survey map (114 scans; ENU ``y = PUTMC_Y0 - y_img``); with
  bags too, their fingerprints are added to it.

It also writes ``DIR/params.yaml`` configuring ``wifi_fix_node`` for the map
(``radiomap: <absolute DIR>``, ``method``; with ``--floor-plans`` also ``floor_plans`` and powed k-NN's
path-loss field inside the plans, as ``indoor-loc import ms-indoor`` configures it), so ``indoor-loc run OTHER.mcap --params DIR/params.yaml
--nodes wifi --out X.mcap`` positions another recording of the same building as is.

``indoor-loc radiomap fit [DIR] --params PARAMS [--refit]`` fits ``wifi_fix_node``'s positioner as PARAMS
configures it and saves the fit where the node loads it at start-up (:mod:`indoor_loc.wifi.fit_store`;
by default ``DIR/fit_cache``), so the node is ready in about a second instead of after the fit.

``indoor-loc radiomap info DIR`` prints the manifest's figures, per-source counts, the AP count
distribution and the map spacing.

An existing map (or ``params.yaml``) in DIR is refused unless ``--overwrite``.
"""
from __future__ import annotations

import argparse
from collections import Counter, defaultdict
from pathlib import Path
from typing import Callable

import numpy as np

from indoor_loc.contract import namespace_of_topic
from indoor_loc.errors import ConfigError, InvalidMessageError, MapError
from indoor_loc.params import params_file_text
from indoor_loc.wifi.radiomap import (add_fingerprints, empty_radiomap, interpolate_positions, load_radiomap,
                                      nominal_spacing_m, radiomap_summary, read_manifest, save_radiomap)
from indoor_loc.wifi.types import RadioMap


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="action", metavar="ACTION", required=True)
    b = sub.add_parser("build", help="build a radio map from bags with ground truth and/or the PUTMC map files")
    b.add_argument("bags", nargs="*", type=Path, help="MCAP bags (files or rosbag2 directories)")
    b.add_argument("--out", type=Path, required=True, help="radio map directory to write")
    b.add_argument("--topic-scan", default="wifi/scan", help="relative scan topic (default wifi/scan)")
    b.add_argument("--topic-truth", default="ground_truth",
                   help="relative nav_msgs/Path topic with time-stamped true positions (default ground_truth)")
    b.add_argument("--putmc", type=Path, help="PUTMC dataset directory: start from its 114-scan survey map")
    b.add_argument("--method", default="auto",
                   help="method written to DIR/params.yaml (default auto: powed k-NN for maps with reading ages or "
                        "several floors, else the best measured WKNN with a powed fallback)")
    b.add_argument("--floor-plans", type=Path,
                   help="floor plans of the building (a directory of <floor>/map.yaml + geojson_map.json, as "
                        "`indoor-loc import ms-indoor` writes in OUT/floors): params.yaml then has powed k-NN "
                        "extrapolate the map inside the plans (the path-loss field)")
    b.add_argument("--overwrite", action="store_true", help="replace an existing radio map in --out")
    i = sub.add_parser("info", help="summarise a radio map directory")
    i.add_argument("directory", type=Path)
    f = sub.add_parser("fit", help="fit wifi_fix_node's positioner to its radio map ahead of time and save the fit "
                                   "where the node loads it at start-up (fit_cache)")
    f.add_argument("radiomap", type=Path, nargs="?",
                   help="radio map directory (default: the params file's wifi_fix_node radiomap)")
    f.add_argument("--params", type=Path, required=True,
                   help="the params file the node runs with (e.g. an importer's OUT/params.yaml)")
    f.add_argument("--namespace", default="", help="the node's namespace, for params files keyed by it (default: root)")
    f.add_argument("--cache-dir", help="save the fit here (default: the params' fit_cache_dir, else RADIOMAP/fit_cache)")
    f.add_argument("--refit", action="store_true", help="fit and save even when the saved fit is up to date")


def fingerprints_from_bags(bags: list[Path], *, topic_scan: str = "wifi/scan",
                           topic_truth: str = "ground_truth") -> tuple[list, np.ndarray, list[str], dict]:
    """Scans paired with interpolated true positions from bags.

    Returns (scans, positions (N, 2) m, source labels, report) where ``report`` has per-namespace
    counts: scans, used, outside_truth, invalid (by reason), no_truth.
    """
    from indoor_loc.bag import bag_topics, read_bag
    from msg_adapters.path import path_from_msg
    from msg_adapters.wifi_scan import scan_from_msg

    topics = bag_topics(bags)
    wanted = [t for t in topics if namespace_of_topic(t, topic_scan) is not None or namespace_of_topic(t, topic_truth) is not None]
    scans: dict[str, list] = defaultdict(list)
    truth: dict[str, list] = defaultdict(list)
    truth_z: dict[str, float] = {}
    invalid: dict[str, Counter] = defaultdict(Counter)
    for m in read_bag(bags, topics=wanted):
        ns = namespace_of_topic(m.topic, topic_scan)
        if ns is not None:
            try:
                scans[ns].append(scan_from_msg(m.msg))
            except InvalidMessageError as err:
                invalid[ns][err.reason] += 1
            continue
        ns = namespace_of_topic(m.topic, topic_truth)
        if ns is not None:
            try:
                truth[ns].append(path_from_msg(m.msg))
                if m.msg.poses:
                    truth_z[ns] = float(m.msg.poses[0].pose.position.z)
            except InvalidMessageError as err:
                invalid[ns][f"truth_{err.reason}"] += 1
    stem = bags[0].stem if len(bags) == 1 else "bag"
    out_scans, out_pos, out_src = [], [], []
    report: dict[str, dict] = {}
    for ns in sorted(set(scans) | set(truth) | set(invalid)):
        lst = sorted(scans.get(ns, []), key=lambda s: s.stamp_ns)
        rep = {"scans": len(lst), "used": 0, "outside_truth": 0, "no_truth": 0, "invalid": dict(invalid.get(ns, {})),
               "z_m": truth_z.get(ns, 0.0)}
        report[ns or "/"] = rep
        if not truth.get(ns):
            rep["no_truth"] = len(lst)
            continue
        t = np.concatenate([p[0] for p in truth[ns]]).astype(np.int64)
        xy = np.concatenate([p[1] for p in truth[ns]]).reshape(-1, 2)
        t, keep = np.unique(t, return_index=True)      # merged paths: one pose per stamp
        xy = xy[keep]
        pos, inside = interpolate_positions([s.stamp_ns for s in lst], t, xy)
        rep["used"] = int(inside.sum())
        rep["outside_truth"] = int((~inside).sum())
        label = ns.strip("/").replace("/", "_") or stem
        rep["label"] = label
        for s, p, ok in zip(lst, pos, inside):
            if ok:
                out_scans.append(s)
                out_pos.append(p)
                out_src.append(label)
    return out_scans, np.array(out_pos, float).reshape(-1, 2), out_src, report


def build(bags: list[Path], out: Path, *, putmc: Path | None = None, topic_scan: str = "wifi/scan",
          topic_truth: str = "ground_truth", method: str = "auto", floor_plans: Path | None = None,
          overwrite: bool = False) -> tuple[RadioMap, dict]:
    """Build, save and write params.yaml; returns (map, report). An existing map in ``out`` is
    refused (ConfigError) unless ``overwrite``; ``floor_plans`` (checked before anything is written)
    goes into params.yaml with the path-loss field (:func:`~indoor_loc.wifi.methods.recommended_params`)."""
    from indoor_loc.output_paths import check_outputs
    from indoor_loc.wifi.methods import METHODS, recommended_params
    if method != "auto" and method not in METHODS:
        raise ConfigError(f"--method: expected one of {sorted(METHODS)}, got {method!r}")
    if not bags and putmc is None:
        raise ConfigError("nothing to build from: give bags and/or --putmc DATASET_DIR")
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise ConfigError(f"--out {out} exists and is not a directory")
    check_outputs([out / name for name in ("radiomap.yaml", "aps.csv", "fingerprints.csv", "params.yaml")],
                  overwrite=overwrite, what=f"radio map {out}")
    plans = ""
    if floor_plans is not None:
        from indoor_loc.wifi.walkable import load_floor_plans
        load_floor_plans(floor_plans)          # ConfigError naming what is wrong, before anything is written
        plans = str(Path(floor_plans).resolve())
    report: dict = {}
    rm = empty_radiomap()
    if putmc is not None:
        from indoor_loc.datasets.putmc import read_survey_map
        rm = read_survey_map(putmc)
        report["putmc_survey"] = {"scans": rm.n_scans, "aps": rm.n_aps}
    if bags:
        for b in bags:
            if not b.exists():
                raise ConfigError(f"input bag {b} does not exist")
        scans, pos, src, per_ns = fingerprints_from_bags(bags, topic_scan=topic_scan, topic_truth=topic_truth)
        report["bags"] = per_ns
        if scans:
            z_of = {rep["label"]: rep["z_m"] for rep in per_ns.values() if "label" in rep}
            rm = add_fingerprints(rm, pos, scans, src, z_m=[z_of.get(s, 0.0) for s in src])
    if rm.n_scans == 0:
        per_ns = report.get("bags", {})
        if not any(rep["scans"] for rep in per_ns.values()):
            raise MapError(f"no fingerprint could be built: the bags hold no */{topic_scan} messages "
                           "(give the recordings with WiFi scans and ground truth, e.g. an importer's walkNN.mcap)")
        raise MapError("no fingerprint could be built (no scan within a ground-truth time span): "
                       + "; ".join(f"{ns}: {rep['scans']} scans, {rep['outside_truth']} outside the truth's time "
                                   f"span, {rep['no_truth']} without */{topic_truth}, "
                                   f"{sum(rep['invalid'].values())} invalid" for ns, rep in per_ns.items()))
    inputs = [str(p) for p in bags] + ([f"putmc:{putmc}"] if putmc is not None else [])
    save_radiomap(rm, out, created_by="indoor-loc radiomap build", inputs=inputs)
    chosen = recommended_params(rm, plans) if method == "auto" else \
        {"method": method, **({"floor_plans": plans} if plans else {})}
    params = {"wifi_fix_node": {"radiomap": str(Path(out).resolve()), **chosen}}
    (Path(out) / "params.yaml").write_text(params_file_text(
        params, header="wifi_fix_node configured for this radio map (indoor-loc radiomap build);\n"
                       "the /**/ key reaches wifi_fix_node in any namespace"))
    return rm, report


def info_lines(directory: Path) -> list[str]:
    man = read_manifest(directory)
    rm = load_radiomap(directory)
    s = radiomap_summary(rm)
    lines = [f"{directory}: {man['format']} v{man['version']}, frame {rm.frame_id!r}",
             f"  scans {s['counts']['scans']}, APs {s['counts']['aps']}, readings {s['counts']['readings']}",
             f"  APs per scan: {s['aps_per_scan']}",
             f"  bounds (m): x {s['bounds_m']['x']}, y {s['bounds_m']['y']}",
             f"  survey spacing (median distance to the nearest other surveyed position on the floor): "
             f"{nominal_spacing_m(rm):.2f} m",
             "  sources: " + ", ".join(f"{k} {v}" for k, v in s["sources"].items())]
    heard = ~np.isnan(rm.rssi_dbm)
    if heard.any():
        lines.append(f"  RSSI range: {np.nanmin(rm.rssi_dbm):.0f} .. {np.nanmax(rm.rssi_dbm):.0f} dBm; "
                     f"APs heard in 1 scan only: {int((heard.sum(axis=0) == 1).sum())}")
    zs, counts = np.unique(np.asarray(rm.z_m, float), return_counts=True)
    if len(zs) > 1 or rm.floors:
        names = {float(v): k for k, v in rm.floors.items()}
        lines.append("  floors: " + ", ".join(f"{names.get(float(z), '?')} z={z:g} m ({c} scans)"
                                              for z, c in zip(zs, counts)))
    ages = np.asarray(rm.age_ms, float)[~np.isnan(np.asarray(rm.age_ms, float))] if rm.age_ms is not None else []
    if len(ages):
        lines.append(f"  reading ages: median {np.median(ages):.0f} ms, {100 * np.mean(ages > 1000):.0f} % older "
                     "than 1 s (cached results)")
    created = man.get("created") or {}
    if created:
        lines.append(f"  created {created.get('utc', '?')} by {created.get('by', '?')}")
    return lines


def fit(params_file: Path, radiomap: Path | None = None, *, namespace: str = "", cache_dir: str | None = None,
        refit: bool = False, log: Callable[[str, str], None] | None = None) -> list[Path]:
    """Fit ``wifi_fix_node``'s positioner as the params file configures it (``radiomap`` and ``cache_dir``
    override its ``radiomap`` and ``fit_cache_dir``) and save the fit where the node looks for it. Returns
    the files saved: none when the saved fit is up to date (unless ``refit``). ConfigError when the params
    turn ``fit_cache`` off or name no radio map."""
    from indoor_loc.params import load_params_file, params_for_node, params_from_dict
    from indoor_loc.pipeline.wifi_fix_stage import NODE_NAME, WifiFixParams, WifiFixStage
    values = params_for_node(load_params_file(params_file), NODE_NAME, namespace)
    if radiomap is not None:
        values["radiomap"] = str(radiomap)
    if cache_dir is not None:
        values["fit_cache_dir"] = cache_dir
    params = params_from_dict(WifiFixParams, values)
    if not params.radiomap:
        raise ConfigError(f"{params_file}: {NODE_NAME} has no radiomap (give RADIOMAP)")
    if not params.fit_cache:
        raise ConfigError(f"{params_file}: {NODE_NAME} has fit_cache: false; the node would not load a saved fit")
    stage = WifiFixStage(params, fit_now=False)            # reads the map and plans as the node does
    store = stage.fit_store()
    assert store is not None and stage.radio_map is not None
    stage.fit_positioner(stage.radio_map, log or (lambda level, text: print(text)), refit=refit, store=store)
    return store.saved


def main(args: argparse.Namespace) -> int:
    if args.action == "info":
        print("\n".join(info_lines(args.directory)))
        return 0
    if args.action == "fit":
        saved = fit(args.params, args.radiomap, namespace=args.namespace, cache_dir=args.cache_dir, refit=args.refit)
        if not saved:
            print("the saved fit is up to date (--refit to fit again)")
        return 0
    rm, report = build(list(args.bags), args.out, putmc=args.putmc, topic_scan=args.topic_scan,
                       topic_truth=args.topic_truth, method=args.method, floor_plans=args.floor_plans,
                       overwrite=args.overwrite)
    if "putmc_survey" in report:
        print(f"PUTMC survey map: {report['putmc_survey']['scans']} scans, {report['putmc_survey']['aps']} APs")
    for ns, rep in report.get("bags", {}).items():
        inv = sum(rep["invalid"].values())
        print(f"  {ns}: {rep['scans']} scans, {rep['used']} used, {rep['outside_truth']} outside the truth's "
              f"time span, {rep['no_truth']} without truth, {inv} invalid"
              + (f" ({', '.join(f'{k}={v}' for k, v in rep['invalid'].items())})" if inv else ""))
    print(f"radio map: {rm.n_scans} scans, {rm.n_aps} APs -> {args.out} (+ params.yaml)")
    return 0
