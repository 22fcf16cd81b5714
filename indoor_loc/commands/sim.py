"""``indoor-loc sim OUT_DIR``: simulate walkers in a building and write bags, radio map, graph, params.

Writes ``OUT_DIR/sim.mcap`` (every walker under its own namespace), ``radiomap/``,
``building.geojson``, ``truth/<walker>.csv``, ``params.yaml`` and ``scenario.yaml`` (see
:mod:`indoor_loc.sim.write`), then prints a summary. The same seed writes the same run. Outputs of an earlier run in OUT_DIR are
refused unless ``--overwrite``.
"""
from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path

from indoor_loc.errors import ConfigError


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("out_dir", type=Path, help="output directory (created)")
    parser.add_argument("--building", type=Path, default=None,
                        help="building GeoJSON (default: the shipped sample building)")
    parser.add_argument("--walkers", type=int, default=3, help="number of walkers (1..8, default 3)")
    parser.add_argument("--robots", type=int, default=0,
                        help="differential-drive robots with wheel odometry (0..8, default 0; /robot1, ...)")
    parser.add_argument("--duration", type=float, default=90.0, help="run length, s (default 90)")
    parser.add_argument("--seed", type=int, default=7, help="random seed (default 7)")
    parser.add_argument("--imu-hz", type=float, default=100.0, help="IMU rate, Hz (default 100)")
    parser.add_argument("--mag-hz", type=float, default=50.0, help="magnetometer rate, Hz (default 50)")
    parser.add_argument("--scan-period", type=float, default=4.0, help="WiFi scan period, s (default 4)")
    parser.add_argument("--format", choices=("mcap", "getsensordata"), default="mcap",
                        help="getsensordata: also write OUT_DIR/getsensordata/<walker>.txt, GetSensorData logfiles of "
                             "the run (indoor-loc bag to-getsensordata; default: only the bag)")
    parser.add_argument("--floors", type=int, choices=(2, 3), default=2,
                        help="3: the three-floor office with stairs and a lift, walkers changing floors, a radio "
                             "map with the floors and powed fixes that detect them (default 2: the sample building, "
                             "walkers on the ground floor)")
    parser.add_argument("--baro", action="store_true", help="simulate a phone barometer (baro/pressure, with weather "
                                                            "drift, door spikes, noise; indoor_loc/sim/baro.py)")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace the outputs of an earlier run in OUT_DIR (refused otherwise)")


#: What ``indoor-loc sim`` writes into OUT_DIR (:func:`indoor_loc.sim.write.write_run`).
OUTPUTS = ("sim.mcap", "radiomap", "building.geojson", "graph.yaml", "floor_plans", "truth",
           "params.yaml", "scenario.yaml")


def config_from_args(args: argparse.Namespace):
    from indoor_loc.sim.baro import BaroSimParams
    from indoor_loc.sim.rf import ScannerParams
    from indoor_loc.sim.scenario import SimConfig
    from indoor_loc.sim.walker import ImuParams
    try:
        cfg = SimConfig(walkers=args.walkers, duration_s=args.duration, seed=args.seed,
                        robots=getattr(args, "robots", 0),
                        imu=dataclasses.replace(ImuParams(), rate_hz=args.imu_hz, mag_rate_hz=args.mag_hz),
                        scanner=dataclasses.replace(ScannerParams(), period_s=args.scan_period),
                        change_floors=getattr(args, "floors", 2) == 3,
                        baro=BaroSimParams() if getattr(args, "baro", False) else None)
        cfg.validate()
    except ValueError as err:
        raise ConfigError(str(err)) from err
    return cfg


def generate(out_dir: Path, cfg, building_path: Path | None = None, *, quiet: bool = False,
             building=None) -> dict[str, Path]:
    from indoor_loc.sim.building import load_building, sample_building
    from indoor_loc.sim.scenario import simulate
    from indoor_loc.sim.write import write_run

    t0 = time.perf_counter()
    if building is None:
        building = sample_building() if building_path is None else load_building(building_path)
    run = simulate(building, cfg)
    paths = write_run(run, out_dir)
    if not quiet:
        print(f"simulated {len(run.walkers)} walkers x {cfg.duration_s:g} s in {building.name} "
              f"({building.n_floors} floors, {len(building.node_xyz)} graph nodes, {len(building.aps)} APs / "
              f"{len(building.all_bssids())} BSSIDs) in {time.perf_counter() - t0:.1f} s")
        for w in run.walkers:
            print(f"  /{w.name}: step {w.params.step_length_m:.2f} m, cadence {w.params.cadence_hz:.2f} Hz, "
                  f"{w.motion.steps[-1]:.0f} steps, {len(w.scans)} scans")
        for r in run.robots:
            print(f"  /{r.name}: robot at {r.params.speed_mps:.2f} m/s, odometry at {r.params.odom_rate_hz:g} Hz, "
                  f"{len(r.scans)} scans")
        for role, p in paths.items():
            print(f"  {role:9s} {p}")
    return paths


def main(args: argparse.Namespace) -> int:
    from indoor_loc.output_paths import check_outputs
    out = Path(args.out_dir)
    if out.exists() and not out.is_dir():
        raise ConfigError(f"OUT_DIR {out} exists and is not a directory")
    gsd = getattr(args, "format", "mcap") == "getsensordata"
    check_outputs([out / name for name in OUTPUTS + (("getsensordata",) if gsd else ())], overwrite=args.overwrite,
                  what=f"sim into {out}")
    cfg = config_from_args(args)
    building = None
    if getattr(args, "floors", 2) == 3:
        if args.building is not None:
            raise ConfigError("--floors 3 simulates the three-floor office: it cannot be given with --building")
        from indoor_loc.sim.building import make_tower_building
        building = make_tower_building()
    paths = generate(args.out_dir, cfg, args.building, building=building)
    if gsd:
        from indoor_loc.commands.to_getsensordata import convert_sim
        convert_sim(paths, out / "getsensordata")
    return 0
