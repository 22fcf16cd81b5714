"""Why whole walks' WiFi fixes sit metres off on ms_site2: two physical hypotheses measured per walk.

``python -m indoor_loc.bench.fix_causes --data ../shared/datasets [--floors B1,F7]`` positions every test
scan of the documented split (survey walks 1st/3rd/5th of every five build the map; :mod:`indoor_loc.bench.wifi_ms`)
with the powed k-NN matcher and prints, per floor and per test walk:

- **device RSS offset**: the walk's true offset — the median over its scans of the median difference
  between its readings and the survey's readings of the same APs within 3 m of the truth — beside the
  matcher's online estimate at the walk's end and the walk's fix bias |mean(fix − truth)|;
- **scan time**: a scan's readings are older than its stamp (``last_seen``; the median age of its five
  strongest APs); the mean along-track error of the fixes (the walking direction from the truth, negative
  = behind) and the floor's mean error when both the survey map and the test truth are placed at the
  readings' measurement time (stamp − that age) instead of the stamp.
"""
from __future__ import annotations

import argparse
from collections import defaultdict
from pathlib import Path

import numpy as np

#: readings whose age stands for the scan's measurement time (the strongest ones decide a match)
STRONGEST = 5
#: survey readings within this distance of the truth define a walk's true device offset, m
OFFSET_RADIUS_M = 3.0


def measurement_stamp(scan) -> int:
    """The scan's stamp minus the median age of its strongest readings (ns)."""
    if scan.age_ms is None or not len(scan):
        return int(scan.stamp_ns)
    top = np.argsort(-np.asarray(scan.rssi_dbm, float))[:STRONGEST]
    return int(scan.stamp_ns - np.median(np.asarray(scan.age_ms, float)[top]) * 1e6)


def true_offset_db(scan, xy: np.ndarray, rm) -> float:
    """Median difference (dB) between the scan's readings and the survey's of the same APs near ``xy``."""
    near = np.flatnonzero(np.linalg.norm(rm.positions - xy, axis=1) < OFFSET_RADIUS_M)
    if not len(near):
        return float("nan")
    col = {b: i for i, b in enumerate(rm.bssids)}
    diffs = []
    for b, r in zip(scan.bssid, scan.rssi_dbm):
        j = col.get(b)
        if j is not None:
            m = rm.rssi_dbm[near, j]
            m = m[np.isfinite(m)]
            if len(m):
                diffs.append(float(r) - float(np.median(m)))
    return float(np.median(diffs)) if len(diffs) >= 5 else float("nan")


def _load(root: Path, floors: list[str], at_measurement: bool):
    import indoor_loc.datasets.ms_indoor as mi
    from indoor_loc.bench import wifi_ms
    plain = mi.scans_with_truth

    def at_reading_time(trace):
        if not trace.scans:
            return [], np.zeros((0, 2))
        xy, inside = trace.truth_at([measurement_stamp(s) for s in trace.scans])
        return [s for s, k in zip(trace.scans, inside) if k], xy[inside]
    if at_measurement:
        mi.scans_with_truth = at_reading_time
    try:
        return wifi_ms.load_site(root, only=floors)
    finally:
        mi.scans_with_truth = plain


def floor_report(name: str, stamp: dict, meas: dict, root: Path) -> list[str]:
    from indoor_loc.bench.wifi_ms import locate_walks
    from indoor_loc.datasets.ms_indoor import read_trace
    from indoor_loc.wifi.methods import make_positioner
    out = []
    means = []
    for f in (stamp, meas):
        pos = make_positioner("powed", {}).fit(f["map"])
        fixes = locate_walks(pos, f["scans"])
        xy = np.array([np.asarray(x.xy, float)[:2] if x.ok else [np.nan, np.nan] for x in fixes]).reshape(-1, 2)
        e = np.linalg.norm(xy - np.asarray(f["truth"]).reshape(-1, 2), axis=1)
        means.append(float(np.nanmean(e)) if np.isfinite(e).any() else float("nan"))
        if f is stamp:
            kept = (fixes, xy)
    fixes, xy = kept
    walks: dict[str, list] = defaultdict(list)
    traces: dict[str, object] = {}
    for s, tru, fx, p in zip(stamp["scans"], stamp["truth"], fixes, xy):
        if not fx.ok:
            continue
        tid = s.source.rsplit("/", 1)[-1]
        if tid not in traces:
            traces[tid] = read_trace(next((root / name / "path_data_files").glob(tid + "*")), imu=False)
        tr = traces[tid]
        ahead, inside = tr.truth_at([s.stamp_ns - 500_000_000, s.stamp_ns + 500_000_000])
        v = ahead[1] - ahead[0]
        along = float((p - tru) @ (v / np.linalg.norm(v))) if inside.all() and np.linalg.norm(v) > 0.2 else np.nan
        walks[tid].append((p - tru, along, true_offset_db(s, tru, stamp["map"]), fx.info.get("offset_db", np.nan)))
    out.append(f"### {name}: {sum(len(v) for v in walks.values())} located test scans\n")
    out.append(f"mean error, map and truth at the scan stamps: {means[0]:.2f} m; at the readings' measurement "
               f"time: {means[1]:.2f} m")
    al = np.array([a for v in walks.values() for _, a, _, _ in v], float)
    al_mean = float(np.nanmean(al)) if np.isfinite(al).any() else float("nan")
    out.append(f"mean along-track error: {al_mean:+.2f} m (negative = behind the walker)\n")
    out.append("| walk | scans | fix bias (m) | along-track (m) | true device offset (dB) | online offset (dB) |")
    out.append("|---|---|---|---|---|---|")
    for tid, v in walks.items():
        e = np.array([x[0] for x in v])
        out.append(f"| {tid[:8]} | {len(v)} | {np.linalg.norm(e.mean(axis=0)):.1f} | {np.nanmean([x[1] for x in v]):+.1f} | "
                   f"{np.nanmedian([x[2] for x in v]) if np.isfinite([x[2] for x in v]).any() else float('nan'):+.1f} | "
                   f"{v[-1][3]:+.1f} |")
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m indoor_loc.bench.fix_causes", description=__doc__.split("\n")[0])
    ap.add_argument("--data", default="../shared/datasets")
    ap.add_argument("--floors", default="B1,F7")
    ap.add_argument("--site", default="", help="a site directory of the format (default DATA/ms_site2)")
    a = ap.parse_args(argv)
    root = Path(a.site) if a.site else Path(a.data) / "ms_site2"
    floors = [f for f in a.floors.split(",") if f]
    stamp, meas = _load(root, floors, False), _load(root, floors, True)
    for name in floors:
        print("\n".join(floor_report(name, stamp[name], meas[name], root)) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
