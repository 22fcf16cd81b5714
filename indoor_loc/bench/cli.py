"""``indoor-loc bench NAME`` (the names: :data:`BENCHES`): benchmarks print tables, side by side with peers
in one run."""
from __future__ import annotations

import argparse
import importlib
from pathlib import Path

BENCHES = {
    "heading": "indoor_loc.bench.heading",
    "imu": "indoor_loc.bench.imu",
    "wifi": "indoor_loc.bench.wifi",
    "steps": "indoor_loc.bench.steps",
    "backend": "indoor_loc.bench.backend",
    "pf": "indoor_loc.bench.pf",
    "throughput": "indoor_loc.bench.throughput",
    "live": "indoor_loc.bench.live",
    "chaos": "indoor_loc.bench.chaos",
    "scale": "indoor_loc.bench.scale",
    "robot": "indoor_loc.bench.robot",
    "floors": "indoor_loc.bench.floors",
    "ble": "indoor_loc.bench.ble_ms",
    "fusion": "indoor_loc.bench.fusion",
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("which", choices=sorted(BENCHES), help="which benchmark")
    parser.add_argument("--data", type=Path, default=Path("../shared/datasets"),
                        help="datasets directory (default ../shared/datasets)")
    parser.add_argument("--quick", action="store_true", help=(
        "smaller run. heading: a quarter of the TyRex trials, the first 60 s of each BROAD trial, "
        "no Madgwick; imu: 6 PUTMC walks, the first 60 s of each BROAD trial, shorter throughput runs; "
        "steps: a quarter of the Oxford traces; wifi: a smaller WKNN grid and 100 timed queries instead "
        "of 300 (putmc; --dataset ms_site2 has no smaller run); backend: 5 reduced-map draws instead of "
        "50, one graph run per configuration instead of best of 3, fresh processes for 2 configurations "
        "x 1 run instead of all 5 x 3, --live at 10x only; pf: one run, the PDR and 10 s WiFi-only rows; "
        "throughput: walks 1-3 instead of 1-12; live: users 1,2, rates 2,5, 30 s (each unless given); "
        "chaos: 40 s of walking, 100 hostile messages per port; floors: 180 s walks and 10 min of drift "
        "instead of 600 s and 30 min"))
    parser.add_argument("--json", type=Path, help="also write the figures as JSON here")
    parser.add_argument("--live", action="store_true", help="backend: also replay all walks live over DDS "
                                                            "through backend_node at 1x and 10x")
    parser.add_argument("--dataset", default="", help="dataset of the benchmark when it has several "
                                                      "(wifi: putmc (default) or ms_site2; fusion: ms_site2; "
                                                      "ble: ms_site2 (default) or sim)")
    parser.add_argument("--site", type=Path, help="wifi: a site directory of the Microsoft Indoor Location "
                                                  "Competition 2.0 format (<floor>/path_data_files/...): the "
                                                  "ms_site2 tables on its floors")
    parser.add_argument("--floors", default="", help="wifi --site/ms_site2, ble, fusion: comma-separated floor names "
                                                     "(default all)")
    parser.add_argument("--floor-levels", default="", help="wifi --site/ms_site2: storey index per floor, "
                                                           "NAME=LEVEL,... (default: from the floor names)")
    parser.add_argument("--metadata", type=Path, help="wifi --site: the floors' plan files as <floor>/... when "
                                                      "the site's floor directories hold only traces")
    parser.add_argument("--runs", type=int, default=3, help="pf: Monte Carlo runs (seeds 0..runs-1)")
    parser.add_argument("--work", type=Path, default=Path("out/bench_pf"), help="pf: cache for the import and the replay; fusion: "
                             "the same, WORK/<site> (default out/bench_fusion); floors: out/bench_floors")
    parser.add_argument("--particles", type=int, default=1000, help="pf: particles per filter")
    parser.add_argument("--walks", default="all", help="pf: comma-separated walk numbers (default all 24)")
    parser.add_argument("--no-perf", action="store_true", help="pf: skip the performance section")
    parser.add_argument("--learn", action="store_true", help="pf: also score transitions learned from the odd walks on the even walks")
    parser.add_argument("--users", default="", help="live: numbers of users to try (default 1,2,4); scale: the "
                                                    "steps (default 10,25,50,100,150,200)")
    parser.add_argument("--rates", default="", help="live: replay rates to try, rising (default 2,5,10,20)")
    parser.add_argument("--duration", type=float, default=0.0, help="live, chaos: simulated seconds per user "
                                                                    "(default 60; chaos --soak: of the looped world, 300)")
    parser.add_argument("--walkers", type=int, default=0, help="chaos: simulated walkers (default 1; --soak 2)")
    parser.add_argument("--rate", type=float, default=0.0, help="chaos: replay rate (default 2; --soak 5)")
    parser.add_argument("--cases", type=int, default=0, help="chaos: hostile messages drawn per input port and "
                                                             "walker (default 2000; 10000 for the issue's figure)")
    parser.add_argument("--faults", default="", help="chaos: comma-separated trials among hostile,empty,kill,loop "
                                                     "(default all; the clean reference always runs)")
    parser.add_argument("--nodes", default="", help="chaos: nodes to run, e.g. imu_node,wifi_fix_node (default all: "
                                                    "imu_node, wifi_fix_node, pdr_kf_node, tll_pf, backend_node)")
    parser.add_argument("--ports", default="", help="chaos: hostile messages only on these input ports, e.g. "
                                                    "initialpose,wifi/fix (default all seven)")
    parser.add_argument("--kill-nodes", default="", help="chaos: nodes to kill, e.g. imu_node,tll_pf (default all)")
    parser.add_argument("--clock", choices=("sim", "wall"), default="sim",
                        help="chaos: the nodes' clock: sim (use_sim_time, the bench publishes /clock with the stream, "
                             "as a live deployment whose stamps are the present; default) or wall (a replay without "
                             "--clock: the bag's stamps months behind the nodes' clock, which cannot vouch for any)")
    parser.add_argument("--soak", type=float, default=0.0, help="chaos: soak instead: HOURS of simulated time at "
                                                                "--rate, RSS and per-message cost over time")
    parser.add_argument("--imu-hz", type=float, default=0.0, help="scale: IMU rate of the simulated users (default 50)")
    parser.add_argument("--shards", default="", help="scale: processes per stage to try, e.g. 1,2 (default 1,2)")
    parser.add_argument("--warmup", type=float, default=0.0, help="scale: s after adding users before measuring (default 15)")
    parser.add_argument("--window", type=float, default=0.0, help="scale: s measured per step (default 25)")
    parser.add_argument("--heading-source", default="", help="scale: imu_node's heading_source (default auto, i.e. "
                                                             "VQF; aekf: the simulator's own)")
    parser.add_argument("--robots", type=int, default=2, help="robot: simulated robots (default 2; --duration: "
                                                              "their run, default 1800 s; --quick: 1 robot x 600 s)")
    parser.add_argument("--kidnap-duration", type=float, default=-1.0, help="robot: the kidnapped robots' run, "
                                                                            "carried at its half, s (default 600; 0 = skip)")
    parser.add_argument("--set", action="append", default=[], metavar="NODE.KEY=VALUE",
                        help="fusion: override a parameter of the import's params.yaml for every namespace's node "
                             "(repeatable; e.g. tll_pf.n_particles=500); each variant is cached apart")
    parser.add_argument("--walks-per-floor", type=int, default=0,
                        help="fusion: only the first N test walks of each floor (a development subset)")
    parser.add_argument("--per-walk", action="store_true", help="fusion: also print every walk's mean errors")
    parser.add_argument("--sensor-qos", choices=("reliable", "best_effort"), default="reliable",
                        help="live: reliability of the nodes' sensor inputs (default reliable, as for a replay)")


def main(args: argparse.Namespace) -> int:
    return int(importlib.import_module(BENCHES[args.which]).run(args) or 0)
