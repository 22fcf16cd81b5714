"""Player: MCAP bag(s) -> DDS in log-time order, like ``ros2 bag play``.

``ros2 run indoor_loc player walk01.mcap --rate 2 --clock --loop``

- Messages are published as stored (serialised bytes, no deserialisation) at their log time
  scaled by ``--rate``; several bags are merged in time order.
- ``--clock [HZ]`` publishes ``rosgraph_msgs/Clock`` on ``/clock`` (default 100 Hz) in bag time,
  for nodes started with ``use_sim_time:=true``. It never runs past the stamp of the next message
  to publish: a player that fell behind (a stall on a loaded machine) does not tell the nodes a
  time whose data they have not been sent yet.
- Publishers are reliable (they serve reliable and best-effort subscribers alike);
  transient_local for the contract's latched topics (``ground_truth``, ``map/graph``,
  ``backend/wifi_map``, ``pf/pose``, under any namespace) and for topics whose recorded
  publishers were all transient_local, so late subscribers still get the last message.
- ``/diagnostics`` about once a second (wall clock): messages published, playback progress in bag
  time, topics without a subscriber (WARN), rate, loop count.
- ``--topics`` keeps only some topics, ``--remap OLD:=NEW`` renames them, ``--start-offset S``
  skips the first S seconds of the bag, ``--loop`` repeats.
- ``--wait-for-subscribers`` holds playback until every topic has its subscribers: at least one,
  or as many as ``--min-subscribers`` says (``N`` for every topic, ``TOPIC=N`` for one: a full name,
  or a name relative to any namespace such as ``imu/data_raw=2``). Say how many there are when
  several processes subscribe to a topic: each subscription is matched on its own, so a count that
  is merely non-zero and stable can be the recorder alone while a node's subscription is still
  being matched, and the node would miss the first messages. The counts are logged when playing
  starts; topics below their count when the wait runs out are a WARN (log and ``/diagnostics``).
- ``--consumers TOPIC=NODE[,NODE...]`` (implies ``--wait-for-subscribers``) waits for the nodes that
  consume a topic by name (``imu/data_raw=imu_node``), whatever else subscribes (a live view, a
  recorder): see :mod:`indoor_loc.nodes.consumers`. Consumers still missing when the wait runs out
  are a WARN (log and ``/diagnostics``).
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

import rclpy
from rclpy.duration import Duration
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.signals import SignalHandlerOptions
from diagnostic_msgs.msg import DiagnosticArray
from rosgraph_msgs.msg import Clock

from indoor_loc.bag import bag_info, read_raw
from indoor_loc.bag.reader import bag_files
from indoor_loc.bag.schemas import parse_qos_yaml
from indoor_loc.contract import TOPICS, Qos, msg_class, split_ns
from indoor_loc.errors import BagError, ConfigError
from indoor_loc.nodes.consumers import Consumers, met_by_observers, missing_consumers
from indoor_loc.nodes.help import run_option_node
from indoor_loc.nodes.process import check_stop, ignore_signals, raise_on_signals, restore_signals
from indoor_loc.nodes.qos import qos_profile
from indoor_loc.nodes.stage_node import DIAGNOSTICS_PERIOD_S
from msg_adapters.diagnostics import status_array

NODE_NAME = "player"
#: --wait-for-subscribers: the subscriber counts must be stable this long before playing (s). The
#: count is the player's side of each match; a subscriber's side can complete a moment later on a
#: busy machine (a volatile subscriber then starts at the first message sent after it matched), which
#: this margin also covers.
SUBSCRIBERS_SETTLE_S = 1.0
#: History of each (volatile) publisher: a reliable writer keeps what its slowest subscriber has not
#: acknowledged yet, and overwrites the oldest beyond this (a loss for that subscriber, counted there
#: as a sequence gap). 10 000 = 5 s of a 10x replay of a 200 Hz IMU for a subscriber starved of CPU.
PUB_DEPTH = 10000


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options shared by ``indoor-loc play`` and the ``player`` executable."""
    parser.add_argument("bags", nargs="+", type=Path, help="MCAP bag(s), merged in time order")
    parser.add_argument("-r", "--rate", type=float, default=1.0, help="playback speed factor (default 1.0)")
    parser.add_argument("-l", "--loop", action="store_true", help="play again from the start when done")
    parser.add_argument("--clock", type=float, nargs="?", const=100.0, default=0.0, metavar="HZ",
                        help="publish /clock in bag time at HZ (default 100 when given)")
    parser.add_argument("--topics", nargs="+", metavar="TOPIC", help="play only these topics (full names)")
    parser.add_argument("--remap", nargs="+", default=[], metavar="OLD:=NEW", help="rename topics")
    parser.add_argument("--start-offset", type=float, default=0.0, metavar="S",
                        help="skip the first S seconds of the bag (default 0)")
    parser.add_argument("--delay", type=float, default=0.0, metavar="S",
                        help="wait S seconds after creating publishers before playing (discovery)")
    parser.add_argument("--wait-for-subscribers", type=float, nargs="?", const=30.0, default=0.0, metavar="S",
                        help="before playing, wait up to S s (default 30) until every topic has its subscribers "
                             "(see --min-subscribers)")
    parser.add_argument("--min-subscribers", nargs="+", default=[], metavar="N|TOPIC=N",
                        help="subscribers to wait for: N for every topic (default 1), TOPIC=N for one topic (a "
                             "full name, or relative to any namespace: imu/data_raw=2); implies "
                             "--wait-for-subscribers")
    parser.add_argument("--consumers", nargs="+", default=[], metavar="TOPIC=NODE[,NODE]",
                        help="nodes that consume a topic, waited for by name whatever else subscribes (a view, a "
                             "recorder): imu/data_raw=imu_node wifi/scan=wifi_fix_node,/backend_node; implies "
                             "--wait-for-subscribers")


def parse_remaps(items: list[str]) -> dict[str, str]:
    out = {}
    for item in items:
        old, sep, new = item.partition(":=")
        if not sep or not old or not new:
            raise ConfigError(f"play.remap: expected OLD:=NEW, got {item!r}")
        out["/" + old.lstrip("/")] = "/" + new.lstrip("/")
    return out


class MinSubscribers:
    """How many subscribers ``--wait-for-subscribers`` waits for on a topic: a default for every
    topic and per-topic counts, each given by its full name or by a name relative to any namespace
    (``imu/data_raw`` matches ``/walk16/imu/data_raw``; the longest match wins)."""

    def __init__(self, items: list[str] | tuple[str, ...] = ()) -> None:
        self.default = 1
        self.per_topic: dict[str, int] = {}
        for item in items:
            name, sep, value = str(item).rpartition("=")
            try:
                n = int(value)
            except ValueError:
                n = -1
            if n < 0 or (sep and not name.strip("/")):
                raise ConfigError(f"play.min_subscribers: expected N or TOPIC=N with N >= 0, got {item!r}")
            if sep:
                self.per_topic[name if name.startswith("/") else name.strip("/")] = n
            else:
                self.default = n

    def __call__(self, topic: str) -> int:
        if topic in self.per_topic:
            return self.per_topic[topic]
        best = None
        for name, n in self.per_topic.items():
            if not name.startswith("/") and topic.endswith("/" + name) and (best is None or len(name) > len(best[0])):
                best = (name, n)
        return best[1] if best is not None else self.default

    def unused(self, topics: list[str]) -> list[str]:
        """Per-topic entries that match none of ``topics`` (a typo would otherwise wait for nothing)."""
        return sorted(name for name in self.per_topic
                      if not any(t == name or (not name.startswith("/") and t.endswith("/" + name)) for t in topics))


def latched(topic: str, recorded_qos: str) -> bool:
    """Whether ``topic`` is played transient_local: a latched contract topic, or recorded so."""
    _, rel = split_ns(topic, set(TOPICS))
    spec = TOPICS.get(rel)
    if spec is not None:
        return spec.qos == Qos.LATCHED
    profiles = parse_qos_yaml(recorded_qos)
    return bool(profiles) and all(p.get("durability") == "transient_local" for p in profiles)


class PlayerNode(Node):
    """Publishes the messages of bags at bag-time pace (see module docstring)."""

    def __init__(self, bags: list[Path], *, rate: float = 1.0, loop: bool = False, clock_hz: float = 0.0,
                 topics: list[str] | None = None, remap: dict[str, str] | None = None,
                 start_offset_s: float = 0.0, **node_kwargs: Any) -> None:
        super().__init__(NODE_NAME, **node_kwargs)
        if not rate > 0:
            raise ConfigError(f"play.rate: expected > 0, got {rate}")
        if clock_hz < 0:
            raise ConfigError(f"play.clock: expected >= 0 Hz, got {clock_hz}")
        if start_offset_s < 0:
            raise ConfigError(f"play.start_offset: expected >= 0 s, got {start_offset_s}")
        self.bags, self.rate, self.loop, self.clock_hz = list(bags), float(rate), loop, float(clock_hz)
        self.start_offset_ns = int(round(start_offset_s * 1e9))
        self.remap = dict(remap or {})
        info = bag_info(self.bags)
        if topics is not None:
            missing = sorted(set(topics) - set(info))
            if missing:
                self.get_logger().warning(f"topics not in the bag(s): {missing}")
            info = {k: v for k, v in info.items() if k in set(topics)}
        if not info:
            raise BagError(f"nothing to play in {[str(b) for b in self.bags]}")
        self._pubs: dict[str, Any] = {}
        for name in sorted(info):
            t = info[name]
            out = self.remap.get(name, name)
            keep = latched(out, t.qos_yaml) or latched(name, t.qos_yaml)
            qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1 if keep else PUB_DEPTH,
                             reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL if keep else DurabilityPolicy.VOLATILE)
            try:
                cls = msg_class(t.type)
            except (ImportError, AttributeError, ValueError):
                self.get_logger().warning(f"{name}: type {t.type} is not installed here; not played")
                continue
            self._pubs[name] = self.create_publisher(cls, out, qos)
            self.get_logger().info(f"{name}{' -> ' + out if out != name else ''} [{t.type}] {t.count} msgs"
                                   f"{' (transient_local)' if keep else ''}")
        self.topics = sorted(self._pubs)
        if not self.topics:
            raise BagError("none of the bag's message types is installed here")
        self._clock_pub = (self.create_publisher(Clock, "/clock", QoSProfile(depth=10)) if self.clock_hz > 0
                           else None)
        self.published = 0
        self.loops = 0
        self.last_bag_ns: int | None = None          # log time of the last message played
        self._diag_pub = self.create_publisher(DiagnosticArray, "/diagnostics", qos_profile(Qos.RELIABLE))
        self._next_diag = 0.0
        self.play_s = 0.0                # wall time of the playback (after any waiting)
        self.short: dict[str, tuple[int, int]] = {}   # topic -> (subscribers, asked for) when playing started
        self.no_consumer: dict[str, list[str]] = {}   # topic -> named consumers missing when playing started

    def wait_for_subscribers(self, timeout_s: float, minimum: MinSubscribers | None = None,
                             consumers: Consumers | None = None) -> bool:
        """Block until every played topic has its subscribers (``minimum(topic)``, by default one)
        and its named ``consumers`` (each has a subscription in the graph and every subscription in
        the graph is matched), and the counts have not changed for ``SUBSCRIBERS_SETTLE_S`` (a
        recorder with ``-a`` subscribes to the topics one after another, after the nodes did), or
        until the timeout. Logs the count of every topic when it returns; topics still short are a WARN."""
        need = minimum or MinSubscribers()
        consumers = consumers or Consumers()
        for name in need.unused(self.out_topics()) + consumers.unused(self.out_topics()):
            self.get_logger().warning(f"--min-subscribers/--consumers {name}: no played topic has that name")
        want = {t: need(self._pubs[t].topic_name) for t in self._pubs}
        named = {t: consumers(self._pubs[t].topic_name) for t in self._pubs}

        def absent() -> dict[str, list[str]]:
            out = {}
            for t, nodes in named.items():
                if not nodes:
                    continue
                infos = self.get_subscriptions_info_by_topic(self._pubs[t].topic_name)
                missing = missing_consumers(nodes, [(i.node_name, i.node_namespace) for i in infos])
                if not missing and self._pubs[t].get_subscription_count() < len(infos):
                    missing = ["(a subscription not matched yet)"]
                if missing:
                    out[self._pubs[t].topic_name] = missing
            return out
        end = time.monotonic() + timeout_s
        last: list[int] | None = None
        since = time.monotonic()
        while time.monotonic() < end and rclpy.ok(context=self.context):
            check_stop()
            counts = [p.get_subscription_count() for p in self._pubs.values()]
            if counts != last:
                last, since = counts, time.monotonic()
            elif (all(c >= want[t] for t, c in zip(self._pubs, counts))
                  and time.monotonic() - since >= SUBSCRIBERS_SETTLE_S and not absent()):
                break
            time.sleep(0.02)
        counts = {t: p.get_subscription_count() for t, p in self._pubs.items()}
        self.get_logger().info("subscribers when playing starts: " + ", ".join(
            f"{self._pubs[t].topic_name} {n}" + (f" (of {want[t]})" if n < want[t] else "") for t, n in counts.items()))
        self.short = {self._pubs[t].topic_name: (n, want[t]) for t, n in counts.items() if n < want[t]}
        self.no_consumer = absent()
        if self.short:
            self.get_logger().warning(
                "playing with fewer subscribers than asked on " + ", ".join(
                    f"{t} ({n} of {w})" for t, (n, w) in self.short.items())
                + ": a subscriber that matches later misses the first messages")
        observed = [self._pubs[t].topic_name for t in self._pubs if not named[t] and met_by_observers(
            want[t], [(i.node_name, i.node_namespace)
                      for i in self.get_subscriptions_info_by_topic(self._pubs[t].topic_name)])]
        if observed:
            self.get_logger().warning(
                "the subscriber count of " + ", ".join(observed) + " was met by the view or the recorder, which "
                "consume nothing: name the consuming nodes with --consumers TOPIC=NODE so they miss nothing")
        if self.no_consumer:
            self.get_logger().warning(
                f"playing after {timeout_s:g} s without the consumers of " + ", ".join(
                    f"{t} ({', '.join(m)})" for t, m in self.no_consumer.items())
                + ": they miss the first messages")
        return not self.short and not self.no_consumer

    def out_topics(self) -> list[str]:
        """The played topics under the names they are published as (after ``--remap``)."""
        return [p.topic_name for p in self._pubs.values()]

    def diagnostics(self, now_ns: int) -> DiagnosticArray:
        """The player's DiagnosticStatus: published count, progress, topics nobody subscribes to."""
        alone = [t for t, p in self._pubs.items() if p.get_subscription_count() == 0]
        values = {"published": str(self.published), "topics": str(len(self._pubs)), "rate": f"{self.rate:g}",
                  "loops": str(self.loops), "last_bag_stamp_ns": str(self.last_bag_ns or ""),
                  "without_subscribers": ", ".join(alone),
                  "started_short_of_subscribers": ", ".join(f"{t} ({n} of {w})" for t, (n, w) in self.short.items()),
                  "started_without_consumers": "; ".join(f"{t} ({', '.join(m)})" for t, m in self.no_consumer.items()),
                  "bags": ", ".join(str(b) for b in self.bags)}
        level, message = ((1, f"{len(alone)} topic(s) played without a subscriber") if alone else
                          (1, f"{len(self.short)} topic(s) started with fewer subscribers than asked") if self.short
                          else (1, f"{len(self.no_consumer)} topic(s) started without their consumers")
                          if self.no_consumer
                          else (0, "ok"))
        return status_array(self.get_fully_qualified_name(), level, message, values, now_ns)

    def _maybe_diagnostics(self, force: bool = False) -> None:
        now = time.monotonic()
        if force or now >= self._next_diag:
            self._next_diag = now + DIAGNOSTICS_PERIOD_S
            self._diag_pub.publish(self.diagnostics(time.time_ns()))

    def _publish_clock(self, bag_ns: int) -> None:
        if self._clock_pub is not None:
            msg = Clock()
            msg.clock.sec, msg.clock.nanosec = divmod(int(bag_ns), 1_000_000_000)
            self._clock_pub.publish(msg)

    def play_once(self) -> bool:
        """Play the bags once; False if interrupted (context shut down)."""
        first: int | None = None
        wall0 = 0.0
        clock_period = 1.0 / self.clock_hz if self.clock_hz > 0 else 0.0
        next_clock = 0.0
        for m in read_raw(self.bags, self.topics):
            if first is None:
                first = m.stamp_ns + self.start_offset_ns
                wall0 = time.monotonic()
                next_clock = wall0
            if m.stamp_ns < first:
                continue
            target = wall0 + (m.stamp_ns - first) * 1e-9 / self.rate
            while True:
                check_stop()
                if not rclpy.ok(context=self.context):
                    return False
                now = time.monotonic()
                if clock_period and now >= next_clock:
                    self._publish_clock(min(first + int((now - wall0) * self.rate * 1e9), m.stamp_ns))
                    next_clock += clock_period
                    if next_clock < now:          # fell behind (slow machine): don't burst
                        next_clock = now + clock_period
                if now >= target:
                    break
                self._maybe_diagnostics()
                wake = min(target, next_clock) if clock_period else target
                time.sleep(max(0.0, min(wake - now, 0.05)))
            self._pubs[m.topic].publish(m.data)
            self.published += 1
            self.last_bag_ns = m.stamp_ns
            self._maybe_diagnostics()
        if first is None:
            self.get_logger().warning("no message at or after the start offset")
        return True

    def play(self) -> None:
        t0 = time.monotonic()
        while self.play_once() and self.loop:
            self.loops += 1
            self.get_logger().info("looping")
        self.play_s = time.monotonic() - t0
        self._maybe_diagnostics(force=True)
        for pub in list(self._pubs.values()) + ([self._clock_pub] if self._clock_pub else []):
            if rclpy.ok(context=self.context):
                pub.wait_for_all_acked(Duration(seconds=2.0))


def check_options(options: argparse.Namespace) -> None:
    """Reject bad options before touching DDS."""
    if not options.rate > 0:
        raise ConfigError(f"play.rate: expected > 0, got {options.rate}")
    if options.clock < 0:
        raise ConfigError(f"play.clock: expected >= 0 Hz, got {options.clock}")
    if options.start_offset < 0:
        raise ConfigError(f"play.start_offset: expected >= 0 s, got {options.start_offset}")
    for bag in bag_files(options.bags):
        if not bag.is_file():
            raise BagError(f"bag {bag} does not exist" + ("" if bag.is_absolute() else f" (in {Path.cwd()})"))
    parse_remaps(options.remap)
    MinSubscribers(options.min_subscribers)
    Consumers(options.consumers)


def run(options: argparse.Namespace, ros_args: list[str] | None = None) -> int:
    check_options(options)
    remap = parse_remaps(options.remap)
    # indoor-loc passes no ROS arguments: rcl must not parse the command line (OLD:=NEW remaps).
    # rclpy's signal handlers are off: a signal sets a flag that playback checks between two
    # messages (an exception raised by a signal handler inside an rclpy call can come out as a
    # RuntimeError and a traceback instead of a clean stop).
    rclpy.init(args=ros_args if ros_args is not None else sys.argv[:1], signal_handler_options=SignalHandlerOptions.NO)
    node = None
    old = raise_on_signals()
    try:
        node = PlayerNode(list(options.bags), rate=options.rate, loop=options.loop, clock_hz=options.clock,
                          topics=options.topics, remap=remap, start_offset_s=options.start_offset)
        if options.wait_for_subscribers > 0 or options.min_subscribers or options.consumers:
            node.wait_for_subscribers(options.wait_for_subscribers or 30.0, MinSubscribers(options.min_subscribers),
                                      Consumers(options.consumers))
        if options.delay > 0:
            end = time.monotonic() + options.delay
            while (left := end - time.monotonic()) > 0:
                check_stop()
                time.sleep(min(left, 0.05))
        node.play()
        print(f"played {node.published} messages in {node.play_s:.2f} s", file=sys.stderr)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        ignore_signals(old)
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
        restore_signals(old)
    return 0


def main(args: list[str] | None = None) -> int:
    """``player`` executable: same options as ``indoor-loc play``, plus ``--ros-args ...``."""
    return run_option_node("player", __doc__.splitlines()[0], add_arguments, run, args)


if __name__ == "__main__":
    sys.exit(main())
