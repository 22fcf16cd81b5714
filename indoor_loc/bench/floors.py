"""``indoor-loc bench floors``: floors in every estimator, with and without the barometer.

Simulated multi-floor walks in the three-floor office (:func:`~indoor_loc.sim.building.make_tower_building`:
stairs and a lift, walkers changing floors, a phone barometer with weather drift, door spikes, noise
and quantisation; :mod:`indoor_loc.sim.baro`), and one walker staying on one floor for
``--drift-min`` minutes of weather drift. Each world runs through the package's own pipeline:
``imu`` and ``wifi`` (powed fixes with floor detection) once, then ``pdr_kf``, ``pf`` and ``backend``
twice, on the same inputs without and with ``baro/pressure``. Per estimator (the causal outputs
``wifi/fix``, ``pdr_kf/pose``, ``pf/pose``, ``backend/<user>/pose``; each sample's floor is the floor
nearest its z):

- floor correct: % of the truth's 10 Hz samples on a floor (transits on stairs and in the lift
  excluded) at which the newest estimate so far is on the true floor;
- changes within 5 s: % of the true floor changes (arrival on a new floor) at which the estimate is
  on the new floor 5 s after the arrival;
- false changes: changes of the estimate's floor more than 10 s from any true transit, per hour;
- scan-time horizontal error: mean / p95 (m) of the newest estimate at each WiFi scan's stamp.

Nothing here was tuned on these worlds' seeds beyond what the unit tests fix (the detector's
thresholds were set from the physics: storey 3.5 m, door spikes up to 3 s); see docs/floors.md.
ms_site2 has no pressure readings: its floors are WiFi floor detection only (``bench wifi --dataset
ms_site2`` gives the powed detector's per-scan floor accuracy); this bench does not replay it.
"""
from __future__ import annotations

import argparse
import csv
import time
from pathlib import Path

import numpy as np

SEC = 1_000_000_000
WINDOW_S = 5.0
ESTIMATORS = ("wifi/fix", "pdr_kf/pose", "pf/pose", "backend/{user}/pose")


def simulate_world(out: Path, *, walkers: int, duration_s: float, seed: int, change_floors: bool,
                   start_floor: int = 0) -> dict:
    """Simulate and write a world with a barometer; returns write_run's paths plus ``baro`` (a bag of
    the barometer topics only), ``floor_z`` and the run. A world already written and replayed in
    ``out`` (same seed, same code) is simulated again for the scoring but not rewritten."""
    from indoor_loc.bag import BagWriter
    from indoor_loc.bag.reader import bag_topics, read_raw
    from indoor_loc.sim.baro import BaroSimParams
    from indoor_loc.sim.building import make_tower_building
    from indoor_loc.sim.scenario import SimConfig, simulate
    from indoor_loc.sim.walker import ImuParams
    from indoor_loc.sim.write import write_run

    b = make_tower_building()
    cfg = SimConfig(walkers=walkers, duration_s=duration_s, seed=seed, change_floors=change_floors,
                    start_floor=start_floor, baro=BaroSimParams(), imu=ImuParams(rate_hz=50.0, mag_rate_hz=25.0))
    run = simulate(b, cfg)
    if (out / "baro.mcap").exists() and (out / "front.mcap").exists():     # written and replayed before: reuse
        return {"bag": out / "sim.mcap", "params": out / "params.yaml", "truth": out / "truth",
                "baro": out / "baro.mcap", "floor_z": b.floor_z, "run": run}
    paths = write_run(run, out)
    baro_topics = [t for t in bag_topics(paths["bag"]) if t.endswith("/baro/pressure")]
    with BagWriter(out / "baro.mcap") as bag:
        for t in baro_topics:
            bag.add_topic(t, "sensor_msgs/msg/FluidPressure")
        for m in read_raw(paths["bag"], baro_topics):
            bag.write_raw(m.topic, m.data, m.stamp_ns)
    return {**paths, "baro": out / "baro.mcap", "floor_z": b.floor_z, "run": run}


def replay(world: dict, out: Path) -> dict[str, Path]:
    """imu + wifi once, then the estimators without and with the barometer."""
    from indoor_loc.pipeline.offline import run_offline

    front = out / "front.mcap"
    if not front.exists():
        run_offline([world["bag"]], front, nodes=["imu", "wifi"], params=world["params"], progress=False,
                    copy=("ground_truth", "wifi/scan"))
    res = {}
    for name, bags in (("no_baro", [front]), ("baro", [front, world["baro"]])):
        res[name] = out / f"est_{name}.mcap"
        if not res[name].exists():
            run_offline(bags, res[name], nodes=["pdr_kf", "pf", "backend"], params=world["params"], progress=False,
                        copy=("wifi/fix",))
    return res


def _truth(truth_csv: Path, floor_z: np.ndarray, hand_m: float = 1.1):
    rows = list(csv.DictReader(open(truth_csv)))
    t = np.array([int(r["stamp_ns"]) for r in rows], np.int64)
    xyz = np.array([[float(r["x"]), float(r["y"]), float(r["z"])] for r in rows])
    floor = np.array([int(r["floor"]) for r in rows])
    on_floor = np.abs(xyz[:, 2] - hand_m - floor_z[floor]) < 0.3
    return t, xyz, floor, on_floor


def _estimates(bag: Path) -> dict[tuple[str, str], tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """(user, estimator) -> stamps (N,), xy (N, 2), z (N,) of every pose estimate in the bag."""
    from indoor_loc.bag import read_bag
    out: dict[tuple[str, str], list] = {}
    for m in read_bag(bag):
        parts = m.topic.strip("/").split("/")
        if parts[0] == "backend" and len(parts) == 3 and parts[2] == "pose":
            user, est = parts[1], "backend/{user}/pose"
        elif "/".join(parts[1:]) in ("wifi/fix", "pdr_kf/pose", "pf/pose"):
            user, est = parts[0], "/".join(parts[1:])
        else:
            continue
        st = m.msg.header.stamp
        p = m.msg.pose.pose.position
        out.setdefault((user, est), []).append((st.sec * SEC + st.nanosec, p.x, p.y, p.z))
    res = {}
    for k, rows in out.items():
        a = np.array(sorted(rows))
        res[k] = (a[:, 0].astype(np.int64), a[:, 1:3], a[:, 3])
    return res


def score(world: dict, bag: Path, *, t0_ns: int) -> dict[str, dict]:
    """Per estimator, pooled over the walkers: the figures of the module docstring."""
    fz = np.asarray(world["floor_z"], float)
    run = world["run"]
    ests = _estimates(bag)
    acc: dict[str, dict] = {e: {"on": 0, "ok": 0, "changes": 0, "detected": 0, "false": 0, "hours": 0.0, "err": []}
                            for e in ESTIMATORS}
    for w in run.walkers:
        t, xyz, floor, on_floor = _truth(Path(world["truth"]) / f"{w.name}.csv", fz)
        # true changes: arrival on a floor different from the last floor stood on
        arrivals, transits = [], []
        last_floor, left = None, None
        for k in range(len(t)):
            if on_floor[k]:
                if last_floor is not None and floor[k] != last_floor:
                    arrivals.append((t[k], floor[k]))
                    transits.append((left, t[k]))
                last_floor = floor[k]
                left = t[k]
        scan_t = np.array([s.stamp_ns for s in w.scans], np.int64) + t0_ns
        for e in ESTIMATORS:
            key = (w.name, e)
            if key not in ests:
                continue
            st, xy, z = ests[key]
            efl = np.argmin(np.abs(z[:, None] - fz[None]), axis=1)
            idx = np.searchsorted(st, t, side="right") - 1
            have = idx >= 0
            a = acc[e]
            m = on_floor & have
            a["on"] += int(m.sum())
            a["ok"] += int((efl[idx[m]] == floor[m]).sum())
            for ta, fa in arrivals:
                k = np.searchsorted(st, ta + int(WINDOW_S * SEC), side="right") - 1
                a["changes"] += 1
                a["detected"] += int(k >= 0 and efl[k] == fa)
            changes = st[1:][np.diff(efl) != 0]
            for tc in changes:
                near = any(lo - 10 * SEC <= tc <= hi + 10 * SEC for lo, hi in transits)
                a["false"] += int(not near)
            a["hours"] += (t[-1] - t[0]) / SEC / 3600.0
            k = np.searchsorted(st, scan_t, side="right") - 1
            good = k >= 0
            a["err"] += list(np.hypot(*(xy[k[good]] - w.scan_xy[good]).T))
    return acc


def _row(name: str, a: dict) -> str:
    pct = 100.0 * a["ok"] / a["on"] if a["on"] else float("nan")
    det = f"{a['detected']}/{a['changes']}" if a["changes"] else "-"
    err = np.array(a["err"]) if a["err"] else np.array([np.nan])
    fph = a["false"] / a["hours"] if a["hours"] else float("nan")
    return (f"| {name} | {pct:.2f} | {det} | {a['false']} ({fph:.1f}/h) | {np.nanmean(err):.2f} / "
            f"{np.nanpercentile(err, 95):.2f} |")


def run(args: argparse.Namespace) -> int:
    from indoor_loc.sim.scenario import T0_NS

    quick = bool(getattr(args, "quick", False))
    walkers = int(getattr(args, "walkers", 0) or 3)
    duration = float(getattr(args, "duration", 0.0) or (180.0 if quick else 600.0))
    drift_min = 10.0 if quick else 30.0
    work = Path(getattr(args, "work", None) or "out/bench_floors")
    if work.name == "bench_pf":
        work = work.parent / "bench_floors"
    t_start = time.perf_counter()
    worlds = {
        f"walks: {walkers} walkers x {duration:g} s, stairs + lift, drift + spikes":
            (work / f"walks_{walkers}x{duration:g}", dict(walkers=walkers, duration_s=duration, seed=21, change_floors=True)),
        f"drift: 1 walker x {drift_min:g} min on floor 1, drift + spikes":
            (work / f"drift_{drift_min:g}min", dict(walkers=1, duration_s=60.0 * drift_min, seed=22, change_floors=False,
                                                    start_floor=1)),
    }
    results = {}
    for title, (d, kw) in worlds.items():
        d.mkdir(parents=True, exist_ok=True)
        t = time.perf_counter()
        world = simulate_world(d, **kw)
        bags = replay(world, d)
        print(f"{title}: simulated and replayed in {time.perf_counter() - t:.0f} s ({d})", flush=True)
        results[title] = {name: score(world, bag, t0_ns=T0_NS) for name, bag in bags.items()}
    print()
    for title, res in results.items():
        print(f"### {title}\n")
        print("| estimator | floor correct % of time | changes on the new floor within 5 s | false changes | "
              "scan-time error mean / p95 (m) |")
        print("|---|---|---|---|---|")
        for variant, label in (("no_baro", "without barometer"), ("baro", "with barometer")):
            for e in ESTIMATORS:
                if variant == "baro" and e == "wifi/fix":
                    continue                     # the WiFi node does not read the barometer
                print(_row(f"`{e}` {label if e != 'wifi/fix' else '(WiFi floor detection only)'}", res[variant][e]))
        print()
    print(f"total {time.perf_counter() - t_start:.0f} s; ms_site2 has no pressure readings (WiFi floor detection "
          "only: see `indoor-loc bench wifi --dataset ms_site2`); BLE with and without, where beacons exist: "
          "`indoor-loc bench ble --dataset sim` (fixed beacons in this office) and `indoor-loc bench ble` (ms_site2)")
    return 0
