"""``indoor-loc run IN.mcap [IN2.mcap ...] --nodes imu,wifi --params FILE --out OUT.mcap``

Reads the input bags, drives the same Stage objects the live nodes use in stamp order, as fast as
the CPU allows, and writes every output topic (same names, types and namespaces as live) plus
``/diagnostics`` once a second of bag time to OUT.mcap. One stage instance per node kind and user
namespace found in the inputs (a namespace is "a user": ``/walk07/imu/data`` -> ``/walk07``).
Outputs of one stage that another stage of the same namespace takes (``wifi/scan`` from the scan
node into the fix node, say) are passed on at once, as DDS would.

Runs of IMU messages (``sensor_msgs/Imu``, ``MagneticField``) of one namespace and topic, going
to one per-user stage with a batch path (``Stage.on_batch``), are decoded in bulk into arrays
(:mod:`indoor_loc.bag.bulk`) and handed over with :meth:`Stage.process_batch`, which handles them
as :meth:`Stage.process` handles each message: same outputs, counters and order within the
namespace. A run ends at the next message of another topic of that namespace, at a tick, or after
:data:`MAX_RUN` messages; a run that does not decode in bulk, or holds a message the adapter
rejects, is taken message by message. Messages no stage takes and ``--copy`` does not name are
not deserialised. The bags are read as runs of one topic (:func:`indoor_loc.bag.reader.read_runs`,
no object per message), each message handled as if it came alone. A stage's ``/diagnostics``
status is rebuilt only when the runner called the stage since its last one or a recent-rejection or
recent-loss window changed; otherwise that status is written again with the new stamp (the same
message, :data:`REUSE_DIAGNOSTICS`). (Namespaces are independent, so the output bag may hold one user's outputs
written a little later than another's; their stamps and contents are the same.)

A stage's notices (:meth:`Stage.take_notices`: the back-end's word on a user's clock jumping back,
say), which a live node logs as WARN, are printed on stderr, each once, as they come (``indoor-loc
run: warning: /backend_node: ...``), and listed in :attr:`RunSummary.notices`.

Multi-user stages (``Stage.MULTI_USER``, the back-end) are one instance across all bags in the root
namespace: they receive every user's messages (from the bags and from the per-user stages) with the
user's name, and their outputs are written under the root (``/backend/walk07/path``).

Replay order (``--order``):
- ``merged``: all bags in one stamp order — users concurrent, as live (simulated or recorded
  multi-user data on one clock);
- ``sequential``: one bag after another, in command-line order; at the end of each bag the
  per-user stages of its namespaces finish (their last outputs reach the multi-user stages) and
  every multi-user stage gets ``finish_user``. This is how Nowicki & Skrzypczyński 2019's joint configuration
  processes its sequences 1…24 (each may match the map and all earlier sequences' scans), and the
  only meaningful order for walks recorded on separate clocks. Ticks restart with each bag;
- ``auto`` (default): ``sequential`` if a multi-user stage asks for it in its parameters
  (``offline_order``), else ``merged``.
"""
from __future__ import annotations

import argparse
import bisect
import os
import sys
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable

from indoor_loc.contract import ODOM, join_ns, split_ns
from indoor_loc.errors import ConfigError
from indoor_loc.output_paths import check_output
from indoor_loc.params import load_params_file, misplaced_keys, node_key, params_for_node, params_from_dict
from indoor_loc.pipeline.registry import STAGES, stage_class
from indoor_loc.pipeline.stage import ORDERS, Stage, user_of_namespace

TICK_NS = 1_000_000_000
#: Ticks stop across a longer gap in the data and resume with it (1 Hz grid kept), ns.
GAP_NS = 10 * TICK_NS
#: Longest run of IMU messages decoded and handled as one batch.
MAX_RUN = 2048
DIAGNOSTICS_TYPE = "diagnostic_msgs/msg/DiagnosticArray"
#: Write an unchanged stage's last ``/diagnostics`` status again with the new stamp instead of
#: building it afresh (same message; False builds every one, for comparison).
REUSE_DIAGNOSTICS = True


@dataclass
class RunSummary:
    messages_in: int = 0
    messages_out: int = 0
    per_stage: dict[str, dict[str, str]] = field(default_factory=dict)
    bag_span_s: float = 0.0            # sum over namespaces of each one's first -> last stamp
    span_by_ns: dict[str, float] = field(default_factory=dict)
    ticks: int = 0
    wall_s: float = 0.0
    cpu_s: float = 0.0                 # CPU time of this process during the run
    order: str = "merged"
    #: the stages' notices in the order said: (node, e.g. ``/backend_node``, text)
    notices: list[tuple[str, str]] = field(default_factory=list)
    #: requested nodes that had nothing to do (no input topic in any namespace), warned about
    idle: list[str] = field(default_factory=list)


def with_producers(nodes: list[str], idle: list[str], available: set[str]) -> list[str]:
    """``nodes`` plus the nodes that produce what the ``idle`` ones take, followed back to the
    topics the input has (``available``, full names), preferring producers the input can feed:
    the ``--nodes`` to suggest when nothing feeds them (``pf`` on a raw walk -> ``imu,wifi,pf``)."""
    io: dict[str, tuple[set[str], set[str]]] = {}
    for name in STAGES:
        cls = stage_class(name)
        st = cls(cls.PARAMS(), namespace="")
        io[name] = ({p.topic for p in st.inputs()}, {p.topic for p in st.outputs()})
    in_bag = {r for ins, outs in io.values() for r in ins | outs
              if any(t.lstrip("/") == r or t.endswith("/" + r) for t in available)}
    have = set(in_bag)
    feedable: set[str] = set()
    while True:                                     # what the input can drive, producers included
        more = {n for n, (ins, outs) in io.items() if n not in feedable and ins & have}
        if not more:
            break
        feedable |= more
        have |= {r for n in more for r in io[n][1]}
    chosen, todo = set(nodes), list(idle)
    while todo:
        needed = io[todo.pop()][0] - in_bag
        makers = [n for n, (ins, outs) in io.items() if n not in chosen and needed & (outs - ins)]
        for name in [n for n in makers if n in feedable] or makers:
            chosen.add(name)
            todo.append(name)
    return [n for n in STAGES if n in chosen] + [n for n in nodes if n not in STAGES]


def span_namespace(ns: str, rel: str, user_namespaces: Iterable[str]) -> tuple[str] | tuple[()]:
    """The user whose bag time a topic counts towards: its own namespace when the topic is one the
    nodes know; any other topic (``/walk16/ground_truth``, ``/tf``) counts for the user namespace it
    lies under, or for none, so that topics no node uses do not appear as a namespace of their own."""
    if ns or not rel.startswith("/"):
        return (ns,)
    users = set(user_namespaces)
    under = [u for u in users if u and rel.startswith(u + "/")]
    if under:
        return (max(under, key=len),)
    return ("",) if "" in users else ()


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("bags", nargs="+", type=Path, help="input MCAP bag(s)")
    parser.add_argument("--nodes", default="imu,wifi",
                        help=f"comma-separated nodes to run, from {sorted(STAGES)}, in any order (default imu,wifi)")
    parser.add_argument("--params", type=Path, help="ROS 2 params YAML (e.g. the importer's params.yaml)")
    parser.add_argument("--out", type=Path, required=True, help="output MCAP bag (never one of the inputs)")
    parser.add_argument("--overwrite", action="store_true", help="replace --out if it exists (default: refuse)")
    parser.add_argument("--copy", default="ground_truth",
                        help="comma-separated input topics (relative) copied to the output (default ground_truth)")
    parser.add_argument("--order", choices=("auto",) + ORDERS, default="auto",
                        help="replay several bags merged in stamp order or one after another (sequential); "
                             "auto: what the multi-user stages' params ask for (offline_order), else merged")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar (none unless stderr is a terminal)")
    parser.add_argument("--no-batch", action="store_true",
                        help="hand every IMU message to its stage one by one, as live (default: runs of IMU "
                             "messages decoded in bulk through the stage's batch path; same output)")


def _warn_misplaced(params_file: dict | None, node_name: str, ns: str) -> None:
    for key in misplaced_keys(params_file or {}, node_name, ns):
        print(f"indoor-loc run: warning: params key {key!r} does not apply to {join_ns(ns, node_name)} "
              f"(a bare node name matches only the root namespace, as in rcl); key it {node_key(node_name)!r}",
              file=sys.stderr)


def build_stages(nodes: Iterable[str], namespaces: Iterable[str], params_file: dict | None,
                 topics_by_ns: dict[str, set[str]]) -> dict[str, list[Stage]]:
    """One stage per (namespace, node kind) whose inputs appear in that namespace or are produced
    by another stage running there, whatever the order of ``nodes``; each list is ordered producers
    first (topological order of the topics), so end-of-input flushes reach the consumers."""
    out: dict[str, list[Stage]] = {}
    for ns in sorted(namespaces):
        candidates: list[Stage] = []
        for name in nodes:
            cls = stage_class(name)
            if cls.MULTI_USER:
                continue
            _warn_misplaced(params_file, cls.NODE_NAME, ns)
            values = params_for_node(params_file or {}, cls.NODE_NAME, ns)
            candidates.append(cls(params_from_dict(cls.PARAMS, values), namespace=ns))
        available = set(topics_by_ns.get(ns, set()))
        chosen: list[Stage] = []
        progress = True
        while progress:                      # fixed point: add every stage whose inputs are available
            progress = False
            for st in candidates:
                if st not in chosen and any(p.topic in available for p in st.inputs()):
                    chosen.append(st)
                    available |= {p.topic for p in st.outputs()}
                    progress = True
        if chosen:
            out[ns] = _topological(chosen)
    return out


def _topological(stages: list[Stage]) -> list[Stage]:
    """Order stages so that a producer of a topic comes before its consumers (ties: given order)."""
    produced = {s: {p.topic for p in s.outputs()} for s in stages}
    ordered: list[Stage] = []
    left = list(stages)
    while left:
        for s in left:
            ins = {p.topic for p in s.inputs()}
            if not any(ins & produced[o] for o in left if o is not s):
                break
        else:                                   # a cycle: keep the given order for the rest
            s = left[0]
        ordered.append(s)
        left.remove(s)
    return ordered


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


def run_offline(bags: list[Path], out: Path, *, nodes: list[str], params: Path | None = None,
                copy: Iterable[str] = ("ground_truth",), progress: bool = True, order: str = "auto",
                overwrite: bool = False, batch: bool = True) -> RunSummary:
    """Replay ``bags`` through the stages ``nodes`` into ``out`` (see the module doc).

    ``out`` must not be an input, and must not exist unless ``overwrite``; the bag is written to a
    temporary file beside it and renamed at the end, so a failed run leaves an existing file intact.
    Ticks (timers, ``/diagnostics``) run once a second of bag time while data flows; across a gap
    in the data (recordings made days apart) they resume with the data instead of running once per
    second of the gap. A stage whose ``tick``/``finish`` raises counts ``internal_error`` and the
    run goes on. A requested node that no namespace can feed is warned about (stderr and
    :attr:`RunSummary.idle`) while the others run; a ConfigError only when no requested node can run.
    ``batch=False`` hands every message to its stages one by one, as live (same output).
    """
    import time

    from indoor_loc.bag import BagWriter, MessageDecoder, RawMessage, bag_topics
    from indoor_loc.bag.reader import read_runs, records_of
    from indoor_loc.bag.bulk import BULK_TYPES, bulk_items, with_header_stamp
    from msg_adapters.diagnostics import RECENT_NS, stage_diagnostics
    from msg_adapters.time import header_ns

    t0 = time.perf_counter()
    c0 = time.process_time()
    for b in bags:
        if not Path(b).is_file():
            raise ConfigError(f"input bag {b} does not exist")
    if order not in ("auto",) + ORDERS:
        raise ConfigError(f"order: expected one of {('auto',) + ORDERS}, got {order!r}")
    out = check_output(out, inputs=bags, overwrite=overwrite, what="--out")
    params_file = load_params_file(params) if params else None
    topics = bag_topics(bags)                       # {full topic: (type, count)}
    topics_by_ns: dict[str, set[str]] = defaultdict(set)
    relative_names = set()
    inputs_of: dict[str, list[str]] = {}
    for name in nodes:
        cls = stage_class(name)
        st = cls(cls.PARAMS(), namespace="")
        inputs_of[name] = [p.topic for p in st.inputs()]
        relative_names |= {p.topic for p in st.inputs()} | {p.topic for p in st.outputs()}
    relative_names |= set(copy)
    relative_names.add(ODOM)          # a robot's odometry: read whenever a stage's motion_source says so
    for full in topics:
        ns, rel = split_ns(full, relative_names)
        topics_by_ns[ns].add(rel)
    stages = build_stages(nodes, topics_by_ns.keys(), params_file, topics_by_ns)
    multi = build_multi_user_stages(nodes, params_file)
    running = {s.NODE_NAME for lst in stages.values() for s in lst} | {s.NODE_NAME for s in multi}
    idle = [n for n in nodes if stage_class(n).NODE_NAME not in running]
    idle_notice = ""
    if idle:
        text = ("nothing to do for node(s) " + ", ".join(f"{n} (needs one of {inputs_of[n]})" for n in idle)
                + f": no namespace of the input has these topics, and no other node given produces them "
                  f"(inputs: {sorted(topics)[:8]}{' ...' if len(topics) > 8 else ''})")
        if not running:                  # no requested node has anything to do: the run is pointless
            raise ConfigError(f"{text}; add the producing nodes to --nodes "
                              f"(e.g. {','.join(with_producers(nodes, idle, set(topics)))})")
        # the others run (a walk without WiFi scans still gets its PDR): say so, once, and go on
        idle_notice = f"{text}; the other nodes run without them"
        print(f"indoor-loc run: warning: {idle_notice}", file=sys.stderr)
    for ns, st in [(ns, st) for ns, lst in stages.items() for st in lst] + [("", st) for st in multi]:
        standing = st.extra_diagnostics().get("error")
        if standing:   # a required input (radio map, graph) is missing: say so once, as a live node does
            print(f"{st.NODE_NAME}{' in ' + ns if ns else ''} cannot work: {standing}"
                  + ("" if params else " (no --params given; an importer writes OUT/params.yaml)"), file=sys.stderr)
    # (namespace, relative topic) -> per-user stages that take it, resolved once
    takers: dict[tuple[str, str], list[Stage]] = {}
    for ns, lst in stages.items():
        for s in lst:
            for p in s.inputs():
                if s.handles(p.topic):
                    takers.setdefault((ns, p.topic), []).append(s)
    span: dict[str, list[int]] = {}
    span_owner: dict[str, tuple[str] | tuple[()]] = {}   # full topic -> (namespace,) or () if no user's
    order = resolve_order(order, multi)
    copy = set(copy)
    total = sum(c for _, c in topics.values())
    summary = RunSummary()
    summary.idle = list(idle)
    if idle_notice:
        summary.notices.append(("indoor-loc run", idle_notice))
    last_ns = None

    bar = None
    if progress and sys.stderr.isatty():
        from tqdm import tqdm
        bar = tqdm(total=total, unit="msg", desc="indoor-loc run", file=sys.stderr, mininterval=0.5)

    def say_notices(ns: str, s: Stage) -> None:
        """The stage's notices, each once, on stderr (beside the progress bar, if any)."""
        for text in s.take_notices():
            node = join_ns(ns, s.NODE_NAME)
            summary.notices.append((node, text))
            line = f"indoor-loc run: warning: {node}: {text}"
            if bar is not None:
                bar.write(line, file=sys.stderr)
            else:
                print(line, file=sys.stderr)

    partial = out.with_name(out.name + ".partial")
    try:
        with BagWriter(partial) as writer:
            def emit(ns: str, producer: Stage | None, outs: list[tuple[str, Any]], now_ns: int) -> None:
                if producer is not None and producer.notices:
                    say_notices(ns, producer)
                for rel, msg in outs:
                    stamp = header_ns(msg)
                    writer.write(join_ns(ns, rel), msg, stamp if stamp else now_ns)
                    summary.messages_out += 1
                    if producer is not None and producer.MULTI_USER:
                        continue      # multi-user outputs go to the root namespace, not to per-user stages
                    for s in takers.get((ns, rel), ()):
                        if s is not producer:
                            touched(s)
                            emit(ns, s, s.process(rel, msg, now_ns), now_ns)
                    feed_multi(ns, rel, msg, now_ns)

            def feed_multi(ns: str, rel: str, msg: Any, now_ns: int) -> None:
                user = user_of_namespace(ns)
                if not user:
                    return
                for s in multi:
                    if s.handles(rel):
                        touched(s)
                        emit("", s, s.process(rel, msg, now_ns, user), now_ns)

            # /diagnostics: a stage's status changes only through the calls this runner makes on it
            # (messages, batches, its own tick, finish) and, at a given state, through the recent
            # windows of its rejections and losses. While neither changed since its last status,
            # the status written is that one's CDR with the new stamp (the same message).
            diag_cdr: dict[Stage, tuple[tuple[bool, ...], bytes]] = {}

            def touched(s: Stage) -> None:
                diag_cdr.pop(s, None)

            def write_diagnostics(ns: str, s: Stage, now_ns: int) -> None:
                d = s.diag
                recent = tuple(ev is not None and now_ns - ev <= RECENT_NS
                               for ev in (d.last_reject_ns, d.last_loss_ns, d.last_internal_ns))
                known = diag_cdr.get(s)
                if known is not None and known[0] == recent and REUSE_DIAGNOSTICS:
                    data = with_header_stamp(known[1], now_ns)
                    if data is not None:
                        writer.write_raw("/diagnostics", data, now_ns)
                        return
                data = writer.write("/diagnostics", stage_diagnostics(join_ns(ns, s.NODE_NAME), s, now_ns), now_ns)
                diag_cdr[s] = (recent, data)

            def tick(now_ns: int, namespaces: Iterable[str]) -> None:
                summary.ticks += 1
                for ns in namespaces:
                    for s in stages.get(ns, []):
                        if type(s).tick is not Stage.tick:
                            touched(s)
                        emit(ns, s, s.run_tick(now_ns), now_ns)
                        say_notices(ns, s)      # also those of batches that published nothing
                        write_diagnostics(ns, s, now_ns)
                for s in multi:
                    if type(s).tick is not Stage.tick:
                        touched(s)
                    emit("", s, s.run_tick(now_ns), now_ns)
                    say_notices("", s)
                    write_diagnostics("", s, now_ns)

            decode = MessageDecoder()
            split_cache: dict[str, tuple[str, str]] = {}
            batch_ok: dict[tuple[str, str, str], bool] = {}
            pending: dict[str, list] = {}   # ns -> [topic, type, [RawRun, ...], messages]: a run of one topic

            def feeds_back(stage: Stage, ns: str) -> bool:
                """True if the stage's outputs reach it again through other stages (``emit`` never
                gives a stage its own outputs directly)."""
                seen: set[tuple[str, int]] = set()
                todo = [(p.topic, stage) for p in stage.outputs()]
                while todo:
                    rel, producer = todo.pop()
                    if (rel, id(producer)) in seen:
                        continue
                    seen.add((rel, id(producer)))
                    for s in takers.get((ns, rel), ()):
                        if s is producer:
                            continue
                        if s is stage:
                            return True
                        todo += [(p.topic, s) for p in s.outputs()]
                return False

            def batchable(ns: str, rel: str, type_name: str) -> bool:
                key = (ns, rel, type_name)
                ok = batch_ok.get(key)
                if ok is None:
                    who = takers.get((ns, rel), [])
                    ok = batch_ok[key] = (batch and not multi and type_name in BULK_TYPES and rel not in copy and len(who) == 1
                                          and who[0].batch_handles(rel) and not feeds_back(who[0], ns))
                return ok

            def flush(ns: str) -> None:
                rel, type_name, parts, _ = pending.pop(ns)
                stage = takers[(ns, rel)][0]
                touched(stage)
                stamps = parts[0].stamps if len(parts) == 1 else [t for p in parts for t in p.stamps]
                records = records_of(parts)
                items = None if records is None else bulk_items(type_name, records)
                if items is None:                 # not one layout, or a message to reject: one by one
                    topic = join_ns(ns, rel)
                    for p in parts:
                        for k, now in enumerate(p.stamps):
                            msg = decode(RawMessage(topic, type_name, now, p.data(k), now)).msg
                            emit(ns, stage, stage.process(rel, msg, now), now)
                    return
                for now, out_rel, out_msg in stage.process_batch(rel, items, stamps):
                    emit(ns, stage, [(out_rel, out_msg)], now)

            def flush_all() -> None:
                for ns in list(pending):
                    flush(ns)

            def play(files: list[Path], namespaces: list[str]) -> int | None:
                """Replay ``files`` run by run (consecutive messages of one topic): every message is
                handled as if it came alone (ticks, runs for the batch path, flushes)."""
                nonlocal last_ns
                next_tick: int | None = None
                start = end = None
                for r in read_runs(files):
                    stamps = r.stamps
                    n = len(stamps)
                    summary.messages_in += n
                    if bar is not None:
                        bar.update(n)
                    last_ns = stamps[-1] if last_ns is None else max(last_ns, stamps[-1])
                    start = stamps[0] if start is None else start
                    end = stamps[-1]
                    nsrel = split_cache.get(r.topic)
                    if nsrel is None:
                        nsrel = split_cache[r.topic] = split_ns(r.topic, relative_names)
                    ns, rel = nsrel
                    owner = span_owner.get(r.topic)
                    if owner is None:
                        owner = span_owner[r.topic] = span_namespace(ns, rel, stages.keys())
                    if owner:
                        sp = span.setdefault(owner[0], [stamps[0], stamps[0]])
                        sp[1] = end
                    batched = batchable(ns, rel, r.type)
                    i = 0
                    while i < n:
                        now = stamps[i]
                        if next_tick is None:
                            next_tick = now + TICK_NS
                        if now >= next_tick:
                            if pending:
                                flush_all()
                            while now >= next_tick:
                                tick(next_tick, namespaces)
                                next_tick += TICK_NS
                                if now - next_tick >= GAP_NS:   # a gap in the data: skip the empty seconds
                                    next_tick += (now - next_tick) // TICK_NS * TICK_NS
                        k = n if stamps[-1] < next_tick else bisect.bisect_left(stamps, next_tick, i + 1, n)
                        if batched:                  # messages i..k-1 join the namespace's run
                            run = pending.get(ns)
                            if run is not None and (run[0] != rel or run[1] != r.type):
                                flush(ns)
                                run = None
                            while i < k:
                                if run is None:
                                    run = pending[ns] = [rel, r.type, [], 0]
                                take = min(k - i, MAX_RUN - run[3])
                                run[2].append(r if take == n else r.part(i, i + take))
                                run[3] += take
                                i += take
                                if run[3] >= MAX_RUN:
                                    flush(ns)
                                    run = None
                            continue
                        if ns in pending:
                            flush(ns)
                        who = takers.get((ns, rel), ())
                        to_multi = bool(user_of_namespace(ns)) and any(s.handles(rel) for s in multi)
                        if not (who or to_multi or rel in copy):
                            i = k
                            continue                     # nobody takes them: not deserialised
                        for j in range(i, k):
                            now = stamps[j]
                            msg = decode(RawMessage(r.topic, r.type, now, r.data(j), now)).msg
                            if rel in copy:
                                writer.write(r.topic, msg, now)
                            for s in who:
                                touched(s)
                                emit(ns, s, s.process(rel, msg, now), now)
                            feed_multi(ns, rel, msg, now)
                        i = k
                flush_all()
                return end

            if order == "sequential":
                end = None
                for bag in bags:
                    bag_ns = sorted({split_ns(t, relative_names)[0] for t in bag_topics([bag])})
                    end = play([bag], bag_ns)
                    end = end if end is not None else (last_ns or 0)
                    for ns in bag_ns:          # this bag's users are done: flush their stages, then tell
                        for s in stages.get(ns, []):
                            touched(s)
                            emit(ns, s, s.run_finish(), end)
                        for s in multi:
                            if user_of_namespace(ns):
                                touched(s)
                                emit("", s, s.run_finish_user(user_of_namespace(ns)), end)
                    tick(end, bag_ns)
                for s in multi:
                    touched(s)
                    emit("", s, s.run_finish(), end or 0)
                tick(end or 0, [])
            else:
                end = play(list(bags), sorted(stages)) or 0
                for ns, lst in stages.items():
                    for s in lst:
                        touched(s)
                        emit(ns, s, s.run_finish(), end)
                for s in multi:
                    touched(s)
                    emit("", s, s.run_finish(), end)
                tick(end, sorted(stages))
        os.replace(partial, out)
    finally:
        for ns, st in [(ns, st) for ns, lst in stages.items() for st in lst] + [("", st) for st in multi]:
            say_notices(ns, st)      # none is left normally (the last tick took them); a failed run's too
        if partial.exists():
            partial.unlink()
        if bar is not None:
            bar.close()
    for ns, lst in stages.items():
        for s in lst:
            summary.per_stage[join_ns(ns, s.NODE_NAME)] = s.diag.summary()
    for s in multi:
        summary.per_stage[join_ns("", s.NODE_NAME)] = s.diag.summary()
    summary.span_by_ns = {ns or "/": (b - a) * 1e-9 for ns, (a, b) in sorted(span.items())}
    summary.bag_span_s = sum(summary.span_by_ns.values())
    summary.order = order
    summary.wall_s = time.perf_counter() - t0
    summary.cpu_s = time.process_time() - c0
    return summary


def main(args: argparse.Namespace) -> int:
    nodes = [n.strip() for n in args.nodes.split(",") if n.strip()]
    for n in nodes:
        stage_class(n)
    s = run_offline(list(args.bags), args.out, nodes=nodes, params=args.params,
                    copy=[c for c in args.copy.split(",") if c], progress=not args.no_progress,
                    order=args.order, overwrite=args.overwrite, batch=not args.no_batch)
    per_ns = ", ".join(f"{ns} {v:.1f} s" for ns, v in s.span_by_ns.items())
    print(f"{s.messages_in} messages in, {s.messages_out} out; bag time {per_ns} ({s.bag_span_s:.1f} s in all) "
          f"in {s.wall_s:.2f} s wall, {s.cpu_s:.2f} s CPU ({s.bag_span_s / max(s.wall_s, 1e-9):.0f}x real time, {s.order}) -> {args.out}")
    clean = [n for n, kv in s.per_stage.items() if kv.get("rejected.total", "0") == "0"]
    print(f"  {len(s.per_stage)} node instances; {len(clean)} rejected nothing")
    for name, kv in s.per_stage.items():
        if name not in clean:
            print(f"  {name}: rejected {kv['rejected.total']} (" + ", ".join(
                f"{k[9:]}={v}" for k, v in kv.items() if k.startswith("rejected.") and k != "rejected.total") + ")")
    return 0
