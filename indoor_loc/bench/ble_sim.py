"""``indoor-loc bench ble --dataset sim``: WiFi fixes with and without BLE beacons that do not rotate
(known, fixed ids), in the simulator's three-floor office.

The world of ``bench floors`` (:func:`~indoor_loc.sim.building.make_tower_building`, the simulator's
seed 21: three walkers changing floors by stairs and lift; ``--quick`` 180 s, else 600 s) with beacons
(:mod:`indoor_loc.sim.ble`) in the east half of every floor (x ≥ 20 m: the stairwell's end; the lift's
end has none), at least 8 m apart. The survey phone hears them at every survey point; each walker's
phone once a second. As ``wifi_fix_node`` does with ``ble.enabled`` (:mod:`indoor_loc.wifi.ble`), the
readings of the 5 s before each WiFi scan join it as ``ble:<id>`` entries, in the radio map (survey
scans) and in the located scans alike. Positioning: powed k-NN, the simulator's method (its defaults:
nothing here is tuned; BLE changes no parameter). Rows: every scan, the scans taken in the beacons' half of
the building (where beacons exist), the scans taken in the other half; mean / median / p95 horizontal error (m) and the
fix's floor right (%), WiFi only and WiFi + BLE, on the same scans.
"""
from __future__ import annotations

import argparse
import time

import numpy as np

SEED = 21
ZONE = (20.0, -1e3, 1e3, 1e3)        # x >= 20 m: the east half of every floor
WINDOW_S = 5.0


def world(duration_s: float, seed: int = SEED):
    """The simulated run, its beacons' field and every scan set: dict with ``maps`` {plain, fused},
    per walker ``scans`` {plain, fused}, ``truth_xy``, ``truth_floor``."""
    from indoor_loc.sim.ble import BeaconField, BleSimParams, place_beacons
    from indoor_loc.sim.building import make_tower_building
    from indoor_loc.sim.scenario import SimConfig, simulate
    from indoor_loc.sim.walker import ImuParams
    from indoor_loc.wifi.ble import BleWindow, merge_scans
    from indoor_loc.wifi.radiomap import add_fingerprints, empty_radiomap

    b = make_tower_building()
    run = simulate(b, SimConfig(walkers=3, duration_s=duration_s, seed=seed, change_floors=True,
                                imu=ImuParams(rate_hz=25.0, mag_rate_hz=25.0)))
    bp = BleSimParams()
    beacons = place_beacons(b, tuple(range(b.n_floors)), ZONE, bp)
    rng = np.random.default_rng([seed, 28])
    field = BeaconField(b, beacons, run.config.rf, bp, rng)
    fz = np.asarray(b.floor_z, float)
    fused_survey = []
    for s, xy, f in zip(run.survey_scans, run.survey_xy, run.survey_floor):
        win = BleWindow(WINDOW_S)
        heard = field.read(s.stamp_ns, np.array([xy[0], xy[1], fz[f] + 1.1]), int(f), rng)
        if heard is not None:
            win.add(heard)
        fused_survey.append(win.merge(s))
    floors = {f"floor {k}": float(z) for k, z in enumerate(fz)}
    z = fz[run.survey_floor]
    maps = {k: add_fingerprints(empty_radiomap(), run.survey_xy, sc, "survey", z_m=z, floors=floors)
            for k, sc in (("plain", run.survey_scans), ("fused", fused_survey))}
    walkers = []
    for w in run.walkers:
        ble = field.along(w.motion.t_ns, w.motion.xyz, w.motion.floor, duration_s, rng, w.name)
        t_s = w.motion.t_ns * 1e-9
        fl = np.array([int(w.motion.floor[min(int(np.searchsorted(t_s, s.stamp_ns * 1e-9)), len(t_s) - 1)])
                       for s in w.scans], int)
        walkers.append({"name": w.name, "scans": {"plain": list(w.scans), "fused": merge_scans(w.scans, ble, WINDOW_S)},
                        "truth_xy": np.asarray(w.scan_xy, float), "truth_floor": fl})
    return {"maps": maps, "walkers": walkers, "beacons": beacons, "floor_z": fz}


def locate(d: dict) -> dict:
    """Per variant (plain, fused): located (N,), error (N,) m, floor right (N,), and with_ble (N,)."""
    from indoor_loc.wifi.ble import is_ble_key
    from indoor_loc.wifi.methods import make_positioner
    fz = d["floor_z"]
    out: dict = {}
    for k in ("plain", "fused"):
        pos = make_positioner("powed", {})
        pos.fit(d["maps"][k])
        ok, err, right = [], [], []
        for w in d["walkers"]:
            if hasattr(pos, "reset"):
                pos.reset()
            for s, xy, f in zip(w["scans"][k], w["truth_xy"], w["truth_floor"]):
                fix = pos.locate(s)
                ok.append(bool(fix.ok))
                err.append(float(np.hypot(*(fix.xy - xy))) if fix.ok else np.nan)
                right.append(bool(fix.ok and int(np.argmin(np.abs(fz - fix.z))) == f))
        out[k] = (np.array(ok), np.array(err), np.array(right))
    out["with_ble"] = np.array([any(is_ble_key(b) for b in s.bssid) for w in d["walkers"] for s in w["scans"]["fused"]])
    out["in_zone"] = np.concatenate([w["truth_xy"][:, 0] >= ZONE[0] for w in d["walkers"]])
    return out


def _cell(ok: np.ndarray, e: np.ndarray, right: np.ndarray) -> str:
    if not ok.any():
        return "no fix"
    x = e[ok]
    return (f"{x.mean():.2f} / {np.median(x):.2f} / {np.percentile(x, 95):.2f} m, "
            f"floor {100.0 * right[ok].mean():.1f} %")


def run(args: argparse.Namespace) -> int:
    duration = float(getattr(args, "duration", 0.0) or (180.0 if getattr(args, "quick", False) else 600.0))
    t0 = time.perf_counter()
    d = world(duration)
    r = locate(d)
    wb, zone = r["with_ble"], r["in_zone"]
    print(f"simulated three-floor office, seed {SEED}, 3 walkers x {duration:g} s; {len(d['beacons'])} fixed BLE "
          f"beacons (x >= 20 m on every floor), window {WINDOW_S:g} s; powed k-NN; mean / median / p95 error\n")
    print("| scans | n | WiFi only | WiFi + BLE |")
    print("|---|---|---|---|")
    for name, sel in (("all", np.ones(len(wb), bool)), ("in the beacons' half (x >= 20 m)", zone),
                      ("in the other half (no beacon)", ~zone)):
        cells = [_cell(*(a[sel] for a in r[k])) for k in ("plain", "fused")]
        print(f"| {name} | {int(sel.sum())} | {cells[0]} | {cells[1]} |")
    print(f"\n{int(wb.sum())} of {len(wb)} scans heard a beacon in their window ({time.perf_counter() - t0:.0f} s)")
    return 0
