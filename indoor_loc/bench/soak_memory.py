"""Memory of the downstream stages over hours of simulated input, in-process (no DDS).

``python -m indoor_loc.bench.soak_memory --hours 8 --stages pf,pdr_kf,backend``

The stages are pure, so what grows per simulated hour in ``tll_pf``, ``pdr_kf_node`` and
``backend_node`` can be found without processes: the simulated walkers' world (as the soak of
:mod:`indoor_loc.bench.chaos_soak` plays it) is put once through the front-end stages (``imu``,
``wifi``) and their outputs (``pdr/odom``, ``wifi/fix``, ``wifi/scan``) are then replayed, pass after
pass, into fresh downstream stages as fast as the CPU allows. Each pass's stamps are shifted by the
passes before it (time runs on, as in the soak) and each pass's odometry is moved to start where the
previous pass ended (a live ``imu_node`` integrates on; without it every pass would teleport).
The stages get a tick every simulated second, as live.

Per stage kind, every simulated ``--every`` hours: the bytes ``tracemalloc`` holds (the stage alone in
the process) and the CPU time per 1000 messages; at the end, the slopes per simulated hour and the
source lines whose allocations grew most (``--top``): the structures that grow.
"""
from __future__ import annotations

import argparse
import copy
import gc
import math
import sys
import time
import tracemalloc
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

SEC = 1_000_000_000
#: The downstream stages of the soak and what they take from the front ends.
DOWNSTREAM = ("pf", "pdr_kf", "backend")
FRONT_TOPICS = ("pdr/odom", "wifi/fix", "wifi/scan")


@dataclass
class Feed:
    """The front ends' outputs of one pass of the world: ``(stamp ns, namespace, topic, message)`` in
    stamp order, and per namespace the odometry pose at the pass's start and end."""
    events: list[tuple[int, str, str, Any]]
    t0_ns: int
    period_ns: int
    odom_start: dict[str, tuple[float, float, float]] = field(default_factory=dict)
    odom_end: dict[str, tuple[float, float, float]] = field(default_factory=dict)
    params: dict | None = None                     # the simulated world's parameters file, loaded


def _yaw(q: Any) -> float:
    return math.atan2(2 * (q.w * q.z + q.x * q.y), 1 - 2 * (q.y * q.y + q.z * q.z))


def _pose(msg: Any) -> tuple[float, float, float]:
    p = msg.pose.pose
    return (p.position.x, p.position.y, _yaw(p.orientation))


def front_feed(walkers: int = 2, duration: float = 300.0, seed: int = 7, *, work: Path) -> Feed:
    """One pass of the simulated world through ``imu`` and ``wifi`` stages (as the chaos soak's nodes)."""
    from rclpy.serialization import deserialize_message

    from indoor_loc.bag import bag_info, read_raw
    from indoor_loc.bench.chaos import simulate
    from indoor_loc.contract import msg_class
    from indoor_loc.params import load_params_file
    from indoor_loc.pipeline.offline import build_stages

    sim = simulate(work, walkers, duration, seed=seed, imu_hz=50.0)
    params = load_params_file(sim["params"])
    info = bag_info([sim["bag"]])
    topics = sorted(t for t in info if t.rsplit("/", 2)[-2:] in (["imu", "data_raw"], ["imu", "mag"], ["wifi", "scan"]))
    nss = sorted({"/" + t.split("/")[1] for t in topics})
    stages = build_stages(["imu", "wifi"], nss, params, {ns: {"imu/data_raw", "imu/mag", "wifi/scan"} for ns in nss})
    events: list[tuple[int, str, str, Any]] = []
    tick_at: int | None = None
    first = last = None
    for m in read_raw([sim["bag"]], topics):
        ns, rel = "/" + m.topic.split("/")[1], m.topic.split("/", 2)[2]
        first = m.stamp_ns if first is None else first
        last = m.stamp_ns
        if tick_at is None:
            tick_at = m.stamp_ns + SEC
        while m.stamp_ns >= tick_at:
            for lst in stages.values():
                for s in lst:
                    s.run_tick(tick_at)
            tick_at += SEC
        msg = deserialize_message(bytes(m.data), msg_class(info[m.topic].type))
        if rel == "wifi/scan":
            events.append((m.stamp_ns, ns, rel, msg))
        queue = [(rel, msg)]
        while queue:
            r, mm = queue.pop(0)
            for s in stages[ns]:
                if s.handles(r):
                    for o_rel, o_msg in s.process(r, mm, m.stamp_ns):
                        if o_rel in ("pdr/odom", "wifi/fix"):
                            events.append((m.stamp_ns, ns, o_rel, o_msg))
    assert first is not None and last is not None
    feed = Feed(sorted(events, key=lambda e: e[0]), first, last - first + SEC, params=params)
    for ns in nss:
        odo = [e[3] for e in feed.events if e[1] == ns and e[2] == "pdr/odom"]
        if odo:
            feed.odom_start[ns], feed.odom_end[ns] = _pose(odo[0]), _pose(odo[-1])
    return feed


def _compose(a: tuple[float, float, float], b: tuple[float, float, float]) -> tuple[float, float, float]:
    c, s = math.cos(a[2]), math.sin(a[2])
    return (a[0] + c * b[0] - s * b[1], a[1] + s * b[0] + c * b[1], a[2] + b[2])


def _inverse(a: tuple[float, float, float]) -> tuple[float, float, float]:
    c, s = math.cos(a[2]), math.sin(a[2])
    return (-(c * a[0] + s * a[1]), s * a[0] - c * a[1], -a[2])


def restamp(msg: Any, stamp_ns: int, shift: tuple[float, float, float] | None = None) -> Any:
    """A copy of ``msg`` stamped ``stamp_ns`` (an odometry pose also moved by the rigid ``shift``)."""
    out = copy.deepcopy(msg)
    out.header.stamp.sec, out.header.stamp.nanosec = divmod(int(stamp_ns), SEC)
    if shift is not None:
        p = out.pose.pose
        x, y, yaw = _compose(shift, (p.position.x, p.position.y, _yaw(p.orientation)))
        p.position.x, p.position.y = x, y
        # keep roll/pitch out: the odometry is planar (a yaw quaternion)
        p.orientation.x = p.orientation.y = 0.0
        p.orientation.z, p.orientation.w = math.sin(yaw / 2), math.cos(yaw / 2)
    return out


def make_stage(kind: str, params_file: dict | None, namespaces: list[str]) -> dict[str, Any]:
    """``{namespace: stage}`` for a per-user kind, ``{"": stage}`` for the multi-user back-end."""
    from indoor_loc.params import params_for_node, params_from_dict
    from indoor_loc.pipeline.registry import stage_class
    cls = stage_class(kind)
    if cls.MULTI_USER:
        stages = {"": cls(params_from_dict(cls.PARAMS, params_for_node(params_file or {}, cls.NODE_NAME, "")))}
    else:
        stages = {ns: cls(params_from_dict(cls.PARAMS, params_for_node(params_file or {}, cls.NODE_NAME, ns)),
                          namespace=ns) for ns in namespaces}
    for s in stages.values():
        s.raw_outputs = True           # as in every node (nodes/stage_node.py): outputs it can serialise go as CDR
    return stages


@dataclass
class Sample:
    sim_h: float
    traced_mb: float
    messages: int
    cpu_s: float
    sizes: dict[str, int] = field(default_factory=dict)   # a stage's own size report (bounded structures)


def soak_stage(kind: str, feed: Feed, params_file: dict | None, hours: float, *, every_h: float = 0.5,
               top: int = 8, trace: bool = True, log: Any = print) -> dict[str, Any]:
    """Replay ``feed`` for ``hours`` of simulated time into fresh stages of ``kind``; samples every
    ``every_h`` simulated hours (see the module doc)."""
    from indoor_loc.pipeline.stage import user_of_namespace
    namespaces = sorted({e[1] for e in feed.events})
    gc.collect()
    if trace:
        tracemalloc.start(4)
    base = tracemalloc.get_traced_memory()[0] if trace else 0
    stages = make_stage(kind, params_file, namespaces)
    passes = max(1, int(math.ceil(hours * 3600 * SEC / feed.period_ns)))
    samples: list[Sample] = []
    snaps: list[Any] = []
    next_sample_h = 0.0
    messages = 0
    cpu = 0.0
    pose: dict[str, tuple[float, float, float]] = {ns: (0.0, 0.0, 0.0) for ns in namespaces}  # pass-k odom shift
    step = {ns: _compose(feed.odom_end[ns], _inverse(feed.odom_start[ns])) for ns in feed.odom_start}
    tick_at = feed.t0_ns + SEC
    for k in range(passes):
        shift_ns = k * feed.period_ns
        for stamp, ns, rel, msg in feed.events:
            t = stamp + shift_ns
            sim_h = (t - feed.t0_ns) / SEC / 3600
            if sim_h >= next_sample_h:
                gc.collect()
                cur = tracemalloc.get_traced_memory()[0] - base if trace else 0
                samples.append(Sample(sim_h, cur / 2**20, messages, cpu, _sizes(stages)))
                if trace:
                    snaps.append(tracemalloc.take_snapshot())
                prev = samples[-2] if len(samples) > 1 else None
                window = (f"{1e3 * (cpu - prev.cpu_s) / (messages - prev.messages):.2f}"
                          if prev is not None and messages > prev.messages else "–")
                log(f"{kind}: {sim_h:.2f} sim h, traced {cur / 2**20:.2f} MB, {messages} msgs, "
                    f"{1e3 * cpu / max(messages, 1):.2f} ms/msg so far, {window} ms/msg since the last sample, "
                    f"sizes {samples[-1].sizes}")
                next_sample_h += every_h
            m = restamp(msg, t, pose[ns] if rel == "pdr/odom" else None)    # the feed's work, not the stage's
            c0 = time.process_time()
            while t >= tick_at:
                for s in stages.values():
                    s.run_tick(tick_at)
                tick_at += SEC
            for s_ns, s in stages.items():
                if s_ns in ("", ns) and s.handles(rel):
                    if s.MULTI_USER:
                        s.process(rel, m, t, user_of_namespace(ns))
                    else:
                        s.process(rel, m, t)
                    s.take_notices()
                    messages += 1
            cpu += time.process_time() - c0
        for ns in step:
            pose[ns] = _compose(pose[ns], step[ns])
    gc.collect()
    cur = tracemalloc.get_traced_memory()[0] - base if trace else 0
    end_h = passes * feed.period_ns / SEC / 3600
    samples.append(Sample(end_h, cur / 2**20, messages, cpu, _sizes(stages)))
    growth: list[str] = []
    if trace:
        snaps.append(tracemalloc.take_snapshot())
        if len(snaps) >= 3:
            diff = snaps[-1].compare_to(snaps[1], "traceback")
            for st in diff[:top]:
                frames = [f"{f.filename.split('indoor_loc/')[-1]}:{f.lineno}" for f in st.traceback
                          if "indoor_loc" in f.filename or "msg_adapters" in f.filename][:4]
                growth.append(f"{st.size_diff / 2**20:+.3f} MB ({st.count_diff:+d} blocks) at " + " < ".join(frames))
        tracemalloc.stop()
    return {"kind": kind, "samples": samples, "growth": growth, **slopes(samples, warmup_h=feed.period_ns / SEC / 3600)}


def _sizes(stages: dict[str, Any]) -> dict[str, int]:
    """What the stages hold, summed over users: the structures bounded for long runs, and the
    process's resident memory (``rss_mb``)."""
    out: dict[str, int] = {"rss_mb": _rss_mb()}
    for s in stages.values():
        found: dict[str, int] = {}
        graph = getattr(s, "graph", None)
        if hasattr(graph, "counts"):
            found.update(graph.counts())
        tracker = getattr(s, "tracker", None)
        if tracker is not None:
            found.update(estimates=len(tracker.estimates), path_archive=len(getattr(s, "_archive", ())),
                         smoother_steps=len(tracker.history) + sum(len(g) for g in tracker.segments))
        if hasattr(s, "_epochs"):
            found.update(final_poses=len(s._final), window_epochs=len(s._epochs))
        if getattr(s, "map_odom", None) is not None:
            found.update(odom_track=sum(len(u.track.stamps) for u in s.map_odom.users.values()))
        budget = getattr(s, "_budget", None)
        if budget is not None:
            found.update(smoother_kb=budget.held // 1024, smoother_trimmed=budget.trimmed_steps)
        found.update(process_s=len(s.diag.process_s))
        for k, v in found.items():
            out[k] = out.get(k, 0) + int(v)
    return out


def _rss_mb() -> int:
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) // 1024
    except OSError:
        pass
    return 0


def slopes(samples: list[Sample], *, warmup_h: float) -> dict[str, float | None]:
    """Least-squares slopes per simulated hour after the warm-up: traced MB, and CPU ms per 1000
    messages per window (between two samples)."""
    late = [s for s in samples if s.sim_h >= warmup_h]
    mem = None
    if len(late) >= 3:
        mem = float(np.polyfit([s.sim_h for s in late], [s.traced_mb for s in late], 1)[0])
    win_t, win_cost = [], []
    for a, b in zip(late, late[1:]):
        if b.messages > a.messages:
            win_t.append((a.sim_h + b.sim_h) / 2)
            win_cost.append(1e3 * (b.cpu_s - a.cpu_s) / (b.messages - a.messages) * 1e3)  # ms per 1000 msgs
    cost = float(np.polyfit(win_t, win_cost, 1)[0]) if len(win_t) >= 3 else None
    return {"mb_per_h": mem, "cost_ms_per_1000_per_h": cost,
            "cost_ms_per_1000_first": win_cost[0] if win_cost else None,
            "cost_ms_per_1000_last": win_cost[-1] if win_cost else None}


def main(argv: list[str] | None = None) -> int:
    import tempfile

    ap = argparse.ArgumentParser(prog="python -m indoor_loc.bench.soak_memory", description=__doc__.split("\n\n")[0])
    ap.add_argument("--hours", type=float, default=8.0)
    ap.add_argument("--stages", default=",".join(DOWNSTREAM))
    ap.add_argument("--walkers", type=int, default=2)
    ap.add_argument("--duration", type=float, default=300.0)
    ap.add_argument("--every", type=float, default=0.5, help="simulated hours between samples")
    ap.add_argument("--top", type=int, default=8)
    ap.add_argument("--no-trace", action="store_true", help="CPU cost only (tracemalloc slows Python down)")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="soak_memory_") as tmp:
        t0 = time.monotonic()
        feed = front_feed(args.walkers, args.duration, work=Path(tmp))
        params = feed.params
        print(f"front ends: {len(feed.events)} messages per {feed.period_ns / SEC:.0f} s pass "
              f"({time.monotonic() - t0:.0f} s)", flush=True)
        results = []
        for kind in args.stages.split(","):
            r = soak_stage(kind, feed, params, args.hours, every_h=args.every, top=args.top, trace=not args.no_trace,
                           log=lambda s: print(s, flush=True))
            results.append(r)
            print(f"\n{kind}: traced memory slope {_f(r['mb_per_h'], '+.3f')} MB per simulated h; cost "
                  f"{_f(r['cost_ms_per_1000_first'], '.1f')} → {_f(r['cost_ms_per_1000_last'], '.1f')} ms CPU per 1000 "
                  f"messages, slope {_f(r['cost_ms_per_1000_per_h'], '+.2f')} per simulated h", flush=True)
            for g in r["growth"]:
                print("  grew " + g, flush=True)
    return 0


def _f(v: Any, spec: str) -> str:
    return "–" if v is None else format(v, spec)


if __name__ == "__main__":
    sys.exit(main())
