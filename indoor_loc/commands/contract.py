"""``indoor-loc contract``: print the message contract as the code declares it (``indoor_loc/contract.py``)."""
from __future__ import annotations

import argparse

from indoor_loc.contract import TOPICS, USER_TOPICS


def add_arguments(parser: argparse.ArgumentParser) -> None:
    pass


def main(args: argparse.Namespace) -> int:
    print("| topic | type | QoS | frame | meaning |")
    print("|---|---|---|---|---|")
    for t in [*TOPICS.values(), *USER_TOPICS.values()]:
        print(f"| `{t.name}` | `{t.type}` | {t.qos.value} | `{t.frame}` | {t.doc} |")
    return 0
