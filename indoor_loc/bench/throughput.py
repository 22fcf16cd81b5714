"""``indoor-loc bench throughput``: offline replay speed per stage, next to its peers in one run.

For the same bags, one after another in one process (one core):
- ``mcap raw``: iterate every stored message with the ``mcap`` reader (no decoding);
- ``rosbags decode``: read and deserialise every message with ``rosbags`` alone (its reader and CDR
  deserialiser: the plain-Python peer an offline replay is measured against);
- ``run --nodes X``: :func:`indoor_loc.pipeline.offline.run_offline` for each stage (with the nodes
  that feed it: ``pdr_kf`` needs ``imu`` and ``wifi``), writing its output bag to a scratch directory;
  for ``imu`` also message by message (``--no-batch``).

Every timing leaves out the one-off imports (the peers' modules and ``rosbags``' type store, the
stages' modules) and counts the work on the messages. Rows give messages read, the IMU messages
among them, CPU and wall time, messages/s and IMU messages/s (per CPU second: on a shared machine
wall time measures the neighbours) and the CPU time over the ``rosbags decode`` CPU time. Default data: PUTMC walks 1–12 imported with the
package's importer (cached in ``--work``), with the importer's ``params.yaml``.
"""
from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path
from typing import Iterable

#: stage -> the --nodes of its offline run (the stage and what feeds it)
STAGE_NODES: dict[str, tuple[str, ...]] = {
    "imu": ("imu",),
    "wifi": ("wifi",),
    "pdr_kf": ("imu", "wifi", "pdr_kf"),
    "pf": ("imu", "wifi", "pdr_kf", "pf"),
}
IMU_TYPES = ("sensor_msgs/msg/Imu", "sensor_msgs/msg/MagneticField")


def _files(bags: Iterable[Path]) -> list[Path]:
    from indoor_loc.bag.reader import bag_files
    return bag_files(list(bags))


def mcap_raw_rate(bags: Iterable[Path]) -> dict:
    """Iterate every stored message of ``bags`` (file order), no decoding."""
    from mcap.reader import make_reader
    n = n_imu = 0
    t0, c0 = time.perf_counter(), time.process_time()
    for path in _files(bags):
        with open(path, "rb") as f:
            for schema, _, _ in make_reader(f).iter_messages(log_time_order=False):
                n += 1
                n_imu += schema is not None and schema.name in IMU_TYPES
    return _row("mcap raw", "", n, n_imu, time.perf_counter() - t0, time.process_time() - c0)


def rosbags_decode_rate(bags: Iterable[Path]) -> dict:
    """Read and deserialise every message of ``bags`` with ``rosbags`` alone (its rosbag2 reader on
    each MCAP file, its CDR deserialiser with the ROS 2 Jazzy types)."""
    from rosbags.rosbag2 import Reader
    from rosbags.typesys import Stores, get_typestore
    store = get_typestore(Stores.ROS2_JAZZY)
    n = n_imu = 0
    t0, c0 = time.perf_counter(), time.process_time()
    for path in _files(bags):
        with Reader(path) as reader:
            for connection, _, raw in reader.messages():
                store.deserialize_cdr(raw, connection.msgtype)
                n += 1
                n_imu += connection.msgtype in IMU_TYPES
    return _row("rosbags decode", "", n, n_imu, time.perf_counter() - t0, time.process_time() - c0)


def _row(what: str, nodes: str, n: int, n_imu: int, wall_s: float, cpu_s: float) -> dict:
    return {"what": what, "nodes": nodes, "messages": n, "imu_messages": n_imu, "wall_s": wall_s,
            "cpu_s": cpu_s, "msgs_per_s": n / max(cpu_s, 1e-9), "imu_msgs_per_s": n_imu / max(cpu_s, 1e-9)}


def offline_stage_rates(bags: Iterable[Path], *, params: Path | None = None,
                        stages: Iterable[str] = ("imu", "wifi", "pdr_kf"),
                        scratch: Path | None = None) -> list[dict]:
    """Messages/s of ``indoor-loc run`` per stage on ``bags``, after the two peers (``mcap raw``,
    ``rosbags decode``) measured on the same bags in the same process.

    Each row: ``what``, ``nodes``, ``messages``, ``imu_messages``, ``wall_s``, ``cpu_s``,
    ``msgs_per_s`` and ``imu_msgs_per_s`` (per CPU second) and ``vs_rosbags`` (CPU time ÷ the
    ``rosbags decode`` CPU time). ``imu`` is run twice: batch path, then message by message.
    """
    from indoor_loc.bag.reader import bag_topics
    from indoor_loc.errors import ConfigError
    from indoor_loc.pipeline.offline import run_offline
    from indoor_loc.pipeline.registry import stage_class

    bags = _files(bags)
    for stage in stages:                 # modules imported before any timing, as for the peers
        for node in STAGE_NODES.get(stage, ()):
            stage_class(node)
    n_imu = sum(c for t, c in bag_topics(bags).values() if t in IMU_TYPES)
    rows = [mcap_raw_rate(bags), rosbags_decode_rate(bags)]
    with tempfile.TemporaryDirectory(dir=scratch) as tmp:
        for stage in stages:
            if stage not in STAGE_NODES:
                raise ConfigError(f"bench throughput: unknown stage {stage!r}; expected one of {sorted(STAGE_NODES)}")
            nodes = list(STAGE_NODES[stage])
            for batch in (True, False) if stage == "imu" else (True,):
                out = Path(tmp) / f"{stage}.mcap"
                s = run_offline(bags, out, nodes=nodes, params=params, progress=False, batch=batch)
                out.unlink()
                rows.append(_row(f"run --nodes {','.join(nodes)}" + ("" if batch else " --no-batch"), stage,
                                 s.messages_in, n_imu, s.wall_s, s.cpu_s))
    ref = rows[1]["cpu_s"]
    for r in rows:
        r["vs_rosbags"] = r["cpu_s"] / max(ref, 1e-9)
    return rows


def format_rows(rows: list[dict]) -> str:
    lines = ["| what | messages | IMU messages | CPU s | wall s | messages/s | IMU messages/s | CPU ÷ rosbags decode |",
             "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['what']} | {r['messages']} | {r['imu_messages']} | {r['cpu_s']:.2f} | {r['wall_s']:.2f} | "
                     f"{r['msgs_per_s']:.0f} | {r['imu_msgs_per_s']:.0f} | {r['vs_rosbags']:.2f} |")
    return "\n".join(lines)


def prepare(data: Path, work: Path) -> Path:
    """Import PUTMC into ``work/import`` once (the package's importer); returns that directory."""
    from indoor_loc.cli import main as cli_main
    from indoor_loc.errors import DatasetError

    putmc = data / "putmc"
    if not (putmc / "PUTMC_Floor3_Xperia_trajs").is_dir():
        raise DatasetError(f"PUTMC not found at {putmc}")
    imp = work / "import"
    if not (imp / "params.yaml").exists():
        if cli_main(["import", "putmc", str(putmc), str(imp)]):
            raise DatasetError("PUTMC import failed")
    return imp


def run(args: argparse.Namespace) -> int:
    """Entry point: PUTMC walks 1–12 (``--quick``: 1–3), stages imu, wifi, pdr_kf."""
    import json

    work = getattr(args, "work", None)
    if work is None or Path(work) == Path("out/bench_pf"):       # the shared CLI's default belongs to pf
        work = Path("out/bench_throughput")
    imp = prepare(Path(args.data), Path(work))
    walks = range(1, 4) if getattr(args, "quick", False) else range(1, 13)
    bags = [imp / f"walk{w:02d}.mcap" for w in walks]
    rows = offline_stage_rates(bags, params=imp / "params.yaml", scratch=Path(work))
    print(f"PUTMC walks {walks[0]}-{walks[-1]} ({len(bags)} bags), one process, one after another:")
    print(format_rows(rows))
    if getattr(args, "json", None):
        Path(args.json).write_text(json.dumps(rows, indent=1))
    return 0
