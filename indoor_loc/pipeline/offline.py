"""``indoor-loc run IN.mcap [IN2.mcap ...] --nodes imu,wifi --params FILE --out OUT.mcap``

Reads the input bags, drives the same Stage objects the live nodes use in stamp order, as fast as
the CPU allows, and writes every output topic (same names, types and namespaces as live) plus
``/diagnostics`` once a second of bag time to OUT.mcap. One stage instance per node kind and user
namespace found in the inputs (a namespace is "a user": ``/walk07/imu/data`` -> ``/walk07``).
Outputs of one stage that another stage of the same namespace takes (``wifi/scan`` from the scan
node into the fix node, say) are passed on at once, as DDS would.

Multi-user stages (``Stage.MULTI_USER``, the back-end) are one instance across all bags in the root
namespace: they receive every user's messages (from the bags and from the per-user stages) with the
user's name, and their outputs are written under the root (``/backend/walk07/path``).

Replay order (``--order``):
- ``merged``: all bags in one stamp order — users concurrent, as live (simulated or recorded
  multi-user data on one clock);
- ``sequential``: one bag after another, in command-line order; at the end of each bag the
  per-user stages of its namespaces finish (their last outputs reach the multi-user stages) and
  every multi-user stage gets ``finish_user``. This is how the seed-001 paper's joint configuration
  processes its sequences 1…24 (each may match the map and all earlier sequences' scans), and the
  only meaningful order for walks recorded on separate clocks. Ticks restart with each bag;
- ``auto`` (default): ``sequential`` if a multi-user stage asks for it in its parameters
  (``offline_order``), else ``merged``.
"""
from __future__ import annotations

import argparse
import sys
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable

from indoor_loc.contract import join_ns, split_ns
from indoor_loc.errors import ConfigError
from indoor_loc.params import load_params_file, params_for_node, params_from_dict
from indoor_loc.pipeline.registry import STAGES, stage_class
from indoor_loc.pipeline.stage import ORDERS, Stage, user_of_namespace

TICK_NS = 1_000_000_000


@dataclass
class RunSummary:
    messages_in: int = 0
    messages_out: int = 0
    per_stage: dict[str, dict[str, str]] = field(default_factory=dict)
    bag_span_s: float = 0.0
    wall_s: float = 0.0
    order: str = "merged"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("bags", nargs="+", type=Path, help="input MCAP bag(s)")
    parser.add_argument("--nodes", default="imu,wifi",
                        help=f"comma-separated nodes to run, from {sorted(STAGES)} (default imu,wifi)")
    parser.add_argument("--params", type=Path, help="ROS 2 params YAML (e.g. the importer's params.yaml)")
    parser.add_argument("--out", type=Path, required=True, help="output MCAP bag")
    parser.add_argument("--copy", default="ground_truth",
                        help="comma-separated input topics (relative) copied to the output (default ground_truth)")
    parser.add_argument("--order", choices=("auto",) + ORDERS, default="auto",
                        help="replay several bags merged in stamp order or one after another (sequential); "
                             "auto: what the multi-user stages' params ask for (offline_order), else merged")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def build_stages(nodes: Iterable[str], namespaces: Iterable[str], params_file: dict | None,
                 topics_by_ns: dict[str, set[str]]) -> dict[str, list[Stage]]:
    """One stage per (namespace, node kind) whose inputs appear in that namespace."""
    out: dict[str, list[Stage]] = defaultdict(list)
    for ns in sorted(namespaces):
        for name in nodes:
            cls = stage_class(name)
            if cls.MULTI_USER:
                continue
            values = params_for_node(params_file or {}, cls.NODE_NAME, ns)
            params = params_from_dict(cls.PARAMS, values)
            stage = cls(params, namespace=ns)
            if any(p.topic in topics_by_ns.get(ns, set()) for p in stage.inputs()) or _feeds(stage, out[ns]):
                out[ns].append(stage)
    return out


def build_multi_user_stages(nodes: Iterable[str], params_file: dict | None) -> list[Stage]:
    """One instance (root namespace) of every multi-user stage among ``nodes``."""
    out = []
    for name in nodes:
        cls = stage_class(name)
        if cls.MULTI_USER:
            values = params_for_node(params_file or {}, cls.NODE_NAME, "")
            out.append(cls(params_from_dict(cls.PARAMS, values), namespace=""))
    return out


def resolve_order(order: str, multi: list[Stage]) -> str:
    if order != "auto":
        return order
    return "sequential" if any(s.offline_order() == "sequential" for s in multi) else "merged"


def _feeds(stage: Stage, others: list[Stage]) -> bool:
    produced = {p.topic for s in others for p in s.outputs()}
    return any(p.topic in produced for p in stage.inputs())


def run_offline(bags: list[Path], out: Path, *, nodes: list[str], params: Path | None = None,
                copy: Iterable[str] = ("ground_truth",), progress: bool = True, order: str = "auto") -> RunSummary:
    import time

    from indoor_loc.bag import BagWriter, bag_topics, read_bag
    from msg_adapters.diagnostics import stage_diagnostics
    from msg_adapters.time import header_ns

    t0 = time.perf_counter()
    for b in bags:
        if not Path(b).is_file():
            raise ConfigError(f"input bag {b} does not exist")
    if order not in ("auto",) + ORDERS:
        raise ConfigError(f"order: expected one of {('auto',) + ORDERS}, got {order!r}")
    params_file = load_params_file(params) if params else None
    topics = bag_topics(bags)                       # {full topic: (type, count)}
    topics_by_ns: dict[str, set[str]] = defaultdict(set)
    relative_names = set()
    for name in nodes:
        cls = stage_class(name)
        st = cls(cls.PARAMS(), namespace="")
        relative_names |= {p.topic for p in st.inputs()} | {p.topic for p in st.outputs()}
    relative_names |= set(copy)
    for full in topics:
        ns, rel = split_ns(full, relative_names)
        topics_by_ns[ns].add(rel)
    stages = build_stages(nodes, topics_by_ns.keys(), params_file, topics_by_ns)
    multi = build_multi_user_stages(nodes, params_file)
    order = resolve_order(order, multi)
    copy = set(copy)
    total = sum(c for _, c in topics.values())
    summary = RunSummary()
    last_ns = None

    bar = None
    if progress:
        from tqdm import tqdm
        bar = tqdm(total=total, unit="msg", desc="indoor-loc run", file=sys.stderr, mininterval=0.5)

    with BagWriter(out) as writer:
        def emit(ns: str, producer: Stage | None, outs: list[tuple[str, Any]], now_ns: int) -> None:
            for rel, msg in outs:
                stamp = header_ns(msg)
                writer.write(join_ns(ns, rel), msg, stamp if stamp else now_ns)
                summary.messages_out += 1
                if producer is not None and producer.MULTI_USER:
                    continue      # multi-user outputs go to the root namespace, not to per-user stages
                for s in stages.get(ns, []):
                    if s is not producer and s.handles(rel):
                        emit(ns, s, s.process(rel, msg, now_ns), now_ns)
                feed_multi(ns, rel, msg, now_ns)

        def feed_multi(ns: str, rel: str, msg: Any, now_ns: int) -> None:
            user = user_of_namespace(ns)
            if not user:
                return
            for s in multi:
                if s.handles(rel):
                    emit("", s, s.process(rel, msg, now_ns, user), now_ns)

        def tick(now_ns: int, namespaces: Iterable[str]) -> None:
            for ns in namespaces:
                for s in stages.get(ns, []):
                    emit(ns, s, s.tick(now_ns), now_ns)
                    writer.write("/diagnostics", stage_diagnostics(join_ns(ns, s.NODE_NAME), s, now_ns), now_ns)
            for s in multi:
                emit("", s, s.tick(now_ns), now_ns)
                writer.write("/diagnostics", stage_diagnostics(join_ns("", s.NODE_NAME), s, now_ns), now_ns)

        def play(files: list[Path], namespaces: list[str]) -> int | None:
            nonlocal last_ns
            next_tick: int | None = None
            start = end = None
            for m in read_bag(files):
                summary.messages_in += 1
                if bar is not None:
                    bar.update(1)
                now = m.stamp_ns
                last_ns = now if last_ns is None else max(last_ns, now)
                start = now if start is None else start
                end = now
                if next_tick is None:
                    next_tick = now + TICK_NS
                while now >= next_tick:
                    tick(next_tick, namespaces)
                    next_tick += TICK_NS
                ns, rel = split_ns(m.topic, relative_names)
                if rel in copy:
                    writer.write(m.topic, m.msg, now)
                for s in stages.get(ns, []):
                    if s.handles(rel):
                        emit(ns, s, s.process(rel, m.msg, now), now)
                feed_multi(ns, rel, m.msg, now)
            if start is not None:
                summary.bag_span_s += (end - start) * 1e-9
            return end

        if order == "sequential":
            end = None
            for bag in bags:
                bag_ns = sorted({split_ns(t, relative_names)[0] for t in bag_topics([bag])})
                end = play([bag], bag_ns)
                end = end if end is not None else (last_ns or 0)
                for ns in bag_ns:          # this bag's users are done: flush their stages, then tell
                    for s in stages.get(ns, []):
                        emit(ns, s, s.finish(), end)
                    for s in multi:
                        if user_of_namespace(ns):
                            emit("", s, s.finish_user(user_of_namespace(ns)), end)
                tick(end, bag_ns)
            for s in multi:
                emit("", s, s.finish(), end or 0)
            tick(end or 0, [])
        else:
            end = play(list(bags), sorted(stages)) or 0
            for ns, lst in stages.items():
                for s in lst:
                    emit(ns, s, s.finish(), end)
            for s in multi:
                emit("", s, s.finish(), end)
            tick(end, sorted(stages))
    if bar is not None:
        bar.close()
    for ns, lst in stages.items():
        for s in lst:
            summary.per_stage[join_ns(ns, s.NODE_NAME)] = s.diag.summary()
    for s in multi:
        summary.per_stage[join_ns("", s.NODE_NAME)] = s.diag.summary()
    summary.order = order
    summary.wall_s = time.perf_counter() - t0
    return summary


def main(args: argparse.Namespace) -> int:
    nodes = [n.strip() for n in args.nodes.split(",") if n.strip()]
    for n in nodes:
        stage_class(n)
    s = run_offline(list(args.bags), args.out, nodes=nodes, params=args.params,
                    copy=[c for c in args.copy.split(",") if c], progress=not args.no_progress,
                    order=args.order)
    print(f"{s.messages_in} messages in, {s.messages_out} out; {s.bag_span_s:.1f} s of bag time in "
          f"{s.wall_s:.2f} s wall ({s.bag_span_s / max(s.wall_s, 1e-9):.0f}x real time, {s.order}) -> {args.out}")
    clean = [n for n, kv in s.per_stage.items() if kv.get("rejected.total", "0") == "0"]
    print(f"  {len(s.per_stage)} node instances; {len(clean)} rejected nothing")
    for name, kv in s.per_stage.items():
        if name not in clean:
            print(f"  {name}: rejected {kv['rejected.total']} (" + ", ".join(
                f"{k[9:]}={v}" for k, v in kv.items() if k.startswith("rejected.") and k != "rejected.total") + ")")
    return 0
