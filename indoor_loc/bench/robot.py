"""``indoor-loc bench robot``: simulated differential-drive robots with their own wheel odometry as
the estimators' motion input, side by side with odometry alone and with walkers using PDR on the
same paths; then the kidnapped robot.

Every figure comes from the package's own pipeline: the simulated building, robots and walkers
(:mod:`indoor_loc.sim`) are written as bags and replayed through the same stages the live nodes run
(``indoor-loc run``, :func:`indoor_loc.pipeline.offline.run_offline`): ``wifi`` (WKNN fixes against the
survey), ``pf`` (``tll_pf``), ``pdr_kf`` and ``backend``, with ``motion_source: odom`` for the robots
and the package's PDR (``imu``) for the walkers.

Rows:

- ``odometry alone``: the robot's wheel odometry laid on the map at its true start pose (dead
  reckoning, aligned once);
- ``wifi/fix``: the WiFi fixes alone (what every estimator corrects with);
- each estimator with the robot's odometry (``motion_source: odom``);
- the same estimator on a walker walking the robot's path with a phone (PDR), for reference.

Errors are at the WiFi scans' stamps (each estimator's newest estimate at or before the scan, as a
user sees it live), pooled over the robots: mean and p95 over the run, mean over the first and the
last five minutes, and the mean after five minutes (the goal: every estimator with the robot's
odometry below odometry alone and below PDR on the same path). The kidnapped robot is carried,
odometry blind, to a node at least 15 m away halfway through its run: the table gives, per
estimator, how many WiFi scans (and seconds) pass until its error is back within
5 m of the truth for three scans in a row (``RECOVER_M``: a third of the shortest carry).

Nothing was tuned on these runs: the estimators run with their defaults plus ``motion_source: odom``;
the simulated robot's error sizes are set in :class:`indoor_loc.sim.robot.RobotParams` from the
odometry literature, before any estimator ran on them.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import time
from collections import defaultdict
from pathlib import Path

import numpy as np

from indoor_loc.sim.scenario import T0_NS

ESTIMATORS = (("pf/pose", "tll_pf"), ("pdr_kf/pose", "pdr_kf_node"), ("backend", "backend_node"))
WINDOW_S = 300.0
RECOVER_RUN = 3
#: relocalised: within this of the truth (a third of the shortest carry, 15 m) for RECOVER_RUN scans in a row, m
RECOVER_M = 5.0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--robots", type=int, default=2, help="simulated robots (default 2)")
    parser.add_argument("--duration", type=float, default=1800.0, help="robot run length, s (default 1800)")
    parser.add_argument("--kidnap-duration", type=float, default=600.0,
                        help="the kidnapped robots' run length, s; carried at its half (default 600; 0 = skip)")
    parser.add_argument("--seed", type=int, default=11, help="simulation seed (default 11)")
    parser.add_argument("--work", type=Path, default=Path("out/bench_robot"), help="work directory")
    parser.add_argument("--json", type=Path, help="also write the figures as JSON here")


# ----------------------------------------------------------------------------------------------
def simulate_bench(robots: int, duration_s: float, seed: int, *, kidnap: bool = False, walker_s: float = 600.0):
    """The robots, and a walker on each robot's path for at most ``walker_s`` of walking (PDR
    reference: the path's start, the same links in the same order; none for the kidnapped run)."""
    from indoor_loc.sim.building import sample_building
    from indoor_loc.sim.robot import RobotParams, pedestrian_twin_plan
    from indoor_loc.sim.scenario import NAMES, SimConfig, SimWalker, scans_along, simulate
    from indoor_loc.sim.walker import WalkerParams, sample_motion, synthesize_imu

    rp = RobotParams(kidnap_at_s=duration_s / 2 if kidnap else None)
    cfg = SimConfig(walkers=1, robots=robots, duration_s=duration_s, seed=seed, robot=rp)
    run = simulate(sample_building(), cfg)
    twins = []
    if not kidnap:
        rng = np.random.default_rng([seed, 7])
        freqs = np.array(run.field.freq_mhz)
        order = np.unique(freqs)
        frac = np.array([(list(order).index(f) + 0.5) / len(order) for f in freqs])
        for k, r in enumerate(run.robots):
            wp = WalkerParams(name=f"{NAMES[k]}_on_{r.name}", step_length_m=0.72, cadence_hz=1.8)
            plan = pedestrian_twin_plan(r, wp)
            dur = float(min(plan.t_s[-1], duration_s, walker_s))
            motion = sample_motion(plan, wp, cfg.imu.rate_hz, dur, run.building.floor_z)
            imu = synthesize_imu(motion, run.building, cfg.imu, rng)
            scans, scan_xy = scans_along(run.field, motion, rng, cfg.scanner, dur, frac, wp.name)
            twins.append(SimWalker(wp, plan, motion, imu, scans, scan_xy))
    return run, twins


#: Outputs the figures do not read, off so that the bench runs in minutes (they change no estimate):
#: the particle cloud, the end-of-input smoothed paths, the periodic paths.
QUIET = {"tll_pf": {"particles_every": 0, "smooth": False, "path_period_s": 0.0},
         "pdr_kf_node": {"smooth_period_s": 0.0}, "backend_node": {"path_period_s": 0.0}}


def write_inputs(run, directory: Path) -> Path:
    """The survey radio map, the building graph and the simulation's params.yaml (what
    :func:`indoor_loc.sim.write.write_run` writes besides the bag); returns the params file."""
    import yaml

    from indoor_loc.graph import save_graph
    from indoor_loc.sim.building import building_graph
    from indoor_loc.sim.write import node_params
    from indoor_loc.wifi.radiomap import add_fingerprints, empty_radiomap, save_radiomap

    directory.mkdir(parents=True, exist_ok=True)
    rm = add_fingerprints(empty_radiomap(), run.survey_xy, run.survey_scans, source="survey")
    rm_dir = save_radiomap(rm, directory / "radiomap", created_by="indoor-loc bench robot")
    graph = save_graph(building_graph(run.building), directory / "graph.yaml", source={"tool": "indoor-loc bench robot"})
    path = directory / "params.yaml"
    path.write_text(yaml.safe_dump(node_params(run, rm_dir, graph), sort_keys=False))
    return path


def _params(base: Path, out: Path, robots: list, backend_source: str) -> Path:
    """The simulation's params.yaml with the robots' own nodes on ``motion_source: odom`` (and the
    back-end's for a run of robots), :data:`QUIET` outputs off."""
    import yaml

    from indoor_loc.sim.robot_write import robot_node_params
    data = yaml.safe_load(base.read_text()) | robot_node_params(robots)
    for node, values in QUIET.items():
        data.setdefault(f"/**/{node}", {"ros__parameters": {}})["ros__parameters"].update(values)
    data["/**/backend_node"]["ros__parameters"]["motion_source"] = backend_source
    out.write_text(yaml.safe_dump(data, sort_keys=False))
    return out


def replay(run, walkers: list, robots: list, work: Path, tag: str) -> Path:
    """Write the bag of ``walkers`` + ``robots`` and replay it through the estimators."""
    from indoor_loc.pipeline.offline import run_offline
    from indoor_loc.sim.write import write_bag

    files = work / "sim"
    base = files / "params.yaml"
    if not base.exists():
        base = write_inputs(run, files)
    bag = work / f"{tag}.mcap"
    write_bag(dataclasses.replace(run, walkers=walkers, robots=robots), bag, robot_imu=False)
    params = _params(base, work / f"{tag}_params.yaml", robots, "odom" if robots else "pdr")
    nodes = (["wifi"] if robots else ["imu", "wifi"]) + ["pdr_kf", "pf", "backend"]
    out = work / f"{tag}_out.mcap"
    run_offline([bag], out, nodes=nodes, params=params, progress=False, overwrite=True)
    return out


def estimates(out: Path) -> dict[tuple[str, str], np.ndarray]:
    """(user, estimator topic) -> (N, 3) stamp ns, x, y in stamp order."""
    from indoor_loc.bag import read_bag
    from msg_adapters.pose import pose_from_msg

    est: dict[tuple[str, str], list] = defaultdict(list)
    for m in read_bag([out]):
        t = m.topic
        key = None
        for top in ("pf/pose", "pdr_kf/pose", "wifi/fix"):
            if t.endswith("/" + top):
                key = (t[1:-len(top) - 1], top)
        if t.startswith("/backend/") and t.endswith("/pose"):
            key = (t.split("/")[2], "backend")
        if key is not None:
            p = pose_from_msg(m.msg)
            est[key].append((p.stamp_ns, p.xy[0], p.xy[1]))
    out_arr = {}
    for k, v in est.items():
        a = np.array(v, dtype=np.float64)
        a[:, 0] = np.array([r[0] for r in v], np.int64) - T0_NS
        out_arr[k] = a[np.argsort(a[:, 0], kind="stable")]
    return out_arr


def scan_errors(track: np.ndarray | None, scan_ns: np.ndarray, scan_xy: np.ndarray) -> np.ndarray:
    """Error, m, of the newest estimate at or before each scan stamp (NaN before the first)."""
    if track is None or not len(track):
        return np.full(len(scan_ns), np.nan)
    idx = np.searchsorted(track[:, 0], scan_ns.astype(np.float64), side="right") - 1
    e = np.full(len(scan_ns), np.nan)
    ok = idx >= 0
    e[ok] = np.hypot(track[idx[ok], 1] - scan_xy[ok, 0], track[idx[ok], 2] - scan_xy[ok, 1])
    return e


def odometry_alone(robot) -> np.ndarray:
    """(N, 3) relative stamp, x, y: the robot's odometry laid on the map at its true start pose."""
    m, o = robot.motion, robot.odom
    x0, y0 = m.body_xyz[0, :2]
    th0 = float(m.heading[0])
    c, s = np.cos(th0), np.sin(th0)
    return np.column_stack([o.t_ns.astype(np.float64), x0 + c * o.pose[:, 0] - s * o.pose[:, 1],
                            y0 + s * o.pose[:, 0] + c * o.pose[:, 1]])


def _scan_truth(w) -> tuple[np.ndarray, np.ndarray]:
    return np.array([s.stamp_ns for s in w.scans], np.int64), np.asarray(w.scan_xy, float)


def summarise(errs: list[tuple[np.ndarray, np.ndarray]], duration_s: float) -> dict[str, float]:
    """Pooled figures of (scan stamps ns, errors m) pairs."""
    t = np.concatenate([a for a, _ in errs]) * 1e-9 if errs else np.zeros(0)
    e = np.concatenate([b for _, b in errs]) if errs else np.zeros(0)
    ok = np.isfinite(e)
    t, e = t[ok], e[ok]
    if not len(e):
        return {}

    def mean(mask) -> float:
        return float(e[mask].mean()) if mask.any() else float("nan")
    return {"n": int(len(e)), "mean": float(e.mean()), "p95": float(np.percentile(e, 95)),
            "first_5min": mean(t < WINDOW_S), "after_5min": mean(t >= WINDOW_S),
            "last_5min": mean(t >= duration_s - WINDOW_S)}


def recovery(scan_ns: np.ndarray, err: np.ndarray, kidnap_ns: int) -> tuple[int | None, float | None]:
    """(WiFi scans after the kidnapping until relocalised, seconds): the first scan from which
    ``RECOVER_RUN`` scans in a row are within ``RECOVER_M`` of the truth (None: never)."""
    after = np.flatnonzero(scan_ns >= kidnap_ns)
    good = np.isfinite(err[after]) & (err[after] <= RECOVER_M)
    for k in range(len(after) - RECOVER_RUN + 1):
        if good[k:k + RECOVER_RUN].all():
            return k + 1, float((scan_ns[after[k]] - kidnap_ns) * 1e-9)
    return None, None


def score(run, twins: list, out_r: Path, out_w: Path, duration_s: float) -> dict[str, dict]:
    """The table's rows from the replays of the robots (``out_r``) and the walkers (``out_w``)."""
    est = estimates(out_r) | estimates(out_w)
    pooled: dict[str, list] = defaultdict(list)
    for r, w in zip(run.robots, twins):
        sn, sxy = _scan_truth(r)
        pooled["odometry alone"].append((sn, scan_errors(odometry_alone(r), sn, sxy)))
        pooled["wifi/fix (robot)"].append((sn, scan_errors(est.get((r.name, "wifi/fix")), sn, sxy)))
        wn, wxy = _scan_truth(w)
        # the part of the robot's path the walker covered (its plan is the robot's, time-scaled)
        same = sn <= w.motion.t_ns[-1] * (w.params.step_length_m * w.params.cadence_hz / r.params.speed_mps)
        for top, node in ESTIMATORS:
            e = scan_errors(est.get((r.name, top)), sn, sxy)
            pooled[f"{node} + robot odometry"].append((sn, e))
            pooled[f"{node} + robot odometry, walker's part"].append((sn[same], e[same]))
            pooled[f"{node} + PDR (walker, same path)"].append((wn, scan_errors(est.get((w.name, top)), wn, wxy)))
    return {name: summarise(errs, duration_s) for name, errs in pooled.items()}


def score_kidnap(krun, out_k: Path) -> dict[str, list]:
    """Per estimator and kidnapped robot: the scans and seconds until relocalised (:func:`recovery`)."""
    kest = estimates(out_k)
    kid: dict[str, list] = defaultdict(list)
    for r in krun.robots:
        sn, sxy = _scan_truth(r)
        assert r.kidnap_ns is not None
        for top, node in ESTIMATORS:
            n, secs = recovery(sn, scan_errors(kest.get((r.name, top)), sn, sxy), r.kidnap_ns)
            kid[node].append({"robot": r.name, "scans": n, "seconds": secs})
    return kid


def run_bench(robots: int, duration_s: float, kidnap_s: float, seed: int, work: Path) -> dict:
    work.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    c0 = time.process_time()
    run, twins = simulate_bench(robots, duration_s, seed)
    out_r = replay(run, [], run.robots, work, "robots")
    out_w = replay(run, twins, [], work, "walkers")
    result: dict = {"robots": robots, "duration_s": duration_s, "seed": seed,
                    "rows": score(run, twins, out_r, out_w, duration_s),
                    "walker_duration_s": [float(w.motion.t_ns[-1] * 1e-9) for w in twins]}
    if kidnap_s > 0:
        krun, _ = simulate_bench(robots, kidnap_s, seed + 1, kidnap=True)
        result["kidnap"] = score_kidnap(krun, replay(krun, [], krun.robots, work / "kidnap", "robots"))
    result["wall_s"] = time.perf_counter() - t0
    result["cpu_s"] = time.process_time() - c0
    return result


def print_result(res: dict) -> None:
    print(f"indoor-loc bench robot: {res['robots']} robots x {res['duration_s'] / 60:g} min (seed {res['seed']}), "
          f"walkers on the same paths ({', '.join(f'{d / 60:.1f}' for d in res['walker_duration_s'])} min)")
    print(f"{'row':52s} {'scans':>5s} {'mean':>6s} {'p95':>6s} {'0-5min':>7s} {'>5min':>6s} {'last5':>6s}   (m)")
    for name, r in res["rows"].items():
        if r:
            print(f"{name:52s} {r['n']:5d} {r['mean']:6.2f} {r['p95']:6.2f} {r['first_5min']:7.2f} "
                  f"{r['after_5min']:6.2f} {r['last_5min']:6.2f}")
    rows = res["rows"]
    odo = rows.get("odometry alone", {}).get("after_5min", float("nan"))
    for _, node in ESTIMATORS:
        mine = rows.get(f"{node} + robot odometry", {}).get("after_5min", float("nan"))
        pdr = rows.get(f"{node} + PDR (walker, same path)", {}).get("mean", float("nan"))
        part = rows.get(f"{node} + robot odometry, walker's part", {}).get("mean", float("nan"))
        ok = mine < odo and part < pdr
        print(f"goal {node}: after 5 min {mine:.2f} m vs odometry alone {odo:.2f} m; on the walker's part of the "
              f"path {part:.2f} m vs PDR {pdr:.2f} m: {'met' if ok else 'NOT met'}")
    if "kidnap" in res:
        print(f"kidnapped robot (carried >= 15 m, odometry blind, halfway): the WiFi scan (and seconds after the "
              f"carry) from which {RECOVER_RUN} scans in a row are within {RECOVER_M:g} m")
        for node, lst in res["kidnap"].items():
            cells = ", ".join(f"{d['robot']}: " + (f"scan {d['scans']} / {d['seconds']:.1f} s" if d["scans"]
                                                   else "not recovered") for d in lst)
            print(f"  {node:14s} {cells}")
    print(f"wall time {res['wall_s']:.0f} s, CPU {res.get('cpu_s', float('nan')):.0f} s")


def run(args: argparse.Namespace) -> int:
    """``indoor-loc bench robot`` (the bench CLI's shared options)."""
    quick = bool(getattr(args, "quick", False))
    robots = 1 if quick and args.robots == 2 else args.robots
    duration = args.duration or (600.0 if quick else 1800.0)
    kidnap = args.kidnap_duration if args.kidnap_duration >= 0 else (300.0 if quick else 600.0)
    work = args.work if args.work != Path("out/bench_pf") else Path("out/bench_robot")
    res = run_bench(robots, duration, kidnap, 11, work)
    print_result(res)
    if args.json:
        args.json.write_text(json.dumps(res, indent=1))
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="indoor-loc bench robot", description=__doc__.splitlines()[0])
    add_arguments(parser)
    args = parser.parse_args(argv)
    res = run_bench(args.robots, args.duration, args.kidnap_duration, args.seed, args.work)
    print_result(res)
    if args.json:
        args.json.write_text(json.dumps(res, indent=1))
    return 0
