"""``indoor-loc up CONFIG.yaml [--dry-run]``: start a set of nodes from a bring-up YAML, like a launch
file (the supervisor is :mod:`indoor_loc.supervisor`)."""
from __future__ import annotations

import argparse
import shlex
from pathlib import Path

from indoor_loc.supervisor import Bringup, load_config


def add_arguments(parser: argparse.ArgumentParser) -> None:
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
