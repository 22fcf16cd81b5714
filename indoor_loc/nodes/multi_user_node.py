"""A per-user stage served for many users by one process: ``imu_node --multi-user`` (any stage node).

:class:`MultiUserStageNode` runs :func:`indoor_loc.pipeline.multi_user.multi_user` of a stage as a
:class:`~indoor_loc.nodes.stage_node.StageNode` (its parameters, QoS, liveness, stop and
``/diagnostics`` as every node), in the root namespace (or a site's), subscribing to each served
user's inputs (``/alice/imu/data_raw``) and publishing the per-user node's outputs under the user's
namespace (``/alice/pdr/odom``).

- **Users**: those of ``users``, or every namespace where another node publishes one of the
  stage's inputs (the graph is polled every ``DISCOVERY_PERIOD_S``; the node's own publishers, such
  as ``imu_node``'s ``imu/data``, do not count), kept when the name matches ``user_pattern`` and
  :func:`~indoor_loc.pipeline.multi_user.shard_of` puts it in this shard (``shard_index`` of
  ``shard_count``). A user whose inputs have had no other publisher for ``user_timeout_s`` has left:
  its end-of-input outputs are published, its subscriptions closed and its state dropped.
- **/diagnostics**: the node's own status (``/imu_node``: users served, totals, the users no shard
  serves) and one status per user named as the per-user node's (``/alice/imu_node``: the user's
  counters, rejections, inputs' liveness, ``served_by``), so a monitor reads a user's health the
  same way whichever mode serves it.
- **Shards**: every shard also notices the users of the other shards. A user is *served* while a
  status named ``/<user>/<node name>`` was heard on ``/diagnostics`` within ``user_timeout_s`` (from
  any shard, or a per-user node). A user whose inputs are published but who has not been served for
  that long is *unserved*: each surviving shard says so (WARN, ``unserved.count``,
  ``unserved.users``, the shard that should serve them). Nothing takes the user over automatically:
  restart the shard (a supervisor's ``Restart=always``); the restarted shard discovers its users again
  and starts them afresh (docs/scaling.md).
"""
from __future__ import annotations

import heapq
import struct
import time
from typing import Any, Callable

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.duration import Duration
from rclpy.node import Node
from rclpy.qos import QoSProfile

from indoor_loc.bag.bulk import BULK_TYPES, bulk_items
from indoor_loc.contract import Qos, join_ns, msg_class, namespace_of_topic
from indoor_loc.nodes.liveness import LEFT, STALLED
from indoor_loc.nodes.qos import qos_profile, subscription_qos
from indoor_loc.nodes.process import ACK_RESERVE_S, stop_time_ns
from indoor_loc.nodes.stage_node import FINISH_ACK_TIMEOUT_S, StageNode
from indoor_loc.pipeline.multi_user import Ended, MultiUserStage, multi_user, shard_of
from indoor_loc.pipeline.stage import Stage, namespace_of_user, user_of_namespace
from msg_adapters.diagnostics import stage_diagnostics, status_names_cdr, with_inputs


#: How often the users' inputs are taken (s, wall clock): each poll takes what every user's inputs
#: queued since the last one and hands each user's runs to its stage.
POLL_PERIOD_S = 0.05
#: At most this many messages are taken from one input per poll (the rest wait for the next).
TAKE_PER_INPUT = 250
#: On a stop, taking the input still queued ends this long (s) before the time kept for publishing
#: the end-of-input outputs, which leaves it for finishing the users.
DRAIN_RESERVE_S = 2.0
#: The publishers of a user that left are destroyed once their subscribers have acknowledged every
#: message, or at the latest this long after it left (s).
CLOSE_WAIT_S = 5.0


class MultiUserStageNode(StageNode):
    """``stage_cls`` (a per-user stage) for every user of this shard, in one node.

    The users' subscriptions and publishers belong to a second node of the process (``<name>_io``, the
    same DDS participant) that no executor waits on: with hundreds of users the executor would rebuild
    its wait set over all of them for every message. A timer takes every user's queued input messages
    each :data:`POLL_PERIOD_S` instead (at most that much latency added), merges each user's topics in
    stamp order and hands the runs to the user's stage, decoded in bulk where
    :mod:`indoor_loc.bag.bulk` can (``sensor_msgs/Imu``, ``MagneticField``); its own ``imu/data``
    coming back is dropped before decoding (:meth:`Stage.echoes`). What this costs: no
    ``matched``/incompatible-QoS events and no ``qos_overrides.`` parameters for per-user topics (the
    node-wide ``sensor_reliability`` still applies)."""

    def __init__(self, stage_cls: type[Stage], **node_kwargs: Any) -> None:
        #: users of other shards (or not matching the pattern) whose inputs are published: user -> monotonic
        #: time it was last seen served (or first seen)
        self._others: dict[str, float] = {}
        #: user -> monotonic time a status ``/<user>/<node name>`` was last heard on /diagnostics
        self._heard: dict[str, float] = {}
        self._io: Node | None = None
        self.echoes_dropped = 0
        #: user -> its inputs' last reports, kept when they are closed (it left) for its last status
        self._closed_inputs: dict[str, list] = {}
        #: publishers of users that left, to destroy once acknowledged: (monotonic deadline, publishers)
        self._closing: list[tuple[float, list]] = []
        super().__init__(multi_user(stage_cls), **node_kwargs)
        self.stage: MultiUserStage
        self.stage.raw_outputs = True
        # a stage may poll less often (ImuStage: its runs, and so its cost per sample, grow with the period)
        self.create_timer(getattr(stage_cls, "MULTI_USER_POLL_S", POLL_PERIOD_S), self._poll)
        self._me = {(self.get_name(), self.get_namespace()), (self.get_name() + "_io", self.get_namespace())}
        self._suffix = "/" + self.stage.NODE_NAME
        self._own_outputs_of: dict[str, None] = {}
        self._own_outputs: set[str] = set()
        p = self.stage.params
        if p.shard_count > 1 or p.user_pattern != "*" or self._fixed_users:   # others may serve some users
            self.create_subscription(DiagnosticArray, "/diagnostics", self._on_diagnostics,
                                     qos_profile(Qos.RELIABLE), raw=True)

    # -- users -----------------------------------------------------------------------------------------
    def _follow(self, user: str) -> None:
        """Subscribe to the user's inputs and open its outputs: its own stage's ports, which its
        ``user_params`` overrides may change (a robot's ``odom`` for ``pdr/odom``)."""
        if not user or user in self.user_subs or not self.stage.serves(user):
            return
        self._closed_inputs.pop(user, None)
        ns = namespace_of_user(user)
        self.user_subs[user] = [self._open_input(p, join_ns(ns, p.topic), user) for p in self.stage.user_inputs(user)]
        for port in self.stage.user_outputs_of(user):       # ready (and matched) before the first output
            self._publisher(port.topic)
        self._user_seen[user] = self._monotonic()
        self._finished_users.discard(user)
        over = self.stage.user_params_text(user)
        self.get_logger().info(f"following user {user!r}" + (f" (user_params: {over})" if over else ""))

    def _published_by_others(self, topic: str, rel: str) -> bool:
        """Whether a node other than this one publishes ``topic`` (one of the stage's inputs, ``rel``)."""
        if len(self._own_outputs_of) != len(self.stage.templates):     # a template made since (user_params)
            self._own_outputs_of = dict.fromkeys(self.stage.templates)
            self._own_outputs = {p.topic for st in self.stage.templates.values() for p in st.outputs()}
        if rel not in self._own_outputs:
            return self.count_publishers(topic) > 0
        return any((i.node_name, i.node_namespace) not in self._me for i in self.get_publishers_info_by_topic(topic))

    def _users_publishing(self) -> set[str]:
        """The users in whose namespace another node publishes one of the stage's inputs."""
        found: set[str] = set()
        if self._fixed_users:
            for user in self._fixed_users:
                name = user_of_namespace(user)
                ns = namespace_of_user(name)
                if any(self._published_by_others(join_ns(ns, p.topic), p.topic) for p in self._inputs_of(name)):
                    found.add(name)
            return found
        rels = [p.topic for p in self.stage.inputs()]       # every user's (per-user overrides included)
        for topic, _types in self.get_topic_names_and_types():
            for rel in rels:
                ns = namespace_of_topic(topic, rel)
                if ns:
                    user = user_of_namespace(ns)
                    if user and user not in found and any(p.topic == rel for p in self._inputs_of(user)) \
                            and self._published_by_others(topic, rel):
                        found.add(user)
        return found

    def _inputs_of(self, user: str) -> list:
        """The user's inputs if this shard serves it (its overrides resolved), else the node's."""
        return self.stage.user_inputs(user) if self.stage.serves(user) else self.stage.template.inputs()

    def _discover_users(self) -> None:
        """Follow this shard's new users, notice users leaving, and watch the other shards' users."""
        now = self._monotonic()
        publishing = self._users_publishing()
        for user in sorted(publishing):
            if self.stage.serves(user):
                self._follow(user)
            elif user not in self._others:
                self._others[user] = now
        for user in list(self._others):
            if user not in publishing:
                del self._others[user]          # gone (or never ours to watch)
        ended = set(self.stage.ended)
        self._users_leaving(now, lambda user: user in publishing)
        for user in sorted(set(self.stage.ended) - ended):
            self.get_logger().info(f"user {user!r} finished: its end-of-input outputs are published; its output "
                                   f"topics close once their subscribers have them")
            self._close_outputs_later(user, now)
        self._close_outputs(now)

    # -- a user that left: its outputs close, as a per-user node's when it ends ------------------------
    def _close_outputs_later(self, user: str, now: float) -> None:
        """The publishers of a user that left: no longer used (a user coming back gets new ones),
        destroyed once every subscriber has acknowledged what they sent (or after
        :data:`CLOSE_WAIT_S`), so downstream multi-user nodes see the user leave too (its inputs there
        have no publisher any more) and finish it in turn."""
        pubs = [self._pubs.pop(t) for t in [p.topic for p in self.stage.user_outputs_of(user)] if t in self._pubs]
        if pubs:
            self._closing.append((now + CLOSE_WAIT_S, pubs))

    def _close_outputs(self, now: float) -> None:
        waiting = []
        for until, pubs in self._closing:
            if now < until and not all(p.wait_for_all_acked(Duration(nanoseconds=0)) for p in pubs):
                waiting.append((until, pubs))
                continue
            for pub in pubs:
                self._io_node().destroy_publisher(pub)
        self._closing = waiting

    def _before_user_finishes(self, user: str) -> None:
        # what it sent before leaving, still queued (a backlog: many polls' worth), comes first
        while True:
            before = self.taken
            self._poll(only=user)
            if self.taken == before:
                break

    # -- the users' inputs and outputs on the io node -------------------------------------------------
    def _io_node(self) -> Node:
        if self._io is None:
            self._io = Node(self.get_name() + "_io", namespace=self.get_namespace(), context=self.context,
                            start_parameter_services=False, enable_rosout=False)
        return self._io

    def _subscribe(self, port: Any, topic: str, callback: Callable[[Any, Any], None], raw: bool = False,
                   qos: QoSProfile | None = None):
        qos = qos if qos is not None else subscription_qos(port.qos, self.sensor_reliability)
        return self._io_node().create_subscription(msg_class(port.type), topic, callback, qos, raw=True)

    def _create_publisher(self, cls: type, topic: str, qos: QoSProfile):
        if not topic.startswith("/"):
            return super()._create_publisher(cls, topic, qos)
        return self._io_node().create_publisher(cls, topic, qos)

    def _close_input(self, inp: Any) -> None:
        if inp.user:
            report = inp.watch.report(self.get_clock().now().nanoseconds)
            state = LEFT if report.state == STALLED else report.state
            self._closed_inputs.setdefault(inp.user, []).append(report._replace(topic=inp.topic, state=state))
        super()._close_input(inp)

    def destroy_subscription(self, subscription: Any) -> bool:
        if self._io is not None and subscription in self._io.subscriptions:
            return self._io.destroy_subscription(subscription)
        return super().destroy_subscription(subscription)

    def destroy_node(self) -> None:
        if self._io is not None:
            self._io.destroy_node()
            self._io = None
        super().destroy_node()

    def _poll(self, only: str | None = None) -> None:
        """Take every user's (``only`` that user's) queued input messages and hand them to the users'
        stages (class doc)."""
        pending: dict[str, dict[str, list[tuple[int, int, bytes]]]] = {}
        for inp in list(self._inputs.values()):
            user = inp.user
            if not user or (only is not None and user != only):
                continue
            sub = inp.sub
            for _ in range(TAKE_PER_INPUT):
                with sub.handle:
                    got = sub.handle.take_message(sub.msg_type, True)
                if got is None:
                    break
                booked = self._received(inp, got[0], got[1])
                if booked is None:
                    continue
                if self.stage.user_echoes(user, inp.topic, booked[0]):
                    self.echoes_dropped += 1
                    continue
                pending.setdefault(user, {}).setdefault(inp.topic, []).append(booked)
        for user, topics in pending.items():
            self._user_runs(user, topics)
        if pending:
            self._log_rejections()

    def _user_runs(self, user: str, topics: dict[str, list[tuple[int, int, bytes]]]) -> None:
        """One user's messages of one poll: topics merged in header-stamp order (each keeps its arrival
        order), each run of one topic to the stage (in bulk where it can)."""
        merged = heapq.merge(*([(stamp, topic, recv, data) for stamp, recv, data in q] for topic, q in topics.items()),
                             key=lambda m: m[0])
        run_topic: str | None = None
        run: list[tuple[int, bytes]] = []
        for _stamp, topic, recv, data in merged:
            if topic != run_topic and run:
                self._user_run(user, run_topic, run)     # type: ignore[arg-type]
                run = []
            run_topic = topic
            run.append((recv, data))
        if run:
            self._user_run(user, run_topic, run)         # type: ignore[arg-type]

    def _user_run(self, user: str, topic: str, run: list[tuple[int, bytes]]) -> None:
        inp = self._inputs[join_ns(namespace_of_user(user), topic)]
        if inp.port.type in BULK_TYPES and self.stage.batch_handles(topic, user):
            items = bulk_items(inp.port.type, [d for _, d in run])
            if items is not None:
                self._publish([(t, m) for _, t, m in
                               self.stage.process_user_batch(user, topic, items, [r for r, _ in run])])
                return
        self._process_each(inp, topic, run, label=inp.resolved, user=user)

    def _deliver(self, w: Any, data: bytes, info: Any, *, probe: bool = False) -> None:
        """A message the stuck-subscription guard hands on (its probe's): as one run of its user."""
        booked = self._received(w, data, info, probe=probe)
        if booked is not None and w.user:
            self._user_runs(w.user, {w.topic: [booked]})
            self._log_rejections()

    # -- the stop ----------------------------------------------------------------------------------------
    def shutdown(self) -> None:
        """End of input for every user, one user after another, each user's outputs published as soon
        as they are made, so the users finished before the stop's deadline keep their end-of-input
        outputs (``tll_pf``'s smoothed path takes about a second of CPU per user and minute of its
        window: the one stop bound does not cover hundreds of users; users leaving before the stop are
        finished as they leave, without a deadline). A user whose finish would not end before the
        deadline (judged by the longest one so far) is skipped and named in a WARN."""
        deadline = self.stop_deadline if self.stop_deadline is not None else time.monotonic() + FINISH_ACK_TIMEOUT_S
        self._drain_polls(deadline - ACK_RESERVE_S - DRAIN_RESERVE_S)
        longest = 0.0
        skipped = []
        for user in sorted(self.stage.users):
            if time.monotonic() + longest > deadline - ACK_RESERVE_S:
                skipped.append(user)
                continue
            t0 = time.monotonic()
            self._publish(self.stage.run_finish_user(user))
            self._log_rejections()
            longest = max(longest, time.monotonic() - t0)
        if skipped:
            self.get_logger().warning(
                f"stopping: no time left before the stop deadline for the end-of-input outputs of {len(skipped)} "
                f"user(s): {', '.join(skipped[:20])}{' ...' if len(skipped) > 20 else ''} (their outputs so far "
                f"stand; users that leave before the stop are finished without a deadline)")
            for user in skipped:            # not finished; its counters stay for its last status
                self.stage.ended[user] = Ended(self.stage.users.pop(user))
        super().shutdown()

    def _drain_polls(self, until: float) -> int:
        """Hand the users' stages what DDS delivered before the stop signal and is still queued (the
        users' inputs are taken by the poll timer, which the process's drain may not have reached);
        until none is left, a message received after the signal was taken, or ``until`` (monotonic
        s). Returns how many were taken."""
        start = self.taken
        stop_ns = stop_time_ns()
        while time.monotonic() < until and self.last_rx_ns <= stop_ns:
            before = self.taken
            self._poll()
            if self.taken == before:
                break
        return self.taken - start

    # -- the other shards -----------------------------------------------------------------------------
    def _on_diagnostics(self, data: bytes) -> None:
        now = self._monotonic()
        try:
            names = status_names_cdr(data)
        except (ValueError, struct.error, UnicodeDecodeError):
            return                                   # not ours to judge: its publisher's problem
        for name in names:
            if name.endswith(self._suffix):
                user = user_of_namespace(name[: -len(self._suffix)])
                if user:
                    self._heard[user] = now

    def unserved(self) -> dict[str, int]:
        """The users of other shards whose inputs are published but whom no node has served (no status
        ``/<user>/<node name>`` heard) for ``user_timeout_s``: user -> the shard that should serve it."""
        now = self._monotonic()
        timeout = float(self.stage.params.user_timeout_s)
        out = {}
        for user, since in self._others.items():
            last = max(since, self._heard.get(user, since))
            if now - last > timeout:
                out[user] = shard_of(user, self.stage.params.shard_count)
        return out

    # -- /diagnostics ----------------------------------------------------------------------------------
    def diagnostics_msg(self, now_ns: int) -> DiagnosticArray:
        """The node's status (totals, users, unserved users of other shards) and one status per user."""
        arr = stage_diagnostics(self.get_fully_qualified_name(), self.stage, now_ns)
        st = arr.status[0]
        followed = sorted(u for u in self.user_subs if u not in self._finished_users)
        for kv in st.values:            # the users followed (subscribed), also before their first message
            if kv.key == "users":
                kv.value = ",".join(followed)
            elif kv.key == "users.count":
                kv.value = str(len(followed))
        unserved = self.unserved()
        if unserved:
            names = sorted(unserved)
            shards = sorted(set(unserved.values()))
            st.values.append(KeyValue(key="unserved.count", value=str(len(names))))
            st.values.append(KeyValue(key="unserved.users", value=",".join(names)))
            st.values.append(KeyValue(key="unserved.shards", value=",".join(map(str, shards))))
            what = (f"{len(names)} user(s) unserved for more than {self.stage.params.user_timeout_s:g} s: "
                    f"{', '.join(names[:10])}{' ...' if len(names) > 10 else ''} (shard(s) "
                    f"{', '.join(map(str, shards))} of {self.stage.params.shard_count}: is its process running?)")
            st.level = max(st.level, DiagnosticStatus.WARN)
            st.message = what if st.message == "ok" else f"{what}; {st.message}"
        else:
            st.values.append(KeyValue(key="unserved.count", value="0"))
        st.values.append(KeyValue(key="echoes_dropped", value=str(self.echoes_dropped)))
        by_user: dict[str, list] = {}
        for inp in self._inputs.values():
            if inp.user:
                report = inp.watch.report(now_ns)
                if inp.user in self._finished_users and report.state == STALLED:
                    report = report._replace(state=LEFT)
                by_user.setdefault(inp.user, []).append(report._replace(topic=inp.topic))
        fqn = self.get_fully_qualified_name()
        for user in sorted(set(self.stage.users) | set(by_user) | set(self.stage.ended)):
            # its stage, or the counters it ended with (finished: left, or the node stopping)
            inner = self.stage.user_status_stage(user)
            if inner is None:           # followed, no message yet
                inner = _Waiting(namespace_of_user(user))
            reports = by_user.get(user)
            if reports is None:         # its inputs are closed (it left): this is its last status
                reports = self._closed_inputs.pop(user, [])
                self.stage.ended.pop(user, None)
            one = with_inputs(stage_diagnostics(f"{namespace_of_user(user)}{self._suffix}", inner, now_ns),
                              reports, now_ns)
            one.status[0].values.append(KeyValue(key="served_by", value=fqn))
            over = self.stage.user_params_text(user)
            if over:
                one.status[0].values.append(KeyValue(key="user_params", value=over))
            one.status[0].values.append(KeyValue(key="busy_s", value=f"{self.stage.busy_s.get(user, 0.0):.3f}"))
            arr.status.append(one.status[0])
        return arr


class _Waiting:
    """A followed user before its first message: no counters yet."""

    def __init__(self, namespace: str) -> None:
        from indoor_loc.pipeline.stage import StageDiagnostics
        self.namespace = namespace
        self.diag = StageDiagnostics()

    @staticmethod
    def extra_diagnostics() -> dict[str, str]:
        return {"initialised": "false (no message yet)"}


def multi_user_factory(stage_cls: type[Stage]) -> tuple[type[Stage], Callable[[], StageNode] | None]:
    """``run_stage_node``'s stage class (for ``--help``) and node factory under ``--multi-user`` (a stage
    that is multi-user already, the back-end, is run as it is)."""
    if stage_cls.MULTI_USER:
        return stage_cls, None

    def make() -> MultiUserStageNode:
        return MultiUserStageNode(stage_cls)
    return multi_user(stage_cls), make
