"""A child for the bring-up tests: prints its arguments, waits ``--after`` s (forever when < 0)
and exits with ``--code``; SIGINT/SIGTERM end it with status 0, like a well-behaved node.

``--log FILE`` appends a line to FILE once it is started (signal handlers in place);
``--until-lines FILE N`` does not exit before FILE has N lines either (``--after`` is then the
least time it runs): a test orders its children by what they did, not by how fast this machine
starts them."""
from __future__ import annotations

import argparse
import signal
import sys
import time


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--after", type=float, default=-1.0)
    ap.add_argument("--code", type=int, default=0)
    ap.add_argument("--log", default="")
    ap.add_argument("--until-lines", nargs=2, metavar=("FILE", "N"), default=None)
    ap.add_argument("rest", nargs="*")
    args, _ = ap.parse_known_args()
    stop = []
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda s, f: stop.append(s))
    print(f"exit_peer start argv={sys.argv[1:]}", flush=True)
    if args.log:
        with open(args.log, "a") as f:
            f.write("started\n")
    deadline = time.monotonic() + args.after if args.after >= 0 else float("inf")
    while not stop and not (time.monotonic() >= deadline and _has_lines(args.until_lines)):
        time.sleep(0.02)
    if stop:
        print(f"exit_peer stopped by signal {stop[0]}", flush=True)
        return 0
    print(f"exit_peer exiting with {args.code}", file=sys.stderr, flush=True)
    return args.code


def _has_lines(until: list[str] | None) -> bool:
    if until is None:
        return True
    try:
        with open(until[0]) as f:
            return len(f.readlines()) >= int(until[1])
    except FileNotFoundError:
        return False


if __name__ == "__main__":
    sys.exit(main())
