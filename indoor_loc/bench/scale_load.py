"""The load of ``indoor-loc bench scale``: N simulated users published live, stamped with the wall clock.

``python -m indoor_loc.bench.scale_load SIM.mcap --topics imu/data_raw,wifi/scan`` reads the
simulated walkers' messages (:mod:`indoor_loc.sim`, one namespace per walker) and publishes them as
users ``u000``, ``u001``, ...: user *k* replays walker *k* mod (walkers), from the moment it joins,
its messages due at join time + their offset in the walk (looped: the walk starts again, stamps go on)
and stamped with that due time (the header stamp rewritten in the CDR bytes), so a consumer's
latency is its reception time minus the stamp. Reliable publishers, serialised bytes as stored.

Commands on stdin, one a line: ``users N`` (users 0..N-1 publish from now on; users join, none
leave), ``quit``. Every second it prints ``sent WALL_NS USERS TOPIC=COUNT ... lag_ms=MAX`` (messages
published so far per relative topic; the largest delay of a publish behind its due time in that
second).
"""
from __future__ import annotations

import heapq
import os
import select
import struct
import sys
import time
from pathlib import Path

_STAMP = struct.Struct("<iI")


def load_walks(bag: Path, rels: list[str]) -> list[list[tuple[int, str, str, bytes]]]:
    """Per walker (sorted by name): its messages on ``rels`` as (offset ns from the walk's first
    message, relative topic, type, CDR bytes), in time order."""
    from indoor_loc.bag import read_raw
    walks: dict[str, list[tuple[int, str, str, bytes]]] = {}
    for m in read_raw([bag]):
        parts = m.topic.split("/", 2)
        if len(parts) == 3 and parts[2] in rels:
            walks.setdefault(parts[1], []).append((m.stamp_ns, parts[2], m.type, bytes(m.data)))
    out = []
    for name in sorted(walks):
        msgs = sorted(walks[name], key=lambda x: x[0])
        t0 = msgs[0][0]
        out.append([(t - t0, rel, tp, data) for t, rel, tp, data in msgs])
    return out


def user_name(k: int) -> str:
    return f"u{k:03d}"


def main(argv: list[str] | None = None) -> int:
    import rclpy
    from rclpy.node import Node

    from indoor_loc.contract import Qos, msg_class
    from indoor_loc.nodes.qos import publisher_qos

    args = sys.argv[1:] if argv is None else argv
    bag = Path(args[0])
    rels = args[args.index("--topics") + 1].split(",") if "--topics" in args else ["imu/data_raw", "wifi/scan"]
    walks = load_walks(bag, rels)
    period = [w[-1][0] + 20_000_000 for w in walks]          # a looped walk goes on 20 ms after its last message
    rclpy.init()
    node = Node("scale_load")
    # as deep as the nodes' own reliable publishers (nodes/qos.py: 1000, 20 s at 50 Hz): the contract's 50
    # (1 s) was overwritten before a node starved of CPU on a shared machine had acknowledged it, a loss
    # of the generator's history rather than of the node
    qos = publisher_qos(Qos.RELIABLE)
    pubs: dict[tuple[int, str], object] = {}
    heap: list[tuple[int, int, int, int]] = []               # (due ns, user, index in its walk, loop)
    joined: dict[int, int] = {}                              # user -> join wall ns
    sent = {rel: 0 for rel in rels}
    lag_max = 0
    next_report = time.time_ns() + 1_000_000_000
    users = 0
    stdin = sys.stdin.fileno()
    os.set_blocking(stdin, False)
    buf = b""
    try:
        while True:
            if select.select([stdin], [], [], 0)[0]:
                chunk = os.read(stdin, 4096)
                if not chunk:
                    break
                buf += chunk
                *lines, rest = buf.split(b"\n")
                buf = rest
                for line in lines:
                    cmd = line.decode().split()
                    if cmd[:1] == ["quit"]:
                        return 0
                    if cmd[:1] == ["users"]:
                        want = int(cmd[1])
                        now = time.time_ns()
                        for k in range(users, want):
                            w = walks[k % len(walks)]
                            for rel, tp in {(m[1], m[2]) for m in w}:
                                pubs[(k, rel)] = node.create_publisher(msg_class(tp), f"/{user_name(k)}/{rel}", qos)
                            joined[k] = now + 1_000_000_000           # a second for discovery first
                            heapq.heappush(heap, (joined[k] + w[0][0], k, 0, 0))
                        users = max(users, want)
            now = time.time_ns()
            while heap and heap[0][0] <= now:
                due, k, i, loop = heapq.heappop(heap)
                w = walks[k % len(walks)]
                _, rel, _, data = w[i]
                out = bytearray(data)
                sec, nsec = divmod(due, 1_000_000_000)
                _STAMP.pack_into(out, 4, sec, nsec)
                pubs[(k, rel)].publish(bytes(out))
                sent[rel] += 1
                lag_max = max(lag_max, now - due)
                i += 1
                if i == len(w):
                    i, loop = 0, loop + 1
                heapq.heappush(heap, (joined[k] + loop * period[k % len(walks)] + w[i][0], k, i, loop))
            if now >= next_report:
                counts = " ".join(f"{rel}={n}" for rel, n in sent.items())
                print(f"sent {now} {users} {counts} lag_ms={lag_max / 1e6:.1f}", flush=True)
                lag_max = 0
                next_report += 1_000_000_000
            wait = (heap[0][0] - time.time_ns()) / 1e9 if heap else 0.05
            if wait > 0:
                time.sleep(min(wait, 0.05))
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
