"""``indoor-loc view [--port 8765] [--building FILE]``: serve a running system over Foxglove WebSocket.

The same node as ``ros2 run indoor_loc indoor_loc_view`` (see :mod:`indoor_loc.nodes.view_node`).
"""
from __future__ import annotations

import argparse


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from indoor_loc.nodes.view_node import add_arguments as view_arguments
    view_arguments(parser)


def main(args: argparse.Namespace) -> int:
    from indoor_loc.nodes.view_node import run
    return run(args)
