"""Whether an input reaches the node, and whole: messages lost on the way (gaps in the publisher's
sequence numbers, :class:`SequenceGaps`), and per input topic (:class:`InputWatch`) whether it is
flowing, how long since its last message, and how often its publisher restarted.

No rclpy here: the node hands in the message info, its clock and the publishers it sees in the
graph, so the rules are tested without DDS.
"""
from __future__ import annotations

from collections import deque
from typing import Any, Callable, NamedTuple

#: An input is *stalled* once it has had no message for this many of its mean periods ...
STALL_PERIODS = 3.0
#: ... and at least this long (ns, node clock): a slow or irregular input is not a stall at once.
STALL_FLOOR_NS = 2_000_000_000
#: Before its second message an input's period is unknown (a scan every 4 s or every 30 s): it is
#: stalled only after this long (ns).
STALL_UNKNOWN_PERIOD_NS = 30_000_000_000
#: Arrival times kept per input to measure its mean period (the newest ones).
PERIOD_WINDOW = 64

WAITING = "waiting"     # no message yet (or the node has no clock yet: sim time before /clock)
FLOWING = "flowing"     # the last message is recent
STALLED = "stalled"     # it was flowing and stopped: no message for longer than its stall limit
RECEIVED = "received"   # an occasional input (``Port.stream`` False) has had a message; never stalled
LEFT = "left"           # a multi-user stage's user who left (no publishers for its timeout): silence expected


class SequenceGaps:
    """Messages lost on the way to a subscription, from gaps in the publisher's sequence numbers
    (``publication_sequence_number`` of the message info; DDS numbers each writer's samples 1, 2,
    3...). ``publishers`` is refreshed by the caller; a count of 0 is one taken before the publisher
    was seen: the message just taken has one.

    rclpy does not say which publisher a message came from. With several publishers their numbers
    interleave, and each number is given to the publisher's run it can continue: the run whose last
    number is the largest below it (a number that continues none, while fewer runs than publishers
    are known, starts a run of its own; one below every run starts them afresh). Publishers whose
    numbers are far apart (a node's odometry beside a flood from another) are counted exactly; when
    their numbers are close some losses are missed, and rarely (a run mistaken for another at its
    start) one is counted that did not happen (:func:`interleaved_gaps`, ``test/test_node_base.py``)."""

    def __init__(self, on_late_start: Callable[[int], None] | None = None) -> None:
        self.last: int | None = None
        self.publishers = 1
        self.runs: list[int] = []        # with several publishers: the last number of each run
        self._started = False
        #: called once if the first message taken is not its publisher's first (``seq - 1`` were
        #: published before this subscription matched: not a loss on a volatile topic, but what a
        #: replay started too early looks like)
        self.on_late_start = on_late_start

    def gap(self, info: Any, recount: Callable[[], int] | None = None) -> int:
        """Messages missing before this one; ``recount()`` (the topic's publisher count now) is
        asked before a gap is reported, so a publisher that joined since the last refresh (its
        numbers interleave) is not mistaken for a loss."""
        before = self.last
        n = self._gap(info)
        if n and recount is not None:
            self.publishers = recount()
            if self.publishers > 1:          # a second publisher's numbers, not a loss: two runs
                self.runs = [r for r in (before, self.last) if r is not None]
                self.last = None
                return 0
        return n

    def _gap(self, info: Any) -> int:
        seq = info.get("publication_sequence_number") if isinstance(info, dict) else None
        if self.publishers > 1:
            self.last = None
            return interleaved_gaps(self.runs, seq, self.publishers) if seq else 0
        self.runs = []
        if not seq:
            return 0
        last, self.last = self.last, seq
        if not self._started:
            self._started = True
            if seq > 1 and self.on_late_start is not None:
                self.on_late_start(seq - 1)
        if last is None or seq <= last:          # first message, or a restarted publisher
            return 0
        return seq - last - 1


def interleaved_gaps(runs: list[int], seq: int, publishers: int) -> int:
    """Messages lost just before number ``seq`` of one of ``publishers`` publishers whose numbers
    interleave; ``runs`` (the last number of each publisher's run seen so far) is updated in place
    (see :class:`SequenceGaps`)."""
    below = [r for r in runs if r < seq]
    if below:
        best = max(below)
        if seq == best + 1 or len(runs) >= publishers:
            runs[runs.index(best)] = seq
            return seq - best - 1
    if len(runs) < publishers:           # a run not seen before (its numbers before it: not ours to count)
        runs.append(seq)
        return 0
    runs[:] = [seq]                      # below every run: a publisher restarted, which one is unknown
    return 0


class InputReport(NamedTuple):
    """One input's liveness as plain values (for ``/diagnostics``)."""
    topic: str
    state: str                 # WAITING, FLOWING, STALLED or RECEIVED
    age_s: float | None        # node-clock seconds since its last message (None before one)
    stall_after_s: float       # no message for longer than this is a stall
    required: bool
    restarts: int              # its publisher restarted (sequence numbers anew, or another publisher)
    last_restart_ns: int | None
    last_gap_s: float | None   # the latest stall that ended: seconds without a message
    resubscribed: int          # the subscription was made anew because it stopped delivering


class InputWatch:
    """Liveness of one input topic, on the node's clock (``now_ns``; 0 = no clock yet).

    - *state*: :data:`WAITING` before its first message, :data:`FLOWING`, or :data:`STALLED` once it
      has had no message for ``max(STALL_PERIODS x its mean period, STALL_FLOOR_NS)``
      (:data:`STALL_UNKNOWN_PERIOD_NS` before its second message); the mean period is measured over
      its last :data:`PERIOD_WINDOW` arrivals, afresh after each stall and after the clock went back.
    - *restarts* of its publisher: its sequence numbers starting again (at or below the last one
      taken; with several publishers only after a stall, since their numbers interleave), or, in
      the graph (:meth:`publishers_seen`), a publisher not seen before appearing once the one
      before left or the input stalled. Both signs of one restart count once. The messages lost at
      the end of the old stream cannot be known from sequence numbers; the gap (time without a
      message, ``last_gap_ns``) is kept instead.
    - *lost* messages: gaps in the sequence numbers (:class:`SequenceGaps`), except the first
      numbers of a new publisher.
    """

    def __init__(self, topic: str, *, required: bool = False, stream: bool = True,
                 on_late_start: Callable[[int], None] | None = None) -> None:
        self.topic = topic
        self.required = required
        self.stream = stream
        self.gaps = SequenceGaps(on_late_start)
        #: the topic's publisher GIDs in the graph now (set by the node; asked when the numbers jump)
        self.publishers: Callable[[], frozenset[bytes]] | None = None
        self.count = 0
        self.last_ns: int | None = None
        self._arrivals: deque[int] = deque(maxlen=PERIOD_WINDOW)
        self.restarts = 0
        self.last_restart_ns: int | None = None
        self.last_gap_ns: int | None = None
        self.resubscribed = 0
        self._known: frozenset[bytes] = frozenset()   # publishers (GIDs) in the graph at the last look
        self._had_publisher = False
        self._left = False               # a publisher left since the last one appeared
        self._expect_new = False         # a restart seen in the graph: its first message is still to come
        self._seq_restart = False        # a restart seen in the sequence numbers, not yet in the graph
        #: the message just booked (:meth:`message`) is the first of a restarted publisher's stream
        self.fresh = False

    # -- timing -------------------------------------------------------------------------------------
    def period_ns(self) -> float | None:
        """Mean time between its recent messages (ns), None before two."""
        a = self._arrivals
        return (a[-1] - a[0]) / (len(a) - 1) if len(a) >= 2 else None

    def stall_after_ns(self) -> int:
        period = self.period_ns()
        if period is None:
            return STALL_UNKNOWN_PERIOD_NS
        return max(int(STALL_PERIODS * period), STALL_FLOOR_NS)

    def _silent(self, now_ns: int) -> bool:
        """Whether the input has had no message for longer than its stall limit (a stream only)."""
        return (self.stream and bool(now_ns) and self.last_ns is not None
                and now_ns - self.last_ns > self.stall_after_ns())

    def state(self, now_ns: int) -> str:
        if not now_ns or not self.count:
            return WAITING
        if not self.stream:
            return RECEIVED
        return STALLED if self._silent(now_ns) else FLOWING

    def report(self, now_ns: int) -> InputReport:
        age = max(now_ns - self.last_ns, 0) * 1e-9 if now_ns and self.last_ns is not None else None
        gap = self.last_gap_ns * 1e-9 if self.last_gap_ns is not None else None
        return InputReport(self.topic, self.state(now_ns), age, self.stall_after_ns() * 1e-9, self.required,
                           self.restarts, self.last_restart_ns, gap, self.resubscribed)

    # -- messages -------------------------------------------------------------------------------------
    def message(self, info: Any, now_ns: int,
                publishers: Callable[[], frozenset[bytes]] | None = None) -> int:
        """Book one message taken (its rclpy message info; the node's clock now). ``publishers()``
        (the topic's publisher GIDs in the graph now; default :attr:`publishers`) is asked only when
        the numbers jump. Returns how many messages were lost just before it."""
        seq = info.get("publication_sequence_number") if isinstance(info, dict) else None
        last = self.gaps.last
        last_ns = self.last_ns
        if (seq is not None and last is not None and seq == last + 1 and now_ns and last_ns is not None
                and last_ns <= now_ns <= last_ns + STALL_FLOOR_NS and not self._expect_new):
            # the common case, kept cheap (every message of a 200 Hz input): the next number, soon
            # after the last message (a stall limit is never below the floor)
            self.count += 1
            self.gaps.last = seq
            self.last_ns = now_ns
            self._arrivals.append(now_ns)
            self.fresh = False
            return 0
        expected, restarts = self._expect_new, self.restarts
        publishers = publishers or self.publishers
        stopped = self._silent(now_ns)
        if seq and last is not None:
            if seq <= last:                          # numbered anew: another publisher
                if self.gaps.publishers <= 1 or stopped:
                    self._new_stream(now_ns)
            elif seq > last + 1 and publishers is not None:
                self.publishers_seen(publishers(), now_ns, stopped=stopped)
                if self._expect_new:                 # a new publisher's first numbers, not a loss
                    self.gaps.last = None
                    self._new_stream(now_ns)
        self._expect_new = False
        self.fresh = expected or self.restarts > restarts
        self._arrive(now_ns, stopped)
        return self.gaps.gap(info, (lambda: len(publishers())) if publishers is not None else None)

    def _arrive(self, now_ns: int, stopped: bool) -> None:
        self.count += 1
        if not now_ns:
            return
        if self.last_ns is not None and (now_ns < self.last_ns or stopped):
            if stopped:
                self.last_gap_ns = now_ns - self.last_ns
            self._arrivals.clear()                   # a new flow (or a new clock): its period afresh
        self.last_ns = now_ns
        self._arrivals.append(now_ns)

    def _new_stream(self, now_ns: int) -> None:
        if self._expect_new:                         # counted from the graph already
            self._expect_new = False
            return
        self.restarts += 1
        self.last_restart_ns = now_ns or None
        self._seq_restart = True

    # -- the graph ------------------------------------------------------------------------------------
    def publishers_seen(self, gids: frozenset[bytes], now_ns: int, *, stopped: bool | None = None) -> None:
        """The topic's publishers (GIDs) in the graph now (looked at about once a second)."""
        new, gone = gids - self._known, self._known - gids
        if gone:
            self._left = True
            self.gaps.runs = []              # which run was the one gone is unknown: runs afresh
        if new:
            stalled = self._silent(now_ns) if stopped is None else stopped
            if self._seq_restart:
                pass                                 # the restart its sequence numbers showed
            elif self._had_publisher and self.count and (self._left or stalled):
                self.restarts += 1
                self.last_restart_ns = now_ns or None
                self._expect_new = True
            self._left = False
        self._seq_restart = False
        self._known = gids
        self._had_publisher = self._had_publisher or bool(gids)
        self.gaps.publishers = len(gids)
