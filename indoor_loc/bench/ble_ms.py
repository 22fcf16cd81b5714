"""``indoor-loc bench ble``: WiFi fixes with and without the BLE beacons, per floor of ms_site2
(``python -m indoor_loc.bench.ble_ms --window-s S`` for another window).

Data: the Microsoft Indoor Location Competition 2.0 sample, site 2 (:mod:`indoor_loc.datasets.ms_indoor`),
its ``TYPE_BEACON`` rows as BLE scans (:mod:`indoor_loc.datasets.ms_indoor_ble`). Per floor, the documented
interleaved split (survey walks build the floor's radio map from every scan inside the waypoint span, test
walks' in-span scans are located and scored against their interpolated true positions), run twice on the
same scans: WiFi only, and WiFi + BLE — the readings of the ``window_s`` before each scan joined to it as
``ble:<id>`` entries, in the map (survey scans) and in the located scans alike (:func:`indoor_loc.wifi.ble.merge_scans`,
what ``wifi_fix_node`` does live with ``ble.enabled``). Positioning: the importer's default (powed k-NN with
the path-loss field inside the floor plan) and powed k-NN without the field. Rows: every test scan, and the
test scans that had a beacon in their window (the only ones BLE can change).

The window (5 s, the ``ble.window_s`` default) was chosen before any run, not tuned; BLE changes no
parameter of the positioning. Figures are printed for every floor; ``--floors`` restricts them.
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any

import numpy as np

from indoor_loc.bench.wifi_ms import FIELD_PLAN, errors, locate_walks
from indoor_loc.wifi.ble import is_ble_key, merge_scans
from indoor_loc.wifi.methods import make_positioner
from indoor_loc.wifi.radiomap import add_fingerprints, empty_radiomap

METHODS = (("powed + field in plan (importer default)", FIELD_PLAN), ("powed, no field", {}))


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--data", type=Path, default=Path("../shared/datasets"), help="datasets directory")
    parser.add_argument("--floors", default="", help="comma-separated floors (default: all)")
    parser.add_argument("--window-s", type=float, default=5.0, help="BLE window before each scan, s (default 5)")


def floor_sets(fl, window_s: float) -> dict[str, Any]:
    """A floor's survey map and test scans, each without and with BLE (see module doc)."""
    from indoor_loc.bench.wifi_ms import _readable
    from indoor_loc.datasets.ms_indoor import STOREY_HEIGHT_M, has_truth_span, scans_with_truth, split_map_test, trace_id_of
    ids = {trace_id_of(p): p for p in fl.trace_files}
    survey, test = split_map_test([i for i in ids if has_truth_span(ids[i])])
    notes: list[str] = []
    z = fl.z_m(STOREY_HEIGHT_M)
    out: dict[str, Any] = {"notes": notes}
    for role, walk_ids in (("survey", survey), ("test", test)):
        plain, fused, truth, src = [], [], [], []
        for tid, tr in _readable(fl.name, ids, walk_ids, notes):
            sc, xy = scans_with_truth(tr)
            plain += sc
            fused += merge_scans(sc, tr.ble, window_s)
            truth.append(xy)
            src += [f"{fl.name}/{tid}"] * len(sc)
        out[role] = {"plain": plain, "fused": fused, "truth": np.vstack(truth) if truth else np.zeros((0, 2)),
                     "src": src}
    s = out["survey"]
    out["maps"] = {k: add_fingerprints(empty_radiomap(), s["truth"], s[k], s["src"], z_m=z, floors={fl.name: z})
                   for k in ("plain", "fused")}
    return out


def _stats(ok: np.ndarray, e: np.ndarray) -> str:
    if not ok.any():
        return "  (no fix)"
    x = e[ok]
    return f"{ok.sum():>4}/{len(ok):<4} {x.mean():6.2f} {np.median(x):6.2f} {np.percentile(x, 95):6.2f}"


def run(args: argparse.Namespace) -> int:
    """``indoor-loc bench ble`` (the shared bench options: ``--data``, ``--floors``; the window is 5 s);
    ``--dataset sim``: the simulator's fixed beacons (:mod:`indoor_loc.bench.ble_sim`)."""
    if getattr(args, "dataset", "") == "sim":
        from indoor_loc.bench import ble_sim
        return ble_sim.run(args)
    return main(argparse.Namespace(data=args.data, floors=getattr(args, "floors", ""),
                                   window_s=getattr(args, "window_s", 5.0)))


def main(args: argparse.Namespace) -> int:
    from indoor_loc.datasets.ms_indoor_site import read_site
    from indoor_loc.errors import ConfigError, MapError
    from indoor_loc.wifi.walkable import plan_walkable
    root = Path(args.data) / "ms_site2"
    if not root.exists():
        raise ConfigError(f"{root} not found (--data: the datasets directory)")
    site = read_site(root)
    only = [f for f in args.floors.split(",") if f.strip()]
    print(f"BLE window {args.window_s:g} s; per floor: located / scans, mean, median, p95 error (m)\n")
    print(f"{'floor':<6} {'method':<42} {'scans':<15} {'WiFi only':>26} {'WiFi + BLE':>26}  beacons in map")
    for fl in site.floors:
        if only and fl.name not in only:
            continue
        t0 = time.perf_counter()
        d = floor_sets(fl, args.window_s)
        walkable = None
        try:
            walkable = plan_walkable(fl.plans / "geojson_map.json", (fl.width_m, fl.height_m))
        except (MapError, OSError):
            pass
        test = d["test"]
        with_ble = np.array([any(is_ble_key(b) for b in s.bssid) for s in test["fused"]], bool)
        n_ble = sum(1 for b in d["maps"]["fused"].bssids if is_ble_key(b))
        for label, params in METHODS:
            res = {}
            for k in ("plain", "fused"):
                pos = make_positioner("powed", dict(params))
                if "field_weight" in params:
                    pos.walkable = walkable
                pos.fit(d["maps"][k])
                res[k] = errors(locate_walks(pos, test[k]), test["truth"])[:2]
            for sel_name, sel in (("all", np.ones(len(with_ble), bool)), ("with a beacon", with_ble)):
                a = _stats(res["plain"][0][sel], res["plain"][1][sel])
                b = _stats(res["fused"][0][sel], res["fused"][1][sel])
                print(f"{fl.name:<6} {label:<42} {sel_name:<15} {a:>26} {b:>26}  {n_ble}")
        print(f"{'':<6} ({time.perf_counter() - t0:.0f} s; {with_ble.sum()} of {len(with_ble)} test scans heard a "
              f"beacon in the window)" + (f"; {'; '.join(d['notes'])}" if d["notes"] else ""))
    return 0


if __name__ == "__main__":
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_arguments(p)
    raise SystemExit(main(p.parse_args()))
