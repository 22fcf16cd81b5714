"""StageNode: runs a :class:`~indoor_loc.pipeline.stage.Stage` as an rclpy node.

- ROS parameters are declared from the stage's Params dataclass (defaults and docs in one place);
  invalid values, ill-typed values and unknown names (a typo in a params file) stop start-up with
  a clear error and exit status 2; later ``ros2 param set`` calls on them are refused (parameters
  are read at start-up).
- Subscriptions/publishers come from the stage's ports with the contract's QoS, overridable the
  standard ROS 2 way (``qos_overrides./<ns>/<topic>.subscription.reliability|depth|history`` and
  ``….publisher.…`` parameters, rclpy ``QoSOverridingOptions``). Inputs of the *sensor* profile are
  best effort, so they match real drivers' best-effort publishers; ``sensor_reliability: reliable``
  (a node parameter, any namespace) makes them reliable, so a replay from the reliable player is
  never dropped in DDS. A publisher whose QoS cannot match a subscription is logged as an ERROR and
  counted (``rejected.incompatible_qos``, WARN in ``/diagnostics``), never a silent lack of input.
- A bad message is logged (throttled), counted and dropped; the node keeps running. The stage's
  notices (:meth:`Stage.take_notices`: a user's clock jumping back, say) are logged as WARN, each
  once, after every call into the stage.
- Fast path: an input the stage takes in runs (``Stage.batch_handles``) of a type
  :mod:`indoor_loc.bag.bulk` decodes (``sensor_msgs/Imu``, ``MagneticField``) is subscribed raw (CDR
  bytes, no Python message per sample). Each callback also takes whatever is already queued on the
  node's raw inputs (up to ``TAKE_MAX``), merges the topics in header-stamp order (each topic in its
  arrival order) and hands each run of one topic to ``Stage.process_batch``, decoded in bulk with the
  adapters' checks; a run that does not decode in bulk, or holds a message the adapter would reject,
  is deserialised and processed message by message, so each rejection keeps its reason. Nothing is
  held back for later: a timer tick sees every message taken before it, as before.
- ``/diagnostics`` gets one DiagnosticStatus about once a second (on the node's clock, so in bag
  time under ``use_sim_time``).
- SIGINT and SIGTERM end the node cleanly: the messages DDS had delivered to the node before the
  signal are processed first (bounded by ``DRAIN_TIMEOUT_S``; a second signal stops at once), then the
  stage's ``finish()`` outputs are published before the context shuts down.
- Multi-user stages (``Stage.MULTI_USER``): the node subscribes to the stage's inputs in every
  user namespace — those of the stage's ``users`` parameter, or, when it is empty, every namespace
  in which a publisher of one of the inputs appears (the ROS graph is polled every
  ``DISCOVERY_PERIOD_S``). A user whose input publishers have all been gone for the stage's
  ``user_timeout_s`` has left: ``finish_user`` runs (its outputs are published) and a discovered
  user's subscriptions are destroyed; it is followed again if it comes back. Per-user output
  publishers (``backend/<user>/path``) are created on first use.
"""
from __future__ import annotations

import array
import argparse
import copy
import dataclasses
import heapq
import os
import signal
import struct
import sys
import threading
import time
from typing import Any, Callable, Mapping, Sequence

import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from rcl_interfaces.msg import ParameterDescriptor, SetParametersResult
from rclpy.duration import Duration
from rclpy.exceptions import ParameterException
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.event_handler import PublisherEventCallbacks, SubscriptionEventCallbacks
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.qos_overriding_options import InvalidQosOverridesError, QoSOverridingOptions
from rclpy.serialization import deserialize_message
from rclpy.signals import SignalHandlerOptions

from indoor_loc.bag.bulk import BULK_TYPES, bulk_items

from indoor_loc.contract import Qos, join_ns, msg_class, namespace_of_topic
from indoor_loc.errors import BagError, ConfigError, IndoorLocError
from msg_adapters.diagnostics import stage_diagnostics, status_array
from indoor_loc.params import (flatten, leaves, load_params_file, misplaced_keys, nest_dotted, node_key,
                               params_from_dict, params_to_dict)
from indoor_loc.pipeline.stage import Stage, namespace_of_user, user_of_namespace

QOS_PROFILES: dict[Qos, QoSProfile] = {
    Qos.SENSOR: QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=200,
                           reliability=ReliabilityPolicy.BEST_EFFORT, durability=DurabilityPolicy.VOLATILE),
    Qos.RELIABLE: QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=50,
                             reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE),
    Qos.LATCHED: QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                            reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL),
    Qos.BEST_EFFORT: QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=5,
                                reliability=ReliabilityPolicy.BEST_EFFORT, durability=DurabilityPolicy.VOLATILE),
}

DIAGNOSTICS_PERIOD_S = 1.0
#: How long a stopping node waits for subscribers to acknowledge its last outputs (s).
FINISH_ACK_TIMEOUT_S = 8.0
#: How often a multi-user node polls the ROS graph for users joining and leaving (s).
DISCOVERY_PERIOD_S = 1.0
#: Parameters every rclpy node may carry besides the stage's own (not "unknown").
_BUILTIN_PARAMS = ("use_sim_time", "start_type_description_service")
#: Node parameter (beside the stage's own): reliability of the subscriptions to *sensor* inputs.
SENSOR_RELIABILITY_PARAM = "sensor_reliability"
_RELIABILITY = {"best_effort": ReliabilityPolicy.BEST_EFFORT, "reliable": ReliabilityPolicy.RELIABLE}
#: How often the spin loop returns to Python so SIGINT/SIGTERM are handled promptly (s).
_SPIN_PERIOD_S = 0.1
#: On SIGINT/SIGTERM a node processes what was queued for it before the signal for at most this
#: long (s; below ``indoor-loc up``'s 10 s between SIGINT and SIGTERM).
DRAIN_TIMEOUT_S = 8.0


#: History depth of the nodes' *subscriptions*, sized for bursts rather than for the steady rate:
#: a replay at 5x, a scheduler hiccup on a loaded machine or a slow first callback must not make
#: DDS overwrite messages the node has not taken yet (2000 IMU samples = 10 s at 200 Hz, ~1 MB).
SUB_DEPTH = {Qos.SENSOR: 2000, Qos.RELIABLE: 1000, Qos.BEST_EFFORT: 100}
#: ... and of reliable sensor inputs (``sensor_reliability: reliable``, a replay): a replay faster than
#: the node can follow on a busy machine queues the difference here (10 000 = 10 s of a 5x replay of a
#: 200 Hz IMU, ~4 MB) instead of overwriting it.
SUB_DEPTH_REPLAY = 10000
#: Raw sensor inputs (see ``StageNode`` "Fast path"): at most this many messages are taken from the
#: subscriptions per callback, so one burst cannot hold up timers and other inputs for long.
TAKE_MAX = 2048


def qos_profile(qos: Qos) -> QoSProfile:
    return QOS_PROFILES[qos]


#: History of a *sensor* output's publisher (``imu/data``): being reliable, it keeps what a subscriber
#: has not acknowledged yet, and overwrites the oldest beyond this — a loss for a subscriber starved of
#: CPU for a moment (the recorder during a fast replay). 2000 = 10 s at 200 Hz, 2 s of a 5x replay.
PUB_DEPTH_SENSOR = 2000
#: ... and of a *reliable* output's publisher (``pdr/odom``, ``wifi/fix``, poses): the contract's 50
#: is overrun by a burst of outputs — a node draining its queue at a stop, or catching up after a
#: stall — while a subscriber is starved of CPU (900 drained outputs lost one for a paused
#: subscriber); as deep as a reliable input's subscription (:data:`SUB_DEPTH`).
PUB_DEPTH_RELIABLE = 1000


def publisher_qos(qos: Qos) -> QoSProfile:
    """The QoS an output is published with: the contract's, except that *sensor* outputs are
    published reliable (a reliable writer serves best-effort and reliable readers alike, so a
    node whose sensor inputs were made reliable still hears another node's ``imu/data``), with a
    history of :data:`PUB_DEPTH_SENSOR`, and *reliable* outputs keep :data:`PUB_DEPTH_RELIABLE`."""
    base = QOS_PROFILES[qos]
    if qos == Qos.RELIABLE:
        return QoSProfile(history=base.history, depth=max(base.depth, PUB_DEPTH_RELIABLE),
                          reliability=base.reliability, durability=base.durability)
    if qos != Qos.SENSOR:
        return base
    return QoSProfile(history=base.history, depth=max(base.depth, PUB_DEPTH_SENSOR),
                      reliability=ReliabilityPolicy.RELIABLE, durability=base.durability)


def subscription_qos(qos: Qos, sensor_reliability: str = "best_effort") -> QoSProfile:
    """The contract QoS of an input, with the burst-sized depth of :data:`SUB_DEPTH`; *sensor*
    inputs get ``sensor_reliability`` (``best_effort``, the contract, or ``reliable``)."""
    base = QOS_PROFILES[qos]
    depth = SUB_DEPTH.get(qos, base.depth)
    reliability = _RELIABILITY[sensor_reliability] if qos == Qos.SENSOR else base.reliability
    if qos == Qos.SENSOR and reliability == ReliabilityPolicy.RELIABLE:
        depth = SUB_DEPTH_REPLAY
    return QoSProfile(history=base.history, depth=max(depth, base.depth), reliability=reliability,
                      durability=base.durability)


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


def _ros_value(value: Any) -> Any:
    """A Params default as a ROS parameter value (tuples -> lists; empty lists -> unset)."""
    if isinstance(value, tuple):
        value = list(value)
    if isinstance(value, list) and not value:
        return None
    return value


def _py_value(value: Any) -> Any:
    """A ROS parameter value as plain Python (arrays -> lists)."""
    if isinstance(value, (list, tuple, array.array)):
        return list(value)
    return value


class StageNode(Node):
    """An rclpy Node that feeds a Stage and publishes what it returns."""

    def __init__(self, stage_cls: type[Stage], **node_kwargs: Any) -> None:
        super().__init__(stage_cls.NODE_NAME, **node_kwargs)
        try:
            self._build(stage_cls)
        except BaseException:
            # a node that cannot start leaves nothing behind in the graph (its name is free for the
            # start-up error report, see :func:`report_startup_error`)
            self.destroy_node()
            raise

    def _build(self, stage_cls: type[Stage]) -> None:
        self._stage_cls = stage_cls
        self._gaps: dict[str, SequenceGaps] = {}    # resolved input topic -> sequence-gap counter
        self.taken = 0                              # input messages handled (all topics)
        self.last_rx_ns = 0                         # reception time (system clock) of the last one
        self.sensor_reliability = self._declare_sensor_reliability()
        values = self._declare_params(stage_cls.PARAMS)
        params = params_from_dict(stage_cls.PARAMS, values)   # raises ConfigError -> start-up fails
        self.stage: Stage = stage_cls(params, namespace=self.get_namespace())
        self.add_on_set_parameters_callback(self._on_set_params)
        self._pubs = {p.topic: self._create_publisher(msg_class(p.type), p.topic, publisher_qos(p.qos))
                      for p in self.stage.outputs()}
        # inputs the stage takes in runs (raw CDR, decoded in bulk): topic -> (subscription, gaps, type)
        self._raw: dict[str, tuple[Any, SequenceGaps, str]] = {}
        self._subs = [] if self.stage.MULTI_USER else [
            self._subscribe_raw(p) if self._batchable(p) else self._subscribe(p, p.topic, self._callback(p.topic))
            for p in self.stage.inputs()]
        if not self.stage.MULTI_USER:
            self._check_qos_overrides()
        # multi-user stages: user -> its subscriptions; user -> when its publishers were last seen
        self.user_subs: dict[str, list] = {}
        self._user_seen: dict[str, float] = {}
        self._finished_users: set[str] = set()
        self._fixed_users = tuple(getattr(self.stage.params, "users", ()) or ())
        if self.stage.MULTI_USER:
            for user in self._fixed_users:
                self._follow(user_of_namespace(user))
            self.create_timer(DISCOVERY_PERIOD_S, self._discover_users)
        self._diag_pub = self.create_publisher(DiagnosticArray, "/diagnostics", qos_profile(Qos.RELIABLE))
        self._last_rejected = 0
        self._refresh_publisher_counts()
        self.create_timer(DIAGNOSTICS_PERIOD_S, self._on_timer)
        self.get_logger().info(
            f"{stage_cls.NODE_NAME} up: in {[p.topic for p in self.stage.inputs()]}, "
            f"out {[p.topic for p in self.stage.outputs()]}")
        standing = self.stage.extra_diagnostics().get("error")
        if standing:   # a required input (radio map, graph) is missing: say so now, not per message
            self.get_logger().error(f"{stage_cls.NODE_NAME} cannot work: {standing}")

    def check_params_files(self, paths: list[str]) -> list[str]:
        """Log an ERROR for every key of these params files that names this node but does not
        reach it (a bare ``node_name:`` key while the node runs in a namespace: rcl ignores it
        without a word). Returns the messages."""
        msgs = []
        for path in paths:
            try:
                files = load_params_file(path)
            except ConfigError:
                continue          # rcl already refused or accepted the file; nothing to add
            for key in misplaced_keys(files, self.get_name(), self.get_namespace()):
                msgs.append(f"params file {path}: key {key!r} does not apply to {self.get_fully_qualified_name()} "
                            f"(rcl matches a bare node name only in the root namespace); its parameters are "
                            f"NOT in force. Key it {node_key(self.get_name())!r} to reach the node in any namespace")
        for m in msgs:
            self.get_logger().error(m)
        return msgs

    # -- QoS -------------------------------------------------------------------------------------
    def _declare_sensor_reliability(self) -> str:
        desc = ParameterDescriptor(
            description="reliability of the subscriptions to sensor inputs (imu/*): "
                        "best_effort (matches every publisher, e.g. real drivers) or reliable (a replay: "
                        "nothing dropped in DDS; a best-effort publisher then does not match)",
            read_only=True)
        value = self.declare_parameter(SENSOR_RELIABILITY_PARAM, "best_effort", desc).value
        if value not in _RELIABILITY:
            raise ConfigError(f"{SENSOR_RELIABILITY_PARAM}: expected one of {sorted(_RELIABILITY)}, got {value!r}")
        return str(value)

    def _subscribe(self, port: Any, topic: str, callback: Callable[[Any, Any], None], raw: bool = False):
        """A subscription to ``port`` on ``topic`` with its QoS (overridable by parameters)."""
        events = SubscriptionEventCallbacks(incompatible_qos=self._on_incompatible(topic, "publisher"))
        try:
            return self.create_subscription(
                msg_class(port.type), topic, callback, subscription_qos(port.qos, self.sensor_reliability),
                qos_overriding_options=QoSOverridingOptions.with_default_policies(), event_callbacks=events,
                raw=raw)
        except (InvalidQosOverridesError, RuntimeError, ValueError) as err:
            raise ConfigError(f"QoS of subscription {topic!r}: {err}") from err

    def _create_publisher(self, cls: type, topic: str, qos: QoSProfile):
        events = PublisherEventCallbacks(incompatible_qos=self._on_incompatible(topic, "subscription"),
                                         matched=self._on_matched(topic))
        try:
            return self.create_publisher(cls, topic, qos, event_callbacks=events,
                                         qos_overriding_options=QoSOverridingOptions.with_default_policies())
        except (InvalidQosOverridesError, RuntimeError, ValueError) as err:
            raise ConfigError(f"QoS of publisher {topic!r}: {err}") from err

    def _on_matched(self, topic: str) -> Callable[[Any], None]:
        """Log each change of an output's matched subscriptions: DDS matches a new subscriber
        asynchronously, and what is published before it matched never reaches it (volatile), so
        a tool that must not miss the first outputs (a recorder) waits for this line."""
        def cb(status: Any) -> None:
            self.get_logger().info(f"{topic}: {status.current_count} matched subscription(s)")
        return cb

    def _on_incompatible(self, topic: str, other: str) -> Callable[[Any], None]:
        def cb(event: Any) -> None:
            policy = getattr(getattr(event, "last_policy_kind", None), "name", "?").lower()
            reason = "incompatible_qos"
            self.stage._reject(reason, f"{topic}: a {other} with incompatible QoS ({policy}) does not match")
            self.get_logger().error(
                f"{self.resolve_topic_name(topic)}: a {other} with incompatible QoS ({policy}) cannot be matched; "
                f"its messages do NOT reach this node ({event.total_count} so far). "
                f"{'Set sensor_reliability or ' if other == 'publisher' else ''}qos_overrides."
                f"{self.resolve_topic_name(topic)}.{'subscription' if other == 'publisher' else 'publisher'}"
                f".reliability to match", throttle_duration_sec=5.0)
        return cb

    def _check_qos_overrides(self) -> None:
        """A ``qos_overrides.`` parameter naming no topic of this node (a typo, or a topic written
        without the node's namespace) would be ignored by rclpy without a word: refuse it."""
        overrides = getattr(self, "_parameter_overrides", {}) or {}
        stray = sorted(n for n in overrides if n.startswith("qos_overrides.") and not self.has_parameter(n))
        if stray:
            known = sorted(n for n in self._parameters if n.startswith("qos_overrides."))
            raise ConfigError(f"{self.get_fully_qualified_name()}: QoS override(s) {stray} name no topic of this "
                              f"node (topics are fully qualified, with the namespace); expected some of {known}")

    # -- parameters ------------------------------------------------------------------------------
    def _declare_params(self, params_cls: type) -> dict[str, Any]:
        """Declare one ROS parameter per Params field and return the values in force (nested for
        groups: a group's fields are declared with dotted names, ``stepometer.window_s``).

        Parameters are dynamically typed so ``step_length_m: 1`` in a YAML file (an int for a
        float) is coerced by :func:`params_from_dict` instead of failing inside rclpy; type errors
        are reported there as ConfigError. Overrides naming no field are a ConfigError too.
        """
        values: dict[str, Any] = {}
        names = []
        overrides = getattr(self, "_parameter_overrides", {}) or {}
        for name, f, default in leaves(params_cls):
            if isinstance(default, dict):
                # a free-form mapping (its owner validates it): each ``name.key`` given is declared
                for key in sorted(k for k in overrides if k.startswith(name + ".")):
                    names.append(key)
                    desc = ParameterDescriptor(description=f.metadata.get("doc", ""), dynamic_typing=True,
                                               read_only=True)
                    values[key] = _py_value(self.declare_parameter(key, None, desc).value)
                continue
            names.append(name)
            desc = ParameterDescriptor(description=f.metadata.get("doc", ""), dynamic_typing=True,
                                       read_only=True)   # read at start-up; a change needs a restart
            p = self.declare_parameter(name, _ros_value(default), desc)
            value = _py_value(p.value)
            if value is None and isinstance(default, (list, tuple)):
                value = type(default)()
            if value is not None or default is None:
                values[name] = value
        unknown = sorted(n for n in overrides if not self.has_parameter(n)
                         and n not in _BUILTIN_PARAMS and not n.startswith("qos_overrides."))
        if unknown:
            names = sorted(names)
            raise ConfigError(f"{params_cls.__name__}: unknown parameter(s) {unknown} for "
                              f"{self.get_fully_qualified_name()}; expected some of {names}")
        return nest_dotted(values)

    def _on_set_params(self, changes: list) -> SetParametersResult:
        fields = {name for name, _, _ in leaves(self._stage_cls.PARAMS)}
        ours = [p for p in changes if p.name in fields]
        if not ours:
            return SetParametersResult(successful=True)   # use_sim_time and friends
        current = flatten(params_to_dict(self.stage.params))
        current.update({p.name: _py_value(p.value) for p in ours})
        try:
            params_from_dict(self._stage_cls.PARAMS, current)
        except IndoorLocError as err:
            return SetParametersResult(successful=False, reason=str(err))
        # Parameters are read at start-up; changing them live needs a restart of the node.
        return SetParametersResult(successful=False, reason="parameters are read-only at run time; restart the node")

    # -- users (multi-user stages) -------------------------------------------------------------------
    def _follow(self, user: str) -> None:
        if not user or user in self.user_subs:
            return
        ns = namespace_of_user(user)
        self.user_subs[user] = [self._subscribe(p, join_ns(ns, p.topic), self._callback(p.topic, user))
                                for p in self.stage.inputs()]
        for port in self.stage.user_outputs():      # ready (and matched) before the first output
            self._publisher(port.topic.format(user=user))
        self._user_seen[user] = self._monotonic()
        self._finished_users.discard(user)
        self.get_logger().info(f"following user {user!r}")

    @staticmethod
    def _monotonic() -> float:
        return time.monotonic()

    def _discover_users(self) -> None:
        """Follow new users (namespaces publishing one of the inputs) and notice users leaving."""
        now = self._monotonic()
        if not self._fixed_users:
            rels = [p.topic for p in self.stage.inputs()]
            for name, _types in self.get_topic_names_and_types():
                for rel in rels:
                    ns = namespace_of_topic(name, rel)
                    if ns:
                        user = user_of_namespace(ns)
                        if user and self.count_publishers(name) > 0:
                            self._follow(user)
        timeout = float(getattr(self.stage.params, "user_timeout_s", 10.0))
        for user in list(self.user_subs):
            ns = namespace_of_user(user)
            if any(self.count_publishers(join_ns(ns, p.topic)) > 0 for p in self.stage.inputs()):
                self._user_seen[user] = now
                self._finished_users.discard(user)
                continue
            if user in self._finished_users or now - self._user_seen[user] < timeout:
                continue
            self.get_logger().info(f"user {user!r} left (no publishers for {timeout:g} s)")
            self._finished_users.add(user)
            self._publish(self.stage.run_finish_user(user))
            self._log_rejections()
            if not self._fixed_users:
                for sub in self.user_subs.pop(user):
                    self.destroy_subscription(sub)
                self._user_seen.pop(user, None)

    # -- messages ----------------------------------------------------------------------------------
    def _callback(self, topic: str, user: str | None = None) -> Callable[[Any, Any], None]:
        resolved = join_ns(namespace_of_user(user), topic) if user else topic
        gaps = self._gaps.setdefault(resolved, SequenceGaps(self._late_start(resolved)))

        def recount() -> int:
            return self.count_publishers(resolved)

        def cb(msg: Any, info: Any) -> None:
            self.taken += 1
            self.last_rx_ns = int(info.get("received_timestamp") or 0) if isinstance(info, dict) else 0
            now_ns = self.get_clock().now().nanoseconds
            lost = gaps.gap(info, recount)
            if lost:
                self.stage.diag.count_lost(topic, lost, now_ns)
                self.get_logger().warning(f"{topic}: {lost} message(s) lost before reaching this node "
                                          f"({sum(self.stage.diag.lost.values())} so far)", throttle_duration_sec=5.0)
            self._publish(self.stage.process(topic, msg, now_ns, user))
            self._log_rejections()
        return cb

    def _late_start(self, topic: str) -> Callable[[int], None]:
        """Said once when an input's first message is not its publisher's first: normal when a node
        joins a running driver (INFO), input missed in a replay (``sensor_reliability: reliable``:
        WARN; start the player once every subscriber has matched, see ``--min-subscribers``)."""
        def said(n: int) -> None:
            replay = self.sensor_reliability == "reliable"
            (self.get_logger().warning if replay else self.get_logger().info)(
                f"{self.resolve_topic_name(topic)}: the first message received is its publisher's #{n + 1}: {n} were "
                f"published before this subscription matched" + ("; a replay started too early" if replay else ""))
        return said

    # -- fast path: raw sensor inputs handled in runs ----------------------------------------------
    def _batchable(self, port: Any) -> bool:
        """Whether ``port`` is taken raw and handled in runs: a per-user stage with a batch path for
        it (:meth:`Stage.batch_handles`) and a message type :func:`indoor_loc.bag.bulk.bulk_items` decodes."""
        return not self.stage.MULTI_USER and port.type in BULK_TYPES and self.stage.batch_handles(port.topic)

    def _subscribe_raw(self, port: Any):
        gaps = self._gaps.setdefault(port.topic, SequenceGaps(self._late_start(port.topic)))
        sub = self._subscribe(port, port.topic, self._raw_callback(port.topic), raw=True)
        self._raw[port.topic] = (sub, gaps, port.type)
        return sub

    def _raw_callback(self, topic: str) -> Callable[[bytes, Any], None]:
        def cb(data: bytes, info: Any) -> None:
            self._take_raw({topic: [self._received(topic, data, info)]})
        return cb

    def _received(self, topic: str, data: bytes, info: Any) -> tuple[int, int, bytes]:
        """Book one raw message as the per-message callback does (count, reception time, sequence
        gaps); returns ``(header stamp ns, node-clock receive ns, data)``."""
        self.taken += 1
        self.last_rx_ns = int(info.get("received_timestamp") or 0) if isinstance(info, dict) else 0
        now_ns = self.get_clock().now().nanoseconds
        gaps = self._raw[topic][1]
        lost = gaps.gap(info, lambda: self.count_publishers(topic))
        if lost:
            self.stage.diag.count_lost(topic, lost, now_ns)
            self.get_logger().warning(f"{topic}: {lost} message(s) lost before reaching this node "
                                      f"({sum(self.stage.diag.lost.values())} so far)", throttle_duration_sec=5.0)
        return _cdr_stamp_ns(data), now_ns, data

    def _take_raw(self, pending: dict[str, list[tuple[int, int, bytes]]]) -> None:
        """Take every message already queued on the raw inputs (at most :data:`TAKE_MAX`), merge the
        topics in header-stamp order (each topic keeps its arrival order) and hand each run of one
        topic to the stage's batch path, decoded in bulk; a run that does not decode in bulk (or
        holds a message the adapter rejects) is deserialised and processed message by message, so
        every rejection is counted under its own reason as before."""
        n = sum(len(v) for v in pending.values())
        for topic, (sub, _gaps, _type) in self._raw.items():
            queue = pending.setdefault(topic, [])
            while n < TAKE_MAX:
                with sub.handle:
                    got = sub.handle.take_message(sub.msg_type, True)
                if got is None:
                    break
                queue.append(self._received(topic, got[0], got[1]))
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
        type_name = self._raw[topic][2]
        recv = [r for r, _ in run]
        items = bulk_items(type_name, [d for _, d in run])
        if items is not None:
            self._publish([(t, m) for _, t, m in self.stage.process_batch(topic, items, recv)])
            return
        cls = msg_class(type_name)
        for recv_ns, data in run:
            try:
                msg = deserialize_message(data, cls)
            except Exception as err:  # noqa: BLE001 - a node never dies on a message
                self.stage.diag.now_ns = recv_ns
                self.stage._reject("undecodable", f"{topic}: {type(err).__name__}: {err}")
                continue
            self._publish(self.stage.process(topic, msg, recv_ns))

    def _refresh_publisher_counts(self) -> None:
        for topic, gaps in self._gaps.items():
            gaps.publishers = self.count_publishers(topic)

    def _publisher(self, topic: str):
        pub = self._pubs.get(topic)
        if pub is None and self.stage.MULTI_USER:
            port = self.stage.output_port(topic)
            if port is not None:
                pub = self._pubs[topic] = self._create_publisher(msg_class(port.type), topic, publisher_qos(port.qos))
        return pub

    def _publish(self, outs: list) -> None:
        for topic, msg in outs:
            pub = self._publisher(topic)
            if pub is None:
                self.stage._reject("internal_error", f"stage returned undeclared output topic {topic!r}")
                self.get_logger().error(f"stage returned undeclared output topic {topic!r}", throttle_duration_sec=5.0)
                continue
            try:
                pub.publish(msg)
            except TypeError as err:     # wrong message class for the port: a stage bug, not fatal
                self.stage._reject("internal_error", f"publish on {topic!r}: {err}")
                self.get_logger().error(f"cannot publish on {topic!r}: {err}", throttle_duration_sec=5.0)

    def _log_rejections(self) -> None:
        """After a call into the stage: the latest rejection (throttled) and every notice (each once)."""
        total = sum(self.stage.diag.rejected.values())
        if total != self._last_rejected:
            self._last_rejected = total
            self.get_logger().warning(
                f"dropped message ({self.stage.diag.last_error_reason}; {total} so far): "
                f"{self.stage.diag.last_error.splitlines()[0] if self.stage.diag.last_error else ''}",
                throttle_duration_sec=5.0)
        for text in self.stage.take_notices():
            self.get_logger().warning(text)

    def _on_timer(self) -> None:
        self._refresh_publisher_counts()
        now_ns = self.get_clock().now().nanoseconds
        self._publish(self.stage.run_tick(now_ns))
        self._log_rejections()
        self._diag_pub.publish(self.diagnostics_msg(now_ns))

    def diagnostics_msg(self, now_ns: int) -> DiagnosticArray:
        return stage_diagnostics(self.get_fully_qualified_name(), self.stage, now_ns)

    def shutdown(self) -> None:
        """Publish the stage's end-of-input outputs (call while the context is still valid)."""
        self._publish(self.stage.run_finish())
        self._log_rejections()
        # the end-of-input outputs (a final smoothed path) must reach reliable subscribers before
        # the process ends: wait (bounded) until every reliable publisher's messages are acked
        # (a loaded machine can take seconds); what is still unacknowledged then is said, not lost silently
        for topic, pub in self._pubs.items():
            if pub.qos_profile.reliability == ReliabilityPolicy.RELIABLE and pub.get_subscription_count() > 0:
                if not pub.wait_for_all_acked(Duration(seconds=FINISH_ACK_TIMEOUT_S)):
                    self.get_logger().warning(
                        f"stopping: {topic}: not every subscriber acknowledged the last messages within "
                        f"{FINISH_ACK_TIMEOUT_S:g} s; they may have missed the end of the output")


def _cdr_stamp_ns(data: bytes) -> int:
    """``header.stamp`` (ns) of a little-endian CDR message that starts with a ``std_msgs/Header``
    (every bulk-decoded type); 0 when it cannot be read (the message then sorts first; the stage
    judges it)."""
    if len(data) < 12 or data[:2] != b"\x00\x01":
        return 0
    sec, nsec = struct.unpack_from("<iI", data, 4)
    return sec * 1_000_000_000 + nsec


#: Set by the first SIGINT/SIGTERM (a stop was asked for), and by the second (stop at once).
_STOP = threading.Event()
_STOP_NOW = threading.Event()
#: When the first SIGINT/SIGTERM came (system clock, ns; 0 before).
_STOP_AT_NS = [0]


def _request_stop(signum: int, frame: Any) -> None:
    # Only a flag: an exception raised from a signal handler can surface inside a pybind11 call
    # (rclpy's take_message) as a RuntimeError ("Unable to convert call argument") instead of a
    # KeyboardInterrupt and end the process with a traceback. The spin loops poll the flag.
    if not _STOP.is_set():
        _STOP_AT_NS[0] = time.time_ns()
    (_STOP_NOW if _STOP.is_set() else _STOP).set()


def stop_time_ns() -> int:
    """When the first SIGINT/SIGTERM arrived (system clock, ns), or now if none did: messages DDS
    received before it are the ones a stopping node still handles."""
    return _STOP_AT_NS[0] if _STOP.is_set() and _STOP_AT_NS[0] else time.time_ns()


def stop_requested() -> bool:
    """Whether SIGINT/SIGTERM asked this process to stop (see :func:`raise_on_signals`)."""
    return _STOP.is_set()


def raise_on_signals() -> dict[int, Any]:
    """From now on SIGINT and SIGTERM set :func:`stop_requested`, which the spin loops turn into a
    KeyboardInterrupt between two callbacks (rclpy's own handlers must be off:
    ``rclpy.init(signal_handler_options=SignalHandlerOptions.NO)``, so the context stays valid for a
    clean stop; SIGINT explicitly too: a child started in the background inherits it ignored).
    Returns the previous handlers for :func:`restore_signals` (empty off the main thread)."""
    if threading.current_thread() is not threading.main_thread():
        return {}
    _STOP.clear()
    _STOP_NOW.clear()
    _STOP_AT_NS[0] = 0
    return {sig: signal.signal(sig, _request_stop) for sig in (signal.SIGINT, signal.SIGTERM)}


def check_stop() -> None:
    """Raise KeyboardInterrupt if a signal asked to stop (call between two units of work)."""
    if _STOP.is_set():
        raise KeyboardInterrupt("stop requested by a signal")


def ignore_signals(old: dict[int, Any]) -> None:
    """During clean-up: a second signal must not cut it short."""
    for sig in old:
        signal.signal(sig, signal.SIG_IGN)


def restore_signals(old: dict[int, Any]) -> None:
    for sig, handler in old.items():
        signal.signal(sig, handler)


def drain(executor: SingleThreadedExecutor, node: Node, taken: Callable[[], int],
          timeout_s: float = DRAIN_TIMEOUT_S) -> int:
    """Run the callbacks of the messages DDS delivered before the stop signal (:func:`stop_time_ns`)
    until none is left (three idle spins in a row), a message received after it was handled (``node.last_rx_ns``: a publisher
    still running must not hold the node up), or ``timeout_s`` passes; ``taken()`` counts the
    messages handled so far. Returns how many were handled here."""
    start = taken()
    stop_ns = stop_time_ns()
    deadline = time.monotonic() + timeout_s
    idle = 0
    while (idle < 3 and time.monotonic() < deadline and node.context.ok() and not _STOP_NOW.is_set()
           and int(getattr(node, "last_rx_ns", 0)) <= stop_ns):
        before = taken()
        executor.spin_once(timeout_sec=0.02)
        idle = idle + 1 if taken() == before else 0
    return taken() - start


def spin_node(node: Node, taken: Callable[[], int] | None = None) -> None:
    """Spin until SIGINT/SIGTERM (raised here as KeyboardInterrupt) or an external shutdown.

    rclpy's own signal handlers are off (see :func:`run_stage_node`); the executor wakes up every
    ``_SPIN_PERIOD_S`` to look at :func:`stop_requested`; the context stays valid afterwards. On a
    signal, what is already queued for the node is processed first (:func:`drain`, with
    ``taken`` or the node's ``taken`` counter); a second signal interrupts that. Ends with
    KeyboardInterrupt on a signal.
    """
    executor = SingleThreadedExecutor(context=node.context)
    executor.add_node(node)
    count = taken or (lambda: int(getattr(node, "taken", 0)))
    try:
        while node.context.ok() and not _STOP.is_set():
            executor.spin_once(timeout_sec=_SPIN_PERIOD_S)
        if _STOP.is_set():
            n = drain(executor, node, count)
            if n:
                node.get_logger().info(f"stopping: processed the {n} message(s) already received")
            raise KeyboardInterrupt("stop requested by a signal")
    finally:
        executor.remove_node(node)
        executor.shutdown(timeout_sec=0.0)


def run_stage_node(stage_cls: type[Stage], args: list[str] | None = None, *,
                   node_factory: Callable[[], StageNode] | None = None,
                   port_params: Mapping[str, Sequence[Any]] | None = None) -> int:
    """``main()`` of every stage node: ``-h``/``--help`` prints :func:`node_usage` (with the topics
    the values of ``port_params`` select); otherwise
    ``rclpy.init(args)`` (``--ros-args -r __ns:=/alice --params-file F -p k:=v`` as usual), build
    the node (``node_factory()`` or ``StageNode(stage_cls)``) and spin until SIGINT/SIGTERM.

    Returns 0 on a clean stop, 2 on invalid parameters/arguments (message on stderr).
    """
    argv = list(sys.argv if args is None else args)
    user_args = argv[1:argv.index("--ros-args")] if "--ros-args" in argv else argv[1:]
    if any(a in ("-h", "--help") for a in user_args):
        print(node_usage(stage_cls, port_params))
        return 0
    name = stage_cls.NODE_NAME
    try:
        rclpy.init(args=argv, signal_handler_options=SignalHandlerOptions.NO)
    except (RuntimeError, ValueError) as err:     # rclpy's RCLError is a RuntimeError
        print(f"[{name}] invalid arguments: {err}", file=sys.stderr)
        return 2
    old = raise_on_signals()      # both signals end the spin as KeyboardInterrupt
    node: StageNode | None = None
    status = 0
    try:
        node = node_factory() if node_factory is not None else StageNode(stage_cls)
        node.check_params_files(params_file_args(argv))
        spin_node(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except (IndoorLocError, ParameterException) as err:
        print(f"[{name}] configuration error: {err}", file=sys.stderr)
        status = 2
        if node is None:          # start-up failed: say so in /diagnostics too, not only on stderr
            exit_after(STARTUP_ERROR_WAIT_S + STARTUP_ERROR_ACK_S + STARTUP_ERROR_GRACE_S, status, name)
            report_startup_error(name, f"configuration error: {err}")
    finally:
        ignore_signals(old)
        if node is not None:
            if node.context.ok():
                try:
                    node.shutdown()
                except Exception as err:  # noqa: BLE001 - a stage bug in finish() must not skip clean-up
                    print(f"[{name}] finish() failed: {type(err).__name__}: {err}", file=sys.stderr)
                    status = status or 1
            node.destroy_node()
        rclpy.try_shutdown()
        restore_signals(old)
    return status


#: A node that cannot start waits this long at most for a /diagnostics subscriber to match (s).
STARTUP_ERROR_WAIT_S = 10.0
#: ... but gives up after this long if it has seen no other node at all (s): a little over Fast
#: DDS's periodic participant announcement (3 s), so one lost initial announcement burst is covered.
STARTUP_ERROR_ALONE_S = 4.0
#: ... and for the subscribers it found to acknowledge its ERROR (s; returns as soon as they did). A
#: subscriber whose own side of the match completes later gets the message resent only while this
#: node still exists, which on a loaded machine can take seconds.
STARTUP_ERROR_ACK_S = 5.0
#: ... and the report plus the middleware's shutdown get this much more before the process exits
#: regardless (s): a node that cannot start always ends, also if DDS stalls in its shutdown.
STARTUP_ERROR_GRACE_S = 15.0


def exit_after(seconds: float, status: int, name: str) -> threading.Timer:
    """Make sure this process ends within ``seconds`` with ``status``: a daemon timer that says so on
    stderr and ends the process at once (``os._exit``: no clean-up is left to wait for). For a node
    that is already exiting with an error, whose last steps talk to the middleware."""
    def _exit() -> None:
        print(f"[{name}] still not ended {seconds:g} s after its start-up error: exiting", file=sys.stderr,
              flush=True)
        os._exit(status)
    timer = threading.Timer(seconds, _exit)
    timer.daemon = True
    timer.start()
    return timer


def report_startup_error(node_name: str, message: str, *, wait_s: float = STARTUP_ERROR_WAIT_S,
                         alone_s: float = STARTUP_ERROR_ALONE_S) -> bool:
    """Publish one ``/diagnostics`` ERROR for a node that cannot start (name and namespace from the
    command line's ``--ros-args``, as the node would have had), so a monitor sees it beside the
    running nodes and not only the terminal. A new participant is discovered asynchronously, and on
    a loaded machine that takes seconds: the node waits up to ``wait_s`` for subscribers to match
    (the count must then hold still for a moment, since several monitors match one after another),
    or only ``alone_s`` while it sees no other node in the domain; then it publishes and waits up to
    :data:`STARTUP_ERROR_ACK_S` for the acknowledgements. Returns whether a subscriber acknowledged
    it; never raises (the caller is already reporting an error)."""
    try:
        node = Node(node_name)
    except Exception:  # noqa: BLE001 - the node itself cannot be made: stderr has said it all
        return False
    try:
        pub = node.create_publisher(DiagnosticArray, "/diagnostics", qos_profile(Qos.RELIABLE))
        start = time.monotonic()
        last, since, others = -1, start, False
        while not _STOP.is_set():
            now = time.monotonic()
            if now - start >= wait_s or (not others and now - start >= alone_s):
                break
            n = pub.get_subscription_count()
            if n != last:
                last, since = n, now
            elif n > 0 and now - since >= 0.3:
                break
            others = others or len(node.get_node_names()) > 1
            time.sleep(0.02)
        pub.publish(status_array(node.get_fully_qualified_name(), 2, message, {"error": message}, time.time_ns()))
        return bool(pub.get_subscription_count() > 0
                    and pub.wait_for_all_acked(Duration(seconds=STARTUP_ERROR_ACK_S)))
    except Exception:  # noqa: BLE001 - best effort: the error is on stderr already
        return False
    finally:
        node.destroy_node()


def params_file_args(argv: list[str]) -> list[str]:
    """The ``--params-file FILE`` arguments inside ``--ros-args`` sections of ``argv``."""
    out, in_ros = [], False
    for i, a in enumerate(argv):
        if a == "--ros-args":
            in_ros = True
        elif a == "--":
            in_ros = False
        elif in_ros and a == "--params-file" and i + 1 < len(argv):
            out.append(argv[i + 1])
    return out


def _ports_text(ports: Sequence[Any], prefix: str = "") -> str:
    return ", ".join(f"{prefix}{p.topic} [{p.type}]" for p in ports)


def _port_variants(stage: Stage, port_params: Mapping[str, Sequence[Any]], prefix: str) -> tuple[list[str], list[str]]:
    """Help lines (subscriptions, publications) for the topics other values of a parameter select:
    the ports of ``stage`` with each value of ``port_params`` (``{parameter: [other values]}``, top-level
    parameters), compared with its own. Only the ports are asked for (a copy of the stage with the
    other value), so a value that needs files to start (a radio map) is described all the same."""
    subs: list[str] = []
    pubs: list[str] = []
    for name, values in port_params.items():
        default = getattr(stage.params, name)
        for lines, ports in ((subs, lambda s: s.inputs()), (pubs, lambda s: s.outputs() + s.user_outputs())):
            said: dict[str, list[Any]] = {}      # what changes -> the values that change it so
            for value in values:
                alt = copy.copy(stage)
                alt.params = dataclasses.replace(stage.params, **{name: value})
                mine, other = ports(stage), ports(alt)
                added = [p for p in other if p not in mine]
                gone = [p for p in mine if p not in other]
                if added and gone:
                    said.setdefault(f"{_ports_text(added, prefix)} instead of {_ports_text(gone, prefix)}", []).append(value)
                elif added or gone:
                    said.setdefault(f"also {_ports_text(added, prefix)}" if added else
                                    f"without {_ports_text(gone, prefix)}", []).append(value)
            for text, vals in said.items():
                lines.append(f"  with {name} {' or '.join(repr(v) for v in vals)} (default {default!r}): {text}")
    return subs, pubs


def node_usage(stage_cls: type[Stage], port_params: Mapping[str, Sequence[Any]] | None = None) -> str:
    """The node's ``--help``: usage, the stage's doc, its parameters and its topics with the default
    parameters, and, for each value of ``port_params`` (``{parameter: [other values]}``), the topics
    that value subscribes or publishes instead or as well."""
    lines = [f"usage: ros2 run indoor_loc {stage_cls.NODE_NAME} [--ros-args -r __ns:=/USER "
             f"--params-file FILE -p NAME:=VALUE ...]", "", (stage_cls.__doc__ or "").strip(), "", "parameters:"]
    for name, f, default in leaves(stage_cls.PARAMS):
        lines.append(f"  {name} (default {default!r}): {f.metadata.get('doc', '')}")
    try:
        stage = stage_cls(stage_cls.PARAMS(), namespace="")
    except IndoorLocError as err:     # a stage that needs files to start still gets its help printed
        lines += ["", f"(topics unavailable with default parameters: {err})"]
        return "\n".join(lines)
    lines.append("")
    per_user = "/<user>/" if stage.MULTI_USER else ""
    subs, pubs = _port_variants(stage, port_params or {}, per_user)
    lines.append("subscribes: " + _ports_text(stage.inputs(), per_user)
                 + (" in every user namespace (parameter users, else discovered)" if per_user else ""))
    lines += subs
    lines.append("publishes:  " + _ports_text(stage.outputs() + stage.user_outputs()) + ", /diagnostics")
    lines += pubs
    return "\n".join(lines)


def run_option_node(prog: str, description: str, add_arguments: Callable[[argparse.ArgumentParser], None],
                    run: Callable[[argparse.Namespace, list[str]], int], args: list[str] | None = None) -> int:
    """``main()`` of a node with its own command-line options (recorder, player): the options come
    before ``--ros-args`` and only what follows goes to rcl (so ``--remap OLD:=NEW`` is not read by
    rcl as a deprecated remapping rule). ``run(options, rcl_args)``; ConfigError/BagError -> exit 2."""
    argv = sys.argv if args is None else args
    cut = argv.index("--ros-args") if "--ros-args" in argv else len(argv)
    parser = argparse.ArgumentParser(prog=prog, description=description)
    add_arguments(parser)
    options = parser.parse_args(argv[1:cut])
    try:
        return run(options, argv[:1] + argv[cut:])
    except (ConfigError, BagError) as err:
        print(f"{prog}: error: {err}", file=sys.stderr)
        return 2
