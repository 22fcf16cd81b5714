"""A reliable subscription stuck behind a sample DDS refused, found and made anew (the stage nodes'
inputs, :mod:`indoor_loc.nodes.inputs`, and the recorder).

Fast DDS refuses a DATA submessage whose serialized payload is empty
(``MessageReceiver::proc_Submsg_Data``: "Serialized Payload value invalid"), so a reliable reader
never acknowledges that sample, asks for it again and again, and, delivering in order, holds back
every later sample of that publisher until the publisher's history no longer has it (``depth``
samples later: 1 000 for the nodes' reliable outputs, 10 000 for the player's; for a slow topic,
never). A best-effort reader just skips it (one lost message).

So when a reliable subscription with one publisher stalls, the node listens beside it best effort
(a *probe*, raw). If the probe hears that publisher's numbers going on past the next one while the
subscription has nothing queued, the subscription is stuck: the sample it waits for and the ones it
holds back are counted (:meth:`StuckGuard._refused`), the subscription is made anew (a new reader
starts at the publisher's next sample) and, until it delivers, the probe's messages are handed on,
each number once. The probe is closed as soon as the subscription delivers again or the publisher
leaves. While it is open, the publisher sees one more matched subscription.
"""
from __future__ import annotations

from typing import Any, Callable

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from indoor_loc.nodes.liveness import STALLED, InputWatch

#: QoS of a probe: best effort (it never waits for a sample), as deep as a burst between two looks.
PROBE_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100, reliability=ReliabilityPolicy.BEST_EFFORT,
                       durability=DurabilityPolicy.VOLATILE)


def seq_of(info: Any) -> int | None:
    """The publisher's sequence number of a message (rclpy message info), None if unknown."""
    return info.get("publication_sequence_number") if isinstance(info, dict) else None


class Watched:
    """One subscribed topic: its subscription, liveness watch and, while one is open, its probe."""

    def __init__(self, resolved: str, cls: type, watch: InputWatch) -> None:
        self.resolved = resolved
        self.cls = cls
        self.watch = watch
        self.sub: Any = None
        self.callback: Callable[[Any, Any], None] = lambda data, info: None
        self.probe: Any = None
        self.probe_count = 0                # messages the subscription had delivered when the probe opened
        self.recovering = False             # made anew, no message from it yet: the probe's are handed on
        self.skip_upto: int | None = None   # numbers up to this came through the probe already

    def taken_from_subscription(self, seq: int | None) -> bool:
        """The subscription delivered a message numbered ``seq``: closes the way back to normal
        (the caller closes the probe); False for a number the probe already brought."""
        self.recovering = False
        if self.skip_upto is not None and seq:
            if seq <= self.skip_upto:
                return False
            self.skip_upto = None
        return True


class StuckGuard:
    """Mixin of a Node with :class:`Watched` subscriptions (see the module doc). The node provides
    :meth:`_deliver` (hand a message on as its subscription's callback would, ``probe=True`` for the
    probe's), :meth:`_refused` (count the refused and held-back messages) and calls
    :meth:`_guard_stuck` about once a second per subscription, and :meth:`_taken` for every message
    its subscription delivers."""

    get_logger: Callable[[], Any]
    get_clock: Callable[[], Any]
    create_subscription: Callable[..., Any]
    destroy_subscription: Callable[[Any], bool]

    def _deliver(self, w: Any, data: bytes, info: Any, *, probe: bool = False) -> None:
        raise NotImplementedError

    def _refused(self, w: Any, refused_seq: int, held: int, now_ns: int) -> None:
        raise NotImplementedError

    def _subscribe_again(self, w: Watched, qos: QoSProfile) -> Any:
        """A new subscription for ``w`` with the old one's QoS and callback."""
        return self.create_subscription(w.cls, w.resolved, w.callback, qos, raw=True)

    def _taken(self, w: Watched, info: Any) -> bool:
        """A message from ``w``'s subscription: closes the probe; False if the probe brought it already."""
        if w.probe is not None:
            self._close_probe(w)                 # the subscription delivers again
        return w.taken_from_subscription(seq_of(info))

    def _guard_stuck(self, w: Watched, gids: frozenset[bytes], now_ns: int) -> None:
        """About once a second: a stalled reliable subscription with one publisher gets a probe; a
        probe whose publisher left is closed."""
        if w.probe is not None:
            if not gids:
                self._close_probe(w)
                w.recovering = False
        elif (len(gids) == 1 and w.watch.state(now_ns) == STALLED
              and w.sub.qos_profile.reliability == ReliabilityPolicy.RELIABLE):
            w.probe_count = w.watch.count
            w.probe = self.create_subscription(w.cls, w.resolved, lambda data, info: self._on_probe(w, data, info),
                                               PROBE_QOS, raw=True)
            self.get_logger().info(f"{w.resolved}: stalled while its publisher is in the graph; listening beside "
                                   f"the subscription (best effort) for whether it still sends")

    def _close_probe(self, w: Watched) -> None:
        if w.probe is not None:
            self.destroy_subscription(w.probe)
            w.probe = None

    def _drain(self, w: Watched) -> int:
        """Hand on what is queued on the subscription now; returns how many there were."""
        n = 0
        while True:
            with w.sub.handle:
                got = w.sub.handle.take_message(w.sub.msg_type, True)
            if got is None:
                return n
            n += 1
            self._deliver(w, got[0], got[1])

    def _on_probe(self, w: Watched, data: bytes, info: Any) -> None:
        if w.probe is None:
            return
        seq = seq_of(info)
        last = w.watch.gaps.last
        if w.recovering:
            if seq and (last is None or seq > last):
                w.skip_upto = seq                # before: handing it on may take the subscription's queue
                self._deliver(w, data, info, probe=True)
            return
        if w.watch.count > w.probe_count or self._drain(w):
            self._close_probe(w)                 # the subscription delivers after all
            return
        if not seq or last is None or seq <= last + 1:
            return                               # nothing says it stopped short yet
        self._resubscribe(w, last, seq)
        w.skip_upto = seq
        self._deliver(w, data, info, probe=True)

    def _resubscribe(self, w: Watched, last: int, seq: int) -> None:
        """The subscription delivered its publisher's #``last`` and nothing since, while the probe
        hears #``seq``: #``last + 1`` is a sample it cannot take, those up to #``seq - 1`` are held
        back behind it; a new subscription (same QoS, same callback) takes over."""
        held = seq - last - 2
        self._refused(w, last + 1, max(held, 0), self.get_clock().now().nanoseconds)
        w.watch.gaps.last = seq - 1
        qos = w.sub.qos_profile
        self.destroy_subscription(w.sub)
        w.sub = self._subscribe_again(w, qos)
        w.watch.resubscribed += 1
        w.recovering = True
        self.get_logger().warning(
            f"{w.resolved}: the subscription stopped at its publisher's message #{last + 1} (refused by DDS, an "
            f"empty sample?) while the publisher went on to #{seq}; {max(held, 0)} message(s) held back behind it "
            f"are lost; subscribed anew")
