"""``indoor-loc bench chaos --soak HOURS``: memory and per-message cost of every node over hours of
simulated time.

The simulated walkers' world (``--walkers``, default 2, ``--duration`` s, default 300; IMU at 50 Hz,
magnetometer at 25 Hz, a scan every 4 s) is played over and over at ``--rate`` (default 5) to the
same node processes as :mod:`indoor_loc.bench.chaos`, each pass's stamps shifted by the passes before
it, so time runs on for HOURS of simulated time without a jump. Every ``SAMPLE_S`` of wall clock,
per node: resident memory (``VmRSS`` of /proc/<pid>/status), CPU time (/proc/<pid>/stat), messages
taken (the sum of its ``in.<topic>.count``) and its per-message cost, ``process_ms.p50`` of
/diagnostics (the stage's own time per message over its recent messages; CPU time over messages
taken would charge a node that takes one scan every 4 s for its timers and graph polling). Slopes
are least-squares fits against simulated hours after the first pass (warm-up: the filters, maps and
caches fill once).
"""
from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from indoor_loc.bench.chaos_faults import SEC, load_world, with_stamp
from indoor_loc.bench.chaos_run import HANG_S, Harness, cpu_s, rss_kb

#: Seconds of wall clock between two samples of every node.
SAMPLE_S = 20.0


def run_soak(args: argparse.Namespace) -> int:
    from indoor_loc.bench.chaos import bench_env, simulate
    hours = float(args.soak)
    walkers = int(getattr(args, "walkers", 0) or 2)
    duration = float(getattr(args, "duration", 0) or 300.0)
    rate = float(getattr(args, "rate", 0) or 5.0)
    env = bench_env()
    result: dict[str, Any] = {"soak_hours": hours, "walkers": walkers, "world_s": duration, "rate": rate,
                              "ros_domain_id": env["ROS_DOMAIN_ID"], "samples": []}
    with tempfile.TemporaryDirectory(prefix="bench_chaos_soak_") as tmp:
        sim = simulate(Path(tmp), walkers, duration, seed=int(getattr(args, "seed", 7) or 7), imu_hz=50.0)
        world = load_world(sim)
        period_ns = world.t1_ns - world.t0_ns + SEC
        passes = max(1, int(np.ceil(hours * 3600 * SEC / period_ns)))
        print(f"\n## Soak: {walkers} walkers, {hours:g} h of simulated time ({passes} passes of a {duration:g} s "
              f"world, stamps running on) at {rate:g}x over DDS (ROS_DOMAIN_ID {env['ROS_DOMAIN_ID']}, "
              f"{os.cpu_count()} CPUs)\n", flush=True)
        h = Harness(world.walkers, world.sim["params"], env, use_sim_time=False)
        samples: list[dict[str, Any]] = []
        try:
            h.start_nodes()
            if not h.wait_ready():
                print("nodes not ready within 120 s", flush=True)
                return 0
            t0 = time.monotonic()
            next_sample = t0
            sent = 0
            for k in range(passes):
                shift = k * period_ns
                for ns, topic, data in world.stream:
                    at = t0 + (ns + shift - world.t0_ns) / SEC / rate
                    now = time.monotonic()
                    if now >= next_sample:
                        samples.append(_sample(h, (ns + shift - world.t0_ns) / SEC / 3600, now - t0, sent))
                        print(_progress(samples[-1], behind_s=now - at), flush=True)
                        _write_partial(args, result, samples, h, period_ns)
                        next_sample += SAMPLE_S
                    if at > now:
                        time.sleep(at - now)
                    h.pubs[topic].publish(with_stamp(data, ns + shift) if shift else data)
                    sent += 1
            h.settle()
            samples.append(_sample(h, hours, time.monotonic() - t0, sent))
            h.check_deaths()
            result["stop_rcs"] = h.stop_nodes()
        finally:
            for r in h.nodes.values():
                if r.proc is not None and r.proc.proc.poll() is None:
                    r.proc.stop(timeout=10)
            h.close()
    result["samples"] = samples
    result["complete"] = True
    result["nodes"] = summarise(samples, h, warmup_h=period_ns / SEC / 3600)
    print(format_soak(samples, result["nodes"]), flush=True)
    for key, s in result["nodes"].items():
        for b in s["broken"]:
            print(f"PROMISE BROKEN: soak: {key}: {b}", flush=True)
    if getattr(args, "json", None):
        Path(args.json).write_text(json.dumps(result, indent=1))
    return 0


def _sample(h: Harness, sim_h: float, wall_s: float, sent: int) -> dict[str, Any]:
    out: dict[str, Any] = {"sim_h": sim_h, "wall_s": wall_s, "sent": sent, "nodes": {}}
    with h.lock:
        recs = list(h.nodes.values())
    for r in recs:
        if r.proc is None:
            continue
        pid = r.proc.proc.pid
        v = dict(r.values)
        out["nodes"][r.key] = {"rss_kb": rss_kb(pid), "cpu_s": cpu_s(pid),
                               "taken": sum(int(x) for k, x in v.items() if k.startswith("in.") and k.endswith(".count")),
                               "p50_ms": float(v["process_ms.p50"]) if "process_ms.p50" in v else None,
                               "lost": int(v.get("lost.total", 0) or 0)}
    return out


def _write_partial(args: argparse.Namespace, result: dict[str, Any], samples: list[dict[str, Any]], h: Harness,
                   period_ns: int) -> None:
    """The figures so far to ``--json`` after every sample (``"complete": false``), so a soak stopped
    early (or still running) has its samples and slopes up to now on disk."""
    if not getattr(args, "json", None):
        return
    partial = dict(result, samples=samples, complete=False,
                   nodes=summarise(samples, h, warmup_h=period_ns / SEC / 3600))
    tmp = Path(str(args.json) + ".tmp")
    tmp.write_text(json.dumps(partial, indent=1))
    tmp.replace(args.json)


def _progress(s: dict[str, Any], *, behind_s: float) -> str:
    """One line per sample while the soak runs: how far the replay is behind its schedule, and per node
    its memory, messages taken and losses counted so far (a node falling behind shows as losses)."""
    cells = [f"{k} {(n['rss_kb'] or 0) / 1024:.0f} MB {n['cpu_s'] or 0:.0f} s CPU {n['taken']} in "
             f"{n['lost']} lost p50 {n['p50_ms'] if n['p50_ms'] is not None else '-'} ms" for k, n in s["nodes"].items()]
    return (f"soak: {s['sim_h']:.3f} sim h, {s['wall_s']:.0f} s wall, {s['sent']} sent, replay "
            f"{max(0.0, behind_s):.1f} s behind: " + "; ".join(cells))


def _slope(x: list[float], y: list[float]) -> float | None:
    if len(x) < 3:
        return None
    return float(np.polyfit(np.asarray(x), np.asarray(y), 1)[0])


def summarise(samples: list[dict[str, Any]], h: Harness, *, warmup_h: float) -> dict[str, Any]:
    """Per node: RSS and per-message cost at the start (after warm-up) and the end, and their slopes per
    simulated hour; deaths and hangs."""
    out: dict[str, Any] = {}
    for key, rec in h.nodes.items():
        rows = [(s["sim_h"], s["nodes"][key]) for s in samples if key in s["nodes"]]
        rows = [(t, n) for t, n in rows if n["rss_kb"] is not None and n["cpu_s"] is not None]
        late = [(t, n) for t, n in rows if t >= warmup_h] or rows
        rss_t = [t for t, _ in late]
        rss = [n["rss_kb"] / 1024 for _, n in late]
        cost_t = [t for t, n in late if n["p50_ms"] is not None]
        cost = [1e3 * n["p50_ms"] for _, n in late if n["p50_ms"] is not None]
        cpu = [(t, n["cpu_s"]) for t, n in late]
        win_t, win_cost = cpu_per_1000(late)
        # the second half of the run after warm-up: whether what grew at first (a bounded window
        # filling: the particle smoother's 600 s, a path's 20 000 poses, the back-end's graph) levelled off
        mid = (late[0][0] + late[-1][0]) / 2 if late else 0.0
        half_cost = [(t, c) for t, c in zip(win_t, win_cost) if t >= mid]
        s = {"cpu_per_1000_start": win_cost[0] if win_cost else None,
             "cpu_per_1000_end": win_cost[-1] if win_cost else None,
             "cpu_per_1000_per_h": _slope(win_t, win_cost),
             "cpu_per_1000_per_h_2nd_half": _slope([t for t, _ in half_cost], [c for _, c in half_cost]),
             "rss_mb_per_h_2nd_half": _slope([t for t in rss_t if t >= mid], [r for t, r in zip(rss_t, rss) if t >= mid]),
             "rss_mb_start": rss[0] if rss else None, "rss_mb_end": rss[-1] if rss else None,
             "rss_mb_per_h": _slope(rss_t, rss), "cost_us_start": cost[0] if cost else None,
             "cost_us_end": cost[-1] if cost else None, "cost_us_per_h": _slope(cost_t, cost),
             "cpu_s_per_h": _slope([t for t, _ in cpu], [c for _, c in cpu]),
             "deaths": len(rec.deaths), "hangs": len(rec.diag_gaps) + rec.probes_unanswered,
             "lost": rows[-1][1]["lost"] if rows else 0, "broken": []}
        if s["deaths"]:
            s["broken"].append(f"{s['deaths']} death(s): " + "; ".join(rec.deaths)[:300])
        if s["hangs"]:
            s["broken"].append(f"{s['hangs']} hang(s) (/diagnostics silent or a parameter request unanswered > {HANG_S:g} s)")
        if s["rss_mb_start"] and s["rss_mb_per_h"] is not None and s["rss_mb_per_h"] * 8 > 0.10 * s["rss_mb_start"]:
            s["broken"].append(f"memory grows {s['rss_mb_per_h']:+.2f} MB per simulated hour "
                               f"(from {s['rss_mb_start']:.0f} MB)")
        if s["cost_us_start"] and s["cost_us_per_h"] is not None and s["cost_us_per_h"] * 8 > 0.25 * s["cost_us_start"]:
            s["broken"].append(f"per-message cost grows {s['cost_us_per_h']:+.1f} us per simulated hour "
                               f"(from {s['cost_us_start']:.0f} us)")
        if (s["cpu_per_1000_start"] and s["cpu_per_1000_per_h"] is not None
                and s["cpu_per_1000_per_h"] * 8 > 0.25 * s["cpu_per_1000_start"]):
            s["broken"].append(f"CPU per message grows {s['cpu_per_1000_per_h']:+.3f} s per 1000 messages per "
                               f"simulated hour (from {s['cpu_per_1000_start']:.3f})")
        out[key] = s
    return out


#: A cost window spans consecutive samples until the node took at least this many messages in it (a
#: node taking a scan every 4 s would otherwise give a handful per 20 s sample: noise, not a cost).
WINDOW_MIN_MSGS = 200


def cpu_per_1000(rows: list[tuple[float, dict[str, Any]]], min_msgs: int = WINDOW_MIN_MSGS
                 ) -> tuple[list[float], list[float]]:
    """Per window of one node (consecutive samples spanning at least ``min_msgs`` messages taken): its
    midpoint (simulated h) and the node's CPU seconds per 1000 messages it took in it. Unlike
    ``process_ms.p50`` (wall clock, inflated by a loaded machine) this counts what the node really
    spent, its timers and middleware included."""
    t: list[float] = []
    cost: list[float] = []
    rows = [(h, n) for h, n in rows if n["cpu_s"] is not None]
    start = 0
    for k in range(1, len(rows)):
        (ta, a), (tb, b) = rows[start], rows[k]
        if b["taken"] - a["taken"] < min_msgs:
            continue
        t.append((ta + tb) / 2)
        cost.append(1000.0 * (b["cpu_s"] - a["cpu_s"]) / (b["taken"] - a["taken"]))
        start = k
    return t, cost


def _window_cost(prev: dict[str, Any] | None, cur: dict[str, Any] | None) -> str:
    if prev is None or cur is None or prev["cpu_s"] is None or cur["cpu_s"] is None or cur["taken"] <= prev["taken"]:
        return "–"
    return f"{1000.0 * (cur['cpu_s'] - prev['cpu_s']) / (cur['taken'] - prev['taken']):.3f}"


def format_soak(samples: list[dict[str, Any]], nodes: dict[str, Any]) -> str:
    keys = list(nodes)
    picks = samples if len(samples) <= 9 else [samples[int(round(i * (len(samples) - 1) / 8))] for i in range(9)]
    lines = ["| simulated h | wall s | " + " | ".join(f"{k} RSS MB / CPU s / msgs / CPU s per 1000 msgs" for k in keys)
             + " |", "|---|---|" + "---|" * len(keys)]
    prev: dict[str, Any] | None = None
    for s in picks:
        cells = []
        for k in keys:
            n = s["nodes"].get(k)
            # the cost column: CPU s per 1000 messages since the sample shown before
            cells.append("–" if n is None or n["rss_kb"] is None else
                         f"{n['rss_kb'] / 1024:.0f} / {n['cpu_s']:.0f} / {n['taken']:,} / "
                         f"{_window_cost(prev['nodes'].get(k) if prev else None, n)}")
        lines.append(f"| {s['sim_h']:.2f} | {s['wall_s']:.0f} | " + " | ".join(cells) + " |")
        prev = s
    lines += ["", "| node | RSS MB after warm-up → end | RSS slope MB/h | CPU s per 1000 msgs, first → last window | "
                  "its slope per h | process_ms.p50 µs → end | its slope µs/h | CPU s per simulated h | deaths | "
                  "hangs | lost (counted) |",
              "|---|---|---|---|---|---|---|---|---|---|---|"]

    def f(v: Any, spec: str) -> str:
        return "–" if v is None else format(v, spec)
    for k, s in nodes.items():
        lines.append(f"| {k} | {f(s['rss_mb_start'], '.0f')} → {f(s['rss_mb_end'], '.0f')} | "
                     f"{f(s['rss_mb_per_h'], '+.2f')} | {f(s['cpu_per_1000_start'], '.3f')} → "
                     f"{f(s['cpu_per_1000_end'], '.3f')} | {f(s['cpu_per_1000_per_h'], '+.4f')} | "
                     f"{f(s['cost_us_start'], '.0f')} → {f(s['cost_us_end'], '.0f')} | "
                     f"{f(s['cost_us_per_h'], '+.1f')} | {f(s['cpu_s_per_h'], '.0f')} | {s['deaths']} | {s['hangs']} | "
                     f"{s['lost']} |")
    lines += ["", "Slopes per simulated hour (after warm-up; flat: RSS within 10 % and CPU per message within 25 % "
                  "of its start over 8 h):"]
    for k, s in nodes.items():
        flat_rss = s["rss_mb_per_h"] is not None and bool(s["rss_mb_start"]) and \
            abs(s["rss_mb_per_h"]) * 8 <= 0.10 * s["rss_mb_start"]
        flat_cpu = s["cpu_per_1000_per_h"] is not None and bool(s["cpu_per_1000_start"]) and \
            abs(s["cpu_per_1000_per_h"]) * 8 <= 0.25 * s["cpu_per_1000_start"]
        lines.append(f"- {k}: RSS {f(s['rss_mb_per_h'], '+.2f')} MB/h ({'flat' if flat_rss else 'NOT flat'}), "
                     f"CPU {f(s['cpu_per_1000_per_h'], '+.4f')} s per 1000 msgs per h "
                     f"({'flat' if flat_cpu else 'NOT flat'}); second half: RSS "
                     f"{f(s.get('rss_mb_per_h_2nd_half'), '+.2f')} MB/h, CPU "
                     f"{f(s.get('cpu_per_1000_per_h_2nd_half'), '+.4f')} s per 1000 msgs per h")
    return "\n".join(lines)
