"""Whether an input reaches the node whole: messages lost on the way, from the publisher's
sequence numbers."""
from __future__ import annotations

from typing import Any, Callable


class SequenceGaps:
    """Messages lost on the way to a subscription, from gaps in the publisher's sequence numbers
    (``publication_sequence_number`` of the message info; DDS numbers each writer's samples 1, 2,
    3...). rclpy does not say which publisher a message came from, so gaps are counted only while
    the topic has a single publisher (``publishers`` is refreshed by the caller; a count of 0 is
    one taken before the publisher was seen: the message just taken has one)."""

    def __init__(self, on_late_start: Callable[[int], None] | None = None) -> None:
        self.last: int | None = None
        self.publishers = 1
        self._started = False
        #: called once if the first message taken is not its publisher's first (``seq - 1`` were
        #: published before this subscription matched: not a loss on a volatile topic, but what a
        #: replay started too early looks like)
        self.on_late_start = on_late_start

    def gap(self, info: Any, recount: Callable[[], int] | None = None) -> int:
        """Messages missing before this one; ``recount()`` (the topic's publisher count now) is
        asked before a gap is reported, so a publisher that joined since the last refresh (its
        numbers interleave) is not mistaken for a loss."""
        n = self._gap(info)
        if n and recount is not None:
            self.publishers = recount()
            if self.publishers > 1:
                self.last = None
                return 0
        return n

    def _gap(self, info: Any) -> int:
        seq = info.get("publication_sequence_number") if isinstance(info, dict) else None
        if self.publishers > 1:
            self.last = None
            return 0
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
