"""``indoor-loc wifi``: scan the local wireless interface, or parse captured scan output.

    indoor-loc wifi scan --iface wlan0 [--tool iw|nmcli] [--command CMD] [--json]
    indoor-loc wifi parse FILE --format iw|nmcli|json [--fields F,F..] [--json]

Both print the normalised scan (strongest first) and what normalisation dropped and why;
``--keep-random-macs``, ``--min-rssi``, ``--band`` and ``--raw`` change the normalisation.
"""
from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

from indoor_loc.errors import ConfigError
from indoor_loc.params import params_from_dict
from indoor_loc.wifi.iface import TOOLS, InterfaceScanner, build_command
from indoor_loc.wifi.normalize import BANDS, NormalizeParams, NormalizeReport, band_of, normalize_report
from indoor_loc.wifi.parsers import FORMATS, NMCLI_FIELDS, SIGNAL_MAPPINGS, ParseResult, format_json, parse


def _norm_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--keep-random-macs", action="store_true", help="keep locally administered BSSIDs")
    p.add_argument("--min-rssi", type=float, default=-120.0, help="drop readings weaker than this, dBm")
    p.add_argument("--band", action="append", choices=BANDS, help="keep only this band (GHz; repeatable)")
    p.add_argument("--signal-mapping", choices=SIGNAL_MAPPINGS, default="nm",
                   help="0-100 quality -> dBm: nm (0.6 q - 100) or half (q/2 - 100)")
    p.add_argument("--raw", action="store_true", help="print the parsed readings without normalisation")
    p.add_argument("--json", action="store_true", help="print the scan as JSON (cabot-compatible)")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="wifi_command", metavar="{scan,parse}", required=True)
    s = sub.add_parser("scan", help="run one scan of a local interface and print it")
    s.add_argument("--iface", default="wlan0", help="wireless interface (default wlan0)")
    s.add_argument("--tool", choices=TOOLS, default="iw", help="scan with iw (default) or nmcli")
    s.add_argument("--command", dest="scan_cmd", default="", help="command to run instead of the default ({interface} replaced)")
    s.add_argument("--timeout", type=float, default=15.0, help="kill the command after this many s")
    s.add_argument("--no-dump-fallback", action="store_true",
                   help="do not fall back to `iw ... scan dump` when scanning is not permitted")
    _norm_args(s)
    q = sub.add_parser("parse", help="parse captured iw / nmcli / JSON output and print the normalised scan")
    q.add_argument("file", type=Path, help="captured output ('-' = stdin)")
    q.add_argument("--format", choices=FORMATS, required=True, help="what produced the file")
    q.add_argument("--fields", default=",".join(NMCLI_FIELDS), help="nmcli -f list of terse output")
    _norm_args(q)


def _normalize(result: ParseResult, args: argparse.Namespace) -> NormalizeReport:
    if args.raw:
        return NormalizeReport(result.scan, {}, len(result.scan))
    p = params_from_dict(NormalizeParams, {"keep_random_macs": args.keep_random_macs,
                                           "min_rssi_dbm": args.min_rssi, "bands": list(args.band or [])})
    return normalize_report(result.scan, p)


def _print(result: ParseResult, rep: NormalizeReport, args: argparse.Namespace, out=sys.stdout) -> None:
    scan = rep.scan
    if args.json:
        print(format_json(scan), file=out)
    else:
        order = sorted(range(len(scan)), key=lambda i: -float(scan.rssi_dbm[i]))
        print(f"{'BSSID':<17}  {'RSSI dBm':>8}  {'MHz':>7}  {'band':>4}  {'age ms':>7}  SSID", file=out)
        for i in order:
            age = "" if scan.age_ms is None or math.isnan(scan.age_ms[i]) else f"{scan.age_ms[i]:.0f}"
            ssid = scan.ssid[i] if i < len(scan.ssid) and scan.ssid[i] else "<hidden>"
            f = float(scan.freq_mhz[i])
            print(f"{scan.bssid[i]:<17}  {scan.rssi_dbm[i]:>8.1f}  {f:>7.1f}  {band_of(f) or '?':>4}  "
                  f"{age:>7}  {ssid}", file=out)
    err = sys.stderr
    dropped = ", ".join(f"{k}={v}" for k, v in sorted(rep.dropped.items())) or "none"
    print(f"{len(scan)} access points kept of {rep.n_in} read; dropped: {dropped}", file=err)
    if result.truncated:
        print("warning: the output was truncated; incomplete entries were dropped", file=err)
    for w in result.warnings:
        print(f"note: {w}", file=err)


def main(args: argparse.Namespace) -> int:
    if args.wifi_command == "parse":
        try:
            text = sys.stdin.read() if str(args.file) == "-" else args.file.read_text(encoding="utf-8",
                                                                                         errors="replace")
        except OSError as err:
            raise ConfigError(f"cannot read {args.file}: {err}") from err
        kw = {"signal_mapping": args.signal_mapping}
        if args.format == "nmcli":
            kw["fields"] = [f for f in args.fields.split(",") if f]
        result = parse(text, args.format, **kw)
        _print(result, _normalize(result, args), args)
        return 0
    scanner = InterfaceScanner(args.tool, args.iface, command=build_command(args.tool, args.iface, args.scan_cmd),
                               timeout_s=args.timeout, dump_fallback=not args.no_dump_fallback,
                               signal_mapping=args.signal_mapping)
    attempt = scanner.scan()
    if attempt.fallback:
        print(f"note: {scanner.fallback_reason}; used `{' '.join(scanner.dump_command)}`", file=sys.stderr)
    if attempt.error is not None:
        print(f"indoor-loc wifi scan: {attempt.error.reason}: {attempt.error}", file=sys.stderr)
        return 3
    assert attempt.result is not None
    _print(attempt.result, _normalize(attempt.result, args), args)
    print(f"scan took {attempt.duration_s:.2f} s", file=sys.stderr)
    return 0

