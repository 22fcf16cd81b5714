"""``indoor-loc up CONFIG.yaml [--dry-run]``: start a set of nodes from a bring-up YAML, like a launch
file (the supervisor is :mod:`indoor_loc.supervisor`)."""
from __future__ import annotations

import argparse
import shlex
from pathlib import Path

from indoor_loc.supervisor import Bringup, load_config


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.epilog = ("Each node runs as its own process, its output lines prefixed with its name. Ctrl-C (or "
                     "SIGTERM) stops them in waves of stop_order: the player, then the estimators from sources "
                     "to sinks, the recorder last (SIGTERM, then SIGKILL, after stop_timeout_s; a second Ctrl-C "
                     "sends SIGTERM to all at once). Exit status 0 when every node ended cleanly, 1 otherwise. A working "
                     "example: the OUT/bringup.yaml that `indoor-loc demo` writes.")
    parser.add_argument("config", type=Path, help="bring-up YAML (see config/bringup_example.yaml)")
    parser.add_argument("--dry-run", action="store_true", help="print each node's command line and exit")


def main(args: argparse.Namespace) -> int:
    config = load_config(args.config)
    if args.dry_run:
        for spec in config.nodes:
            env = " ".join(f"{k}={shlex.quote(v)}" for k, v in {**config.env, **spec.env}.items())
            print(f"{spec.name}: {env + ' ' if env else ''}{shlex.join(spec.command())}")
        return 0
    return Bringup(config).run()
