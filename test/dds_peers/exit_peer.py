"""A child for the bring-up tests: prints its arguments, waits ``--after`` s (forever when < 0)
and exits with ``--code``; SIGINT/SIGTERM end it with status 0, like a well-behaved node."""
from __future__ import annotations

import argparse
import signal
import sys
import time


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--after", type=float, default=-1.0)
    ap.add_argument("--code", type=int, default=0)
    ap.add_argument("rest", nargs="*")
    args, _ = ap.parse_known_args()
    stop = []
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda s, f: stop.append(s))
    print(f"exit_peer start argv={sys.argv[1:]}", flush=True)
    deadline = time.monotonic() + args.after if args.after >= 0 else float("inf")
    while not stop and time.monotonic() < deadline:
        time.sleep(0.02)
    if stop:
        print(f"exit_peer stopped by signal {stop[0]}", flush=True)
        return 0
    print(f"exit_peer exiting with {args.code}", file=sys.stderr, flush=True)
    return args.code


if __name__ == "__main__":
    sys.exit(main())
