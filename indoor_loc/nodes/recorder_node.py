"""Recorder: DDS topics -> MCAP bag (rosbag2 layout), like ``ros2 bag record -s mcap``.

``ros2 run indoor_loc recorder -t imu/data wifi/scan -o walk.mcap --ros-args -r __ns:=/walk01``
``ros2 run indoor_loc recorder -a -o all.mcap``

- Serialised messages go straight into the bag (``raw=True`` subscriptions: no deserialisation).
- Bursts, not messages: when the executor hands one message to a callback, the callback also takes
  every message already queued on every subscription (``take_message``, at most ``TAKE_MAX`` per
  subscription) and hands the burst to the writer thread as one item, so rclpy's per-callback cost
  (rebuilding the wait set) is paid once per burst. On the executor thread a message costs its take,
  its log time and its sequence-gap count; sorting by log time, serialising and compressing happen
  on the writer thread. DDS keeps up to ``SUB_DEPTH`` messages per topic for bursts.
- QoS of each subscription matches the publishers found: best effort if any publisher is best
  effort, transient_local if every publisher is (latched topics: their last message is received
  even when it was published before the recorder started).
- ``-a`` polls the ROS graph every ``--poll`` seconds and adds new topics as they appear; every
  topic added or left out is logged with the reason.
- Log time = the node clock at reception: the DDS reception time (system clock), or under
  ``use_sim_time`` the simulated time when the burst is taken (bag time); publish time = the
  publisher's source timestamp.
- Loss is counted, never silent: gaps in each publisher's sequence numbers (while a topic has one
  publisher) are logged (WARN), summed in ``/diagnostics`` (WARN) and printed as ``LOST`` at exit.
  The first numbers of a restarted publisher are not a loss (:class:`~indoor_loc.nodes.liveness.InputWatch`).
- A reliable subscription stuck behind a sample DDS refused (an empty one) is found and made anew
  (:mod:`indoor_loc.nodes.stuck`): that sample and those held back behind it are counted lost
  (``refused.<topic>`` too), and recording goes on.
- SIGINT / SIGTERM close the bag cleanly (summary and rosbag2 metadata written) after the messages
  DDS had delivered before the signal are written (a second signal stops at once; what is still
  queued when the spin ends is taken in one last pass). The open chunk is
  closed every ``--flush-interval`` seconds, so SIGKILL loses at most that much; ``indoor-loc bag
  recover`` turns such a file into a valid one.
"""
from __future__ import annotations

import argparse
import re
import sys
import threading
import time
from collections import deque
from pathlib import Path
from typing import Any, Callable

import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.signals import SignalHandlerOptions

from indoor_loc.bag import BagWriter
from indoor_loc.bag.writer import DEFAULT_CHUNK_SIZE
from indoor_loc.bag.schemas import qos_dict
from indoor_loc.contract import Qos, msg_class
from indoor_loc.errors import BagError, ConfigError
from indoor_loc.nodes.help import run_option_node
from indoor_loc.nodes.liveness import InputWatch, SequenceGaps
from indoor_loc.nodes.process import ignore_signals, raise_on_signals, restore_signals, spin_node
from indoor_loc.nodes.qos import qos_profile
from indoor_loc.nodes.stage_node import DIAGNOSTICS_PERIOD_S
from indoor_loc.nodes.stuck import StuckGuard, Watched
from indoor_loc.output_paths import check_output
from msg_adapters.diagnostics import RECENT_NS, status_array

NODE_NAME = "recorder"
#: DDS history per subscription: bursts (a replay at 5x, a busy CPU) wait here until they are taken
#: (10 000 = 10 s of a 5x replay of a 200 Hz IMU, ~4 MB per topic).
SUB_DEPTH = 10000
#: At most this many messages are taken from one subscription per burst, so one busy topic cannot
#: hold up the timers (graph polling, flushing, /diagnostics) for long.
TAKE_MAX = 2048
#: The writer thread flushes the open chunk this often at most when asked (s); see --flush-interval.
_WRITER_IDLE_S = 0.05


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options shared by ``indoor-loc record`` and the ``recorder`` executable."""
    what = parser.add_mutually_exclusive_group(required=True)
    what.add_argument("-t", "--topics", nargs="+", metavar="TOPIC",
                      help="topics to record; relative names resolve in the node namespace (--namespace)")
    what.add_argument("-a", "--all", action="store_true", help="record every topic, adding new ones as they appear")
    parser.add_argument("-o", "--output", type=Path, default=None,
                        help="output .mcap file (default rosbag2_YYYY_MM_DD-HH_MM_SS.mcap); an existing "
                             "file is refused unless --overwrite")
    parser.add_argument("--overwrite", action="store_true", help="replace the output file if it exists")
    parser.add_argument("--namespace", default="", help="node namespace, e.g. /walk01 (default: from --ros-args)")
    parser.add_argument("--chunk-size", type=int, default=DEFAULT_CHUNK_SIZE,
                        help=f"chunk size in bytes before compression (default {DEFAULT_CHUNK_SIZE})")
    parser.add_argument("--compression", choices=("zstd", "lz4", "none"), default="zstd",
                        help="chunk compression (default zstd)")
    parser.add_argument("--flush-interval", type=float, default=1.0,
                        help="close the open chunk at least this often, in s; bounds what SIGKILL loses "
                             "(0 = only when full; default 1.0)")
    parser.add_argument("--poll", type=float, default=1.0, help="graph polling period in s (default 1.0)")
    parser.add_argument("--exclude", default="", help="regex of topics not to record with -a")
    parser.add_argument("--include-hidden", action="store_true",
                        help="with -a, also record hidden topics (a path element starting with '_')")


def _log_time(item: tuple) -> int:
    return item[2]


def default_output() -> Path:
    return Path(time.strftime("rosbag2_%Y_%m_%d-%H_%M_%S.mcap"))


def _policy_name(value: Any) -> str:
    return str(getattr(value, "name", value)).lower()


def _duration_ns(d: Any) -> int:
    return int(getattr(d, "nanoseconds", 0))


def offered_qos(profile: QoSProfile) -> dict[str, Any]:
    """An rclpy QoS profile in rosbag2's metadata layout (version 9)."""
    return qos_dict(reliability=_policy_name(profile.reliability), durability=_policy_name(profile.durability),
                    history=_policy_name(profile.history), depth=int(profile.depth),
                    deadline_ns=_duration_ns(profile.deadline), lifespan_ns=_duration_ns(profile.lifespan),
                    liveliness=_policy_name(profile.liveliness),
                    liveliness_lease_ns=_duration_ns(profile.liveliness_lease_duration),
                    avoid_ros_namespace_conventions=bool(profile.avoid_ros_namespace_conventions))


def subscription_qos(publisher_profiles: list[QoSProfile]) -> QoSProfile:
    """QoS that receives from every publisher: best effort if any publisher is best effort,
    transient_local only if all publishers are (a transient_local subscription matches no
    volatile publisher)."""
    best_effort = any(p.reliability == ReliabilityPolicy.BEST_EFFORT for p in publisher_profiles)
    latched = bool(publisher_profiles) and all(p.durability == DurabilityPolicy.TRANSIENT_LOCAL
                                               for p in publisher_profiles)
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=SUB_DEPTH,
                      reliability=ReliabilityPolicy.BEST_EFFORT if best_effort else ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE)


def is_hidden(topic: str) -> bool:
    return any(part.startswith("_") for part in topic.split("/") if part)


class _WriterThread(threading.Thread):
    """Owns the BagWriter: subscription callbacks only append to a deque (thread-safe, no lock,
    no serialisation or compression on the DDS thread); this thread writes, flushes and closes."""

    def __init__(self, writer: BagWriter) -> None:
        super().__init__(name="recorder-writer", daemon=True)
        self.writer = writer
        self.queue: deque[tuple] = deque()
        self.wake = threading.Event()
        self.stopping = False
        self.written = 0
        self.max_backlog = 0
        self.error: BaseException | None = None
        self.topic_errors: list[str] = []

    def put(self, item: tuple) -> None:
        self.queue.append(item)
        n = len(self.queue)
        if n > self.max_backlog:
            self.max_backlog = n
        if n == 1:
            self.wake.set()

    def run(self) -> None:
        q = self.queue
        write = self.writer.write_raw
        try:
            while True:
                while q:
                    item = q.popleft()
                    kind = item[0]
                    if kind == "b":           # a burst: (topic, data, log ns, publish ns) in arrival order
                        burst = item[1]
                        burst.sort(key=_log_time)  # stable: each topic keeps its order
                        for topic, data, log_ns, pub_ns in burst:
                            write(topic, data, log_ns, publish_ns=pub_ns)
                        self.written += len(burst)
                    elif kind == "t":
                        try:
                            self.writer.add_topic(item[1], item[2], qos_profiles=item[3], topic_type_hash=item[4])
                        except BagError as err:
                            self.topic_errors.append(f"{item[1]}: cannot be recorded: {err}")
                    elif kind == "f":
                        self.writer.flush()
                if self.stopping:
                    return
                self.wake.wait(_WRITER_IDLE_S)
                self.wake.clear()
        except BaseException as err:  # noqa: BLE001 - reported by the node, never silently
            self.error = err

    def stop(self) -> None:
        self.stopping = True
        self.wake.set()
        self.join()


class RecorderNode(StuckGuard, Node):
    """Subscribes (raw) to the selected topics and appends every message to a :class:`BagWriter`
    through a writer thread. Messages lost before reaching the recorder are counted from the
    publishers' sequence numbers and reported (log and ``/diagnostics`` WARN)."""

    def __init__(self, writer: BagWriter, *, topics: list[str] | None, poll_s: float = 1.0,
                 flush_interval_s: float = 1.0, exclude: str = "", include_hidden: bool = False,
                 **node_kwargs: Any) -> None:
        super().__init__(NODE_NAME, **node_kwargs)
        self.writer = writer
        self._wanted = None if topics is None else [self.resolve_topic_name(t) for t in topics]
        self._exclude = re.compile(exclude) if exclude else None
        self._include_hidden = include_hidden
        self._subs: dict[str, Watched] = {}     # topic -> its subscription, liveness and probe
        self._reported: set[tuple[str, str]] = set()
        self.received = 0
        self.last_rx_ns = 0            # reception time (system clock) of the last message
        self.lost: dict[str, int] = {}
        self.refused: dict[str, int] = {}      # samples DDS refused (a stuck subscription made anew)
        self._gaps: dict[str, SequenceGaps] = {}
        self._thread = _WriterThread(writer)
        self._thread.start()
        self._diag_pub = self.create_publisher(DiagnosticArray, "/diagnostics", qos_profile(Qos.RELIABLE))
        self._last_loss_ns: int | None = None
        self._poll()
        self.create_timer(poll_s, self._poll)
        self.create_timer(DIAGNOSTICS_PERIOD_S, self._publish_diagnostics)
        if flush_interval_s > 0:
            self.create_timer(flush_interval_s, lambda: self._thread.put(("f",)))
        what = "all topics" if self._wanted is None else ", ".join(self._wanted)
        self.get_logger().info(f"recording {what} to {writer.path}")

    def _report(self, topic: str, text: str, *, warn: bool = False) -> None:
        """Log once per (topic, text): what is recorded and what is not, and why."""
        if (topic, text) in self._reported:
            return
        self._reported.add((topic, text))
        (self.get_logger().warning if warn else self.get_logger().info)(f"{topic}: {text}")

    def close(self) -> None:
        """Write what is queued and stop the writer thread (the caller closes the BagWriter)."""
        self._thread.stop()
        if self._thread.error is not None:
            raise BagError(f"writing {self.writer.path} failed: {self._thread.error}") from self._thread.error

    def diagnostics(self, now_ns: int) -> DiagnosticArray:
        """The recorder's DiagnosticStatus: messages received / written, writer backlog, losses."""
        lost = sum(self.lost.values())
        recent = lost and self._last_loss_ns is not None and now_ns - self._last_loss_ns <= RECENT_NS
        values = {"topics": str(len(self._subs)), "received": str(self.received), "written": str(self._thread.written),
                  "backlog": str(len(self._thread.queue)), "max_backlog": str(self._thread.max_backlog),
                  "lost.total": str(lost), **{f"lost.{t}": str(n) for t, n in sorted(self.lost.items())},
                  **{f"refused.{t}": str(n) for t, n in sorted(self.refused.items())},
                  "file": str(self.writer.path)}
        level = 2 if self._thread.error is not None else (1 if recent else 0)
        message = (f"writer failed: {self._thread.error}" if self._thread.error is not None
                   else f"{lost} messages lost before reaching the recorder" if recent else "ok")
        return status_array(self.get_fully_qualified_name(), level, message, values, now_ns)

    def _publish_diagnostics(self) -> None:
        now_ns = self.get_clock().now().nanoseconds
        for topic, w in list(self._subs.items()):
            gids = self._publisher_gids(topic)
            w.watch.publishers_seen(gids, now_ns)
            self._guard_stuck(w, gids, now_ns)
        self._diag_pub.publish(self.diagnostics(now_ns))

    def _poll(self) -> None:
        types = dict(self.get_topic_names_and_types())
        candidates = self._wanted if self._wanted is not None else sorted(types)
        for topic in candidates:
            if topic in self._subs:
                self._check_late_publishers(topic)
                continue
            if self._wanted is None:
                if is_hidden(topic) and not self._include_hidden:
                    self._report(topic, "hidden topic, not recorded (use --include-hidden)")
                    continue
                if self._exclude is not None and self._exclude.search(topic):
                    self._report(topic, "matches --exclude, not recorded")
                    continue
            names = types.get(topic)
            if not names:
                self._report(topic, "waiting for a publisher")
                continue
            if len(names) > 1:
                self._report(topic, f"published with several types {names}; not recorded", warn=True)
                continue
            self._subscribe(topic, names[0])

    def _check_late_publishers(self, topic: str) -> None:
        # QoS is chosen when subscribing; a best-effort publisher that appears later does not
        # match a reliable subscription -- say so instead of silently missing its messages.
        sub = self._subs[topic].sub
        if sub.qos_profile.reliability != ReliabilityPolicy.RELIABLE:
            return
        for info in self.get_publishers_info_by_topic(topic):
            if info.qos_profile.reliability == ReliabilityPolicy.BEST_EFFORT:
                self._report(topic, f"best-effort publisher {info.node_namespace.rstrip('/')}/{info.node_name} "
                                    "appeared after the subscription was made reliable: its messages are NOT "
                                    "recorded (restart the recorder)", warn=True)

    def _subscribe(self, topic: str, type_name: str) -> None:
        try:
            cls = msg_class(type_name)
        except (ImportError, AttributeError, ValueError):
            self._report(topic, f"type {type_name} is not installed here; not recorded", warn=True)
            return
        infos = self.get_publishers_info_by_topic(topic)
        profiles = [i.qos_profile for i in infos]
        if not profiles:
            self._report(topic, "waiting for a publisher")
            return
        type_hash = ""
        for i in infos:
            h = getattr(i, "topic_type_hash", None)
            if h is not None and str(h).startswith("RIHS"):
                type_hash = str(h)
                break
        self._thread.put(("t", topic, type_name, [offered_qos(p) for p in profiles], type_hash or None))
        qos = subscription_qos(profiles)
        # a latched topic's silence is no stall (its watch never stalls, so it gets no probe)
        watch = InputWatch(topic, stream=qos.durability != DurabilityPolicy.TRANSIENT_LOCAL, on_late_start=(
            lambda n: self.get_logger().info(f"{topic}: the first message received is its publisher's #{n + 1}: "
                                             f"{n} were published before this subscription matched")))
        watch.publishers = lambda: self._publisher_gids(topic)
        w = self._subs[topic] = Watched(topic, cls, watch)
        self._gaps[topic] = watch.gaps
        w.callback = self._callback(topic)
        w.sub = self.create_subscription(cls, topic, w.callback, qos, raw=True)
        self._report(topic, f"recording [{type_name}] ({_policy_name(qos.reliability)}, "
                            f"{_policy_name(qos.durability)}, {len(profiles)} publisher(s))")

    def _callback(self, topic: str) -> Callable[[bytes, Any], None]:
        self._gaps[topic].publishers = self.count_publishers(topic)

        def cb(data: bytes, info: Any) -> None:   # the executor took one message: take the rest of the burst
            self._take_burst(topic, data, info)
        return cb

    def _publisher_gids(self, topic: str) -> frozenset[bytes]:
        return frozenset(bytes(i.endpoint_gid) for i in self.get_publishers_info_by_topic(topic))

    def _deliver(self, w: Any, data: bytes, info: Any, *, probe: bool = False) -> None:
        self._take_burst(w.resolved, data, info, probe=probe)

    def _refused(self, w: Any, refused_seq: int, held: int, now_ns: int) -> None:
        """A stuck subscription's refused sample and those it held back never reach the bag: lost."""
        self.refused[w.resolved] = self.refused.get(w.resolved, 0) + 1
        self._count_lost(w.resolved, held + 1)

    def _take_burst(self, topic: str, data: bytes, info: Any, *, probe: bool = False) -> None:
        """Book the message the executor took on ``topic`` and take every message already queued on
        every subscription (at most :data:`TAKE_MAX` per subscription), then hand the whole burst to
        the writer thread as one item. The executor's wait-set rebuild (most of the cost of a
        message handled by a callback of its own) is paid once per burst, and the per-message work
        here is the take, the log time and the sequence-gap count; sorting, serialising and
        compressing happen on the writer thread."""
        sim_ns = self._sim_now_ns()
        burst: list[tuple[str, bytes, int, int]] = []
        if isinstance(info, dict):
            lost_now = self._book(burst, sim_ns, topic, data, info, probe=probe)
        else:
            lost_now = 0
            now = sim_ns or time.time_ns()
            burst.append((topic, data, now, now))
        lost_now += self._take_queued(burst, sim_ns, TAKE_MAX)
        self.received += len(burst)
        self._thread.put(("b", burst))
        if lost_now:
            self.get_logger().warning(f"{lost_now} message(s) lost before reaching the recorder "
                                      f"({sum(self.lost.values())} so far: "
                                      + ", ".join(f"{t} {n}" for t, n in sorted(self.lost.items())) + ")",
                                      throttle_duration_sec=5.0)

    def take_remaining(self) -> int:
        """After the spin has stopped: one pass over every subscription recording what DDS still
        holds (at most its history depth, so this ends even while publishers go on). Returns how
        many messages it recorded."""
        burst: list[tuple[str, bytes, int, int]] = []
        self._take_queued(burst, self._sim_now_ns(), None)
        if burst:
            self.received += len(burst)
            self._thread.put(("b", burst))
        return len(burst)

    def _sim_now_ns(self) -> int:
        """The simulated time under ``use_sim_time`` (the log time of a burst), else 0."""
        clock = self.get_clock()
        return clock.now().nanoseconds if clock.ros_time_is_active else 0

    def _take_queued(self, burst: list[tuple[str, bytes, int, int]], sim_ns: int, limit: int | None) -> int:
        """Take what DDS holds on every subscription into ``burst`` (at most ``limit`` messages per
        subscription, or its history depth); returns how many were counted lost on the way."""
        lost = 0
        for t, w in list(self._subs.items()):
            sub = w.sub
            take = sub.handle.take_message
            cls = sub.msg_type
            with sub.handle:
                for _ in range(limit or int(sub.qos_profile.depth)):
                    got = take(cls, True)
                    if got is None:
                        break
                    lost += self._book(burst, sim_ns, t, got[0], got[1])
        return lost

    def _book(self, burst: list[tuple[str, bytes, int, int]], sim_ns: int, topic: str, data: bytes,
              info: dict, *, probe: bool = False) -> int:
        """Append one taken message with its log time -- the node clock at reception: DDS's
        reception time on the system clock, or (``use_sim_time``) ``sim_ns`` -- and count the
        sequence gap before it (a message the probe of a stuck subscription brought already is left
        out); returns the messages counted lost."""
        w = self._subs[topic]
        if not probe and not self._taken(w, info):
            return 0
        rx = info.get("received_timestamp") or 0
        log = sim_ns or rx or time.time_ns()
        burst.append((topic, data, log, info.get("source_timestamp") or log))
        self.last_rx_ns = rx
        lost = w.watch.message(info, log)
        if lost:
            self._count_lost(topic, lost)
        return lost

    def _count_lost(self, topic: str, n: int) -> None:
        self.lost[topic] = self.lost.get(topic, 0) + n
        self._last_loss_ns = self.get_clock().now().nanoseconds


def run(options: argparse.Namespace, ros_args: list[str] | None = None) -> int:
    """Record until SIGINT/SIGTERM; returns the exit code."""
    if options.chunk_size <= 0:
        raise ConfigError(f"record.chunk_size: expected > 0 bytes, got {options.chunk_size}")
    if options.poll <= 0:
        raise ConfigError(f"record.poll: expected > 0 s, got {options.poll}")
    if options.flush_interval < 0:
        raise ConfigError(f"record.flush_interval: expected >= 0 s, got {options.flush_interval}")
    output = options.output or default_output()
    if output.suffix != ".mcap":
        output = output.with_suffix(output.suffix + ".mcap") if output.suffix else output.with_suffix(".mcap")
    check_output(output, overwrite=options.overwrite, what="-o")
    # indoor-loc passes no ROS arguments: rcl must not parse the command line (OLD:=NEW remaps)
    rclpy.init(args=ros_args if ros_args is not None else sys.argv[:1], signal_handler_options=SignalHandlerOptions.NO)
    node = None
    writer = BagWriter(output, chunk_size=options.chunk_size, compression=options.compression)
    old = raise_on_signals()
    try:
        writer.open()
        kwargs = {"namespace": options.namespace} if options.namespace else {}
        node = RecorderNode(writer, topics=None if options.all else list(options.topics),
                            poll_s=options.poll, flush_interval_s=options.flush_interval,
                            exclude=options.exclude, include_hidden=options.include_hidden, **kwargs)
        spin_node(node, lambda: node.received if node is not None else 0)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        ignore_signals(old)
        if node is not None:
            if node.context.ok():
                # what the drain did not reach (a long backlog) is still in DDS: take it before the
                # subscriptions go, so nothing received before the signal is dropped unseen
                kept = node.take_remaining()
                if kept:
                    node.get_logger().info(f"stopping: recorded the {kept} message(s) still queued")
            node.destroy_node()
            node.close()
        writer.close()
        rclpy.try_shutdown()
        restore_signals(old)
    counts = writer.topic_counts()
    print(f"recorded {sum(counts.values())} messages on {len(counts)} topics to {output}", file=sys.stderr)
    if node is not None and node.lost:
        print(f"LOST before reaching the recorder: {sum(node.lost.values())} messages ("
              + ", ".join(f"{t} {n}" for t, n in sorted(node.lost.items())) + ")", file=sys.stderr)
    for topic, n in sorted(counts.items()):
        print(f"  {topic}: {n}", file=sys.stderr)
    return 0


def main(args: list[str] | None = None) -> int:
    """``recorder`` executable: same options as ``indoor-loc record``, plus ``--ros-args ...``."""
    return run_option_node("recorder", __doc__.splitlines()[0], add_arguments, run, args)


if __name__ == "__main__":
    sys.exit(main())
