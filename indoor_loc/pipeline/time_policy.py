"""One time policy for every stage: which message stamps a stage takes, and what a clock jump does.

Every stage (:class:`~indoor_loc.pipeline.stage.Stage`) judges each input message's stamp here
before its handler sees it, with the parameters of the ``time`` group (:class:`TimeParams`,
``time.max_future_s``, ``time.jump_s``, ``time.jump_confirm`` in every node's params):

- **future**: a stamp more than ``max_future_s`` ahead of the node's clock (ROS time, sim time under
  ``use_sim_time``; offline the bag's log time) is rejected (``future_stamp``) without touching
  anything. With no clock yet (sim time before the first ``/clock``) the check waits for one.
- **order**, per *source* (one input topic of one user; the newest accepted stamp is its
  *watermark*): a stamp at or before the watermark, but within ``jump_s`` of it, is judged by the
  topic's :class:`Order` — ``STRICT`` inputs (IMU samples, odometry hops) need a later stamp
  (``non_monotonic_stamp``), ``NONDECREASING`` ones (scans, fixes) an equal or later one
  (``stamp_backwards``), ``ANY`` passes (the stage reorders, e.g. the back-end's window). The
  watermark moves only when the stage's handler accepted the message (it did not raise).
- **jumps back**: a stamp more than ``jump_s`` before its source's watermark is either a straggler (a
  wrongly stamped or replayed message) or the first of a new pass (a bag played in a loop, a simulation
  restarted, a device clock reset). It is held, with every later message of the user that far back,
  until the source decides: ``jump_confirm`` messages of the source in a row, each in step with the one
  before (a strictly later stamp, advanced as much as the node's clock within ``jump_s``: a replayed
  pass moves with the clock, wrong stamps do not), confirm the jump — or at once when the node's clock
  agrees (the source's watermark is more than ``jump_s`` ahead of the node's clock: the old pass is in
  the clock's future, and the far-back stamp within ``jump_s`` of the clock: the new pass is its
  present, and the clock itself went back; a clock lagging the stamps it takes vouches for nothing). A
  confirmed jump resets the user's state in the stage (:meth:`Stage.reset_user`), counts ``time_jumps``,
  says it once (WARN), and the held messages are handled as the new pass's first. A message of the
  source back in step with its watermark shows the held ones were stragglers: each is rejected
  (``stale_stamp``), counted. Ordering *across* a user's topics is never a jump (a user's first scan
  before its first odometry, fixes that lag the odometry by the WiFi node's latency): each topic is a
  source of its own.
- **leaps ahead**: a stamp more than ``leap_s`` after its source's watermark while the node's clock
  cannot vouch for it (it is not within ``max_future_s`` of the clock: a bag replayed without
  ``use_sim_time``, a device clock that is not the node's) is either a wrongly stamped message or
  the source resuming after a pause. It is held (this source only) until ``jump_confirm`` messages
  of the source in a row, each after the previous by less than ``leap_s``, confirm the resume (they
  are handled in order, nothing reset) — or a message of the source in step with its watermark shows
  the held ones were wrongly stamped: each is rejected (``stamp_leap``), counted. Without this, one
  message stamped an hour ahead would move the watermark there and every valid message after it
  would be refused.
- **the node's clock going back** (rclpy's clock-jump callback, :meth:`Stage.run_clock_jump`) by
  more than ``jump_s`` resets every user whose watermarks are ahead of the new clock — once the old
  *epoch* has drained, not at the callback. The messages published just before ``/clock`` went back
  (a replay's last samples, queued in the node) reach the stage in any order with the callback, and
  a user's topics in any order with each other; each source (topic) of the old pass stays *open*
  until its first message of the new epoch (one publisher per topic delivers in order: nothing of
  the old pass follows it). A message of an open source stamped more than ``jump_s`` ahead of the new
  clock (and no more than ``max_future_s`` after the clock before the jump) is judged, and handled,
  in the old pass (its watermark, the clock before the jump); a message of the new epoch is held
  (``EPOCH_HOLD``) until every source of the old pass has moved on or the node's clock has run
  ``jump_s`` past the jump; then the user is reset (``EPOCH``: ``time_jumps``) and the held messages
  are handled as the new pass's first, in their order. So a pass's last outputs do not depend on
  when the callback ran. A user with messages held for a jump back at the callback (the new pass
  came before its clock) is reset at once, as before.
- **after a jump**, a topic's first message stamped more than ``jump_s`` ahead of the user's new
  pass (its other topics, the node's clock) but not after the old pass's newest stamp is of the old
  pass, still in flight (a fix that lags its scan): rejected (``before_jump``), so it cannot set the
  new pass's watermarks to the old stamps.

- **echoes**: a node that subscribes to a topic it publishes (``imu_node``'s ``imu/data``) gets its
  own messages back. The stage tells the policy the stamps it published there (:meth:`TimePolicy.published`)
  and a message stamped like one of them is its own (:meth:`TimePolicy.echo`): dropped before it is
  judged, so it never moves a watermark nor starts or confirms a jump. The stamps are kept per user
  and topic up to :data:`OWN_MAX`, more than DDS can hold back (a subscription's queue plus a take):
  a bounded window of the last few hundred, as there was, let the echoes of one large take (a node
  catching up after a stall publishes thousands at once) come back unrecognised, far behind a
  foreign message on the same topic — three in a row, in step: a "jump" that reset the node.

The policy holds stamps and held messages only; it never looks inside a message. The driver
(:class:`Stage`) asks :meth:`TimePolicy.judge` and acts on the :class:`Verdict`.
"""
from __future__ import annotations

from array import array
from bisect import bisect_left, insort
from dataclasses import dataclass, field as dc_field
from enum import IntEnum
from typing import Any

from indoor_loc.errors import InvalidInputError
from indoor_loc.params import field, require

NS = 1_000_000_000
#: At most this many messages of one user are held while a jump back waits for its confirmation;
#: beyond, the oldest is rejected (``stale_stamp``).
HELD_MAX = 1000
#: Own output stamps remembered per user and topic to recognise their echoes (see the module doc): more
#: than a reliable replay subscription's queue (nodes/qos.py SUB_DEPTH_REPLAY, 10 000) plus one take
#: of the node's raw inputs (nodes/inputs.py TAKE_MAX, 2048) can hold back; 8 bytes each.
OWN_MAX = 16384


class Order(IntEnum):
    """How the stamps of one input topic must follow each other (within ``jump_s``)."""
    STRICT = 0          # each after the previous (IMU samples, odometry hops)
    NONDECREASING = 1   # equal stamps allowed (scans, fixes)
    ANY = 2             # any order: the stage reorders (a reorder window)
    EXEMPT = 3          # not judged at all (initialpose: a person's command, often stamped 0)


@dataclass(frozen=True)
class TimeParams:
    """The ``time`` parameters of every node (see the module doc)."""
    max_future_s: float = field(10.0, "a message stamped more than this ahead of the node's clock (sim time under "
                                      "use_sim_time) is rejected (future_stamp), nothing changed, s")
    jump_s: float = field(2.0, "a stamp this much before its topic's newest accepted one is a jump back: held until "
                               "jump_confirm messages in a row (or the node's clock) confirm it — then the user's state "
                               "is reset (time_jumps, WARN) — or the topic goes on in step (stale_stamp, counted); "
                               "the node's clock going back this far resets at once, s")
    jump_confirm: int = field(3, "messages of one topic in a row, each in step with the previous, that confirm a "
                                 "jump back (a replay loop, a restarted simulation, a device clock reset)")
    leap_s: float = field(60.0, "a stamp this much after its topic's newest accepted one, not within max_future_s "
                                "of the node's clock, is a leap: held until jump_confirm messages in a row continue "
                                "from it (the source resumed after a pause) or the topic goes on from its newest "
                                "(the leap was a wrong stamp: stamp_leap, counted), s")

    def validate(self) -> None:
        n = type(self).__name__
        require(self.max_future_s > 0, n, "max_future_s", "> 0", self.max_future_s)
        require(self.jump_s > 0, n, "jump_s", "> 0", self.jump_s)
        require(self.jump_confirm >= 1, n, "jump_confirm", ">= 1", self.jump_confirm)
        require(self.leap_s > self.jump_s, n, "leap_s", "> jump_s", self.leap_s)


class Verdict(IntEnum):
    PASS = 0        # hand the message to its handler; call :meth:`TimePolicy.accepted` if it took it
    HOLD = 1        # held (a possible jump back): :meth:`TimePolicy.hold` it
    JUMP = 2        # a jump back confirmed by this message: reset the user, then :meth:`TimePolicy.restart`
    LEAP = 3        # a leap ahead: :meth:`TimePolicy.hold_leap` it
    RESUME = 4      # a leap confirmed by this message: :meth:`TimePolicy.resume` gives the held ones to handle
    EPOCH = 5       # the old epoch drained after the node's clock went back: reset the user (said at the
                    # jump), then :meth:`TimePolicy.restart`, then handle the held messages and this one
    EPOCH_HOLD = 6  # of the new epoch while the old one drains: :meth:`TimePolicy.hold_epoch` it


@dataclass
class Held:
    """A message held while a jump back waits for its confirmation."""
    topic: str
    item: Any           # the message, or a batch item (``batch``)
    recv_ns: int
    stamp_ns: int
    batch: bool = False


@dataclass
class _Leap:
    """A source's messages held for a leap ahead (see the module doc)."""
    held: list[Held] = dc_field(default_factory=list)
    last: int = 0                       # the latest held stamp


class OwnStamps:
    """The stamps a stage published on one topic, oldest first (a sorted ``array``; at most
    :data:`OWN_MAX`, the oldest forgotten first): a message stamped like one of them is an echo."""
    __slots__ = ("stamps", "start")

    def __init__(self) -> None:
        self.stamps = array("q")
        self.start = 0                  # stamps[:start] are forgotten (dropped in one go now and then)

    def add(self, stamp_ns: int) -> None:
        st = self.stamps
        if len(st) > self.start and stamp_ns <= st[-1]:
            if stamp_ns == st[-1]:
                return
            insort(st, stamp_ns, lo=self.start)     # after a reset: an older pass published again
        else:
            st.append(stamp_ns)
        if len(st) - self.start > OWN_MAX:
            self.start += 1
            if self.start >= OWN_MAX // 4:
                del st[:self.start]
                self.start = 0

    def __contains__(self, stamp_ns: int) -> bool:
        st = self.stamps
        if len(st) <= self.start or not st[self.start] <= stamp_ns <= st[-1]:
            return False
        i = bisect_left(st, stamp_ns, self.start)
        return i < len(st) and st[i] == stamp_ns

    def __len__(self) -> int:
        return len(self.stamps) - self.start


@dataclass
class _UserTime:
    marks: dict[str, int] = dc_field(default_factory=dict)    # topic -> newest accepted stamp (watermark)
    held: list[Held] = dc_field(default_factory=list)
    cand_topic: str | None = None       # the source whose far-back run is being judged
    cand_last: int = 0                  # its latest far-back stamp
    cand_now: int = 0                   # the node's clock when it came (0: no clock)
    cand_count: int = 0                 # far-back messages of that source in a row
    fence_ns: int | None = None         # after a jump: the old pass's newest stamp (see before_jump)
    #: after the node's clock went back, until the user's first message of the new epoch: the clock
    #: before the jump (messages stamped in the old epoch are judged by it; see the module doc)
    epoch_ns: int | None = None
    clock_max: int = 0                  # the latest node's clock a message of the user was judged at
    epoch_at: int = 0                   # the node's clock just after the jump
    epoch_open: set[str] = dc_field(default_factory=set)   # the old pass's sources not yet moved on
    epoch_held: list[Held] = dc_field(default_factory=list)  # new-epoch messages held until it drains
    jumps: int = 0
    leaps: dict[str, _Leap] = dc_field(default_factory=dict)   # topic -> its messages held for a leap ahead
    #: topic -> the stamps the stage published there (echo recognition; kept across a reset: echoes of
    #: the old pass still come)
    own: dict[str, OwnStamps] = dc_field(default_factory=dict)

    def front(self) -> int | None:
        return max(self.marks.values()) if self.marks else None


class TimePolicy:
    """Stamps judged per user and topic (the module doc); ``user`` is ``""`` for a per-user stage."""

    def __init__(self, params: TimeParams) -> None:
        params.validate()
        self.params = params
        self.future_ns = int(params.max_future_s * NS)
        self.jump_ns = int(params.jump_s * NS)
        self.leap_ns = int(params.leap_s * NS)
        self.users: dict[str, _UserTime] = {}
        self.rejected_held = 0

    def user(self, user: str) -> _UserTime:
        u = self.users.get(user)
        if u is None:
            u = self.users[user] = _UserTime()
        return u

    def published(self, user: str, topic: str, stamp_ns: int) -> None:
        """The stage published a message stamped ``stamp_ns`` on ``topic``, which it also takes: its echo
        will be recognised (:meth:`echo`)."""
        u = self.user(user)
        own = u.own.get(topic)
        if own is None:
            own = u.own[topic] = OwnStamps()
        own.add(stamp_ns)

    def echo(self, user: str, topic: str, stamp_ns: int) -> bool:
        """Whether a message on ``topic`` stamped ``stamp_ns`` is the stage's own output coming back."""
        u = self.users.get(user)
        own = None if u is None else u.own.get(topic)
        return own is not None and stamp_ns in own

    def judge(self, user: str, topic: str, stamp_ns: int, now_ns: int | None, order: Order) -> Verdict:
        """What to do with a message; raises :class:`InvalidInputError` for one to reject (nothing
        changed). A ``PASS`` of the held run's source back in step drops the held messages first
        (:meth:`drop_held` gives them to the caller to count)."""
        u = self.users.get(user)
        if u is not None and now_ns and now_ns > u.clock_max:
            u.clock_max = now_ns
        if u is not None and not u.held and u.fence_ns is None and not u.leaps and u.epoch_ns is None:
            mark = u.marks.get(topic)                            # the common case, first
            if mark is not None and mark < stamp_ns <= mark + self.leap_ns and (
                    not now_ns or stamp_ns <= now_ns + self.future_ns):
                return Verdict.PASS
        if u is not None and u.epoch_ns is not None:
            old = bool(now_ns) and int(now_ns or 0) + self.jump_ns < stamp_ns <= u.epoch_ns + self.future_ns
            drained = bool(now_ns) and int(now_ns or 0) >= u.epoch_at + self.jump_ns
            if old and topic in u.epoch_open and not drained:
                now_ns = u.epoch_ns                              # stamped before the clock went back
            elif old and not drained:                            # its source moved on: a straggler
                raise InvalidInputError(
                    "before_jump", f"{topic} stamp {stamp_ns} ns is of the pass before the node's clock went back, "
                                   f"after the topic's first message of the new pass")
            else:
                u.epoch_open.discard(topic)                      # this source has moved on
                if u.epoch_open and not drained:
                    return Verdict.EPOCH_HOLD
                u.epoch_ns = None                                # the old epoch has drained
                return Verdict.EPOCH
        if order == Order.EXEMPT:
            return Verdict.PASS
        if now_ns and stamp_ns > now_ns + self.future_ns:
            raise InvalidInputError(
                "future_stamp", f"stamp {stamp_ns * 1e-9:.3f} s is {(stamp_ns - now_ns) * 1e-9:.1f} s ahead of the "
                                f"node's clock ({now_ns * 1e-9:.3f} s), more than time.max_future_s "
                                f"({self.params.max_future_s:g} s)")
        u = self.user(user)
        if now_ns and now_ns > u.clock_max:
            u.clock_max = now_ns
        if u.fence_ns is not None:
            self._check_fence(u, topic, stamp_ns, now_ns)
        mark = u.marks.get(topic)
        leap = self._leap(u, topic, stamp_ns, mark, now_ns)
        if leap is not None:
            return leap
        if mark is None:            # a topic's first message: held only if it is as far back as a held run
            return Verdict.HOLD if u.held and stamp_ns < (u.front() or 0) - self.jump_ns else Verdict.PASS
        if stamp_ns < mark - self.jump_ns:                       # far back: a straggler or a new pass
            if u.cand_topic is None or topic != u.cand_topic:
                if u.cand_topic is None:
                    u.cand_topic, u.cand_last, u.cand_now, u.cand_count = topic, stamp_ns, now_ns or 0, 1
                    return Verdict.JUMP if self._clock_agrees(u, mark, now_ns, stamp_ns) else Verdict.HOLD
                return Verdict.HOLD                              # another topic of the same run
            in_step = self._in_step(u, stamp_ns, now_ns or 0)
            u.cand_last, u.cand_now = stamp_ns, now_ns or 0
            if not in_step:
                u.cand_count = 1                                 # not in step: the run starts again
                return Verdict.HOLD
            u.cand_count += 1
            if u.cand_count >= self.params.jump_confirm or self._clock_agrees(u, mark, now_ns, stamp_ns):
                return Verdict.JUMP
            return Verdict.HOLD
        if u.held and topic != u.cand_topic:
            return Verdict.HOLD if stamp_ns < (u.front() or 0) - self.jump_ns else Verdict.PASS
        if u.held and now_ns and u.cand_now and stamp_ns <= mark and self._in_step(u, stamp_ns, now_ns):
            # not after the old pass's newest, but in step with the held run by the node's clock (a
            # short pass replayed: its stamps reach the old watermark before the run is confirmed)
            u.cand_last, u.cand_now, u.cand_count = stamp_ns, now_ns or 0, u.cand_count + 1
            return Verdict.JUMP if u.cand_count >= self.params.jump_confirm else Verdict.HOLD
        if stamp_ns < mark or (stamp_ns == mark and order == Order.STRICT):
            if order == Order.STRICT:
                raise InvalidInputError("non_monotonic_stamp", f"{topic} stamp {stamp_ns} ns is not after the "
                                                               f"previous one's {mark} ns")
            if order == Order.NONDECREASING:
                raise InvalidInputError("stamp_backwards", f"{topic} stamp {stamp_ns} ns is before the previous "
                                                           f"one's {mark} ns")
        return Verdict.PASS

    def _leap(self, u: _UserTime, topic: str, stamp_ns: int, mark: int | None, now_ns: int | None) -> Verdict | None:
        """LEAP / RESUME for a message leaping ahead of its source's watermark or continuing a held
        leap; None when the leap rule has nothing to say (the message is judged as usual)."""
        held = u.leaps.get(topic)
        if held is not None and stamp_ns > held.last and stamp_ns - held.last <= self.leap_ns:
            held.last = stamp_ns                     # continues the held run
            return Verdict.RESUME if len(held.held) + 1 >= self.params.jump_confirm else Verdict.LEAP
        if mark is None or stamp_ns <= mark + self.leap_ns:
            return None
        if now_ns and abs(stamp_ns - now_ns) <= self.future_ns:
            return None                              # the node's clock vouches for it: a source back after a pause
        if held is not None:                         # ahead again but not continuing: the run starts anew
            held.last = stamp_ns
            return Verdict.LEAP if self.params.jump_confirm > 1 else Verdict.RESUME
        u.leaps[topic] = _Leap(last=stamp_ns)
        return Verdict.LEAP if self.params.jump_confirm > 1 else Verdict.RESUME

    def hold_leap(self, user: str, held: Held) -> Held | None:
        """Hold a message of a leap ahead; returns the oldest held one if the bound made room (reject it)."""
        lp = self.user(user).leaps.setdefault(held.topic, _Leap(last=held.stamp_ns))
        lp.held.append(held)
        return lp.held.pop(0) if len(lp.held) > HELD_MAX else None

    def resume(self, user: str, topic: str) -> list[Held]:
        """A leap confirmed: the held messages, oldest first, to be handled in order (the source's
        watermark moves with them as they are accepted)."""
        u = self.user(user)
        lp = u.leaps.pop(topic, None)
        return [] if lp is None else lp.held

    def refuted_leap(self, user: str, topic: str | None = None) -> list[Held]:
        """A message of ``topic`` in step with its watermark passed (``None``: the user's state is reset,
        or its input ended): the messages held for a leap were wrongly stamped (the caller rejects each,
        ``stamp_leap``)."""
        u = self.users.get(user)
        if u is None:
            return []
        topics = list(u.leaps) if topic is None else [topic] if topic in u.leaps else []
        return [h for t in topics for h in u.leaps.pop(t).held]

    def _in_step(self, u: _UserTime, stamp_ns: int, now_ns: int) -> bool:
        """A far-back message continues the held run: its stamp after the run's latest, and — with the
        node's clock — advanced as much as the clock did, within ``jump_s`` (a pass being replayed moves
        with the clock; wrong stamps do not)."""
        if stamp_ns <= u.cand_last:     # a replayed pass moves on; a constant wrong stamp does not
            return False
        if now_ns and u.cand_now:
            return abs((stamp_ns - u.cand_last) - (now_ns - u.cand_now)) <= self.jump_ns
        return True

    def _clock_agrees(self, u: _UserTime, mark: int, now_ns: int | None, stamp_ns: int) -> bool:
        """The node's clock confirms a jump back: the clock itself went back by more than ``jump_s``
        (before the latest clock a message of the user was judged at), the source's old pass is ahead
        of it by more than ``jump_s``, and the far-back stamp is within ``jump_s`` of it (the new pass
        is the clock's present). A clock merely lagging the stamps it takes vouches for nothing: a
        busy node takes ``/clock`` late, tens of seconds behind its data under load, and a wrong stamp
        30 s back would then reset the user at once."""
        now = int(now_ns or 0)
        return (bool(now) and now < u.clock_max - self.jump_ns and mark > now + self.jump_ns
                and abs(stamp_ns - now) <= self.jump_ns)

    def _check_fence(self, u: _UserTime, topic: str, stamp_ns: int, now_ns: int | None) -> None:
        """After a jump, the first message of a topic in the new pass: one stamped more than ``jump_s``
        ahead of the new pass (the user's other topics, the node's clock) but not after the old pass's
        newest stamp is of the old pass, still in flight (a fix lagging its scan). Later messages of the
        topic are judged by its own watermark."""
        front = u.front()
        if front is not None and front > u.fence_ns:             # the new pass is past the old one's end
            u.fence_ns = None
            return
        if topic in u.marks:
            return
        ref = max(front or 0, now_ns or 0)
        if ref and ref + self.jump_ns < stamp_ns <= u.fence_ns:  # type: ignore[operator]
            raise InvalidInputError(
                "before_jump", f"{topic} stamp {stamp_ns} ns is {(stamp_ns - ref) * 1e-9:.1f} s ahead of the new pass "
                               f"since the clock jumped back from {u.fence_ns} ns: a message of the pass before the "
                               f"jump still in flight")

    def in_step(self, user: str, topic: str) -> bool:
        """Whether a PASS of ``topic`` ends the held run as stragglers (the run's own source back in step)."""
        u = self.users.get(user)
        return u is not None and bool(u.held) and topic == u.cand_topic

    def hold(self, user: str, held: Held) -> Held | None:
        """Hold a message; returns the oldest held one if the bound made room (reject it)."""
        u = self.user(user)
        u.held.append(held)
        return u.held.pop(0) if len(u.held) > HELD_MAX else None

    def drop_held(self, user: str) -> list[Held]:
        """The held run turned out to be stragglers: they go (the caller rejects each, ``stale_stamp``)."""
        u = self.user(user)
        held, u.held = u.held, []
        u.cand_topic, u.cand_count = None, 0
        self.rejected_held += len(held)
        return held

    def restart(self, user: str) -> list[Held]:
        """After the user's state was reset for a jump back: watermarks cleared, the old pass fenced
        off, one more jump counted. Returns the held messages, to be handled as the new pass's first."""
        u = self.user(user)
        held, front = u.held + u.epoch_held, u.front()
        if u.epoch_ns is not None or u.epoch_open:              # after the clock went back: its old pass too
            front = max(front or 0, u.epoch_ns or 0)
        u.marks, u.held, u.cand_topic, u.cand_count, u.leaps = {}, [], None, 0, {}
        u.epoch_ns, u.epoch_open, u.epoch_held, u.clock_max = None, set(), [], 0
        if front is not None:
            u.fence_ns = front if u.fence_ns is None else max(u.fence_ns, front)
        u.jumps += 1
        return held

    def accepted(self, user: str, topic: str, stamp_ns: int) -> None:
        """The stage took a message: its source's watermark moves to the stamp (never back)."""
        u = self.user(user)
        mark = u.marks.get(topic)
        if mark is None or stamp_ns > mark:
            u.marks[topic] = stamp_ns

    def passes_run(self, user: str, topic: str, stamps: list[int], now_ns: list[int], order: Order) -> bool:
        """Whether a whole run of one topic would PASS one by one with nothing held (every stamp in
        order after the watermark, none ahead of its clock), so the caller may handle it in one go
        (then :meth:`accepted` its last stamp taken). False: judge the messages one by one."""
        if order == Order.EXEMPT:
            return True
        u = self.users.get(user)
        if u is not None and (u.held or u.fence_ns is not None or u.leaps or u.epoch_ns is not None):
            return False
        prev = None if u is None else u.marks.get(topic)
        for t, now in zip(stamps, now_ns):
            if now and t > now + self.future_ns:
                return False
            if prev is not None and t > prev + self.leap_ns:
                return False
            if prev is not None and (t < prev or (t == prev and order == Order.STRICT)):
                return False
            prev = t
        return True

    def clock_jump(self, now_ns: int, back_ns: int = 0) -> list[str]:
        """The node's clock went back by ``back_ns`` to ``now_ns``: the users whose watermarks are more
        than ``jump_s`` ahead of it. Each with messages held (the new pass already begun) is for the
        caller to reset at once (then :meth:`restart`); the others are reset at their first message
        of the new epoch (``JUMP`` from :meth:`judge`), messages stamped before the jump judged by the
        clock before it until then (the module doc)."""
        users = [name for name, u in self.users.items() if (u.front() or 0) > now_ns + self.jump_ns]
        for name in users:
            u = self.users[name]
            before = now_ns + max(0, back_ns)
            u.epoch_ns = before if u.epoch_ns is None else max(u.epoch_ns, before)
            u.epoch_at = now_ns
            u.epoch_open |= set(u.marks)
        return users

    def deferred(self, user: str) -> bool:
        """Whether the user's reset for a clock jump waits for the old epoch to drain."""
        u = self.users.get(user)
        return u is not None and u.epoch_ns is not None and not u.held

    def hold_epoch(self, user: str, held: Held) -> Held | None:
        """Hold a message of the new epoch; returns the oldest held one if the bound made room (reject it)."""
        u = self.user(user)
        u.epoch_held.append(held)
        return u.epoch_held.pop(0) if len(u.epoch_held) > HELD_MAX else None

    def epoch_pending(self, user: str) -> bool:
        """Whether the user holds messages of a new epoch (its input ended: reset it and hand them on)."""
        u = self.users.get(user)
        return u is not None and bool(u.epoch_held)
