"""``indoor-loc record (-t TOPIC... | -a) -o OUT.mcap``: record DDS topics to an MCAP bag.

The same recorder as ``ros2 run indoor_loc recorder`` (see :mod:`indoor_loc.nodes.recorder_node`).
"""
from __future__ import annotations

import argparse


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from indoor_loc.nodes.recorder_node import add_arguments as recorder_arguments
    recorder_arguments(parser)


def main(args: argparse.Namespace) -> int:
    from indoor_loc.nodes.recorder_node import run
    return run(args)
