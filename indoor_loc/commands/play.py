"""``indoor-loc play BAG... [--rate R] [--loop] [--clock [HZ]]``: publish MCAP bags onto DDS.

The same player as ``ros2 run indoor_loc player`` (see :mod:`indoor_loc.nodes.player_node`).
"""
from __future__ import annotations

import argparse


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from indoor_loc.nodes.player_node import add_arguments as player_arguments
    player_arguments(parser)


def main(args: argparse.Namespace) -> int:
    from indoor_loc.nodes.player_node import run
    return run(args)
