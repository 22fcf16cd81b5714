"""Cross-topic stamp order: one user's messages of several topics taken in stamp order.

The time policy (:mod:`indoor_loc.pipeline.time_policy`) judges each topic on its own; a node takes
its topics side by side, in arrival order, so one topic's messages can come ahead of another's
(a 10 Hz barometer straight from the phone ahead of ``pdr/odom`` that the stepometer reports half
a second late; a fast replay; a loaded machine). A stage whose state depends on the order across
topics puts the messages of those topics in a :class:`ReorderBuffer`: a heap in stamp order (ties
by the caller's rank, then arrival) that releases the messages whose stamp every stream has
passed. The back-end (``backend_node``: ``pdr/odom``, ``wifi/scan``, ``wifi/fix``) and ``tll_pf``
(``pdr/odom`` and ``baro/pressure``) use it, each with its own release rule:

- the back-end: once the user's odometry is ``reorder_window_s`` past a message (or a newer scan
  ``max_scan_wait_s`` past a scan): :meth:`ReorderBuffer.head` / :meth:`ReorderBuffer.pop`;
- ``tll_pf``: the *watermark* rule of :meth:`ReorderBuffer.mark`: a message is due when every
  stream still flowing has reached its stamp; a stream more than the window behind the newest
  stamp of any stream counts as stopped (a phone standing in a lift reports no steps; a barometer
  that stopped), so nothing waits longer than the window for it.

A message older than what was already taken is *too late*: :meth:`ReorderBuffer.push` raises
``too_late`` (counted in ``dropped_late``) unless the caller asks to take it anyway.
"""
from __future__ import annotations

import heapq
from dataclasses import dataclass, field
from typing import Any

from indoor_loc.errors import InvalidMessageError


@dataclass
class ReorderBuffer:
    """A heap of ``(stamp, rank, seq, payload)``; ``taken_ns`` the newest stamp released,
    ``dropped_late`` the messages refused as older than it, ``newest`` each stream's newest stamp."""
    heap: list = field(default_factory=list)
    taken_ns: int | None = None
    dropped_late: int = 0
    newest: dict = field(default_factory=dict)
    _seq: int = 0

    def __len__(self) -> int:
        return len(self.heap)

    def late(self, stamp_ns: int) -> bool:
        """Whether a message of this stamp comes after a newer one was taken."""
        return self.taken_ns is not None and stamp_ns < self.taken_ns

    def refuse_late(self, stamp_ns: int, who: str, why: str) -> None:
        """``too_late`` (counted) for a message older than the newest taken."""
        if self.late(stamp_ns):
            self.dropped_late += 1
            raise InvalidMessageError("too_late", f"{who}stamp {stamp_ns} older than the newest taken "
                                                  f"{self.taken_ns}: {why}")

    def push(self, stamp_ns: int, rank: int, payload: Any, *, who: str = "", why: str = "out of stamp order") -> None:
        """Queue a message (``too_late`` if older than the newest taken: :meth:`refuse_late`)."""
        self.refuse_late(stamp_ns, who, why)
        self._seq += 1
        heapq.heappush(self.heap, (stamp_ns, rank, self._seq, payload))

    def note(self, stream: str, stamp_ns: int) -> None:
        """A message of ``stream`` stamped ``stamp_ns`` arrived (the watermark rule's input)."""
        old = self.newest.get(stream)
        self.newest[stream] = stamp_ns if old is None else max(old, stamp_ns)

    def mark(self, window_ns: int) -> int | None:
        """The stamp every stream still flowing has reached: the oldest newest stamp among the
        streams within ``window_ns`` of the newest of all (None before any message)."""
        if not self.newest:
            return None
        top = max(self.newest.values())
        return min(s for s in self.newest.values() if s >= top - window_ns)

    def head(self) -> tuple[int, int, Any] | None:
        """The oldest queued ``(stamp, rank, payload)``, or None."""
        if not self.heap:
            return None
        stamp, rank, _, payload = self.heap[0]
        return stamp, rank, payload

    def pop(self) -> tuple[int, int, Any]:
        """Take the oldest queued message: ``(stamp, rank, payload)``."""
        stamp, rank, _, payload = heapq.heappop(self.heap)
        self.taken_ns = stamp if self.taken_ns is None else max(self.taken_ns, stamp)
        return stamp, rank, payload

    def due(self, mark_ns: int | None) -> list[tuple[int, int, Any]]:
        """Take every queued message stamped at or before ``mark_ns`` (None: none), in stamp order."""
        out = []
        while self.heap and mark_ns is not None and self.heap[0][0] <= mark_ns:
            out.append(self.pop())
        return out

    def drain(self) -> list[tuple[int, int, Any]]:
        """Take everything queued, in stamp order (end of input, a restart)."""
        out = []
        while self.heap:
            out.append(self.pop())
        return out

    def clear(self) -> None:
        """Forget the queue, the streams and the newest taken (a user starting afresh; counters kept)."""
        self.heap.clear()
        self.newest.clear()
        self.taken_ns = None
