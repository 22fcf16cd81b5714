"""The machinery of one run of the fault benchmark (:mod:`indoor_loc.bench.chaos`): the node processes
of the walkers, the bench's own rclpy node (publishers on every input port, /clock, subscriptions to
/diagnostics and to the scored outputs, parameter requests as a liveness probe) and the playback of
a schedule of serialised messages at a rate.
"""
from __future__ import annotations

import os
import signal
import sys
import threading
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

from indoor_loc.bench.live import Proc, wait_until

#: The nodes of the benchmark: module -> node name (the status name in /diagnostics is ns/name).
NODE_MODULES = {"imu_node": "imu_node", "wifi_fix_node": "wifi_fix_node", "pdr_kf_node": "pdr_kf_node",
                "tll_pf_node": "tll_pf", "backend_node": "backend_node"}
PER_WALKER = ("imu_node", "wifi_fix_node", "pdr_kf_node", "tll_pf_node")
SHARED = ("backend_node",)
#: Stop order (sources first, sinks last), as the demo's supervisor stops them.
STOP_ORDER = ("imu_node", "wifi_fix_node", "pdr_kf_node", "tll_pf_node", "backend_node")
#: Each node's scored output (relative to the walker's namespace; ``{user}`` for the back-end).
OUTPUT = {"imu_node": "pdr/odom", "wifi_fix_node": "wifi/fix", "pdr_kf_node": "pdr_kf/pose",
          "tll_pf_node": "pf/pose", "backend_node": "backend/{user}/pose"}
#: Input ports the bench publishes on (per walker namespace).
PORTS = ("imu/data_raw", "imu/mag", "imu/data", "wifi/scan", "pdr/odom", "wifi/fix", "initialpose")
#: A node whose /diagnostics stop this long (wall clock), or that leaves a parameter request
#: unanswered this long, while its process lives, hangs.
HANG_S = 10.0
#: How often each node is sent a parameter request (s).
PROBE_PERIOD_S = 2.0


@dataclass
class NodeRecord:
    """What the bench saw of one node (one logical node, across restarts)."""
    key: str                                  # "/alice/imu_node" (or "/backend_node")
    module: str
    ns: str
    proc: Proc | None = None
    pids: list[int] = field(default_factory=list)
    killed_by_bench: int = 0
    deaths: list[str] = field(default_factory=list)       # unexpected exits: "exit N: last lines"
    last_diag_wall: float | None = None
    max_diag_gap_s: float = 0.0
    diag_gaps: list[tuple[float, float]] = field(default_factory=list)   # (wall at end of gap, gap s) > HANG_S
    values: dict[str, str] = field(default_factory=dict)   # the last /diagnostics values
    settled: dict[str, str] = field(default_factory=dict)  # ... once the playback was worked off, before the stop
    probe_sent: float | None = None
    probe_max_s: float = 0.0
    probes_unanswered: int = 0
    probes: int = 0
    started_wall: float = 0.0
    ready_wall: float | None = None           # first /diagnostics of the current process

    @property
    def name(self) -> str:
        return NODE_MODULES[self.module]


class Harness:
    """The bench's rclpy node (own context, executor in a thread), the node processes and the playback."""

    def __init__(self, walkers: list[str], params: Path, env: dict[str, str], *, use_sim_time: bool,
                 topics: set[str] | None = None, modules: tuple[str, ...] = STOP_ORDER,
                 log: Callable[[str], None] = print) -> None:
        import rclpy
        from rclpy.context import Context
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.node import Node

        self.walkers, self.params, self.env, self.use_sim_time, self.log = walkers, params, env, use_sim_time, log
        # the topics the bench publishes on (full names; default: the walkers' sensor inputs): no idle
        # publisher beside a node's output, where a second publisher would blind the consumers'
        # sequence-gap loss count (it stands down when a topic has several publishers)
        self.topics = set(topics) if topics is not None else {f"/{w}/{rel}" for w in walkers
                                                               for rel in ("imu/data_raw", "imu/mag", "wifi/scan")}
        self.modules = tuple(m for m in STOP_ORDER if m in modules)   # the nodes to run, in stop order
        self._clock_ns: int | None = None         # sim time: the clock published while not playing
        self._clock_rate = 1.0
        self._playing = False
        self._last_tick = 0.0
        from rclpy.signals import SignalHandlerOptions
        self.ctx = Context()
        # no rclpy signal handlers: Ctrl-C (and SIGTERM, see chaos.run) is a KeyboardInterrupt that
        # stops the node processes on its way out
        rclpy.init(context=self.ctx, signal_handler_options=SignalHandlerOptions.NO)
        self.node = Node("bench_chaos", context=self.ctx)
        self.ex = SingleThreadedExecutor(context=self.ctx)
        self.ex.add_node(self.node)
        self.lock = threading.Lock()
        self._clock_lock = threading.Lock()     # idle /clock ticks (the spin thread) against the playback's
        self.nodes: dict[str, NodeRecord] = {}
        self.pubs: dict[str, Any] = {}
        self.outputs: dict[str, list[tuple[int, float, float, float]]] = {}   # topic -> (stamp, x, y, wall)
        self.bases: dict[str, list[tuple[int, Any]]] = {}                    # derived topic -> (stamp, msg)
        self.sent: dict[str, int] = {}                                        # full topic -> messages published
        self.mine: dict[str, Counter] = {}        # output topic -> hashes of the bytes the bench published there
        self.clock_pub = None
        self._clients: dict[str, Any] = {}
        self._pending: dict[str, Any] = {}
        self._stop = threading.Event()
        self._setup()
        self._thread = threading.Thread(target=self._spin, daemon=True)
        self._thread.start()

    # -- ROS side ----------------------------------------------------------------------------------------
    def _setup(self) -> None:
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
        from rosgraph_msgs.msg import Clock

        from indoor_loc.contract import TOPICS, Qos, msg_class
        from indoor_loc.nodes.qos import qos_profile
        from msg_adapters.diagnostics import diagnostics_from_msg

        pub_qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=5000, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.VOLATILE)
        for full in sorted(self.topics):
            rel = full.split("/", 2)[-1]
            self.pubs[full] = self.node.create_publisher(msg_class(TOPICS[rel].type), full, pub_qos)
        if self.use_sim_time:
            self.clock_pub = self.node.create_publisher(Clock, "/clock", qos_profile(Qos.RELIABLE))

        def on_diag(msg: DiagnosticArray) -> None:
            now = time.monotonic()
            with self.lock:
                for name, st in diagnostics_from_msg(msg).items():
                    rec = self.nodes.get(name)
                    if rec is None:
                        continue
                    if rec.last_diag_wall is not None:
                        gap = now - rec.last_diag_wall
                        rec.max_diag_gap_s = max(rec.max_diag_gap_s, gap)
                        if gap > HANG_S:
                            rec.diag_gaps.append((now, gap))
                    if rec.ready_wall is None:
                        rec.ready_wall = now
                    rec.last_diag_wall = now
                    rec.values = dict(st.values)
        self.node.create_subscription(DiagnosticArray, "/diagnostics", on_diag, qos_profile(Qos.RELIABLE))
        for w in self.walkers:
            for rel in ("wifi/fix", "pdr_kf/pose", "pf/pose", f"backend/{w}/pose", "pdr/odom", "imu/data"):
                full = f"/{rel}" if rel.startswith("backend/") else f"/{w}/{rel}"
                key = rel if not rel.startswith("backend/") else "backend/{user}/pose"
                qos = qos_profile(TOPICS[key].qos if key in TOPICS else Qos.RELIABLE)
                cls = msg_class(TOPICS[key].type if key in TOPICS else "geometry_msgs/msg/PoseWithCovarianceStamped")
                self.node.create_subscription(cls, full, self._on_output(full, rel, cls), qos, raw=True)

    def _on_output(self, full: str, rel: str, cls: type) -> Callable[[bytes], None]:
        """Outputs taken raw: what the bench itself published on the topic (hostile messages on a
        node's output topic, counted by their bytes) is not an output, and bytes that do not
        deserialise are never the bench's business."""
        from rclpy.serialization import deserialize_message
        keep_base = rel in ("pdr/odom", "wifi/fix", "imu/data")
        every = 10 if rel == "imu/data" else 1
        count = [0]
        mine = self.mine.setdefault(full, Counter())

        def cb(data: bytes) -> None:
            h = hash(data)
            with self.lock:
                if mine.get(h):
                    mine[h] -= 1
                    return
            try:
                msg = deserialize_message(data, cls)
            except Exception:  # noqa: BLE001 - not a node's output
                return
            stamp = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
            p = msg.pose.pose.position if hasattr(msg, "pose") else None
            with self.lock:
                if p is not None:
                    self.outputs.setdefault(full, []).append((stamp, float(p.x), float(p.y), time.monotonic()))
                count[0] += 1
                if keep_base and count[0] % every == 0:
                    self.bases.setdefault(full, []).append((stamp, msg))
        return cb

    def _spin(self) -> None:
        last_probe = 0.0
        while not self._stop.is_set():
            try:
                self.ex.spin_once(timeout_sec=0.05)
            except Exception:  # noqa: BLE001 - the context is shutting down
                if self._stop.is_set():
                    return
                raise
            now = time.monotonic()
            if self._clock_ns is not None and not self._playing and now - self._last_tick >= 0.05:
                from rosgraph_msgs.msg import Clock

                from msg_adapters.time import stamp_from_ns
                with self._clock_lock:      # never an idle tick after the playback's first: /clock going back
                    if not self._playing and self._clock_ns is not None:
                        if self._last_tick:
                            self._clock_ns += int((now - self._last_tick) * self._clock_rate * 1e9)
                        self._last_tick = now
                        if self.clock_pub is not None:
                            self.clock_pub.publish(Clock(clock=stamp_from_ns(self._clock_ns)))
            if now - last_probe >= PROBE_PERIOD_S:
                last_probe = now
                self._probe(now)

    def _probe(self, now: float) -> None:
        """A parameter request to every live node; one unanswered for HANG_S while it lives is a hang."""
        from rcl_interfaces.srv import GetParameters
        with self.lock:
            recs = list(self.nodes.values())
        for rec in recs:
            alive = rec.proc is not None and rec.proc.proc.poll() is None and rec.ready_wall is not None
            fut = self._pending.get(rec.key)
            if fut is not None:
                if fut.done():
                    rec.probe_max_s = max(rec.probe_max_s, now - (rec.probe_sent or now))
                    self._pending.pop(rec.key)
                elif now - (rec.probe_sent or now) > HANG_S:
                    if alive:
                        rec.probes_unanswered += 1
                        rec.probe_max_s = max(rec.probe_max_s, now - (rec.probe_sent or now))
                    self._pending.pop(rec.key)
                continue
            if not alive:
                continue
            cli = self._clients.get(rec.key)
            if cli is None:
                cli = self._clients[rec.key] = self.node.create_client(GetParameters, f"{rec.key}/get_parameters")
            if not cli.service_is_ready():
                continue
            req = GetParameters.Request()
            req.names = ["use_sim_time"]
            rec.probe_sent = now
            rec.probes += 1
            self._pending[rec.key] = cli.call_async(req)

    def idle_clock(self, start_ns: int, rate: float = 1.0) -> None:
        """Sim time: publish /clock from ``start_ns`` at ``rate`` whenever the bench is not playing
        (the nodes' timers, /diagnostics among them, run on it)."""
        self._clock_ns, self._clock_rate, self._last_tick = start_ns, rate, 0.0

    def stop_clock(self) -> None:
        self._clock_ns = None

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)
        self.ex.shutdown(timeout_sec=0.0)
        self.node.destroy_node()
        self.ctx.try_shutdown()

    # -- node processes ------------------------------------------------------------------------------------
    def _command(self, module: str, ns: str) -> list[str]:
        cmd = [sys.executable, "-m", f"indoor_loc.nodes.{module}", "--ros-args"]
        if ns:
            cmd += ["-r", f"__ns:={ns}"]
        cmd += ["--params-file", str(self.params), "-p", "sensor_reliability:=reliable"]
        if self.use_sim_time:
            cmd += ["-p", "use_sim_time:=true"]
        return cmd

    def start_nodes(self) -> None:
        for module in self.modules:
            nss = [f"/{w}" for w in self.walkers] if module in PER_WALKER else [""]
            for ns in nss:
                key = f"{ns}/{NODE_MODULES[module]}"
                rec = NodeRecord(key, module, ns)
                with self.lock:
                    self.nodes[key] = rec
                self._spawn(rec)

    def _spawn(self, rec: NodeRecord) -> None:
        rec.proc = Proc(self._command(rec.module, rec.ns), self.env)
        rec.pids.append(rec.proc.proc.pid)
        rec.started_wall = time.monotonic()
        rec.ready_wall = None
        rec.last_diag_wall = None

    def kill(self, key: str) -> None:
        """SIGKILL a node (its process id only)."""
        rec = self.nodes[key]
        assert rec.proc is not None
        rec.killed_by_bench += 1
        rec.proc._noted = True                     # type: ignore[attr-defined]  # its exit is no death
        os.kill(rec.proc.proc.pid, signal.SIGKILL)
        rec.proc.proc.wait(timeout=10)

    def restart(self, key: str) -> None:
        self._spawn(self.nodes[key])

    def check_deaths(self) -> None:
        """Note every node process that exited without the bench asking (a death)."""
        for rec in self.nodes.values():
            p = rec.proc
            if p is not None and p.proc.poll() is not None and not getattr(p, "_noted", False):
                p._noted = True                    # type: ignore[attr-defined]
                rec.deaths.append(f"exit {p.proc.returncode}: " + " / ".join(p.lines[-3:])[-300:])

    def wait_ready(self, timeout: float = 120.0, extra_subs: int = 0) -> bool:
        """Every node has sent /diagnostics and every input the nodes list is matched by the bench's
        publisher as often as nodes take it (+ ``extra_subs``: the recorder), stable for 1 s."""
        def ready() -> bool:
            self.check_deaths()
            with self.lock:
                recs = list(self.nodes.values())
                if any(r.ready_wall is None for r in recs):
                    return False
                want = self._subscribers_wanted(recs)
            return all(self.pubs[t].get_subscription_count() >= n + extra_subs for t, n in want.items())
        if not wait_until(ready, timeout):
            return False
        time.sleep(1.0)
        return True

    def _subscribers_wanted(self, recs: list[NodeRecord]) -> dict[str, int]:
        want: dict[str, int] = {}
        for r in recs:
            for k in r.values:
                if not (k.startswith("in.") and k.endswith(".state")):
                    continue
                rel = k[3:-6]
                for w in self.walkers:
                    if rel.startswith(w + "/"):
                        full = f"/{rel}"
                    elif r.ns == f"/{w}":
                        full = f"/{w}/{rel}"
                    else:
                        continue
                    if full in self.pubs:
                        want[full] = want.get(full, 0) + 1
        return want

    def stop_nodes(self) -> dict[str, int]:
        """SIGINT in dependency order (each wave once the one before has exited); exit statuses."""
        rcs = {}
        for module in STOP_ORDER:
            for rec in [r for r in self.nodes.values() if r.module == module]:
                if rec.proc is not None:
                    alive = rec.proc.proc.poll() is None
                    rc = rec.proc.stop(timeout=30)
                    if alive:
                        rcs[rec.key] = rc
        return rcs

    def settle(self, timeout: float = 180.0) -> float:
        """Wait until the nodes have worked off what was sent: no node's input counts grew for 3
        diagnostics periods and every live node sent /diagnostics in the last 2 s (a node busy with one
        message for a while sends none, and its counts stand still). Returns the seconds it took."""
        t0 = time.monotonic()
        prev, still = None, 0
        while still < 3 and time.monotonic() - t0 < timeout:
            time.sleep(1.0)
            self.check_deaths()
            now = time.monotonic()
            with self.lock:
                cur = {k: sum(int(v) for kk, v in r.values.items() if kk.startswith("in.") and kk.endswith(".count"))
                       for k, r in self.nodes.items()}
                busy = any(r.proc is not None and r.proc.proc.poll() is None and
                           (r.last_diag_wall is None or now - r.last_diag_wall > 2.0) for r in self.nodes.values())
            still = still + 1 if cur == prev and not busy else 0
            prev = cur
        return time.monotonic() - t0

    # -- playback ------------------------------------------------------------------------------------------
    def play(self, schedule: list[tuple[float, str, bytes]], rate_clock: list[tuple[float, int]] | None = None,
             on_time: list[tuple[float, Callable[[], None]]] | None = None) -> float:
        """Publish ``(t_s, full topic, CDR bytes)`` at ``t_s`` (wall seconds from now); ``/clock``
        (``rate_clock``: ``(t_s, clock ns)``, before the messages due at the same time); ``on_time``:
        actions at their times (kills, restarts). Returns the wall time it took."""
        from rosgraph_msgs.msg import Clock

        from msg_adapters.time import stamp_from_ns
        clock = rate_clock or []
        actions = sorted(on_time or [], key=lambda a: a[0])
        ci = ai = 0
        with self._clock_lock:
            self._playing = True
        t0 = time.monotonic()
        for t, topic, data in schedule:
            while ai < len(actions) and actions[ai][0] <= t:
                actions[ai][1]()
                ai += 1
            while ci < len(clock) and clock[ci][0] <= t:
                if self.clock_pub is not None:
                    self.clock_pub.publish(Clock(clock=stamp_from_ns(clock[ci][1])))
                    self._clock_ns = clock[ci][1]
                ci += 1
            delay = t0 + t - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            mine = self.mine.get(topic)
            if mine is not None:
                with self.lock:
                    mine[hash(data)] += 1
            self.pubs[topic].publish(data)
            self.sent[topic] = self.sent.get(topic, 0) + 1
        for _, act in actions[ai:]:
            act()
        for _, ns in clock[ci:]:
            if self.clock_pub is not None:
                self.clock_pub.publish(Clock(clock=stamp_from_ns(ns)))
                self._clock_ns = ns
        if clock:
            self._clock_rate, self._last_tick = self._rate_of(clock), time.monotonic()
        self._playing = False
        return time.monotonic() - t0

    @staticmethod
    def _rate_of(clock: list[tuple[float, int]]) -> float:
        (w0, c0), (w1, c1) = clock[0], clock[-1]
        return (c1 - c0) / 1e9 / (w1 - w0) if w1 > w0 else 1.0


def rss_kb(pid: int) -> int | None:
    """Resident set size of a process, kB (``VmRSS`` of /proc/<pid>/status); None when it is gone."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
    except OSError:
        return None
    return None


def cpu_s(pid: int) -> float | None:
    """User + system CPU time of a process, s (/proc/<pid>/stat); None when it is gone."""
    try:
        text = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    fields = text[text.rindex(")") + 2:].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
