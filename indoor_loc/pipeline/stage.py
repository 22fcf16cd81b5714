"""Stage base class: dispatch, error containment and diagnostics counters.

Subclasses declare ``NODE_NAME``, ``PARAMS`` (a Params dataclass), ``inputs()`` and ``outputs()``
and implement one handler per input topic returning ``[(relative_topic, message), ...]``.
``Stage.process`` never raises on a message: an :class:`InvalidMessageError` is counted under its
reason and dropped; any other exception is counted as ``internal_error`` and reported in
``last_error`` (the node logs it, throttled). Nothing else is lost: the stage state is unchanged
by a rejected message because handlers validate (via msg_adapters) before touching state.
"""
from __future__ import annotations

import traceback
from collections import Counter, defaultdict
from dataclasses import dataclass, field
from typing import Any, Callable, ClassVar

from indoor_loc.contract import Qos
from indoor_loc.errors import InvalidMessageError

Output = tuple[str, Any]  # (relative topic, message)


@dataclass(frozen=True)
class Port:
    topic: str        # relative topic name (contract.TOPICS key or a parameterised name)
    type: str         # "pkg/msg/Name"
    qos: Qos


@dataclass
class TopicStats:
    count: int = 0
    first_ns: int | None = None
    last_ns: int | None = None

    def rate_hz(self) -> float:
        if self.count < 2 or self.first_ns is None or self.last_ns is None or self.last_ns <= self.first_ns:
            return 0.0
        return (self.count - 1) / ((self.last_ns - self.first_ns) * 1e-9)


@dataclass
class StageDiagnostics:
    received: dict[str, TopicStats] = field(default_factory=lambda: defaultdict(TopicStats))
    published: Counter = field(default_factory=Counter)
    rejected: Counter = field(default_factory=Counter)   # reason -> count
    last_error: str = ""
    last_error_reason: str = ""

    def summary(self) -> dict[str, str]:
        """Flat key/values for a DiagnosticStatus."""
        out: dict[str, str] = {}
        for topic, st in sorted(self.received.items()):
            out[f"in.{topic}.count"] = str(st.count)
            out[f"in.{topic}.rate_hz"] = f"{st.rate_hz():.2f}"
            out[f"in.{topic}.last_stamp_ns"] = str(st.last_ns if st.last_ns is not None else "")
        for topic, n in sorted(self.published.items()):
            out[f"out.{topic}.count"] = str(n)
        for reason, n in sorted(self.rejected.items()):
            out[f"rejected.{reason}"] = str(n)
        out["rejected.total"] = str(sum(self.rejected.values()))
        return out


class Stage:
    NODE_NAME: ClassVar[str] = "stage"
    PARAMS: ClassVar[type] = object

    def __init__(self, params: Any, *, namespace: str = "") -> None:
        self.params = params
        self.namespace = namespace
        self.diag = StageDiagnostics()
        self._handlers: dict[str, Callable[[Any, int], list[Output]]] = {}

    # -- declared by subclasses ---------------------------------------------------------------
    def inputs(self) -> list[Port]:
        raise NotImplementedError

    def outputs(self) -> list[Port]:
        raise NotImplementedError

    def on(self, topic: str, handler: Callable[[Any, int], list[Output]]) -> None:
        """Register ``handler(msg, recv_ns) -> outputs`` for an input topic (call in __init__)."""
        self._handlers[topic] = handler

    def handles(self, topic: str) -> bool:
        """True if the stage takes messages on this (relative) input topic."""
        return topic in self._handlers

    def tick(self, now_ns: int) -> list[Output]:
        """Periodic work (timers); called about once a second live and in bag time offline."""
        return []

    def finish(self) -> list[Output]:
        """End of input (offline runs, node shutdown): flush whatever is pending."""
        return []

    def extra_diagnostics(self) -> dict[str, str]:
        """Stage-specific key/values added to the node's DiagnosticStatus."""
        return {}

    # -- driver entry point ------------------------------------------------------------------------
    def process(self, topic: str, msg: Any, recv_ns: int) -> list[Output]:
        """Handle one message. Never raises: rejected messages are counted and dropped."""
        handler = self._handlers.get(topic)
        if handler is None:
            self._reject("unknown_topic", f"no handler for {topic!r}")
            return []
        stats = self.diag.received[topic]
        stats.count += 1
        stats.first_ns = recv_ns if stats.first_ns is None else stats.first_ns
        stats.last_ns = recv_ns
        try:
            outs = handler(msg, recv_ns)
        except InvalidMessageError as err:
            self._reject(err.reason, f"{topic}: {err}")
            return []
        except Exception as err:  # noqa: BLE001 - a node never dies on a message
            self._reject("internal_error", f"{topic}: {type(err).__name__}: {err}\n{traceback.format_exc(limit=4)}")
            return []
        for out_topic, _ in outs:
            self.diag.published[out_topic] += 1
        return outs

    def run_tick(self, now_ns: int) -> list[Output]:
        """:meth:`tick` for drivers: an exception is counted as ``internal_error`` (never escapes
        the timer or aborts an offline run); what the stage published before is kept."""
        return self._guarded("tick", lambda: self.tick(now_ns))

    def run_finish(self) -> list[Output]:
        """:meth:`finish` for drivers, guarded like :meth:`run_tick`."""
        return self._guarded("finish", self.finish)

    def _guarded(self, what: str, fn: Callable[[], list[Output]]) -> list[Output]:
        try:
            outs = fn()
        except Exception as err:  # noqa: BLE001 - a stage bug must not end the node or the run
            self._reject("internal_error", f"{what}(): {type(err).__name__}: {err}\n{traceback.format_exc(limit=4)}")
            return []
        for out_topic, _ in outs:
            self.diag.published[out_topic] += 1
        return outs

    def _reject(self, reason: str, detail: str) -> None:
        self.diag.rejected[reason] += 1
        self.diag.last_error = detail
        self.diag.last_error_reason = reason
