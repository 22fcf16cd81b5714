"""``indoor-loc bag info FILE...`` and ``indoor-loc bag recover IN OUT`` (an existing OUT is refused
unless ``--overwrite``); ``indoor-loc bag to-getsensordata BAG OUT_DIR``
(:mod:`indoor_loc.commands.to_getsensordata`)."""
from __future__ import annotations

import argparse
import datetime as dt
import struct
from pathlib import Path

from indoor_loc.errors import BagError


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="bag_command", metavar="ACTION", required=True)
    info = sub.add_parser("info", help="topics, types, message counts, duration, start/end of bags")
    info.add_argument("bags", nargs="+", type=Path, help="MCAP bag file(s) or bag directories")
    rec = sub.add_parser("recover", help="rewrite a bag whose writer was killed into a valid one")
    rec.add_argument("src", type=Path, help="damaged MCAP bag")
    rec.add_argument("dst", type=Path, help="output MCAP bag (must differ from the input)")
    rec.add_argument("--chunk-size", type=int, default=1 << 20, help="output chunk size in bytes (default 1 MiB)")
    rec.add_argument("--overwrite", action="store_true", help="replace an existing output bag")
    rec.add_argument("--compression", choices=("zstd", "lz4", "none"), default="zstd",
                     help="output chunk compression (default zstd)")
    from indoor_loc.commands.to_getsensordata import add_arguments as add_to_gsd
    add_to_gsd(sub)


def _fmt_time(ns: int) -> str:
    t = dt.datetime.fromtimestamp(ns / 1e9, tz=dt.timezone.utc)
    return f"{t:%Y-%m-%d %H:%M:%S.%f} UTC ({ns / 1e9:.9f} s)"


def _file_summary(path: Path) -> tuple[int, int, int, int, str]:
    """(start ns, end ns, messages, chunks, note) of one bag."""
    from mcap.exceptions import McapError
    from mcap.reader import make_reader

    from indoor_loc.bag.recover import scan_records
    with open(path, "rb") as f:
        try:
            summary = make_reader(f).get_summary()
        except (McapError, struct.error, ValueError, OSError):   # no footer: writer was killed
            summary = None
    if summary is not None and summary.statistics is not None:
        st = summary.statistics
        return st.message_start_time, st.message_end_time, st.message_count, st.chunk_count, ""
    scan = scan_records(path)
    note = ("no summary" + (f"; ends in a partial record ({path.stat().st_size - scan.valid_bytes} bytes "
                            "unreadable): run `indoor-loc bag recover`" if scan.truncated else ""))
    return 0, 0, scan.messages, scan.chunks, note


def info(paths: list[Path]) -> int:
    from indoor_loc.bag.recover import scan_records
    from indoor_loc.bag.reader import bag_info as topics_of
    from indoor_loc.bag.reader import bag_files
    for path in bag_files(paths):
        if not path.is_file():
            raise BagError(f"bag {path} does not exist")
        start, end, count, chunks, note = _file_summary(path)
        print(f"File:      {path} ({path.stat().st_size / 1e6:.2f} MB)")
        if note:
            print(f"Warning:   {note}")
            scan = scan_records(path)
            print(f"Messages:  {scan.messages} readable in {scan.chunks} complete chunks")
            for cid, ch in sorted(scan.channels.items(), key=lambda kv: kv[1].topic):
                schema = scan.schemas.get(ch.schema_id)
                print(f"  {ch.topic}  [{schema.name if schema else '?'}]  {scan.counts.get(cid, 0)} msgs")
            print()
            continue
        print(f"Duration:  {(end - start) / 1e9:.3f} s")
        print(f"Start:     {_fmt_time(start)}")
        print(f"End:       {_fmt_time(end)}")
        print(f"Messages:  {count} in {chunks} chunks")
        topics = topics_of(path)
        width = max((len(t) for t in topics), default=0)
        print(f"Topics:    {len(topics)}")
        for name in sorted(topics):
            t = topics[name]
            print(f"  {name:<{width}}  {t.type:<40}  {t.count:>8} msgs")
        print()
    return 0


def recover_cmd(args: argparse.Namespace) -> int:
    from indoor_loc.bag.recover import recover
    from indoor_loc.output_paths import check_output
    if not args.src.is_file():
        raise BagError(f"bag {args.src} does not exist")
    check_output(args.dst, inputs=[args.src], overwrite=args.overwrite, what="recover: output")
    r = recover(args.src, args.dst, chunk_size=args.chunk_size, compression=args.compression)
    state = "truncated" if r.truncated else "complete"
    print(f"{args.src} ({state}): kept {r.messages} messages on {r.topics} topics from {r.chunks} chunks"
          f"{f', {r.bad_chunks} damaged chunks skipped' if r.bad_chunks else ''}"
          f"{f', {r.lost_bytes} trailing bytes unreadable' if r.lost_bytes else ''}"
          f"{f', {r.messages_without_channel} messages without a channel dropped' if r.messages_without_channel else ''}"
          f" -> {args.dst}")
    return 0


def main(args: argparse.Namespace) -> int:
    if args.bag_command == "info":
        return info(list(args.bags))
    if args.bag_command == "recover":
        return recover_cmd(args)
    if args.bag_command == "to-getsensordata":
        from indoor_loc.commands.to_getsensordata import main as to_gsd
        return to_gsd(args)
    raise BagError(f"unknown bag action {args.bag_command!r}")
