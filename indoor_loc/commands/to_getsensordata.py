"""``indoor-loc bag to-getsensordata BAG OUT_DIR``: GetSensorData logfiles (one per user namespace) from a
bag in the message contract (:mod:`indoor_loc.datasets.getsensordata_writer`), plus ``map_origin.yaml``
(the origin and storey height used, which ``indoor-loc import getsensordata`` reads back from the logs'
directory so the round trip lands in the same map frame). ``indoor-loc sim --format getsensordata`` runs
it on the simulated bag with the walkers' truth files (floors included)."""
from __future__ import annotations

import argparse
from pathlib import Path

import yaml

from indoor_loc.errors import ConfigError

#: the origin of simulated runs' map frame (the CAR-CSIC campus, Arganda del Rey, where the app comes from)
SIM_ORIGIN = (40.3133, -3.4836)
ORIGIN_FILE = "map_origin.yaml"


def add_arguments(sub) -> None:
    p = sub.add_parser("to-getsensordata", help="write GetSensorData logfiles (one per user) from a bag",
                       description="Write GetSensorData logfiles (IPIN competition format), one per user namespace")
    p.add_argument("bag", type=Path, help="MCAP bag in the message contract")
    p.add_argument("out_dir", type=Path, help="output directory (created)")
    p.add_argument("--origin", default=f"{SIM_ORIGIN[0]},{SIM_ORIGIN[1]}",
                   help="latitude,longitude of the map frame's origin, deg (default: %(default)s)")
    p.add_argument("--storey-height-m", type=float, default=4.0, help="POSI floor id = round(z / this) (default 4)")
    p.add_argument("--truth", type=Path, default=None,
                   help="directory of <user>.csv truth files with a floor column (indoor-loc sim's truth/) for POSI")
    p.add_argument("--posi-period-s", type=float, default=1.0,
                   help="at most one POSI reference point per this many seconds (default 1; 0 = every pose)")
    p.add_argument("--overwrite", action="store_true", help="replace logs already in OUT_DIR")


def write_origin(out_dir: Path, origin: tuple[float, float], storey_height_m: float) -> Path:
    path = Path(out_dir) / ORIGIN_FILE
    path.write_text("# the map frame the POSI points were converted from: ENU at this origin, z = floor id x "
                    "storey_height_m\n" + yaml.safe_dump({"frame_id": "map", "latitude_deg": origin[0],
                                                          "longitude_deg": origin[1],
                                                          "storey_height_m": storey_height_m}, sort_keys=False))
    return path


def convert(bag: Path, out_dir: Path, *, origin: tuple[float, float], storey_height_m: float,
            truth: Path | None = None, posi_period_s: float = 1.0, quiet: bool = False) -> dict:
    from indoor_loc.datasets.getsensordata_writer import bag_to_logs
    if not bag.is_file():
        raise ConfigError(f"BAG {bag} does not exist")
    if not storey_height_m > 0 or not posi_period_s >= 0:
        raise ConfigError("--storey-height-m must be > 0 and --posi-period-s >= 0")
    res = bag_to_logs(bag, out_dir, origin=origin, storey_height_m=storey_height_m, truth_dir=truth,
                      posi_period_s=posi_period_s)
    write_origin(out_dir, origin, storey_height_m)
    if not quiet:
        for r in res.values():
            print(f"  {r['file']}: " + ", ".join(f"{k} {v}" for k, v in sorted(r["lines"].items())))
    return res


def convert_sim(paths: dict[str, Path], out_dir: Path) -> dict:
    """The GetSensorData logs of an ``indoor-loc sim`` run (``paths`` as :func:`indoor_loc.commands.sim.generate`
    returns them): POSI every second from the walkers' truth files with their floors, the storey height
    of the building (its mean floor spacing; 4 m on one floor), origin :data:`SIM_ORIGIN`."""
    import numpy as np
    from indoor_loc.sim.building import load_building
    fz = np.asarray(load_building(paths["building"]).floor_z, float)
    h = float(np.mean(np.diff(fz))) if len(fz) > 1 else 4.0
    print(f"  getsensordata {out_dir} (origin {SIM_ORIGIN[0]}, {SIM_ORIGIN[1]}; storey {h:g} m)")
    return convert(paths["bag"], out_dir, origin=SIM_ORIGIN, storey_height_m=h, truth=paths["truth"])


def main(args: argparse.Namespace) -> int:
    from indoor_loc.commands.import_getsensordata import parse_origin
    from indoor_loc.output_paths import check_outputs
    from indoor_loc.bag.reader import bag_topics
    from indoor_loc.contract import split_ns
    origin = parse_origin(args.origin)
    assert origin is not None
    users = sorted({split_ns(t)[0].strip("/") for t in bag_topics(args.bag)} - {""})
    check_outputs([args.out_dir / f"{u}.txt" for u in users] + [args.out_dir / ORIGIN_FILE],
                  overwrite=args.overwrite, what="bag to-getsensordata")
    convert(args.bag, args.out_dir, origin=origin, storey_height_m=args.storey_height_m, truth=args.truth,
            posi_period_s=args.posi_period_s)
    return 0
