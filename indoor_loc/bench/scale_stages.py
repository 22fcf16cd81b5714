"""CPU per message of each stage in-process, fed as a multi-user node feeds it (``bench scale``'s stages
without DDS): far less sensitive to a shared machine's load than the live bench, so a change of a stage's
hot path can be measured before and after on the same inputs.

``python -m indoor_loc.bench.scale_stages [--users 8] [--duration 60] [--imu-hz 50] [--heading-source vqf]
[--stages imu_node,wifi_fix_node,pdr_kf_node,tll_pf] [--repeat 3] [--digest]``

Simulated walkers (:mod:`indoor_loc.sim`, the parameters ``bench scale`` gives its nodes) go through one
multi-user instance per stage: ``imu/data_raw`` in the runs a multi-user ``imu_node`` takes every
``ImuStage.MULTI_USER_POLL_S`` (bulk-decoded, :meth:`MultiUserStage.process_user_batch`), ``wifi/scan``
message by message; ``pdr/odom`` and ``wifi/fix`` made by those front-end stages are serialised and fed
to ``pdr_kf_node`` and ``tll_pf`` as their node feeds them (deserialised, :meth:`MultiUserStage.process`,
in stamp order). Every output is serialised as a node publishes it; the users' end of input (``tll_pf``'s
smoothing) is not timed. What a live node costs besides (taking messages from DDS, polling every user's
subscriptions, ``/diagnostics`` per user, watching the inputs' publishers) is not here: ``bench scale``.
Per stage: process CPU (the smallest of ``--repeat`` runs), messages handled, ms per message and ms per
second of walking per user.
``--digest`` prints a hash of each stage's serialised outputs (the same outputs before and after a change).
"""
from __future__ import annotations

import argparse
import dataclasses
import hashlib
import heapq
import tempfile
import time
from pathlib import Path
from typing import Any

STAGE_NAMES = ("imu_node", "wifi_fix_node", "pdr_kf_node", "tll_pf")
_REGISTRY = {"imu_node": "imu", "wifi_fix_node": "wifi", "pdr_kf_node": "pdr_kf", "tll_pf": "pf"}
_TYPES = {"pdr/odom": "nav_msgs/msg/Odometry", "wifi/fix": "geometry_msgs/msg/PoseWithCovarianceStamped"}


def _make_stage(name: str, files: dict[str, dict[str, Any]]) -> Any:
    from indoor_loc.params import params_for_node, params_from_dict
    from indoor_loc.pipeline.multi_user import multi_user
    from indoor_loc.pipeline.registry import stage_class
    cls = multi_user(stage_class(_REGISTRY[name]))
    st = cls(params_from_dict(cls.PARAMS, params_for_node(files, name, "")), namespace="")
    st.raw_outputs = True
    return st


def _ser(msg: Any) -> bytes:
    from rclpy.serialization import serialize_message
    return msg if isinstance(msg, (bytes, bytearray)) else serialize_message(msg)


def _stamp(data: bytes) -> int:
    return int.from_bytes(data[4:8], "little") * 1_000_000_000 + int.from_bytes(data[8:12], "little")


def run_stage(name: str, files: dict[str, dict[str, Any]], inputs: list[tuple[int, str, str, bytes]],
              poll_s: float) -> tuple[float, int, list[tuple[str, bytes]]]:
    """Feed ``inputs`` ((recv ns, user, relative topic, CDR), in time order) to a fresh multi-user
    ``name`` in polls of ``poll_s``; returns (process CPU s, messages handled, serialised outputs)."""
    from rclpy.serialization import deserialize_message

    from indoor_loc.bag.bulk import BULK_TYPES, bulk_items
    from indoor_loc.contract import msg_class
    st = _make_stage(name, files)
    ports = {p.topic: p.type for p in st.template.inputs()}
    outs: list[tuple[str, bytes]] = []
    poll_ns = int(poll_s * 1e9)
    i, n = 0, len(inputs)
    c0 = time.process_time()
    while i < n:
        end = (inputs[i][0] // poll_ns + 1) * poll_ns
        j = i
        while j < n and inputs[j][0] < end:
            j += 1
        per: dict[str, dict[str, list[tuple[int, bytes]]]] = {}
        for recv, user, rel, data in inputs[i:j]:
            per.setdefault(user, {}).setdefault(rel, []).append((recv, data))
        for user, topics in per.items():
            for rel, run in topics.items():
                tp = ports[rel]
                if tp in BULK_TYPES and st.batch_handles(rel, user):
                    items = bulk_items(tp, [d for _, d in run])
                    if items is not None:
                        outs += [(t, _ser(m)) for _, t, m in st.process_user_batch(user, rel, items,
                                                                                  [r for r, _ in run])]
                        continue
                cls = msg_class(tp)
                for recv, data in run:
                    outs += [(t, _ser(m)) for t, m in st.process(rel, deserialize_message(data, cls), recv, user)]
        i = j
    cpu = time.process_time() - c0
    for user in list(st.users):     # end of input (tll_pf's smoothing): not a cost per message, not timed
        outs += [(t, _ser(m)) for t, m in st.finish_user(user)]
    return cpu, n, outs


def simulate(users: int, duration_s: float, imu_hz: float, work: Path) -> tuple[dict[str, dict[str, Any]],
                                                                               list[tuple[int, str, str, bytes]]]:
    """The simulated walkers' ``imu/data_raw`` and ``wifi/scan`` as (recv ns, user, topic, CDR) in time
    order, and the parameters file ``bench scale`` gives its nodes (as a dict)."""
    from indoor_loc.bag import read_raw
    from indoor_loc.bench.scale import _params
    from indoor_loc.commands.sim import generate
    from indoor_loc.params import load_params_file
    from indoor_loc.sim.scenario import SimConfig
    from indoor_loc.sim.walker import ImuParams
    cfg = SimConfig(walkers=users, duration_s=duration_s, seed=7, imu=dataclasses.replace(ImuParams(), rate_hz=imu_hz))
    cfg.validate()
    sim = generate(work / "sim", cfg, quiet=True)
    files = load_params_file(_params(sim, work))
    msgs = []
    for m in read_raw([sim["bag"]]):
        parts = m.topic.split("/", 2)
        if len(parts) == 3 and parts[2] in ("imu/data_raw", "wifi/scan"):
            data = bytes(m.data)
            msgs.append((_stamp(data) + 2_000_000, parts[1], parts[2], data))
    msgs.sort(key=lambda x: x[0])
    return files, msgs


def _downstream(outs_by_stage: dict[str, list[tuple[str, bytes]]]) -> list[tuple[int, str, str, bytes]]:
    """``pdr/odom`` and ``wifi/fix`` of the front ends as the estimators receive them, in stamp order."""
    lists = []
    for stage in ("imu_node", "wifi_fix_node"):
        rows = []
        for topic, data in outs_by_stage[stage]:
            _, user, rel = topic.split("/", 2)
            if rel in _TYPES:
                rows.append((_stamp(data) + 2_000_000, user, rel, data))
        lists.append(sorted(rows, key=lambda x: x[0]))
    return list(heapq.merge(*lists, key=lambda x: x[0]))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--users", type=int, default=8)
    ap.add_argument("--duration", type=float, default=60.0)
    ap.add_argument("--imu-hz", type=float, default=50.0)
    ap.add_argument("--heading-source", default="", help="imu_node's heading_source (default: bench scale's, auto)")
    ap.add_argument("--stages", default=",".join(STAGE_NAMES))
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--digest", action="store_true")
    args = ap.parse_args(argv)
    import os
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")      # as every node process (indoor_loc/nodes/__init__.py)
    with tempfile.TemporaryDirectory(prefix="scale_stages_") as tmp:     # the maps are read from it
        files, front = simulate(args.users, args.duration, args.imu_hz, Path(tmp))
        _measure(args, files, front)
    return 0


def _measure(args: argparse.Namespace, files: dict[str, dict[str, Any]],
             front: list[tuple[int, str, str, bytes]]) -> None:
    from indoor_loc.pipeline.imu_stage import ImuStage
    wanted = args.stages.split(",")
    if args.heading_source:
        for key, values in files.items():
            if key.rsplit("/", 1)[-1] == "imu_node":
                values["heading_source"] = args.heading_source
    feeds = {"imu_node": [m for m in front if m[2] == "imu/data_raw"],
             "wifi_fix_node": [m for m in front if m[2] == "wifi/scan"]}
    polls = {"imu_node": ImuStage.MULTI_USER_POLL_S}
    outs: dict[str, list[tuple[str, bytes]]] = {}
    print(f"{args.users} users x {args.duration:g} s, IMU {args.imu_hz:g} Hz; process CPU, best of {args.repeat}")
    print("| stage | messages | CPU s | ms per message | ms/s per user | outputs digest |")
    print("|---|---|---|---|---|---|")
    for name in STAGE_NAMES:
        if name in ("pdr_kf_node", "tll_pf") and "pdr_kf_node" not in feeds:
            feeds["pdr_kf_node"] = feeds["tll_pf"] = _downstream(outs)
        best = None
        for _ in range(max(1, args.repeat) if name in wanted else 1):
            cpu, n, o = run_stage(name, files, feeds[name], polls.get(name, 0.05))
            best = cpu if best is None else min(best, cpu)
            outs[name] = o
        if name not in wanted:
            continue
        assert best is not None
        digest = hashlib.sha256(b"".join(t.encode() + d for t, d in outs[name])).hexdigest()[:12] \
            if args.digest else ""
        print(f"| {name} | {n} | {best:.2f} | {1e3 * best / max(1, n):.3f} | "
              f"{1e3 * best / (args.users * args.duration):.2f} | {digest} |", flush=True)


if __name__ == "__main__":
    raise SystemExit(main())
