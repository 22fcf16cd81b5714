"""``indoor-loc contract``: print the message contract as the code declares it (``indoor_loc/contract.py``)."""
from __future__ import annotations

import argparse

from indoor_loc.contract import BOUNDS, TOPICS, USER_TOPICS


def add_arguments(parser: argparse.ArgumentParser) -> None:
    pass


def main(args: argparse.Namespace) -> int:
    print("| topic | type | QoS | frame | meaning |")
    print("|---|---|---|---|---|")
    for t in [*TOPICS.values(), *USER_TOPICS.values()]:
        print(f"| `{t.name}` | `{t.type}` | {t.qos.value} | `{t.frame}` | {t.doc} |")
    print()
    print("Plausibility bounds: a finite value outside them rejects the message under the reason shown.")
    print()
    print("| bound | range | unit | applies to | rejected as | why |")
    print("|---|---|---|---|---|---|")
    for b in BOUNDS.values():
        print(f"| `{b.name}` | [{b.lo:g}, {b.hi:g}] | {b.unit} | {b.applies} | `{b.reason}` | {b.why} |")
    return 0
