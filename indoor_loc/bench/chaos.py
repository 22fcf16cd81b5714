"""``indoor-loc bench chaos``: what the nodes do when their inputs and their neighbours misbehave.

On the simulated walkers (:mod:`indoor_loc.sim`), every node (``imu_node``, ``wifi_fix_node``,
``pdr_kf_node``, ``tll_pf`` per walker, one ``backend_node``) runs as its own process over DDS, fed
by the bench's own publishers in each walker's namespace (the sensor stream of the simulated bag at
``--rate``, serialised bytes as stored). Trials, each with fresh processes:

- ``clean``: the stream alone; the reference of the others.
- ``hostile``: per walker and input port (``imu/data_raw``, ``imu/mag``, ``imu/data``, ``wifi/scan``,
  ``pdr/odom``, ``wifi/fix``, ``initialpose``) ``--cases`` messages drawn by hypothesis
  (:mod:`indoor_loc.bench.hostile`) spread over the first two thirds of the stream, interleaved with
  the valid messages on the same publisher, plus explicit cases (empty samples, bursts of duplicates,
  100 000-AP scans, a user nobody configured); the last third is valid only. The recorder runs too
  and is SIGKILLed at 60 % of the stream; its file is then recovered (``indoor-loc bag recover``).
- ``kill <node>``: each node SIGKILLed at 25 % of the stream and started again at once.
- ``clock loop``: every node on ``use_sim_time``; the stream is played twice with ``/clock``, the
  clock going back to its start for the second pass (as ``indoor-loc play --loop --clock``); the
  first pass is the reference of the second.

Per trial and node: cases tried, deaths, hangs, sticky failures, silent losses, accuracy after
recovery (definitions in docs/benchmarks/chaos.md). ``--soak HOURS`` runs the soak instead
(:mod:`indoor_loc.bench.chaos_soak`). Exit status 0 whatever the figures; a broken promise is said
on a line of its own.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import os
import signal
import tempfile
import time
from pathlib import Path
from typing import Any

from indoor_loc.bench.chaos_faults import (NODE_MODULES, PORTS, RECOVERY_S, SEC, Row, Trial, World, empty_plan, hostile_plan, judge,
                                           load_world, run_trial)

#: Hostile phase: the first two thirds of the stream.
HOSTILE_SHARE = 2 / 3
FAULTS = ("hostile", "empty", "kill", "loop")


def bench_env() -> dict[str, str]:
    """The environment of the bench's processes: its ROS_DOMAIN_ID (the user's, else 42), localhost only."""
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", PYTHONUNBUFFERED="1",
               RCUTILS_COLORIZED_OUTPUT="0")
    env.setdefault("ROS_DOMAIN_ID", "42")
    os.environ["ROS_DOMAIN_ID"] = env["ROS_DOMAIN_ID"]
    return env


def simulate(work: Path, walkers: int, duration: float, seed: int, *, imu_hz: float = 100.0) -> dict[str, Path]:
    from indoor_loc.commands.sim import generate
    from indoor_loc.sim.scenario import SimConfig
    from indoor_loc.sim.walker import ImuParams
    cfg = SimConfig(walkers=walkers, duration_s=duration, seed=seed,
                    imu=dataclasses.replace(ImuParams(), rate_hz=imu_hz, mag_rate_hz=imu_hz / 2))
    cfg.validate()
    return generate(work / "sim", cfg, quiet=True)


def _fmt(v: Any, spec: str = "") -> str:
    return "–" if v is None else format(v, spec)


def format_rows(rows: list[Row]) -> str:
    lines = ["| fault | node | cases tried | deaths | hangs | sticky failures | silent losses | "
             "accuracy after recovery (m, clean m) | note |", "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        acc = "–" if r.accuracy is None else f"{r.accuracy:.2f}× ({r.err_m:.2f}, {r.ref_err_m:.2f})"
        note = r.note + (f"; {r.overcount} booked beyond what was sent" if r.overcount else "")
        lines.append(f"| {r.fault} | {r.node} | {r.cases:,} | {r.deaths} | {r.hangs} | {_fmt(r.sticky)} | "
                     f"{_fmt(r.silent)} | {acc} | {note.strip('; ')[:160]} |")
    return "\n".join(lines)


def _interrupt(signum: int, frame: Any) -> None:
    raise KeyboardInterrupt


def run(args: argparse.Namespace) -> int:
    signal.signal(signal.SIGTERM, _interrupt)        # stop the node processes on the way out, as on Ctrl-C
    if getattr(args, "soak", 0.0):
        from indoor_loc.bench.chaos_soak import run_soak
        return run_soak(args)
    quick = bool(args.quick)
    walkers = int(getattr(args, "walkers", 0) or 1)
    duration = float(getattr(args, "duration", 0) or (40.0 if quick else 60.0))
    rate = float(getattr(args, "rate", 0) or 2.0)
    cases = int(getattr(args, "cases", 0) or (100 if quick else 2000))
    faults = [f for f in (getattr(args, "faults", "") or ",".join(FAULTS)).split(",") if f]
    kills = [k for k in (getattr(args, "kill_nodes", "") or "").split(",") if k]
    modules = _modules(getattr(args, "nodes", "") or "")
    env = bench_env()
    t_start = time.monotonic()
    result: dict[str, Any] = {"walkers": walkers, "duration_s": duration, "rate": rate, "cases_per_port": cases,
                              "ros_domain_id": env["ROS_DOMAIN_ID"], "rows": [], "recorder": {}}
    rows: list[Row] = []

    def log(text: str) -> None:
        print(text, flush=True)

    with tempfile.TemporaryDirectory(prefix="bench_chaos_") as tmp:
        work = Path(tmp)
        sim = simulate(work, walkers, duration, seed=int(getattr(args, "seed", 7) or 7))
        world = load_world(sim)
        log(f"\n## Fault benchmark: {walkers} walker(s) x {world.span_s:.0f} s simulated, replayed at {rate:g}x "
            f"over DDS (ROS_DOMAIN_ID {env['ROS_DOMAIN_ID']}, {os.cpu_count()} CPUs)\n")
        sim_time = (getattr(args, "clock", "sim") or "sim") == "sim"
        result["clock"] = "sim" if sim_time else "wall"
        log("nodes' clock: " + ("sim time, /clock published with the stream (live-like)" if sim_time else
                                "wall clock, the bag stamped months before it (a replay without --clock)") + "\n")
        opts: dict[str, Any] = {"modules": modules, "log": log, "sim_time": sim_time}
        clean = run_trial(world, "clean", env, rate, work, **opts)
        _say(clean, log, result)
        if "hostile" in faults:
            rows += _hostile(world, clean, env, rate, cases, work, result,
                             dict(opts, ports=getattr(args, "ports", "") or ""))
        if "empty" in faults:
            phase_end = world.t0_ns + int(world.span_s * HOSTILE_SHARE * SEC)
            t = run_trial(world, "empty samples", env, rate, work, plan=empty_plan(world, phase_end), **opts)
            _say(t, log, result)
            rows += judge(t, clean, world, from_ns=phase_end + int(RECOVERY_S * SEC))
        if "kill" in faults:
            for key in (kills or list(clean.nodes)):
                if key not in clean.nodes:
                    key = next((k for k in clean.nodes if k.endswith("/" + key)), key)
                t = run_trial(world, f"kill {key}", env, rate, work, kill=key, **opts)
                _say(t, log, result)
                ready = t.marks.get("restarted_ready") or t.marks.get("kill", t.wall0)
                rows += judge(t, clean, world, from_ns=t.stream_ns_at(ready, world.t0_ns) + int(RECOVERY_S * SEC))
        if "loop" in faults:
            t = run_trial(world, "clock loop", env, rate, work, loop=True, **opts)
            _say(t, log, result)
            p2 = t.marks.get("pass2", float("inf"))
            rows += judge(t, t, world, from_ns=world.t0_ns + int(RECOVERY_S * SEC), wall=(p2, float("inf")),
                          ref_wall=(0.0, p2))
    log("\n" + format_rows(rows))
    rec = result["recorder"]
    if rec:
        log(f"\nrecorder SIGKILLed at 60 % of the hostile trial, then `indoor-loc bag recover`: "
            f"{rec.get('recovered', 0):,} messages on {rec.get('topics', 0)} topics recovered; of the "
            f"{rec.get('sent_before_kill', 0):,} the bench had sent before the kill on the topics only it publishes, "
            f"{rec.get('recovered_of_them', 0):,} are in it ({rec.get('recovered_beyond', 0)} more: sent while the kill "
            f"took; bad chunks {rec.get('bad_chunks', '–')}, last chunk cut: {rec.get('truncated', '–')})"
            + (f"; ERROR: {rec['error']}" if "error" in rec else ""))
    broken = [(r, b) for r in rows for b in r.broken()]
    for r, b in broken:
        log(f"PROMISE BROKEN: {r.fault}: {r.node}: {b}")
    if not broken:
        log("every promise kept: 0 deaths, 0 hangs, 0 sticky failures, 0 silent losses, "
            "accuracy after recovery within 10 % of the clean run")
    log(f"\n({time.monotonic() - t_start:.0f} s wall clock)")
    result["rows"] = [dataclasses.asdict(r) for r in rows]
    result["broken"] = [f"{r.fault}: {r.node}: {b}" for r, b in broken]
    if getattr(args, "json", None):
        Path(args.json).write_text(json.dumps(result, indent=1))
    return 0


def _say(t: Trial, log, result: dict[str, Any] | None = None) -> None:
    log(f"trial {t.name}: played in {t.play_s:.1f} s" + (f"; {t.note}" if t.note else ""))
    if result is not None:          # what the verdicts were made from, for --json
        result.setdefault("trials", {})[t.name] = {
            "rate": t.rate, "play_s": t.play_s, "sent": t.sent, "hostile_sent": t.hostile_sent,
            "stop_exit": t.stop_rcs, "note": t.note,
            "nodes": {k: {"settled": r.settled, "deaths": r.deaths, "diag_gaps_s": [g for _, g in r.diag_gaps],
                          "max_diag_gap_s": r.max_diag_gap_s, "probes": r.probes,
                          "probes_unanswered": r.probes_unanswered, "probe_max_s": r.probe_max_s}
                      for k, r in t.nodes.items()},
            # the scored pose outputs (stamp ns, x, y), for a look at what a node did when
            "outputs": {topic: [r[:3] for r in rows] for topic, rows in t.outputs.items()
                        if not topic.endswith("/imu/data")}}


def _modules(names: str) -> tuple[str, ...]:
    """``--nodes`` (node names or modules, comma-separated) as node modules; all by default."""
    from indoor_loc.errors import ConfigError
    if not names:
        return tuple(NODE_MODULES)
    by_name = {v: k for k, v in NODE_MODULES.items()} | {k: k for k in NODE_MODULES}
    bad = [n for n in names.split(",") if n and n not in by_name]
    if bad:
        raise ConfigError(f"--nodes: expected some of {', '.join(NODE_MODULES.values())}, got {', '.join(bad)}")
    return tuple(by_name[n] for n in names.split(",") if n)


def _hostile(world: World, clean: Trial, env: dict[str, str], rate: float, cases: int, work: Path,
             result: dict[str, Any], opts: dict[str, Any]) -> list[Row]:
    log = opts["log"]
    phase_end = world.t0_ns + int(world.span_s * HOSTILE_SHARE * SEC)
    bases = dict(world.decoded)
    bases.update(clean.bases)
    log(f"drawing {cases} hostile messages per port and walker (hypothesis) ...")
    ports = tuple(p for p in (opts.get("ports") or "").split(",") if p) or PORTS
    if set(ports) - set(PORTS):
        from indoor_loc.errors import ConfigError
        raise ConfigError(f"--ports: expected some of {', '.join(PORTS)}, got {', '.join(sorted(set(ports) - set(PORTS)))}")
    plan = hostile_plan(world, bases, cases, phase_end, ports=ports, log=log)
    n = len(plan.events)
    phase_s = world.span_s * HOSTILE_SHARE
    h_rate = min(rate, phase_s * 800.0 / max(1, n))
    if h_rate < rate:
        log(f"  {n:,} hostile messages: replayed at {h_rate:.2f}x to keep them under 800/s")
    opts = {k: v for k, v in opts.items() if k != "ports"}
    t = run_trial(world, "hostile", env, h_rate, work, plan=plan, recorder_kill_at=0.6, **opts)
    _say(t, log, result)
    result["recorder"] = t.recorder
    result["hostile_kinds"] = _kinds(plan)
    return judge(t, clean, world, from_ns=phase_end + int(RECOVERY_S * SEC))


def _kinds(plan) -> dict[str, int]:
    out: dict[str, int] = {}
    for _, _, _, kind in plan.events:
        out[kind] = out.get(kind, 0) + 1
    return out
