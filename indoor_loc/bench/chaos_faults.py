"""The faults of the fault benchmark (:mod:`indoor_loc.bench.chaos`) and how each trial is judged.

A *trial* is one playback of the simulated walkers' sensor stream to a fresh set of node processes
(:class:`~indoor_loc.bench.chaos_run.Harness`), with one fault in it; the ``clean`` trial has none
and is the reference of the others.
"""
from __future__ import annotations

import struct
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from indoor_loc.bench.chaos_run import HANG_S, NODE_MODULES, OUTPUT, PORTS, Harness

SEC = 1_000_000_000
#: Simulated seconds a node gets after a fault before its accuracy is judged again.
RECOVERY_S = 10.0
#: Hostile messages per second at most (all ports together): the replay slows down to fit them.
HOSTILE_MAX_PER_S = 800.0
#: Explicit cases per port beside the drawn ones: empty samples, bursts of duplicates (their size),
#: 100 000-AP scans, messages of a user nobody configured.
EMPTY_PER_PORT = 2
BURST = 500
HUGE_SCANS = 2
HUGE_AP = 100_000
GHOST = "chaos_ghost"
GHOST_PER_PORT = 20
#: APs of the scans hypothesis draws as "huge" (the 100 000-AP ones are the explicit cases).
DRAWN_HUGE_AP = 1_000


@dataclass
class World:
    """The simulated walkers and their stream."""
    sim: dict[str, Path]
    walkers: list[str]
    stream: list[tuple[int, str, bytes]]         # (log ns, full topic, CDR) of the valid inputs
    t0_ns: int
    t1_ns: int
    truths: dict[str, Any]
    decoded: dict[str, list[tuple[int, Any]]]   # full topic -> (stamp, message), every 10th IMU sample

    @property
    def span_s(self) -> float:
        return (self.t1_ns - self.t0_ns) / SEC


def load_world(sim: dict[str, Path]) -> World:
    from rclpy.serialization import deserialize_message

    from indoor_loc.bag import bag_info, read_raw
    from indoor_loc.commands.eval import truth_from_import
    from indoor_loc.contract import msg_class

    info = bag_info([sim["bag"]])
    topics = sorted(t for t in info if t.rsplit("/", 2)[-2:] in (["imu", "data_raw"], ["imu", "mag"], ["wifi", "scan"]))
    walkers = sorted({t.split("/")[1] for t in topics})
    stream = [(m.stamp_ns, m.topic, bytes(m.data)) for m in read_raw([sim["bag"]], topics)]
    decoded: dict[str, list[tuple[int, Any]]] = {}
    for k, (ns, topic, data) in enumerate(stream):
        if "wifi" in topic or k % 10 == 0:
            decoded.setdefault(topic, []).append((ns, deserialize_message(data, msg_class(info[topic].type))))
    return World(sim, walkers, stream, stream[0][0], stream[-1][0], truth_from_import(sim["bag"].parent), decoded)


def with_stamp(data: bytes, stamp_ns: int) -> bytes:
    """CDR bytes of a message that starts with a ``std_msgs/Header``, restamped."""
    return data[:4] + struct.pack("<iI", stamp_ns // SEC, stamp_ns % SEC) + data[12:]


# -- hostile cases --------------------------------------------------------------------------------------
@dataclass
class Plan:
    """Hostile messages to insert: ``(stream ns, full topic, CDR bytes, kind)``."""
    events: list[tuple[int, str, bytes, str]] = field(default_factory=list)

    def per_topic(self) -> dict[str, int]:
        out: dict[str, int] = {}
        for _, t, _, _ in self.events:
            out[t] = out.get(t, 0) + 1
        return out


def draw_cases(topic: str, bases: list[Any], n: int, seed: int) -> list[tuple[int, Any]]:
    """``n`` hostile messages of ``topic`` drawn by hypothesis (:func:`~indoor_loc.bench.hostile.wire_case`):
    ``(index of the base in bases, case)``; hypothesis picks the base too, so a draw depends on
    nothing but its choices."""
    from hypothesis import HealthCheck, Phase, given, settings
    from hypothesis import seed as hseed
    from hypothesis import strategies as st

    from indoor_loc.bench.hostile import wire_case
    out: list[tuple[int, Any]] = []

    @hseed(seed)
    @settings(max_examples=n, database=None, deadline=None, phases=[Phase.generate],
              suppress_health_check=list(HealthCheck))
    @given(st.data())
    def collect(data: Any) -> None:
        if len(out) < n:
            k = data.draw(st.integers(0, len(bases) - 1))
            out.append((k, data.draw(wire_case(topic, bases[k], huge_n=DRAWN_HUGE_AP))))
    collect()
    return out


def hostile_plan(world: World, bases: dict[str, list[tuple[int, Any]]], n_per_port: int, phase_end_ns: int,
                 *, seed: int = 0, ports: tuple[str, ...] = PORTS, log: Callable[[str], None] = print) -> Plan:
    """Per walker and input port, ``n_per_port`` drawn cases spread evenly over
    ``[t0, phase_end_ns]`` (each made from the port's valid message before it, stamped as that one
    unless the case is about stamps), plus the explicit cases."""
    from rclpy.serialization import serialize_message

    from indoor_loc.bench.hostile import huge_scan
    plan = Plan()
    span = phase_end_ns - world.t0_ns
    for wi, w in enumerate(world.walkers):
        for pi, rel in enumerate(PORTS):
            if rel not in ports:
                continue
            full = f"/{w}/{rel}"
            src = rel if rel != "initialpose" else "wifi/fix"        # initialpose made from the fixes
            have = sorted((b for b in bases.get(f"/{w}/{src}", []) if b[0] < phase_end_ns), key=lambda b: b[0])
            if not have:
                log(f"  no valid {full} to make hostile messages from: skipped")
                continue
            t_start = time.monotonic()
            cases = draw_cases(rel, [m for _, m in have], n_per_port, seed + 1000 * wi + pi)
            n = len(cases)
            on_base: dict[int, int] = {}
            for k, c in cases:            # just after its base (1 us apart on the same base)
                on_base[k] = on_base.get(k, 0) + 1
                plan.events.append((have[k][0] + 1000 * on_base[k], full, c.data, c.kind))
            b_stamp, b = have[len(have) // 2]
            data = serialize_message(b)
            mid = world.t0_ns + span // 2
            plan.events += [(mid + 2, full, data, "burst")] * BURST
            if rel == "wifi/scan":
                big = serialize_message(huge_scan(HUGE_AP))
                for k in range(HUGE_SCANS):
                    at = world.t0_ns + span * (k + 1) // (HUGE_SCANS + 1) + 3
                    plan.events.append((at, full, with_stamp(big, b_stamp), "huge_scan"))
            log(f"  {full}: {n} drawn + {BURST + (HUGE_SCANS if rel == 'wifi/scan' else 0)} "
                f"explicit hostile cases ({time.monotonic() - t_start:.1f} s)")
    # a user nobody configured: valid-looking messages in a namespace of their own
    w = world.walkers[0]
    for rel in [p for p in ("pdr/odom", "wifi/fix", "wifi/scan") if p in ports]:
        have = sorted(bases.get(f"/{w}/{rel}", []), key=lambda b: b[0])
        for k in range(GHOST_PER_PORT if have else 0):
            stamp, b = have[k * len(have) // GHOST_PER_PORT]
            plan.events.append((stamp, f"/{GHOST}/{rel}", serialize_message(b), "unknown_user"))
    plan.events.sort(key=lambda e: e[0])
    return plan


def empty_plan(world: World, phase_end_ns: int) -> Plan:
    """Per walker and input port, :data:`EMPTY_PER_PORT` empty serialised samples spread over
    ``[t0, phase_end_ns]`` (on the publisher of the valid stream for the sensor topics)."""
    plan = Plan()
    span = phase_end_ns - world.t0_ns
    for w in world.walkers:
        for pi, rel in enumerate(PORTS):
            for k in range(EMPTY_PER_PORT):
                at = world.t0_ns + span * (k + 1) // (EMPTY_PER_PORT + 1) + pi * SEC // 10 + 1
                plan.events.append((at, f"/{w}/{rel}", b"", "empty_bytes"))
    plan.events.sort(key=lambda e: e[0])
    return plan


# -- a trial ----------------------------------------------------------------------------------------------
@dataclass
class Trial:
    name: str
    rate: float
    nodes: dict[str, Any] = field(default_factory=dict)        # key -> NodeRecord
    outputs: dict[str, list[tuple[int, float, float, float]]] = field(default_factory=dict)
    bases: dict[str, list[tuple[int, Any]]] = field(default_factory=dict)
    sent: dict[str, int] = field(default_factory=dict)
    hostile_sent: dict[str, int] = field(default_factory=dict)
    stop_rcs: dict[str, int] = field(default_factory=dict)
    wall0: float = 0.0
    play_s: float = 0.0
    marks: dict[str, float] = field(default_factory=dict)       # event -> wall time
    killed: str = ""
    note: str = ""
    recorder: dict[str, Any] = field(default_factory=dict)

    def stream_ns_at(self, wall: float, t0_ns: int) -> int:
        return t0_ns + int((wall - self.wall0) * self.rate * SEC)


def schedule(stream: list[tuple[int, str, bytes]], t0_ns: int, rate: float,
             plan: Plan | None = None) -> list[tuple[float, str, bytes]]:
    """The valid stream with the plan's events merged in (each after the valid messages of its ns),
    as ``(wall s, topic, bytes)``."""
    rows = [(ns, 0, topic, data) for ns, topic, data in stream]
    if plan is not None:
        rows += [(ns, 1, topic, data) for ns, topic, data, _ in plan.events]
    rows.sort(key=lambda r: (r[0], r[1]))
    return [((ns - t0_ns) / SEC / rate, topic, data) for ns, _, topic, data in rows]


def run_trial(world: World, name: str, env: dict[str, str], rate: float, work: Path, *,
              plan: Plan | None = None, kill: str = "", kill_at: float = 0.25, recorder_kill_at: float = 0.0,
              loop: bool = False, sim_time: bool = False, modules: tuple[str, ...] = tuple(NODE_MODULES),
              log: Callable[[str], None] = print) -> Trial:
    """One trial (see the module docstring of :mod:`indoor_loc.bench.chaos`). ``sim_time`` (implied by
    ``loop``): the nodes on ``use_sim_time`` and the bench publishing ``/clock`` with the stream, so the
    nodes' clock is the stream's present, as in a live deployment (``--clock sim``)."""
    sim_time = sim_time or loop
    import os
    import signal
    import sys

    from indoor_loc.bench.live import Proc
    trial = Trial(name, rate, killed=kill)
    topics = {t for _, t, _ in world.stream} | ({t for _, t, _, _ in plan.events} if plan is not None else set())
    h = Harness(world.walkers, world.sim["params"], env, use_sim_time=sim_time, topics=topics, modules=modules, log=log)
    rec: Proc | None = None
    rec_out = work / f"{name}.mcap"
    try:
        if sim_time:
            h.idle_clock(world.t0_ns - 600 * SEC, rate=1.0)
        if recorder_kill_at:
            rec = Proc([sys.executable, "-m", "indoor_loc.nodes.recorder_node", "-a", "-o", str(rec_out),
                        "--overwrite", "--poll", "0.2", "--exclude", "^/diagnostics$|^/rosout$|^/parameter_events$"],
                       env)
        h.start_nodes()
        if not h.wait_ready(extra_subs=1 if rec is not None else 0):
            trial.note = "nodes not ready within 120 s: " + "; ".join(
                f"{k}: {' / '.join((r.proc.lines if r.proc else [])[-2:])}" for k, r in h.nodes.items()
                if r.ready_wall is None)[:600]
            return trial
        sched = schedule(world.stream, world.t0_ns, rate, plan)
        span_wall = world.span_s / rate
        actions: list[tuple[float, Callable[[], None]]] = []
        if kill:
            def do_kill() -> None:
                trial.marks["kill"] = time.monotonic()
                h.kill(kill)
                h.restart(kill)
            actions.append((kill_at * span_wall, do_kill))
        if rec is not None:
            def kill_recorder() -> None:
                trial.marks["recorder_kill"] = time.monotonic()
                trial.recorder["sent_before_kill_per_topic"] = dict(h.sent)
                trial.recorder["at_s"] = time.monotonic() - trial.wall0
                os.kill(rec.proc.pid, signal.SIGKILL)
            actions.append((recorder_kill_at * span_wall, kill_recorder))
        clock = clock_ticks(world, rate) if sim_time else None
        trial.wall0 = time.monotonic()
        trial.play_s = h.play(sched, clock, actions)
        trial.marks["end_pass1"] = time.monotonic()
        h.settle()
        if loop:
            trial.marks["pass2"] = time.monotonic()
            h.play(sched, clock, [])
            h.settle()
        trial.marks["settled"] = time.monotonic()
        time.sleep(1.5)                   # one more /diagnostics of every node, then its counters are judged
        with h.lock:
            for r in h.nodes.values():
                r.settled = dict(r.values)
        if kill:
            r = h.nodes[kill]
            trial.marks["restarted_ready"] = r.ready_wall or 0.0
        h.check_deaths()
        for r in h.nodes.values():       # a live node silent at the end hangs too
            if r.proc is not None and r.proc.proc.poll() is None and r.last_diag_wall is not None:
                gap = time.monotonic() - r.last_diag_wall
                if gap > HANG_S:
                    r.diag_gaps.append((time.monotonic(), gap))
        h.stop_clock()
        trial.stop_rcs = h.stop_nodes()
    finally:
        for r in h.nodes.values():
            if r.proc is not None and r.proc.proc.poll() is None:
                r.proc.stop(timeout=10)
        if rec is not None and rec.proc.poll() is None:
            rec.stop(timeout=10)
        with h.lock:
            trial.nodes = dict(h.nodes)
            trial.outputs = {k: list(v) for k, v in h.outputs.items()}
            trial.bases = {k: list(v) for k, v in h.bases.items()}
            trial.sent = dict(h.sent)
        h.close()
    if plan is not None:
        trial.hostile_sent = plan.per_topic()
    if rec is not None:
        trial.recorder.update(recover_recording(rec_out, work / f"{name}_recovered.mcap"))
        trial.recorder["sent_total"] = sum(trial.sent.values())
        # on the topics only the bench publishes (not imu/data, pdr/odom, wifi/fix: the nodes publish
        # there too): what it had sent before the kill, and how much of that the recovered bag holds
        per = trial.recorder.get("per_topic", {})
        before = trial.recorder.get("sent_before_kill_per_topic", {})
        own = [t for t in before if t.rsplit("/", 2)[-2:] not in (["imu", "data"], ["pdr", "odom"], ["wifi", "fix"])]
        trial.recorder["sent_before_kill"] = sum(before[t] for t in own)
        trial.recorder["recovered_of_them"] = sum(min(per.get(t, 0), before[t]) for t in own)
        trial.recorder["recovered_beyond"] = sum(max(0, per.get(t, 0) - before[t]) for t in own)
    return trial


def clock_ticks(world: World, rate: float, every_ns: int = 20_000_000) -> list[tuple[float, int]]:
    """``(wall s, clock ns)`` every ``every_ns`` of stream time, never past the next message."""
    out = []
    t = world.t0_ns
    while t <= world.t1_ns:
        out.append(((t - world.t0_ns) / SEC / rate, t))
        t += every_ns
    return out


def recover_recording(src: Path, dst: Path) -> dict[str, Any]:
    """``indoor-loc bag recover`` of the recorder's file after its SIGKILL: what the bag holds."""
    from indoor_loc.bag import bag_info
    from indoor_loc.bag.recover import recover
    from indoor_loc.errors import IndoorLocError
    if not src.exists():
        return {"error": "no file"}
    try:
        r = recover(src, dst)
        info = bag_info([dst])
    except IndoorLocError as err:
        return {"error": str(err)}
    return {"recovered": r.messages, "topics": len(info), "bad_chunks": r.bad_chunks, "truncated": r.truncated,
            "lost_bytes": r.lost_bytes, "per_topic": {t: i.count for t, i in info.items()}}


# -- judging a trial --------------------------------------------------------------------------------------
@dataclass
class Row:
    fault: str
    node: str
    cases: int
    deaths: int
    hangs: int
    sticky: int | None          # valid outputs missing after the fault (None: not judged)
    silent: int | None          # messages neither processed nor counted (None: not judged)
    overcount: int | None       # counted beyond what was sent (a loss counted that did not happen)
    accuracy: float | None      # error after recovery / the reference's, same window
    err_m: float | None
    ref_err_m: float | None
    note: str = ""

    def broken(self) -> list[str]:
        out = []
        if self.deaths:
            out.append(f"{self.deaths} death(s)")
        if self.hangs:
            out.append(f"{self.hangs} hang(s)")
        if self.sticky:
            out.append(f"{self.sticky} valid output(s) missing after the fault (sticky)")
        if self.silent:
            out.append(f"{self.silent} silent loss(es)")
        if self.accuracy is not None and self.accuracy > 1.10:
            out.append(f"accuracy after recovery {self.accuracy:.2f}x the clean run's")
        return out


def inputs_of(rec: Any, walkers: list[str]) -> dict[str, int]:
    """Full input topic -> in.<topic>.count of a node's last /diagnostics."""
    out = {}
    for k, v in (rec.settled or rec.values).items():
        if k.startswith("in.") and k.endswith(".count"):
            rel = k[3:-6]
            full = f"/{rel}" if rec.ns == "" else f"{rec.ns}/{rel}"
            out[full] = int(v)
    return out


def sent_to(trial: Trial, topic: str) -> int:
    """Messages published on ``topic``: by the bench, and by the nodes (their out.<topic>.count)."""
    n = trial.sent.get(topic, 0)
    for r in trial.nodes.values():
        for k, v in (r.settled or r.values).items():
            if k.startswith("out.") and k.endswith(".count"):
                rel = k[4:-6]
                if (f"/{rel}" if r.ns == "" else f"{r.ns}/{rel}") == topic:
                    n += int(v)
    return n


#: Wall-clock span of the outputs to look at (received in it): all by default.
ALL = (0.0, float("inf"))


def node_error(trial: Trial, world: World, topic: str, user: str, from_ns: int, to_ns: int,
               wall: tuple[float, float] = ALL) -> float | None:
    """Mean distance (m) of ``topic``'s poses (received within ``wall``), interpolated at the
    truth samples in ``[from_ns, to_ns]``, to the truth there."""
    from indoor_loc.eval.metrics import scan_time_errors
    rows = [r for r in trial.outputs.get(topic, []) if wall[0] <= r[3] < wall[1]]
    truth = world.truths.get(user)
    if len(rows) < 2 or truth is None:
        return None
    rows.sort(key=lambda r: r[0])
    stamps = np.array([r[0] for r in rows], dtype=np.int64)
    keep = np.concatenate([[True], np.diff(stamps) > 0])
    xy = np.array([[r[1], r[2]] for r in rows])[keep]
    sel = (truth.scan_ns >= from_ns) & (truth.scan_ns <= to_ns)
    if not sel.any():
        return None
    d, inside = scan_time_errors(stamps[keep], xy, truth.scan_ns[sel], truth.scan_xy[sel])
    return float(np.mean(d[inside])) if inside.any() else None


def output_count(trial: Trial, topic: str, from_ns: int, to_ns: int, wall: tuple[float, float] = ALL) -> int:
    """Distinct stamps of ``topic``'s outputs in ``[from_ns, to_ns]`` (received within ``wall``)."""
    return len({r[0] for r in trial.outputs.get(topic, []) if from_ns <= r[0] <= to_ns and wall[0] <= r[3] < wall[1]})


def judge(trial: Trial, ref: Trial, world: World, *, from_ns: int, wall: tuple[float, float] = ALL,
          ref_wall: tuple[float, float] = ALL) -> list[Row]:
    """One row per node of ``trial`` against the reference trial ``ref`` over ``[from_ns, end]``."""
    rows = []
    hostile_keys = set(trial.hostile_sent)
    for key, rec in trial.nodes.items():
        ins = inputs_of(rec, world.walkers)
        cases = sum(n for t, n in trial.hostile_sent.items() if t in ins or
                    (rec.ns == "" and t.split("/", 2)[-1] in {i.split("/", 2)[-1] for i in ins}))
        if trial.killed == key:
            cases = 1
        deaths = len(rec.deaths)
        hangs = len(rec.diag_gaps) + rec.probes_unanswered
        note = []
        if rec.diag_gaps:
            note.append(f"/diagnostics silent {max(g for _, g in rec.diag_gaps):.0f} s")
        if rec.probes_unanswered:
            note.append(f"{rec.probes_unanswered} parameter request(s) unanswered for {HANG_S:g} s")
        if rec.key in trial.stop_rcs and trial.stop_rcs[rec.key] != 0:
            note.append(f"stop exit {trial.stop_rcs[rec.key]}")
        # silent losses: what was sent to its inputs against what it booked (processed or rejected by
        # the stage, undecodable, lost); not judged for a node that was restarted, or fed by one
        upstream_killed = trial.killed and trial.killed != key and _fed_by(trial, rec, trial.killed)
        silent = overcount = None
        if trial.killed != key and not upstream_killed and ins:
            sent = sum(sent_to(trial, t) for t in ins)
            if rec.ns == "":
                sent += sum(trial.sent.get(t, 0) for t in hostile_keys if t not in ins
                            and t.split("/", 2)[-1] in {i.split("/", 2)[-1] for i in ins})
            vals = rec.settled or rec.values
            booked = sum(ins.values()) + int(vals.get("rejected.undecodable", 0)) + int(vals.get("lost.total", 0))
            silent, overcount = max(0, sent - booked), max(0, booked - sent)
        sticky = err = ref_err = acc = None
        out = OUTPUT[rec.module]
        errs, refs, missing = [], [], 0
        for w in world.walkers if rec.ns == "" else [rec.ns.strip("/")]:
            topic = "/" + out.format(user=w) if "{user}" in out else f"/{w}/{out}"
            n_ref = output_count(ref, topic, from_ns, world.t1_ns, ref_wall)
            n_got = output_count(trial, topic, from_ns, world.t1_ns, wall)
            missing += max(0, n_ref - n_got)
            if rec.module != "imu_node":
                e = node_error(trial, world, topic, w, from_ns, world.t1_ns, wall)
                e_ref = node_error(ref, world, topic, w, from_ns, world.t1_ns, ref_wall)
                if e is not None and e_ref is not None:
                    errs.append(e)
                    refs.append(e_ref)
                elif e_ref is not None:
                    note.append(f"no {topic} after the fault")
        sticky = missing
        if errs:
            err, ref_err = float(np.mean(errs)), float(np.mean(refs))
            acc = err / ref_err if ref_err > 0 else None
        rows.append(Row(trial.name, key, cases, deaths, hangs, sticky, silent, overcount, acc, err, ref_err,
                        "; ".join(note + rec.deaths)))
    return rows


def _fed_by(trial: Trial, rec: Any, killed: str) -> bool:
    """Does ``rec`` take an output of the node ``killed`` (same namespace, or the shared back-end)?"""
    k = trial.nodes[killed]
    outs = {kk[4:-6] for kk in k.values if kk.startswith("out.")} or {OUTPUT[k.module]}
    ins = {kk[3:-6].split("/", 1)[-1] if rec.ns == "" else kk[3:-6] for kk in rec.values if kk.startswith("in.")
           and kk.endswith(".count")}
    return bool(outs & ins) and (rec.ns == "" or rec.ns == k.ns)


__all__ = ["NODE_MODULES", "PORTS", "Plan", "Row", "Trial", "World", "hostile_plan", "judge", "load_world", "run_trial"]
