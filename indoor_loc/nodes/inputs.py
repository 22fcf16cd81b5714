"""The inputs of a :class:`~indoor_loc.nodes.stage_node.StageNode`: one :class:`Input` per subscribed
topic (per user for a multi-user stage), and how their messages reach the stage.

- Every input is subscribed *raw* and deserialised here, so a sample that does not decode (empty,
  truncated, garbage) is counted as ``undecodable`` and dropped. A deserialising subscription would
  drop it inside the middleware without a word (``rmw_fastrtps`` skips a sample its type support
  cannot read), leaving at most a sequence gap.
- Liveness: each input has an :class:`~indoor_loc.nodes.liveness.InputWatch` (flowing, stalled,
  upstream restarts, lost messages), fed with every message and, about once a second, with the
  topic's publishers in the graph (:meth:`InputsMixin._watch_inputs`).
- A reliable subscription stuck behind a sample DDS refused (an empty one) is found with a probe and
  made anew (:mod:`indoor_loc.nodes.stuck`); the sample it waited for is counted ``undecodable``, the
  ones it held back as lost.
- Fast path: an input the stage takes in runs (``Stage.batch_handles``) of a type
  :mod:`indoor_loc.bag.bulk` decodes is handed over in runs (see :meth:`InputsMixin._take_raw`).
"""
from __future__ import annotations

import heapq
import struct
from typing import Any, Callable

from rclpy.qos import QoSProfile
from rclpy.serialization import deserialize_message

from indoor_loc.bag.bulk import BULK_TYPES, bulk_items
from indoor_loc.contract import join_ns, msg_class
from indoor_loc.nodes.liveness import InputWatch, SequenceGaps
from indoor_loc.nodes.stuck import StuckGuard, Watched
from indoor_loc.pipeline.stage import Port, namespace_of_user
from msg_adapters.time import header_ns

#: Raw sensor inputs (the fast path): at most this many messages are taken from the subscriptions
#: per callback, so one burst cannot hold up timers and other inputs for long.
TAKE_MAX = 2048

Booked = tuple[int, int, bytes]     # (header stamp ns, node-clock receive ns, data) of a raw message


class Input(Watched):
    """One subscribed input topic of a stage: its port and user (multi-user stages) besides the
    subscription, watch and probe of :class:`~indoor_loc.nodes.stuck.Watched`."""

    def __init__(self, port: Port, resolved: str, user: str | None, fast: bool, watch: InputWatch) -> None:
        super().__init__(resolved, msg_class(port.type), watch)
        self.port = port
        self.topic = port.topic             # the stage's (relative) name
        self.user = user
        self.fast = fast


def _cdr_stamp_ns(data: bytes) -> int:
    """``header.stamp`` (ns) of a little-endian CDR message that starts with a ``std_msgs/Header``
    (every bulk-decoded type); 0 when it cannot be read (the message then sorts first; the stage
    judges it)."""
    if len(data) < 12 or data[:2] != b"\x00\x01":
        return 0
    sec, nsec = struct.unpack_from("<iI", data, 4)
    return sec * 1_000_000_000 + nsec


class InputsMixin(StuckGuard):
    """The input side of StageNode (a mixin of it; uses its stage, clock, logger, ``_subscribe``,
    ``_publish`` and ``_log_rejections``)."""

    # provided by StageNode / rclpy Node
    stage: Any
    taken: int
    last_rx_ns: int
    sensor_reliability: str
    _inputs: dict[str, Input]
    _gaps: dict[str, SequenceGaps]
    _raw: dict[str, Input]
    _pubs: dict[str, Any]            # the node's own output publishers, by (relative) topic
    get_clock: Callable[[], Any]
    get_logger: Callable[[], Any]
    resolve_topic_name: Callable[..., str]
    get_publishers_info_by_topic: Callable[..., Any]
    create_subscription: Callable[..., Any]
    destroy_subscription: Callable[[Any], bool]
    _subscribe: Callable[..., Any]
    _publish: Callable[[list], None]
    _log_rejections: Callable[[], None]

    # -- opening and closing ---------------------------------------------------------------------------
    def _open_input(self, port: Port, resolved: str, user: str | None = None) -> Input:
        fast = self._batchable(port)
        # named as the stage counts it: ``imu/data_raw``, ``alice/pdr/odom`` (multi-user)
        watch = InputWatch(resolved.lstrip("/"), required=port.required, stream=port.stream,
                           on_late_start=self._late_start(resolved, port.topic, user))
        watch.publishers = lambda: self._publisher_gids(resolved)
        inp = Input(port, resolved, user, fast, watch)
        inp.callback = self._raw_callback(inp) if fast else self._message_callback(inp)
        inp.sub = self._subscribe(port, resolved, inp.callback, raw=True)
        self._inputs[resolved] = inp
        self._gaps[resolved] = watch.gaps
        if fast:
            self._raw[inp.topic] = inp
        return inp

    def _close_input(self, inp: Input) -> None:
        self._close_probe(inp)
        self.destroy_subscription(inp.sub)
        self._inputs.pop(inp.resolved, None)
        self._gaps.pop(inp.resolved, None)

    def _batchable(self, port: Port) -> bool:
        """Whether ``port`` is handled in runs: a per-user stage with a batch path for it
        (:meth:`Stage.batch_handles`) and a message type :func:`indoor_loc.bag.bulk.bulk_items` decodes."""
        return not self.stage.MULTI_USER and port.type in BULK_TYPES and self.stage.batch_handles(port.topic)

    def _late_start(self, topic: str, key: str, user: str | None = None) -> Callable[[int], None]:
        """Said once when an input's first message is not its publisher's first: normal when a node
        joins a running driver (INFO), input missed in a replay (``sensor_reliability: reliable``:
        WARN, and counted as lost; start the player once every consumer has matched, see
        ``--consumers``). Either way ``missed_at_start.<topic>`` in ``/diagnostics`` has the count."""
        def said(n: int) -> None:
            replay = self.sensor_reliability == "reliable"
            self.stage.count_missed_at_start(key, n, user)
            if replay:
                self.stage.count_lost(key, n, self.get_clock().now().nanoseconds, user)
            (self.get_logger().warning if replay else self.get_logger().info)(
                f"{self.resolve_topic_name(topic)}: the first message received is its publisher's #{n + 1}: {n} were "
                f"published before this subscription matched" + ("; a replay started too early" if replay else ""))
        return said

    # -- booking every message -----------------------------------------------------------------------------
    def _publisher_gids(self, topic: str) -> frozenset[bytes]:
        """The topic's publishers in the graph, this node's own left out: on an input the node also
        publishes (``imu_node``'s ``imu/data``) its own stream is no upstream (see :meth:`_own_echo`)."""
        me = (self.get_name(), self.get_namespace())
        return frozenset(bytes(i.endpoint_gid) for i in self.get_publishers_info_by_topic(topic)
                         if (i.node_name, i.node_namespace) != me)

    def _own_echo(self, inp: Input, data: Any) -> bool:
        """Whether a message on ``inp`` is this node's own output coming back (an input topic it also
        publishes, recognised by stamp as the stage does: ``Stage.echoes``). It is dropped before it is
        booked: not taken, not in the input's liveness, and its publisher's sequence numbers (this
        node's own, which the subscription sees only in part) never count as losses of the input.
        Booked, a node's echoes were counted as input taken beside what was sent to it, and a stalled
        echo stream read as hundreds of thousands lost (the soak's over-count, docs/benchmarks/soak.md)."""
        if self.stage.MULTI_USER or inp.topic not in self._pubs:
            return False
        stamp = _cdr_stamp_ns(data) if isinstance(data, (bytes, bytearray)) else header_ns(data)
        return bool(stamp) and self.stage.echoes(inp.topic, stamp)

    def _book(self, inp: Input, info: Any, *, probe: bool = False) -> int | None:
        """Count one message taken (liveness, sequence gaps, reception time); returns the node's
        clock now, or None for a message already processed (a number the probe brought)."""
        if not probe and not self._taken(inp, info):
            return None
        self.taken += 1
        self.last_rx_ns = int(info.get("received_timestamp") or 0) if isinstance(info, dict) else 0
        now_ns = self.get_clock().now().nanoseconds
        lost = inp.watch.message(info, now_ns)
        if inp.watch.fresh:          # a restarted upstream's first message: the stage starts its stream afresh
            self._publish(self.stage.run_upstream_restarted(inp.topic, inp.user))
            self._log_rejections()
        if lost:
            self.stage.count_lost(inp.topic, lost, now_ns, inp.user)
            self.get_logger().warning(f"{inp.resolved}: {lost} message(s) lost before reaching this node "
                                      f"({sum(self.stage.diag.lost.values())} so far)", throttle_duration_sec=5.0)
        return now_ns

    def _message_callback(self, inp: Input) -> Callable[[Any, Any], None]:
        def cb(data: Any, info: Any) -> None:
            self._on_message(inp, data, info)
        return cb

    def _on_message(self, inp: Input, data: Any, info: Any, *, probe: bool = False) -> None:
        """One message (CDR bytes, or a message already deserialised) for the stage."""
        if self._own_echo(inp, data):
            return
        now_ns = self._book(inp, info, probe=probe)
        if now_ns is None:
            return
        msg = data
        if isinstance(data, (bytes, bytearray)):
            try:
                msg = deserialize_message(bytes(data), inp.cls)
            except Exception as err:  # noqa: BLE001 - a node never dies on a message
                self.stage.reject_input("undecodable", f"{inp.resolved}: {len(data)} bytes: {type(err).__name__}: {err}",
                                        now_ns, inp.user)
                self._log_rejections()
                return
        self._publish(self.stage.process(inp.topic, msg, now_ns, inp.user))
        self._log_rejections()

    def _callback(self, topic: str, user: str | None = None) -> Callable[[Any, Any], None]:
        """The callback of the (per-message) input ``topic`` (of ``user``)."""
        return self._message_callback(self._inputs[self._resolved(topic, user)])

    @staticmethod
    def _resolved(topic: str, user: str | None) -> str:
        return join_ns(namespace_of_user(user), topic) if user else topic

    # -- fast path: raw sensor inputs handled in runs ----------------------------------------------
    def _raw_callback(self, inp: Input) -> Callable[[bytes, Any], None]:
        def cb(data: bytes, info: Any) -> None:
            booked = self._received(inp, data, info)
            self._take_raw({inp.topic: [booked]} if booked else {})
        return cb

    def _received(self, inp: Input, data: bytes, info: Any, *, probe: bool = False) -> Booked | None:
        """Book one raw message (:meth:`_book`); returns ``(header stamp ns, node-clock receive ns,
        data)``, None for one already processed or the node's own output coming back."""
        if self._own_echo(inp, data):
            return None
        now_ns = self._book(inp, info, probe=probe)
        return None if now_ns is None else (_cdr_stamp_ns(data), now_ns, data)

    def _take_raw(self, pending: dict[str, list[Booked]]) -> None:
        """Take every message already queued on the raw inputs (at most :data:`TAKE_MAX`), merge the
        topics in header-stamp order (each topic keeps its arrival order) and hand each run of one
        topic to the stage's batch path, decoded in bulk; a run that does not decode in bulk (or
        holds a message the adapter rejects) is deserialised and processed message by message, so
        every rejection is counted under its own reason as before."""
        n = sum(len(v) for v in pending.values())
        for topic, inp in self._raw.items():
            queue = pending.setdefault(topic, [])
            while n < TAKE_MAX:
                with inp.sub.handle:
                    got = inp.sub.handle.take_message(inp.sub.msg_type, True)
                if got is None:
                    break
                booked = self._received(inp, got[0], got[1])
                if booked is not None:
                    queue.append(booked)
                n += 1
        merged = heapq.merge(*([(stamp, topic, recv, data) for stamp, recv, data in q]
                               for topic, q in pending.items() if q), key=lambda m: m[0])
        run_topic: str | None = None
        run: list[tuple[int, bytes]] = []
        for _stamp, topic, recv, data in merged:
            if topic != run_topic and run:
                self._process_run(run_topic, run)   # type: ignore[arg-type]
                run = []
            run_topic = topic
            run.append((recv, data))
        if run:
            self._process_run(run_topic, run)       # type: ignore[arg-type]
        self._log_rejections()

    def _process_run(self, topic: str, run: list[tuple[int, bytes]]) -> None:
        inp = self._raw[topic]
        recv = [r for r, _ in run]
        items = bulk_items(inp.port.type, [d for _, d in run])
        if items is not None:
            self._publish([(t, m) for _, t, m in self.stage.process_batch(topic, items, recv)])
            return
        self._process_each(inp, topic, run, label=topic)

    def _process_each(self, inp: Any, topic: str, run: list[tuple[int, bytes]], *, label: str,
                      user: str | None = None) -> None:
        """A run's messages decoded and handled one by one (a run the bulk decoder did not take); one
        that does not decode is counted (``undecodable``, ``label`` naming its input), never raised."""
        for recv_ns, data in run:
            try:
                msg = deserialize_message(data, inp.cls)
            except Exception as err:  # noqa: BLE001 - a node never dies on a message
                self.stage.reject_input("undecodable", f"{label}: {len(data)} bytes: {type(err).__name__}: {err}",
                                        recv_ns, user)
                continue
            self._publish(self.stage.process(topic, msg, recv_ns, user))

    # -- liveness and stuck subscriptions -------------------------------------------------------------------
    def _watch_inputs(self, now_ns: int) -> None:
        """About once a second: each input's publishers in the graph (restarts, the count its sequence
        gaps need), and a stalled one looked into (:meth:`StuckGuard._guard_stuck`)."""
        for inp in list(self._inputs.values()):
            gids = self._publisher_gids(inp.resolved)
            inp.watch.publishers_seen(gids, now_ns)
            self._guard_stuck(inp, gids, now_ns)

    def _deliver(self, w: Any, data: bytes, info: Any, *, probe: bool = False) -> None:
        if w.fast:
            booked = self._received(w, data, info, probe=probe)
            self._take_raw({w.topic: [booked]} if booked else {})
        else:
            self._on_message(w, data, info, probe=probe)

    def _refused(self, w: Any, refused_seq: int, held: int, now_ns: int) -> None:
        """The sample a stuck subscription waited for is ``undecodable``; those it held back are lost."""
        self.stage.reject_input("undecodable", f"{w.resolved}: its publisher's message #{refused_seq} never arrived: "
                                f"DDS refused it (an empty sample) and the reliable subscription waited for it",
                                now_ns, w.user)
        if held:
            self.stage.count_lost(w.topic, held, now_ns, w.user)
        self._log_rejections()

    def _subscribe_again(self, w: Any, qos: QoSProfile) -> Any:
        return self._subscribe(w.port, w.resolved, w.callback, raw=True, qos=qos)
