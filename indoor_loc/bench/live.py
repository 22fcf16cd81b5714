"""``indoor-loc bench live``: where live replay over DDS starts to lose messages.

For N users (simulated walkers from :mod:`indoor_loc.sim`, 200 Hz IMU + 50 Hz magnetometer + WiFi
scans each) replayed at rate R, every user gets its own ``imu_node``, ``wifi_fix_node`` and
``pdr_kf_node`` process in its namespace (the simulator's params), one ``recorder -a`` records
everything, and ``player -r R --wait-for-subscribers --min-subscribers imu/data_raw=2 …`` plays
the users' topics once the nodes' outputs are matched and every node input has both its subscribers
(the node and the recorder). Per trial: messages each kind of node handled per second (per node, over the
playback and the time it then needed to work off its queue, to within the 1 s of /diagnostics), and
messages lost on the way to it — the input messages that never arrived (sent − received, which also
covers what sequence gaps cannot see) — and in the recorder (bag counts against what was sent). For
each N the rate rises until the first loss anywhere; the table says where it happened. Then the
recorder alone: all N users played straight into ``recorder -a`` at rising rates until it loses a
message (its own limit, without the CPU the nodes take), with how much of that loss it counted.

Choose ``--duration`` so that a user's messages outnumber the nodes' queues (10 000 reliable IMU
messages: 40 s of 250 msg/s), else a fast replay is only absorbed by them. Then the offline
per-stage table of the same bag (:mod:`indoor_loc.bench.throughput`).

The sensor inputs are reliable (``sensor_reliability: reliable``, as for any replay) unless
``--sensor-qos best_effort`` asks for the best-effort subscriptions real drivers are met with.
"""
from __future__ import annotations

import argparse
import dataclasses
import os
import re
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

NODES = ("imu_node", "wifi_fix_node", "pdr_kf_node")
#: What each node must have matched before playing: output topic -> subscriptions (pdr_kf + recorder).
MATCHED = {"imu_node": ("pdr/odom", 2), "wifi_fix_node": ("wifi/fix", 2), "pdr_kf_node": ("pdr_kf/pose", 1)}
#: Inputs of each node kind among the bag's relative topics (pdr_kf's come from the other nodes).
BAG_INPUTS = {"imu_node": ("imu/data_raw", "imu/mag", "imu/data"), "wifi_fix_node": ("wifi/scan",)}


@dataclass
class Trial:
    users: int
    rate: float
    sent: int = 0                    # input messages played
    play_s: float = 0.0              # wall time of the playback
    lag_s: float = 0.0               # after the playback, until the nodes had worked off their queues
    received: dict[str, int] = field(default_factory=dict)   # node kind -> messages received (all users)
    missing: dict[str, int] = field(default_factory=dict)    # node kind -> input messages that never arrived
    recorder_missing: int = 0
    recorder_lost: str = ""          # the recorder's own LOST line (topics and counts), if any
    recorded: int = 0
    note: str = ""

    @property
    def lost(self) -> bool:
        return any(self.missing.values()) or self.recorder_missing > 0


class Proc:
    """A child process whose output lines are collected by a thread."""

    def __init__(self, cmd: list[str], env: dict[str, str]) -> None:
        import threading
        self.proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env,
                                     bufsize=1)
        self.lines: list[str] = []
        self._t = threading.Thread(target=self._read, daemon=True)
        self._t.start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self.lines.append(line.rstrip("\n"))

    def has(self, pattern: str) -> bool:
        rx = re.compile(pattern)
        return any(rx.search(ln) for ln in list(self.lines))

    def stop(self, timeout: float = 30.0) -> int:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
        try:
            rc = self.proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            rc = self.proc.wait(timeout=10)
        self._t.join(timeout=2)
        return rc


def wait_until(cond, timeout: float) -> bool:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if cond():
            return True
        time.sleep(0.1)
    return cond()


def _diagnostics_listener():
    """An rclpy node on its own context keeping the last /diagnostics status of every node."""
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node

    from indoor_loc.contract import Qos
    from indoor_loc.nodes.base import qos_profile
    from msg_adapters.diagnostics import diagnostics_from_msg

    ctx = Context()
    rclpy.init(context=ctx)
    node = Node("bench_live", context=ctx)
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    last: dict[str, Any] = {}

    def on_diag(msg: DiagnosticArray) -> None:
        last.update(diagnostics_from_msg(msg))
    node.create_subscription(DiagnosticArray, "/diagnostics", on_diag, qos_profile(Qos.RELIABLE))

    def close() -> None:
        ex.shutdown(timeout_sec=0.0)
        node.destroy_node()
        ctx.try_shutdown()
    return ex, last, close


def _inputs_received(values: dict[str, str], rels: tuple[str, ...] | None = None) -> int:
    """Messages received on the inputs ``rels`` (all inputs when None) from a node's diagnostics."""
    return sum(int(v) for k, v in values.items() if k.startswith("in.") and k.endswith(".count")
               and (rels is None or k[3:-6] in rels))


def run_trial(sim: dict[str, Path], users: list[str], rate: float, work: Path, env: dict[str, str],
              sensor_qos: str) -> Trial:
    """One replay of ``users`` at ``rate``; see the module docstring."""
    from indoor_loc.bag import bag_info
    from indoor_loc.nodes.base import DIAGNOSTICS_PERIOD_S

    info = bag_info([sim["bag"]])
    ns = {u: f"/{u}" for u in users}
    topics = sorted(t for t in info if any(t.startswith(ns[u] + "/") for u in users))
    trial = Trial(len(users), rate, sent=sum(info[t].count for t in topics))
    out = work / f"rec_{len(users)}u_{rate:g}x.mcap"
    py = sys.executable
    rec = Proc([py, "-m", "indoor_loc.nodes.recorder_node", "-a", "-o", str(out), "--overwrite", "--poll", "0.2",
                 "--exclude", "^/diagnostics$|^/rosout$|^/parameter_events$"], env)
    nodes: dict[tuple[str, str], Proc] = {}
    ex, diags, close = _diagnostics_listener()
    try:
        for u in users:
            for kind in NODES:
                extra = ["-p", "odom_hold_s:=5.0"] if kind == "pdr_kf_node" else []
                nodes[(u, kind)] = Proc([py, "-m", f"indoor_loc.nodes.{kind}", "--ros-args", "-r", f"__ns:={ns[u]}",
                                          "--params-file", str(sim["params"]), "-p",
                                          f"sensor_reliability:={sensor_qos}", *extra], env)

        def matched() -> bool:
            ex.spin_once(timeout_sec=0.0)
            return all(p.has(rf"{MATCHED[k][0]}: {MATCHED[k][1]} matched") for (u, k), p in nodes.items())
        if not wait_until(matched, 120):
            trial.note = "nodes not matched within 120 s"
            return trial
        # every input a node takes has two subscribers, the node and the recorder: wait for both
        # (a non-zero count can be the recorder alone, and the node would miss the first messages)
        need = [f"{rel}=2" for rel in sorted({r for rels in BAG_INPUTS.values() for r in rels})
                if any(t.endswith("/" + rel) for t in topics)]
        player = Proc([py, "-m", "indoor_loc.nodes.player_node", str(sim["bag"]), "-r", f"{rate:g}",
                        "--wait-for-subscribers", "60", "--min-subscribers", *need, "--topics", *topics], env)
        while player.proc.poll() is None:
            ex.spin_once(timeout_sec=0.1)
        player.stop()
        played = [re.search(r"played (\d+) messages in ([\d.]+) s", ln) for ln in player.lines]
        got = [m for m in played if m]
        if not got:
            trial.note = "player failed: " + " / ".join(player.lines[-3:])
            return trial
        trial.play_s = float(got[-1].group(2))
        # the nodes work off their queues: wait until no node's input count grows for 2 periods
        still, prev, end = 0, None, time.monotonic() + 120
        t_end = last_change = time.monotonic()
        while still < 3 and time.monotonic() < end:
            t_next = time.monotonic() + DIAGNOSTICS_PERIOD_S
            while time.monotonic() < t_next:
                ex.spin_once(timeout_sec=0.05)
            cur = {k: _inputs_received(v.values) for k, v in diags.items()}
            if cur != prev:
                last_change = time.monotonic()
            still = still + 1 if cur == prev else 0
            prev = cur
        trial.lag_s = max(0.0, last_change - t_end - DIAGNOSTICS_PERIOD_S)   # diagnostics come once a second
        for kind in NODES:                       # dependency order, recorder last
            for u in users:
                rc = nodes[(u, kind)].stop()
                if rc != 0:
                    trial.note += f"{ns[u]}/{kind} exit {rc}: " + " / ".join(nodes[(u, kind)].lines[-3:])[-300:] + "; "
        for _ in range(int(2 / 0.05)):
            ex.spin_once(timeout_sec=0.05)
        rec.stop()
    finally:
        for p in [*nodes.values(), rec]:
            if p.proc.poll() is None:
                p.stop(timeout=10)
        close()

    # what each node received against what was sent to it
    outs: dict[tuple[str, str], int] = {}
    for u in users:
        for kind in NODES:
            d = diags.get(f"{ns[u]}/{kind}")
            if d is None:
                trial.note += f"no /diagnostics from {ns[u]}/{kind}; "
            values = d.values if d is not None else {}
            # only the inputs sent to it (imu_node also hears its own imu/data)
            rels = None if kind == "pdr_kf_node" else tuple(r for r in BAG_INPUTS[kind] if f"{ns[u]}/{r}" in info)
            got = _inputs_received(values, rels)
            if kind == "pdr_kf_node":
                imu = diags.get(f"{ns[u]}/imu_node")
                wifi = diags.get(f"{ns[u]}/wifi_fix_node")
                want = sum(int((x.values if x else {}).get(key, 0)) for x, key in
                           ((imu, "out.pdr/odom.count"), (wifi, "out.wifi/fix.count")))
            else:
                want = sum(info[f"{ns[u]}/{rel}"].count for rel in BAG_INPUTS[kind] if f"{ns[u]}/{rel}" in info)
            trial.received[kind] = trial.received.get(kind, 0) + got
            trial.missing[kind] = trial.missing.get(kind, 0) + max(0, want - got)
            for k, v in values.items():
                if k.startswith("out.") and k.endswith(".count"):
                    outs[(u, k[4:-6])] = int(v)
    recorded = bag_info([out]) if out.exists() else {}
    want_rec = {t: info[t].count for t in topics}
    for (u, rel), n in outs.items():
        want_rec[f"{ns[u]}/{rel}"] = want_rec.get(f"{ns[u]}/{rel}", 0) + n
    trial.recorded = sum(t.count for name, t in recorded.items() if name in want_rec)
    trial.recorder_missing = sum(max(0, n - (recorded[t].count if t in recorded else 0))
                                 for t, n in want_rec.items() if not t.endswith("/path"))
    trial.recorder_lost = next((ln.strip() for ln in reversed(rec.lines) if "LOST" in ln), "")
    return trial


#: Rates of the recorder-alone trials (all users at once), rising until the first loss.
RECORDER_RATES = (5.0, 10.0, 20.0, 40.0, 80.0)


@dataclass
class RecorderTrial:
    users: int
    rate: float
    sent: int = 0
    play_s: float = 0.0
    recorded: int = 0
    counted: int = 0                 # loss the recorder itself counted (LOST line)
    note: str = ""

    @property
    def missing(self) -> int:
        return max(0, self.sent - self.recorded)


def run_recorder_trial(sim: dict[str, Path], users: list[str], rate: float, work: Path,
                       env: dict[str, str]) -> RecorderTrial:
    """The recorder alone: ``player -r R`` plays the users' topics straight into ``recorder -a``
    (no nodes), so its own limit shows and not the CPU the nodes take."""
    from indoor_loc.bag import bag_info

    info = bag_info([sim["bag"]])
    topics = sorted(t for t in info if any(t.startswith(f"/{u}/") for u in users))
    trial = RecorderTrial(len(users), rate, sent=sum(info[t].count for t in topics))
    out = work / f"rec_alone_{len(users)}u_{rate:g}x.mcap"
    py = sys.executable
    rec = Proc([py, "-m", "indoor_loc.nodes.recorder_node", "-a", "-o", str(out), "--overwrite", "--poll", "0.2",
                 "--exclude", "^/diagnostics$|^/rosout$|^/parameter_events$"], env)
    try:
        if not wait_until(lambda: rec.has("recording all topics"), 60):
            trial.note = "recorder did not start"
            return trial
        player = Proc([py, "-m", "indoor_loc.nodes.player_node", str(sim["bag"]), "-r", f"{rate:g}",
                        "--wait-for-subscribers", "60", "--topics", *topics], env)
        player.proc.wait()
        player.stop()
        got = [m for m in (re.search(r"played (\d+) messages in ([\d.]+) s", ln) for ln in player.lines) if m]
        if not got:
            trial.note = "player failed: " + " / ".join(player.lines[-3:])
            return trial
        trial.play_s = float(got[-1].group(2))
        rec.stop()
    finally:
        if rec.proc.poll() is None:
            rec.stop(timeout=10)
    lost = [m for m in (re.search(r"LOST before reaching the recorder: (\d+)", ln) for ln in rec.lines) if m]
    trial.counted = int(lost[-1].group(1)) if lost else 0
    recorded = bag_info([out]) if out.exists() else {}
    trial.recorded = sum(recorded[t].count for t in topics if t in recorded)
    return trial


def _rate(n: int, s: float) -> str:
    return f"{n / s:,.0f}" if s > 0 else "–"


def run(args: argparse.Namespace) -> int:
    from indoor_loc.commands.sim import generate
    from indoor_loc.sim.scenario import SimConfig

    users = [int(u) for u in str(getattr(args, "users", "") or ("1,2" if args.quick else "1,2,4")).split(",")]
    rates = [float(r) for r in str(getattr(args, "rates", "") or ("2,5" if args.quick else "2,5,10,20")).split(",")]
    duration = float(getattr(args, "duration", 0) or (30.0 if args.quick else 60.0))
    sensor_qos = getattr(args, "sensor_qos", "reliable") or "reliable"
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", PYTHONUNBUFFERED="1")
    env.setdefault("ROS_DOMAIN_ID", str(1 + (int(os.environ.get("INDOOR_LOC_DOMAIN_BASE", "1")) + 60) % 232))
    os.environ["ROS_DOMAIN_ID"] = env["ROS_DOMAIN_ID"]
    from indoor_loc.sim.walker import ImuParams
    cfg = SimConfig(walkers=max(users), duration_s=duration, seed=7,
                    imu=dataclasses.replace(ImuParams(), rate_hz=200.0, mag_rate_hz=50.0))
    cfg.validate()
    with tempfile.TemporaryDirectory(prefix="bench_live_") as tmp:
        work = Path(tmp)
        sim = generate(work / "sim", cfg, quiet=True)
        from indoor_loc.bag import bag_info
        names = sorted({t.split("/")[1] for t in bag_info([sim["bag"]]) if t.count("/") >= 2
                        and t.split("/")[1] != "map"})
        print(f"\n## Live replay over DDS: first loss per node and in the recorder "
              f"({duration:g} s of simulated walking per user, 200 Hz IMU + 50 Hz magnetometer + scans; "
              f"sensor inputs {sensor_qos}; {os.cpu_count()} CPUs)\n")
        print("| users | rate | sent msg/s (all users) | imu_node msg/s per node (lost) | wifi_fix_node (lost) | "
              "pdr_kf_node msg/s per node (lost) | recorder msg/s (lost) | queues worked off after | first loss |")
        print("|---|---|---|---|---|---|---|---|---|")
        for n in users:
            for r in rates:
                t = run_trial(sim, names[:n], r, work, env, sensor_qos)
                s = t.play_s
                where = ", ".join(k for k in NODES if t.missing.get(k)) + (
                    (", " if any(t.missing.values()) else "") + "recorder" if t.recorder_missing else "")
                # node rates over the playback plus the time the nodes needed to work off their queues
                busy = s + t.lag_s
                print(f"| {n} | {r:g}× | {_rate(t.sent, s)} | {_rate(t.received.get('imu_node', 0) // n, busy)} "
                      f"({t.missing.get('imu_node', 0)}) | {t.missing.get('wifi_fix_node', 0)} | "
                      f"{_rate(t.received.get('pdr_kf_node', 0) // n, busy)} ({t.missing.get('pdr_kf_node', 0)}) | "
                      f"{_rate(t.recorded, s)} ({t.recorder_missing}) | {t.lag_s:.0f} s | "
                      f"{where or t.note or 'none'} |", flush=True)
                if t.note:
                    print(f"  note: {t.note}", flush=True)
                if t.recorder_lost:
                    print(f"  recorder: {t.recorder_lost[:400]}", flush=True)
                if t.lost or t.note:
                    break
        print(f"\n## The recorder alone ({max(users)} users, `player -r R` straight into `recorder -a`, no nodes)\n")
        print("| users | rate | sent msg/s | recorder msg/s | not recorded | of which counted (LOST) |")
        print("|---|---|---|---|---|---|")
        for r in RECORDER_RATES:
            rt = run_recorder_trial(sim, names[:max(users)], r, work, env)
            print(f"| {rt.users} | {r:g}× | {_rate(rt.sent, rt.play_s)} | {_rate(rt.recorded, rt.play_s)} | "
                  f"{rt.missing} | {rt.counted} |", flush=True)
            if rt.note:
                print(f"  note: {rt.note}", flush=True)
            if rt.missing or rt.note:
                break
        from indoor_loc.bench.throughput import format_rows, offline_stage_rates
        print(f"\n## The same bag offline ({max(users)} users), per stage: `indoor-loc run` on one core\n")
        print(format_rows(offline_stage_rates([sim["bag"]], params=sim["params"], scratch=work)))
    return 0
