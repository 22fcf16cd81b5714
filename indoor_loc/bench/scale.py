"""``indoor-loc bench scale``: how many users one machine serves live, every stage in multi-user mode.

Simulated walkers (:mod:`indoor_loc.sim`, 8 walks of the sample building; IMU at ``--imu-hz``, 50 Hz by
default, and WiFi scans every 4 s; no magnetometer) are published live over DDS as users ``u000`` …
by one load process (:mod:`indoor_loc.bench.scale_load`), stamped with the wall clock. One process per
stage serves every user — ``imu_node``, ``wifi_fix_node``, ``pdr_kf_node``, ``tll_pf`` started with
``--multi-user`` (or ``--shards`` processes per stage, each with its share) — in a full pipeline:
``imu/data_raw`` → ``pdr/odom``, ``wifi/scan`` → ``wifi/fix``, both → ``pdr_kf/pose`` and ``pf/pose``.

The number of users steps up (``--users``, default 10, 25, 50, 100, 150, 200); at each step, after
``--warmup`` seconds for the new users to be discovered, a window of ``--window`` seconds is measured:
per stage the messages handled per second (``in.*.count`` of its ``/diagnostics``), CPU time of its
processes (``/proc``; also per message handled, which a shared machine does not distort as much as the
wall-clock rate) and resident memory (total, and per user: the growth since the processes were idle over
the users added), latency from the input stamp to the output's reception for a sample of the users (the
DDS reception time of the output minus its header stamp: for ``pdr/odom`` this includes the stepometer's
own delay of about a window, see docs/nodes.md), the backlog at the window's end (messages sent but not
yet handled, in seconds of input) and losses (``lost.*`` and ``rejected.*`` of the nodes). The steps stop
at the first loss or once real time is not held (a backlog of more than ``BACKLOG_MAX_S``, or the load
process itself falling behind by as much). The machine's load average is printed with each step.

Parameters: the simulator's (radio map, graph, step length) with ``tll_pf`` at ``particles_every: 0``
(no ``pf/particles``: a 1000-pose message per user every few hops is for viewing one user) and
``smooth_window_s: 60`` (the smoother's particle history, ~9 MB per user; the default 600 s is ~90 MB
per user after 10 minutes), every node ``user_timeout_s: 120`` and ``sensor_reliability: reliable``;
``imu_node`` on its default heading (``auto``: VQF), or ``--heading-source aekf`` (the simulator's own).
"""
from __future__ import annotations

import argparse
import dataclasses
import os
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from indoor_loc.bench.live import Proc, wait_until

#: stage -> (node module, its input topics counted as handled, its outputs measured for latency)
STAGES: dict[str, tuple[str, tuple[str, ...], str]] = {
    "imu_node": ("indoor_loc.nodes.imu_node", ("imu/data_raw",), "pdr/odom"),
    "wifi_fix_node": ("indoor_loc.nodes.wifi_fix_node", ("wifi/scan",), "wifi/fix"),
    "pdr_kf_node": ("indoor_loc.nodes.pdr_kf_node", ("pdr/odom", "wifi/fix"), "pdr_kf/pose"),
    "tll_pf": ("indoor_loc.nodes.tll_pf_node", ("pdr/odom", "wifi/fix"), "pf/pose"),
}
#: Real time is held while every stage's backlog at the end of a window is below this (s of input).
BACKLOG_MAX_S = 2.0
#: Latency is sampled from every this many users (their outputs subscribed by the bench).
LATENCY_EVERY = 5


@dataclass
class StageRow:
    stage: str
    msgs_per_s: float = 0.0
    cpu_s: float = 0.0
    rss_mb: float = 0.0
    lat_ms: list[float] = field(default_factory=list)
    backlog_s: float = 0.0
    lost: int = 0
    rejected: int = 0
    handled: int = 0
    rss_mb_idle: float = 0.0         # the stage's processes before any user, MB


@dataclass
class Step:
    users: int
    window_s: float
    rows: dict[str, StageRow]
    load_lag_ms: float
    loadavg: str
    note: str = ""

    def held(self) -> bool:
        return (not self.note and all(r.backlog_s <= BACKLOG_MAX_S and r.lost == 0 for r in self.rows.values())
                and self.load_lag_ms <= BACKLOG_MAX_S * 1e3)


def _proc_cpu_s(pid: int) -> float:
    try:
        parts = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return 0.0
    return (int(parts[11]) + int(parts[12])) / os.sysconf("SC_CLK_TCK")


def _proc_rss_mb(pid: int) -> float:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    except OSError:
        pass
    return 0.0


class Monitor:
    """The bench's own rclpy node: every node's /diagnostics, and the sampled users' outputs taken
    raw (reception time from DDS, stamp from the CDR header) by polling, off the executor."""

    def __init__(self) -> None:
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.context import Context
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.node import Node

        from indoor_loc.contract import Qos
        from indoor_loc.nodes.qos import qos_profile
        from msg_adapters.diagnostics import diagnostics_from_msg

        self.ctx = Context()
        rclpy.init(context=self.ctx)
        self.node = Node("bench_scale", context=self.ctx)
        self.io = Node("bench_scale_io", context=self.ctx)
        self.ex = SingleThreadedExecutor(context=self.ctx)
        self.ex.add_node(self.node)
        self.diags: dict[str, Any] = {}
        self.lat: dict[str, list[float]] = {}
        self._subs: list[tuple[str, Any]] = []
        self._qos = qos_profile(Qos.RELIABLE)

        def on_diag(msg: DiagnosticArray) -> None:
            for st in msg.status[:1]:          # the nodes' own status (the users' follow it)
                self.diags.update(diagnostics_from_msg(type(msg)(status=[st])))
        self.node.create_subscription(DiagnosticArray, "/diagnostics", on_diag, self._qos)
        self.node.create_timer(0.1, self._poll)

    def watch_user(self, user: str) -> None:
        from indoor_loc.contract import msg_class
        from indoor_loc.contract import TOPICS
        for _mod, _ins, out in STAGES.values():
            tp = TOPICS[out].type if out in TOPICS else "geometry_msgs/msg/PoseWithCovarianceStamped"
            sub = self.io.create_subscription(msg_class(tp), f"/{user}/{out}", lambda *_: None, self._qos, raw=True)
            self._subs.append((out, sub))

    def _poll(self) -> None:
        from indoor_loc.nodes.inputs import _cdr_stamp_ns
        for out, sub in self._subs:
            while True:
                with sub.handle:
                    got = sub.handle.take_message(sub.msg_type, True)
                if got is None:
                    break
                data, info = got
                self.lat.setdefault(out, []).append((int(info["received_timestamp"]) - _cdr_stamp_ns(data)) * 1e-6)

    def spin(self, seconds: float) -> None:
        end = time.monotonic() + seconds
        while (left := end - time.monotonic()) > 0:
            self.ex.spin_once(timeout_sec=min(0.05, left))

    def close(self) -> None:
        self.ex.shutdown(timeout_sec=0.0)
        self.io.destroy_node()
        self.node.destroy_node()
        self.ctx.try_shutdown()


def _params(sim: dict[str, Path], work: Path, heading_source: str = "") -> Path:
    """The simulator's parameters for the multi-user nodes (see the module doc); ``heading_source`` for
    ``imu_node`` ('' = its default, auto: VQF)."""
    from indoor_loc.params import load_params_file, params_file_text
    files = load_params_file(sim["params"])
    nodes: dict[str, dict[str, Any]] = {}
    for key, values in files.items():
        name = key.rsplit("/", 1)[-1]
        nodes[name] = dict(values)
    nodes.setdefault("imu_node", {}).pop("heading_source", None)        # the default (auto: VQF)
    if heading_source:
        nodes["imu_node"]["heading_source"] = heading_source
    nodes.setdefault("tll_pf", {}).update(particles_every=0, smooth_window_s=60.0)
    for name in STAGES:
        nodes.setdefault(name, {}).update(user_timeout_s=120.0)
    out = work / "scale_params.yaml"
    out.write_text(params_file_text(nodes, "# indoor-loc bench scale: the simulator's parameters, multi-user"))
    return out


def _counts(values: dict[str, str], rels: tuple[str, ...]) -> int:
    return sum(int(values.get(f"in.{r}.count", 0) or 0) for r in rels)


def run_scale(sim: dict[str, Path], work: Path, env: dict[str, str], *, steps: list[int], shards: int,
              warmup: float, window: float, heading_source: str = "") -> list[Step]:
    """One stepped run (see the module doc); returns the steps measured."""
    py = sys.executable
    params = _params(sim, work, heading_source)
    procs: dict[str, list[Proc]] = {}
    for stage, (mod, _, _) in STAGES.items():
        procs[stage] = []
        for i in range(shards):
            extra = ["-r", f"__ns:=/shard{i}", "-p", f"shard_index:={i}", "-p", f"shard_count:={shards}"] \
                if shards > 1 else []
            procs[stage].append(Proc([py, "-m", mod, "--multi-user", "--ros-args", "--params-file", str(params),
                                      "-p", "sensor_reliability:=reliable", *extra], env))
    load = subprocess.Popen([py, "-m", "indoor_loc.bench.scale_load", str(sim["bag"]), "--topics",
                             "imu/data_raw,wifi/scan"], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                            stderr=subprocess.DEVNULL, text=True, env=env, bufsize=1)
    mon = Monitor()
    sent_lines: list[str] = []
    import threading

    def read_load() -> None:
        assert load.stdout is not None
        for line in load.stdout:
            sent_lines.append(line.strip())
    threading.Thread(target=read_load, daemon=True).start()
    results: list[Step] = []
    try:
        names = {stage: [f"/shard{i}/{stage}" if shards > 1 else f"/{stage}" for i in range(shards)]
                 for stage in STAGES}
        if not wait_until(lambda: (mon.spin(0.2), all(n in mon.diags for ns in names.values() for n in ns))[1], 120):
            raise RuntimeError("nodes did not start: " + "; ".join(p.lines[-1] if p.lines else "?"
                                                                   for ps in procs.values() for p in ps))
        mon.spin(2.0)
        rss0 = {s: sum(_proc_rss_mb(p.proc.pid) for p in ps) for s, ps in procs.items()}
        users = 0
        from indoor_loc.bench.scale_load import user_name
        for n in steps:
            assert load.stdin is not None
            load.stdin.write(f"users {n}\n")
            load.stdin.flush()
            for k in range(users, n):
                if k % LATENCY_EVERY == 0:
                    mon.watch_user(user_name(k))
            users = n
            mon.spin(warmup)
            mon.lat.clear()
            cpu0 = {s: sum(_proc_cpu_s(p.proc.pid) for p in ps) for s, ps in procs.items()}
            d0 = {s: [dict(mon.diags[name].values) for name in names[s]] for s in STAGES}
            t0 = time.monotonic()
            mon.spin(window)
            dt = time.monotonic() - t0
            rows = {}
            last = sent_lines[-1] if sent_lines else ""
            sent = {kv.split("=")[0]: int(kv.split("=")[1]) for kv in last.split()[3:] if "=" in kv and "lag" not in kv}
            lags = [float(ln.rsplit("lag_ms=", 1)[1]) for ln in sent_lines[-int(window):] if "lag_ms=" in ln]
            for s, (_, ins, out) in STAGES.items():
                d1 = [dict(mon.diags[name].values) for name in names[s]]
                handled = sum(_counts(v, ins) for v in d1) - sum(_counts(v, ins) for v in d0[s])
                r = StageRow(s, msgs_per_s=handled / dt, handled=handled)
                r.cpu_s = sum(_proc_cpu_s(p.proc.pid) for p in procs[s]) - cpu0[s]
                r.rss_mb = sum(_proc_rss_mb(p.proc.pid) for p in procs[s])
                r.lat_ms = sorted(mon.lat.get(out, []))
                r.lost = sum(int(v.get("lost.total", 0) or 0) for v in d1)
                r.rejected = sum(int(v.get("rejected.total", 0) or 0) for v in d1)
                if s == "imu_node":
                    want = sent.get("imu/data_raw", 0)
                elif s == "wifi_fix_node":
                    want = sent.get("wifi/scan", 0)
                else:   # what the front ends published to it
                    want = sum(int(v.get("out.pdr/odom.count", 0) or 0) for name in names["imu_node"]
                               for v in [mon.diags[name].values]) + \
                        sum(int(v.get("out.wifi/fix.count", 0) or 0) for name in names["wifi_fix_node"]
                            for v in [mon.diags[name].values])
                have = sum(_counts(v, ins) for v in d1)
                rate = max(r.msgs_per_s, 1e-9)
                r.backlog_s = max(0.0, (want - have) / rate) if want else 0.0
                rows[s] = r
            for s in rows:
                rows[s].rss_mb_idle = rss0[s]
            step = Step(n, dt, rows, max(lags, default=0.0), " ".join(Path("/proc/loadavg").read_text().split()[:3]))
            dead = [f"{s}#{i}" for s, ps in procs.items() for i, p in enumerate(ps) if p.proc.poll() is not None]
            if dead:
                step.note = "exited: " + ", ".join(dead)
            results.append(step)
            _print_step(step, shards)
            if not step.held():
                break
    finally:
        try:
            if load.stdin is not None:
                load.stdin.write("quit\n")
                load.stdin.flush()
            load.wait(timeout=10)
        except (OSError, subprocess.TimeoutExpired):
            load.kill()
        for ps in procs.values():
            for p in ps:
                p.stop(timeout=20)
        mon.close()
    return results


def _pct(v: list[float], q: float) -> str:
    if not v:
        return "–"
    return f"{v[min(len(v) - 1, int(q * len(v)))]:.0f}"


def _print_step(step: Step, shards: int) -> None:
    tot_cpu = sum(r.cpu_s for r in step.rows.values())
    tot_rss = sum(r.rss_mb for r in step.rows.values())
    tot_idle = sum(r.rss_mb_idle for r in step.rows.values())
    for r in step.rows.values():
        idle = r.rss_mb_idle
        per_msg = f"{r.cpu_s / r.handled * 1e3:.2f}" if r.handled else "–"
        print(f"| {step.users} | {shards} | {r.stage} | {r.msgs_per_s:,.0f} | {100 * r.cpu_s / step.window_s:.0f} % | "
              f"{per_msg} | {r.rss_mb:.0f} | {(r.rss_mb - idle) / step.users:.2f} | {_pct(r.lat_ms, 0.5)} | "
              f"{_pct(r.lat_ms, 0.99)} | {r.backlog_s:.1f} | {r.lost} | {r.rejected} |", flush=True)
    verdict = "real time, no loss" if step.held() else ("NOT held" + (f" ({step.note})" if step.note else ""))
    print(f"| {step.users} | {shards} | **all** | | **{100 * tot_cpu / step.window_s:.0f} %** "
          f"({1e3 * tot_cpu / step.window_s / step.users:.1f} ms/s per user) | | **{tot_rss:.0f}** | "
          f"**{(tot_rss - tot_idle) / step.users:.2f}** | | | load lag {step.load_lag_ms:.0f} ms | "
          f"loadavg {step.loadavg} | {verdict} |", flush=True)


def run(args: argparse.Namespace) -> int:
    from indoor_loc.commands.sim import generate
    from indoor_loc.sim.scenario import SimConfig
    from indoor_loc.sim.walker import ImuParams

    imu_hz = float(getattr(args, "imu_hz", 0) or 50.0)
    steps = [int(u) for u in str(getattr(args, "users", "") or ("10,50" if args.quick else
                                                                  "10,25,50,100,150,200")).split(",")]
    shard_counts = [int(s) for s in str(getattr(args, "shards", "") or "1,2").split(",")]
    warmup = float(getattr(args, "warmup", 0) or (10.0 if args.quick else 15.0))
    window = float(getattr(args, "window", 0) or (15.0 if args.quick else 25.0))
    heading = str(getattr(args, "heading_source", "") or "")
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", PYTHONUNBUFFERED="1")
    env.setdefault("ROS_DOMAIN_ID", str(1 + (int(os.environ.get("INDOOR_LOC_DOMAIN_BASE", "1")) + 70) % 232))
    os.environ["ROS_DOMAIN_ID"] = env["ROS_DOMAIN_ID"]
    cfg = SimConfig(walkers=8, duration_s=120.0, seed=7, imu=dataclasses.replace(ImuParams(), rate_hz=imu_hz))
    cfg.validate()
    with tempfile.TemporaryDirectory(prefix="bench_scale_") as tmp:
        work = Path(tmp)
        sim = generate(work / "sim", cfg, quiet=True)
        print(f"\n## Users served live over DDS, every stage multi-user ({imu_hz:g} Hz IMU + WiFi scans every 4 s per "
              f"user; imu_node heading_source {heading or 'auto (VQF)'}; {os.cpu_count()} CPUs; window {window:g} s after "
              f"{warmup:g} s warm-up per step)\n")
        print("| users | shards | stage | msgs/s handled | CPU (of one core) | CPU ms per msg | RSS MB | RSS MB per "
              "user (growth since idle) | latency p50 ms | p99 ms | backlog s | lost | rejected |")
        print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
        summary = []
        for shards in shard_counts:
            res = run_scale(sim, work, env, steps=steps, shards=shards, warmup=warmup, window=window,
                            heading_source=heading)
            held = [s.users for s in res if s.held()]
            summary.append((shards, max(held, default=0), res[-1].users if res and not res[-1].held() else None))
        print()
        for shards, best, first_bad in summary:
            print(f"- {shards} process(es) per stage: real time with no loss up to **{best} users**"
                  + (f"; not held at {first_bad}" if first_bad else " (the largest step tried)"))
    return 0


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true")
    raise SystemExit(run(ap.parse_args()))
