"""``indoor-loc``: the package's command line (offline replay, bring-up, bags, import, eval, bench).

Each subcommand lives in its own module exposing ``add_arguments(parser)`` and ``main(args) -> int``
(``"module:function"`` names another entry point, e.g. a node's ``run``); modules are imported only
when their command runs (``--help`` lists them all without importing).
"""
from __future__ import annotations

import argparse
import importlib
import os
import sys

from indoor_loc.errors import IndoorLocError

# name -> (module, one-line help)
COMMANDS: dict[str, tuple[str, str]] = {
    "demo": ("indoor_loc.demo", "the main job: simulated walkers in the sample building, every node live over DDS, scored and plotted"),
    "run": ("indoor_loc.pipeline.offline", "run bags through the nodes offline, as fast as the CPU allows"),
    "up": ("indoor_loc.commands.up", "start a set of nodes from a bring-up YAML (like a launch file)"),
    "record": ("indoor_loc.nodes.recorder_node:run", "record DDS topics to an MCAP bag (the recorder node)"),
    "play": ("indoor_loc.nodes.player_node:run", "publish an MCAP bag onto DDS (rate, loop, /clock; the player node)"),
    "bag": ("indoor_loc.commands.bag", "bag tools: info, recover"),
    "import": ("indoor_loc.commands.import_data", "import a dataset into MCAP bags + params.yaml"),
    "eval": ("indoor_loc.commands.eval", "score trajectories against ground truth"),
    "radiomap": ("indoor_loc.commands.radiomap", "build / inspect WiFi radio maps"),
    "map": ("indoor_loc.commands.map", "building graphs: from a floor-plan image or GeoJSON, draw over the plan"),
    "wifi": ("indoor_loc.commands.wifi", "WiFi tools: scan the local interface, parse captured output"),
    "bench": ("indoor_loc.bench.cli", "benchmarks that print tables, side by side in one run (indoor-loc bench -h lists them)"),
    "contract": ("indoor_loc.commands.contract", "print the message contract as a Markdown table"),
    "view": ("indoor_loc.commands.view", "live view of a running system over the Foxglove WebSocket protocol (Foxglove, Lichtblick)"),
    "sim": ("indoor_loc.commands.sim", "simulate walkers in a building: bags, radio map, graph, params.yaml"),
}


def package_version() -> str:
    """The installed distribution's version (``package.xml`` and ``setup.py`` say the same)."""
    from importlib.metadata import PackageNotFoundError, version
    try:
        return version("indoor_loc")
    except PackageNotFoundError:            # run from a source tree without an install
        return "unknown (not installed)"


def build_parser(selected: str | None = None) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="indoor-loc", description="indoor-loc: the package's command line (offline replay, bring-up, bags, "
        "import, eval, bench). `indoor-loc COMMAND --help` shows a command's options.",
        epilog="The nodes are executables of their own (imu_node, wifi_scan_node, wifi_fix_node, pdr_kf_node, "
               "tll_pf, backend_node, recorder, player, indoor_loc_view, indoor_loc_map); `NODE --help` "
               "prints their parameters and topics.")
    parser.add_argument("--version", action="version", version=f"indoor-loc {package_version()}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, (module, help_) in COMMANDS.items():
        p = sub.add_parser(name, help=help_, description=help_)
        if name == selected:
            importlib.import_module(module.partition(":")[0]).add_arguments(p)
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    selected = next((a for a in argv if not a.startswith("-")), None)
    if selected not in COMMANDS:
        selected = None
    parser = build_parser(selected)
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help()
        return 1
    module, _, function = COMMANDS[args.command][0].partition(":")
    entry = getattr(importlib.import_module(module), function or "main")
    try:
        return int(entry(args) or 0)
    except IndoorLocError as err:
        print(f"indoor-loc {args.command}: error: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:          # output piped into a reader that stopped early (``| head``)
        try:                         # no second error when the interpreter flushes stdout at exit
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, sys.stdout.fileno())
        except (OSError, ValueError):
            pass
        return 141                   # 128 + SIGPIPE, as a shell reports it


if __name__ == "__main__":
    sys.exit(main())
