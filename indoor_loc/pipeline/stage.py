"""Stage base class: dispatch, error containment and diagnostics counters.

Subclasses declare ``NODE_NAME``, ``PARAMS`` (a Params dataclass), ``inputs()`` and ``outputs()``
and implement one handler per input topic returning ``[(relative_topic, message), ...]``.

Multi-user stages (``MULTI_USER = True``, e.g. the factor-graph back-end) are one instance for every
user: their ``inputs()`` are per-user topics taken from *every* user namespace (``/alice/pdr/odom``,
``/bob/pdr/odom``, ...), each handler is called as ``handler(msg, recv_ns, user)`` with the user's
name (the namespace without its leading slash, :func:`user_of_namespace`), and besides the fixed
``outputs()`` they publish per-user topics declared by ``user_outputs()`` as templates containing
``{user}`` (``backend/{user}/path``). ``finish_user(user)`` is called when a user's input ends (its
bag ends in a sequential offline run; its publishers leave the ROS graph live). Offline, one
instance serves all bags (``indoor-loc run --order merged|sequential``, see ``pipeline/offline.py``);
live, ``StageNode`` subscribes to the users of its ``users`` parameter or discovers them from the
graph and follows them as they come and go (``nodes/stage_node.py``).
``Stage.process`` never raises on a message: an :class:`InvalidInputError` (a message that breaks
the contract, or input the core refuses) is counted under its reason and dropped; any other
exception is counted as ``internal_error`` and reported in ``last_error`` (the node logs it,
throttled). Nothing else is lost: the stage state is unchanged by a rejected message because
handlers validate (via msg_adapters) before touching state.

Notices: what a stage has to say once, beyond its counters (a user's clock jumping back, say), it
hands to :meth:`Stage.notice`; the driver takes them with :meth:`Stage.take_notices` after each call
and says each once — the node as a WARN in its log (``nodes/stage_node.py``), ``indoor-loc run`` on stderr
(``pipeline/offline.py``).
"""
from __future__ import annotations

import functools
import struct
import time
import traceback
from collections import Counter, defaultdict, deque
from dataclasses import dataclass, field
from typing import Any, Callable, ClassVar

import numpy as np

from indoor_loc.contract import Qos
from indoor_loc.errors import InvalidInputError
from indoor_loc.pipeline.map_odom import MapOdom, MapOdomSpec
from indoor_loc.pipeline.time_policy import Held, Order, TimeParams, TimePolicy, Verdict
from msg_adapters.time import header_ns

Output = tuple[str, Any]  # (relative topic, message)


@dataclass(frozen=True)
class Port:
    topic: str        # relative topic name (contract.TOPICS key or a parameterised name)
    type: str         # "pkg/msg/Name"
    qos: Qos
    #: an input the stage cannot work without: a live node says ERROR when it stops (else WARN)
    required: bool = False
    #: an input that keeps coming while its upstream runs, so its silence is a stall; False for an
    #: occasional one (``initialpose``), which is never stalled
    stream: bool = True


def rate_hz(count: int, first_ns: int | None, last_ns: int | None) -> float:
    """Mean rate (Hz) of ``count`` events stamped from ``first_ns`` to ``last_ns``; 0 before two
    events or when no time passed."""
    if count < 2 or first_ns is None or last_ns is None or last_ns <= first_ns:
        return 0.0
    return (count - 1) / ((last_ns - first_ns) * 1e-9)


@dataclass
class TopicStats:
    count: int = 0
    first_ns: int | None = None
    last_ns: int | None = None

    def rate_hz(self) -> float:
        return rate_hz(self.count, self.first_ns, self.last_ns)


@dataclass
class StageDiagnostics:
    received: dict[str, TopicStats] = field(default_factory=lambda: defaultdict(TopicStats))
    published: Counter = field(default_factory=Counter)
    rejected: Counter = field(default_factory=Counter)   # reason -> count
    last_error: str = ""
    last_error_reason: str = ""
    lost: Counter = field(default_factory=Counter)        # input topic -> messages lost before us
    #: input topic -> messages its publisher sent before this subscription matched (a replay: also in ``lost``)
    missed_at_start: Counter = field(default_factory=Counter)
    last_reject_ns: int | None = None   # node clock at the latest rejection (recent-window health)
    last_loss_ns: int | None = None     # node clock when a loss was last seen
    last_internal_ns: int | None = None  # node clock of the latest internal error
    time_jumps: int = 0                 # confirmed jumps back (a user's state reset), see pipeline/time_policy.py
    now_ns: int | None = None           # node clock of the message or tick being handled

    def count_lost(self, topic: str, n: int, now_ns: int) -> None:
        """``n`` messages on ``topic`` never reached the stage (publication sequence gap)."""
        self.lost[topic] += n
        self.last_loss_ns = now_ns
    #: wall-clock processing time of the latest messages, s (bounded window): the node's per-update latency
    #: (offline batch runs add one entry per run: its mean per message)
    process_s: deque = field(default_factory=lambda: deque(maxlen=20000))

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
        for topic, n in sorted(self.lost.items()):
            out[f"lost.{topic}"] = str(n)
        out["lost.total"] = str(sum(self.lost.values()))
        for topic, n in sorted(self.missed_at_start.items()):
            out[f"missed_at_start.{topic}"] = str(n)
        out["time_jumps"] = str(self.time_jumps)
        if self.process_s:
            t = np.fromiter(self.process_s, float, len(self.process_s)) * 1e3
            p50, p99 = np.percentile(t, [50, 99])
            out["process_ms.p50"] = f"{p50:.2f}"
            out["process_ms.p99"] = f"{p99:.2f}"
            out["process_ms.max"] = f"{t.max():.2f}"
        return out


def _item_stamp(item: Any) -> int:
    """The stamp (ns) of a batch item: what an adapter returns (a sample with ``stamp_ns``, or a
    ``(stamp_ns, values)`` pair)."""
    stamp = getattr(item, "stamp_ns", None)
    return int(item[0] if stamp is None else stamp)


def _cdr_header_ns(data: bytes | bytearray) -> int | None:
    """``header.stamp`` (ns) of an output already serialised (little-endian CDR starting with a
    ``std_msgs/Header``, ``Stage.raw_outputs``); None when it cannot be read."""
    if len(data) < 12 or data[:2] != b"\x00\x01":
        return None
    sec, nsec = struct.unpack_from("<iI", data, 4)
    return sec * 1_000_000_000 + nsec


def user_of_namespace(namespace: str) -> str:
    """``/walk07`` -> ``walk07`` (the user name a multi-user stage sees; ``""`` for the root)."""
    return namespace.strip("/")


def namespace_of_user(user: str) -> str:
    """``walk07`` -> ``/walk07``."""
    return "/" + user.strip("/") if user.strip("/") else ""


#: Offline replay orders a multi-user stage may ask for (``Stage.offline_order``).
ORDERS = ("merged", "sequential")


class Stage:
    NODE_NAME: ClassVar[str] = "stage"
    PARAMS: ClassVar[type] = object
    #: One instance for all users (inputs from every namespace, handlers get the user, per-user outputs).
    MULTI_USER: ClassVar[bool] = False
    #: How each input topic's stamps must follow each other (:class:`~indoor_loc.pipeline.time_policy.Order`);
    #: a topic not named here: ``NONDECREASING``.
    STAMP_ORDER: ClassVar[dict[str, Order]] = {}
    #: Set by a live driver that publishes ``bytes`` as they are (the multi-user node): a stage may
    #: then return an output already serialised (CDR) where building the message costs much more.
    raw_outputs: bool = False
    #: True while the node handles a ``~/set_pose`` request (an acknowledged command: an initial pose
    #: given so is not held to the initialpose topic's rate bound, fusion/position_trust.CommandRate).
    set_pose_call: bool = False
    #: An estimator's ``map -> <user>/odom`` correction (pipeline/map_odom.py): motion topics, pose output,
    #: correction topic; None: the stage publishes none.
    MAP_ODOM: ClassVar[MapOdomSpec | None] = None

    def __init__(self, params: Any, *, namespace: str = "") -> None:
        self.params = params
        self.namespace = namespace
        self.diag = StageDiagnostics()
        self._handlers: dict[str, Callable[[Any, int], list[Output]]] = {}
        self._batch: dict[str, Callable[[Any, int], list[Output]]] = {}
        #: what the stage has to say (WARN), oldest first, until a driver takes it (:meth:`take_notices`)
        self.notices: list[str] = []
        #: the stamps every input message is judged by (the params' ``time`` group; pipeline/time_policy.py)
        self.time = TimePolicy(getattr(params, "time", None) or TimeParams())
        self.map_odom = MapOdom(self.MAP_ODOM) if self.MAP_ODOM is not None else None

    # -- declared by subclasses ---------------------------------------------------------------
    def inputs(self) -> list[Port]:
        raise NotImplementedError

    def outputs(self) -> list[Port]:
        raise NotImplementedError

    def user_outputs(self) -> list[Port]:
        """Multi-user stages: per-user output ports, topics containing ``{user}``."""
        return []

    def output_port(self, topic: str) -> Port | None:
        """The declared port a returned output topic belongs to (a fixed one or a user template)."""
        for p in self.outputs():
            if p.topic == topic:
                return p
        for p in self.user_outputs():
            head, _, tail = p.topic.partition("{user}")
            if topic.startswith(head) and topic.endswith(tail) and len(topic) > len(head) + len(tail):
                return p
        return None

    def finish_user(self, user: str) -> list[Output]:
        """Multi-user stages: this user's input has ended (flush and publish what is pending)."""
        return []

    def offline_order(self) -> str:
        """How an offline run should replay several bags for this stage: ``"merged"`` (all bags in
        one stamp order, users concurrent) or ``"sequential"`` (one bag after another)."""
        return "merged"

    def on(self, topic: str, handler: Callable[..., list[Output]]) -> None:
        """Register ``handler(msg, recv_ns) -> outputs`` for an input topic (call in __init__);
        multi-user stages: ``handler(msg, recv_ns, user)``."""
        self._handlers[topic] = handler

    def on_batch(self, topic: str, handler: Callable[[Any, int], list[Output]]) -> None:
        """Offer a batch path for ``topic`` (call in __init__; per-user stages only): ``handler(item,
        recv_ns)`` does what the topic's message handler does after its adapter, on what the adapter
        returns (an ``ImuSample`` for ``sensor_msgs/Imu``). See :meth:`process_batch`."""
        self._batch[topic] = handler

    def batch_handles(self, topic: str) -> bool:
        """True if :meth:`process_batch` takes runs of messages on this input topic."""
        return topic in self._batch and not self.MULTI_USER

    def process_batch(self, topic: str, items: list, recv_ns: list[int]) -> list[tuple[int, str, Any]]:
        """A run of messages on one topic, already decoded and validated in bulk into what the
        topic's adapter returns (:func:`indoor_loc.bag.bulk.bulk_items`), handled exactly as
        :meth:`process` handles the messages one after another: same counters, rejections by the
        core, outputs and order. Returns ``[(recv_ns of the message that produced it, topic,
        message), ...]``."""
        handler = self._batch[topic]
        diag = self.diag
        out: list[tuple[int, str, Any]] = []
        if not items:
            return out
        stats = diag.received[topic]
        t0 = time.perf_counter()
        # counters as process() keeps them, updated once per batch (nothing reads them in between)
        stats.count += len(items)
        stats.first_ns = recv_ns[0] if stats.first_ns is None else stats.first_ns
        stats.last_ns = recv_ns[len(items) - 1]
        for item, recv in zip(items, recv_ns):
            diag.now_ns = recv
            for o_topic, o_msg in self._judged(topic, handler, item, recv, "", True):
                out.append((recv, o_topic, o_msg))
        diag.process_s.append((time.perf_counter() - t0) / len(items))   # one entry per run: its mean
        return out

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

    def notice(self, text: str) -> None:
        """Something the driver should say once, as a warning (see the module doc)."""
        self.notices.append(text)

    def take_notices(self) -> list[str]:
        """The notices not taken yet, oldest first; each is returned once."""
        out, self.notices = self.notices, []
        return out

    # -- driver entry point ------------------------------------------------------------------------
    def process(self, topic: str, msg: Any, recv_ns: int, user: str | None = None) -> list[Output]:
        """Handle one message (``user``: whose it is, for multi-user stages). Never raises:
        rejected messages are counted and dropped."""
        handler = self._handlers.get(topic)
        if handler is None:
            self._reject("unknown_topic", f"no handler for {topic!r}")
            return []
        if self.MULTI_USER:
            if not user:
                self._reject("no_user", f"{topic}: a multi-user stage needs the message's user")
                return []
            handler = functools.partial(handler, user=user)
        return self._dispatch(topic, handler, msg, recv_ns, user)

    def _dispatch(self, topic: str, handler: Callable[[Any, int], list[Output]], msg: Any, recv_ns: int,
                  user: str | None) -> list[Output]:
        stats = self.diag.received[f"{user}/{topic}" if self.MULTI_USER else topic]
        stats.count += 1
        stats.first_ns = recv_ns if stats.first_ns is None else stats.first_ns
        stats.last_ns = recv_ns
        self.diag.now_ns = recv_ns
        t0 = time.perf_counter()
        try:
            return self._judged(topic, handler, msg, recv_ns, user or "", False)
        finally:
            self.diag.process_s.append(time.perf_counter() - t0)

    # -- time (one policy for every stage: pipeline/time_policy.py) ---------------------------------
    def stamp_of(self, topic: str, msg: Any) -> int | None:
        """The stamp (ns) a message is judged by: its ``header.stamp``; None (not judged) without a
        header. A stage whose input carries its stamp elsewhere (JSON text) says so here."""
        return header_ns(msg)       # the adapters' own reading: negative_stamp, bad_stamp

    def stamp_order(self, topic: str) -> Order:
        return self.STAMP_ORDER.get(topic, Order.NONDECREASING)

    def echoes(self, topic: str, stamp_ns: int) -> bool:
        """Whether a message on input ``topic`` stamped ``stamp_ns`` is this (per-user) stage's own output
        coming back (a node subscribing to a topic it publishes; :meth:`TimePolicy.echo`): the stage
        drops it unjudged, so a driver may drop it before decoding it."""
        return self.time.echo("", topic, stamp_ns)

    def for_user(self, namespace: str) -> "Stage":
        """A fresh instance of this per-user stage for the user of ``namespace`` (multi-user nodes,
        :mod:`indoor_loc.pipeline.multi_user`): the same parameters, state as before the first message.
        Stages holding large read-only data (a graph, a fitted radio map) override it to share them."""
        return type(self)(self.params, namespace=namespace)

    def reset_user(self, user: str) -> list[Output]:
        """A confirmed jump back in ``user``'s stamps (``""``: this per-user stage's one user): start
        its state afresh as if no message had come (publish what ends with the old pass first, e.g. its
        path). Stages with state override it; the time policy's own state is reset by the caller."""
        return []

    def upstream_restarted(self, topic: str, user: str) -> list[Output]:
        """The publisher of input ``topic`` (of ``user``; ``""`` for a per-user stage) restarted: a new
        process, its sequence numbers anew (the live driver sees it, ``nodes/liveness.py``), and the
        next message on ``topic`` is its first. Stages that integrate a stream (odometry poses) start
        it afresh here. Default: nothing."""
        return []

    def run_upstream_restarted(self, topic: str, user: str | None = None) -> list[Output]:
        """:meth:`upstream_restarted` for drivers, guarded like :meth:`run_tick`."""
        return self._guarded("upstream_restarted", lambda: self.upstream_restarted(topic, user or ""))

    def _handler_for(self, topic: str, user: str, batch: bool) -> Callable[[Any, int], list[Output]]:
        if batch:
            return self._batch[topic]
        handler = self._handlers[topic]
        return functools.partial(handler, user=user) if self.MULTI_USER else handler

    def _judged(self, topic: str, handler: Callable[[Any, int], list[Output]], item: Any, recv_ns: int,
                user: str, batch: bool) -> list[Output]:
        """One message (or batch item) through the time policy and, if it passes, its handler;
        rejections are counted by reason, nothing is raised."""
        who = f"{user}/{topic}" if user else topic
        try:
            stamp = _item_stamp(item) if batch else self.stamp_of(topic, item)
            if stamp is not None and self.time.echo(user, topic, stamp):
                return []                   # our own output coming back (time_policy.py: echoes)
            verdict = Verdict.PASS if stamp is None else self.time.judge(
                user, topic, stamp, recv_ns, self.stamp_order(topic))
        except InvalidInputError as err:
            self._reject(err.reason, f"{who}: {err}")
            return []
        if verdict == Verdict.HOLD:
            assert stamp is not None
            dropped = self.time.hold(user, Held(topic, item, recv_ns, stamp, batch))
            if dropped is not None:
                self._reject_held(user, [dropped])
            return []
        if verdict == Verdict.JUMP:
            assert stamp is not None
            return self._jump(user, Held(topic, item, recv_ns, stamp, batch))
        if verdict == Verdict.EPOCH_HOLD:  # of the new pass while the old one drains (time_policy.py)
            dropped = self.time.hold_epoch(user, Held(topic, item, recv_ns, stamp or 0, batch))
            if dropped is not None:
                self._reject_held(user, [dropped])
            return []
        if verdict == Verdict.EPOCH:       # the clock went back before it (said then): the user's new pass
            reset, held = self._reset_and_restart(user)
            return reset + self._replay_held(user, held + [Held(topic, item, recv_ns, stamp or 0, batch)], None, None)
        if verdict == Verdict.LEAP:
            assert stamp is not None
            dropped = self.time.hold_leap(user, Held(topic, item, recv_ns, stamp, batch))
            if dropped is not None:
                self._reject_leap([dropped])
            return []
        if verdict == Verdict.RESUME:
            assert stamp is not None
            return self._resume(user, Held(topic, item, recv_ns, stamp, batch))
        if stamp is not None and self.time.in_step(user, topic):
            self._reject_held(user, self.time.drop_held(user))
        if stamp is not None:
            self._reject_leap(self.time.refuted_leap(user, topic))
        try:
            outs = handler(item, recv_ns)
        except InvalidInputError as err:
            self._reject(err.reason, f"{who}: {err}")
            return []
        except Exception as err:  # noqa: BLE001 - a node never dies on a message
            self._reject("internal_error", f"{who}: {type(err).__name__}: {err}\n{traceback.format_exc(limit=4)}")
            return []
        if stamp is not None:
            self.time.accepted(user, topic, stamp)
        self._remember_own(user, outs)
        if self.map_odom is not None:
            outs = self._with_map_odom(user, outs, item if not batch and topic in self.map_odom.spec.motion else None)
        for out_topic, _ in outs:
            self.diag.published[out_topic] += 1
        return outs

    def _remember_own(self, user: str, outs: list[Output]) -> None:
        """The stamps of outputs on a topic the stage also takes, so their echoes are recognised
        (:meth:`TimePolicy.echo`)."""
        for out_topic, msg in outs:
            if out_topic in self._handlers:
                stamp = _cdr_header_ns(msg) if isinstance(msg, (bytes, bytearray)) else header_ns(msg)
                if stamp is not None:
                    self.time.published(user, out_topic, stamp)

    def _with_map_odom(self, user: str, outs: list[Output], motion: Any = None) -> list[Output]:
        """``outs`` and the ``map -> odom`` correction of their newest pose (pipeline/map_odom.py);
        ``motion``: the accepted odometry message the correction is to use."""
        assert self.map_odom is not None
        try:
            if motion is not None:
                self.map_odom.motion(user, motion)
            return outs + self.map_odom.corrections(user, outs)
        except Exception as err:  # noqa: BLE001 - the estimate goes out even if its correction cannot
            self._reject("internal_error", f"map_odom: {type(err).__name__}: {err}")
            return outs

    def _reject_held(self, user: str, held: list[Held]) -> None:
        for h in held:
            self._reject("stale_stamp", f"{user + '/' if user else ''}{h.topic}: stamp {h.stamp_ns} ns is more than "
                                        f"time.jump_s before the topic's newest and the topic went on in step: a "
                                        f"straggler or a wrong stamp, not a jump back")

    def _reject_leap(self, held: list[Held]) -> None:
        for h in held:
            self._reject("stamp_leap", f"{h.topic}: stamp {h.stamp_ns} ns leapt more than time.leap_s ahead of the "
                                       f"topic's newest and the topic went on from its newest: a wrong stamp")

    def _resume(self, user: str, last: Held) -> list[Output]:
        """A leap ahead confirmed by ``last``: the held messages and ``last`` handled in order (the
        source resumed after a pause; nothing is reset)."""
        held = self.time.resume(user, last.topic) + [last]
        mark = self.time.user(user).marks.get(last.topic)
        if mark is not None:           # the source goes on from the first held message
            self.time.user(user).marks[last.topic] = held[0].stamp_ns - 1
        return self._replay_held(user, held, None, None)

    def _jump(self, user: str, first: Held) -> list[Output]:
        """A jump back confirmed by ``first``: the user's state reset, the held messages and ``first``
        handled as the new pass's first (their order kept)."""
        mark = self.time.user(user).marks.get(first.topic)
        outs, held = self._reset_and_restart(user)
        return outs + self._replay_held(user, held + [first], mark, first)

    def _reset_and_restart(self, user: str) -> tuple[list[Output], list[Held]]:
        """Reset the user's state in the stage and in the time policy; returns the outputs of the
        reset and the messages held for the new pass."""
        outs = self._guarded("reset_user", lambda: self.reset_user(user))
        self._reject_leap(self.time.refuted_leap(user))      # stamped ahead of the old pass: not the new one's
        if self.map_odom is not None:
            self.map_odom.reset(user)
        held = self.time.restart(user)
        self.diag.time_jumps += 1
        return outs, held

    def _replay_held(self, user: str, held: list[Held], mark: int | None, first: Held | None) -> list[Output]:
        if first is not None:
            back = "" if mark is None else f" {(mark - first.stamp_ns) * 1e-9:.3f} s"
            self.notice(f"{user + ': ' if user else ''}{first.topic} stamps jumped back{back} (a replay loop, a "
                        f"restarted simulation or a clock reset): state reset, the new pass handled from its first "
                        f"message (time jump {self.time.user(user).jumps})")
        outs: list[Output] = []
        for h in held:
            outs += self._judged(h.topic, self._handler_for(h.topic, user, h.batch), h.item, h.recv_ns, user, h.batch)
        return outs

    def run_tick(self, now_ns: int) -> list[Output]:
        """:meth:`tick` for drivers: an exception is counted as ``internal_error`` (never escapes
        the timer or aborts an offline run); what the stage published before is kept."""
        self.diag.now_ns = now_ns
        return self._guarded("tick", lambda: self.tick(now_ns))

    def clock_jump_threshold_ns(self) -> int:
        """How far back the node's clock must jump (ns) for :meth:`run_clock_jump` (``time.jump_s``)."""
        return self.time.jump_ns

    def clock_jump(self, back_ns: int, now_ns: int) -> list[Output]:
        """The node's clock (``/clock`` under ``use_sim_time``) went back by ``back_ns`` to ``now_ns``:
        every user whose stamps are ahead of it starts afresh at once (:meth:`reset_user`), one notice."""
        users = self.time.clock_jump(now_ns, back_ns)
        if not users:
            return []
        names = ", ".join(u or self.namespace or "/" for u in users)
        self.notice(f"the clock jumped back {back_ns * 1e-9:.3f} s to {now_ns * 1e-9:.3f} s (a replay loop or a "
                    f"restarted simulation): state reset for {names} at the first message of the new pass "
                    f"(messages stamped before the jump, still in flight, are the old pass's)")
        outs: list[Output] = []
        for user in users:
            if self.time.deferred(user):
                continue                    # reset by its first message of the new epoch (time_policy.py)
            reset, held = self._reset_and_restart(user)
            outs += reset + self._replay_held(user, held, None, None)
        return outs

    def drop_held(self, user: str) -> list[Output]:
        """End of a user's input with a jump back still unconfirmed: its held messages were stragglers.
        Messages of a new epoch held while the old one drained (the node's clock went back) are the
        new pass's: the user is reset and they are handled (their outputs returned)."""
        outs: list[Output] = []
        if self.time.epoch_pending(user):
            reset, held = self._reset_and_restart(user)
            outs = reset + self._replay_held(user, held, None, None)
        if user in self.time.users and self.time.users[user].held:
            self._reject_held(user, self.time.drop_held(user))
        self._reject_leap(self.time.refuted_leap(user))
        return outs

    def run_clock_jump(self, back_ns: int, now_ns: int) -> list[Output]:
        """:meth:`clock_jump` for drivers, guarded like :meth:`run_tick`."""
        self.diag.now_ns = now_ns
        # each output counted once: the shared clock_jump counts where it makes them (the resets, the held
        # messages handed on), a stage's own override does not
        before = Counter(self.diag.published)
        outs = self._guarded("clock_jump", lambda: self.clock_jump(back_ns, now_ns), count=False)
        made = Counter(t for t, _ in outs)
        made.subtract(Counter(self.diag.published) - before)
        self.diag.published.update(+made)
        return outs

    def run_finish_user(self, user: str) -> list[Output]:
        """:meth:`finish_user` for drivers, guarded like :meth:`run_tick`; the user's messages held for
        an unconfirmed jump back were stragglers (counted, ``stale_stamp``)."""
        outs = self.drop_held(user)
        return outs + self._guarded("finish_user", lambda: self.finish_user(user))

    def run_finish(self) -> list[Output]:
        """:meth:`finish` for drivers, guarded like :meth:`run_tick`; messages still held for an
        unconfirmed jump back were stragglers (counted, ``stale_stamp``)."""
        outs: list[Output] = []
        for user in list(self.time.users):
            outs += self.drop_held(user)
        return outs + self._guarded("finish", self.finish)

    def _guarded(self, what: str, fn: Callable[[], list[Output]], count: bool = True) -> list[Output]:
        try:
            outs = fn()
        except Exception as err:  # noqa: BLE001 - a stage bug must not end the node or the run
            self._reject("internal_error", f"{what}(): {type(err).__name__}: {err}\n{traceback.format_exc(limit=4)}")
            return []
        if not self.MULTI_USER:
            self._remember_own("", outs)
        if self.map_odom is not None and not self.MULTI_USER:
            outs = self._with_map_odom("", outs)
        if count:
            for out_topic, _ in outs:
                self.diag.published[out_topic] += 1
        return outs

    def _reject(self, reason: str, detail: str) -> None:
        self.diag.rejected[reason] += 1
        self.diag.last_error = detail
        self.diag.last_error_reason = reason
        self.diag.last_reject_ns = self.diag.now_ns
        if reason == "internal_error":
            self.diag.last_internal_ns = self.diag.now_ns

    # -- what a driver sees of an input before the stage does (one entry for every kind of stage) ------
    def count_lost(self, topic: str, n: int, now_ns: int, user: str | None = None) -> None:
        """``n`` messages on input ``topic`` (of ``user``, multi-user stages) never reached the stage
        (``lost.<topic>``). A multi-user stage books them on the user's own counters as well."""
        self.diag.count_lost(topic, n, now_ns)

    def count_missed_at_start(self, topic: str, n: int, user: str | None = None) -> None:
        """``n`` messages on ``topic`` were published before the subscription matched
        (``missed_at_start.<topic>``)."""
        self.diag.missed_at_start[topic] += n

    def reject_input(self, reason: str, detail: str, now_ns: int, user: str | None = None) -> None:
        """A message the driver could not hand over (``undecodable``): counted as the stage's own
        rejections are (and, multi-user, on the user's counters)."""
        self.diag.now_ns = now_ns
        self._reject(reason, detail)
