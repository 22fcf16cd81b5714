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
- A bad message is logged (throttled), counted and dropped; the node keeps running. Every input is
  subscribed raw and deserialised by the node, so a sample that does not decode (empty, truncated,
  garbage) is counted ``undecodable``; a reliable subscription stuck behind a sample DDS refused (an
  empty one) is found and made anew (:mod:`indoor_loc.nodes.inputs`). The stage's notices
  (:meth:`Stage.take_notices`: a user's clock jumping back, say) are logged as WARN, each once, after
  every call into the stage.
- Fast path: an input the stage takes in runs (``Stage.batch_handles``) of a type
  :mod:`indoor_loc.bag.bulk` decodes (``sensor_msgs/Imu``, ``MagneticField``) gets no Python message
  per sample: each callback takes whatever is queued on the node's fast inputs, merges them in stamp
  order and hands each run of one topic to ``Stage.process_batch`` (:mod:`indoor_loc.nodes.inputs`).
- Liveness: each input (each user's, for a multi-user stage) says in ``/diagnostics`` whether it is
  waiting, flowing or stalled, how long since its last message, and how often its publisher
  restarted (``in.<topic>.*``; a stalled input is a WARN, an ERROR if the stage marks it
  ``Port.required``; :mod:`indoor_loc.nodes.liveness`).
- The node's clock going back (``/clock`` under ``use_sim_time``: a bag played in a loop, a
  simulation restarted) by at least the stage's :meth:`Stage.clock_jump_threshold_ns` (0: not
  followed) calls :meth:`Stage.run_clock_jump`; its outputs are published and its notices logged.
- ``/diagnostics`` gets one DiagnosticStatus about once a second (on the node's clock, so in bag
  time under ``use_sim_time``).
- SIGINT and SIGTERM end the node cleanly within a bound, one deadline for the whole stop
  (:mod:`indoor_loc.nodes.process`): the messages DDS had delivered to the node before the signal
  are processed first, then the stage's ``finish()`` outputs and a last ``/diagnostics`` status are
  published and their acknowledgements awaited, all publishers together, until the stop's deadline;
  what was cut short is logged. A second signal stops at once.
- Service requests (the parameter services, a node's own) are answered between two callbacks
  whatever is queued (:class:`~indoor_loc.nodes.process.ServicePoll`), so a burst of messages does not
  hold them up; all in the one executor thread (the stage is never entered concurrently).
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
import time
from typing import Any, Callable

from diagnostic_msgs.msg import DiagnosticArray
from rcl_interfaces.msg import ParameterDescriptor, SetParametersResult
from rclpy.clock import Clock, ClockType, JumpHandle, JumpThreshold, TimeJump
from rclpy.duration import Duration
from rclpy.event_handler import PublisherEventCallbacks, SubscriptionEventCallbacks
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rclpy.qos_overriding_options import InvalidQosOverridesError, QoSOverridingOptions

from indoor_loc.contract import Qos, join_ns, msg_class, namespace_of_topic
from indoor_loc.errors import ConfigError, IndoorLocError
from indoor_loc.nodes.inputs import Input, InputsMixin
from indoor_loc.nodes.liveness import LEFT, STALLED, SequenceGaps
from indoor_loc.nodes.qos import RELIABILITY, SENSOR_RELIABILITY_PARAM, publisher_qos, qos_profile, subscription_qos
from indoor_loc.params import (flatten, leaves, load_params_file, misplaced_keys, nest_dotted, node_key,
                               params_from_dict, params_to_dict)
from indoor_loc.pipeline.stage import Stage, namespace_of_user, user_of_namespace
from msg_adapters.diagnostics import stage_diagnostics, with_inputs

#: How often a node publishes its /diagnostics status (s, on its clock).
DIAGNOSTICS_PERIOD_S = 1.0
#: How long a stopping node waits for subscribers to acknowledge its last outputs (s), all
#: publishers together, when no stop deadline was set (``StageNode.stop_deadline``).
FINISH_ACK_TIMEOUT_S = 8.0
#: How often a multi-user node polls the ROS graph for users joining and leaving (s).
DISCOVERY_PERIOD_S = 1.0
#: Parameters every rclpy node may carry besides the stage's own (not "unknown").
_BUILTIN_PARAMS = ("use_sim_time", "start_type_description_service")


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


class StageNode(InputsMixin, Node):
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
        self._inputs: dict[str, Input] = {}         # resolved input topic -> its subscription and watch
        self._gaps: dict[str, SequenceGaps] = {}    # resolved input topic -> its sequence-gap counter
        self._raw: dict[str, Input] = {}            # inputs the stage takes in runs (fast path), by topic
        self.taken = 0                              # input messages handled (all topics)
        self.last_rx_ns = 0                         # reception time (system clock) of the last one
        #: monotonic time by which :meth:`shutdown` is over (set by the process on a stop; None: no bound)
        self.stop_deadline: float | None = None
        self.sensor_reliability = self._declare_sensor_reliability()
        self._declare_extra_params()
        values = self._declare_params(stage_cls.PARAMS)
        params = params_from_dict(stage_cls.PARAMS, values)   # raises ConfigError -> start-up fails
        self.stage: Stage = stage_cls(params, namespace=self.get_namespace())
        # outputs a stage can build already serialised go out as CDR (the same message): a long
        # pf/path or pdr_kf/path costs 0.03 s instead of 0.4 s at 20 000 poses (docs/benchmarks/soak.md)
        self.stage.raw_outputs = True
        self.add_on_set_parameters_callback(self._on_set_params)
        self._pubs = {p.topic: self._create_publisher(msg_class(p.type), p.topic, publisher_qos(p.qos))
                      for p in self.stage.outputs()}
        self._open_extra_outputs()
        if not self.stage.MULTI_USER:
            for p in self.stage.inputs():
                self._open_input(p, p.topic)
            self._check_qos_overrides()
        # multi-user stages: user -> its inputs; user -> when its publishers were last seen
        self.user_subs: dict[str, list[Input]] = {}
        self._user_seen: dict[str, float] = {}
        self._finished_users: set[str] = set()
        self._fixed_users = tuple(getattr(self.stage.params, "users", ()) or ())
        if self.stage.MULTI_USER:
            for user in self._fixed_users:
                self._follow(user_of_namespace(user))
            # steady clock: on sim time a node-clock timer waits for /clock, and a player waiting for
            # this node's subscriptions (``--consumers``) would wait for it in vain
            self.create_timer(DISCOVERY_PERIOD_S, self._discover_users, clock=Clock(clock_type=ClockType.STEADY_TIME))
        self._diag_pub = self.create_publisher(DiagnosticArray, "/diagnostics", qos_profile(Qos.RELIABLE))
        #: monotonic time of the last /diagnostics status (nodes/responsive.py publishes one when it is old)
        self.diag_published_at = time.monotonic()
        self._last_rejected = 0
        self._watch_inputs(self.get_clock().now().nanoseconds)
        self.create_timer(DIAGNOSTICS_PERIOD_S, self._on_timer)
        self._jump_handle = self._follow_clock_jumps()
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

    def _declare_extra_params(self) -> None:
        """Node parameters of a mixin (``nodes/tf_out.py``), declared before the stage's own."""

    def _open_extra_outputs(self) -> None:
        """Publishers of a mixin beside the stage's outputs, once the stage is built."""

    # -- QoS -------------------------------------------------------------------------------------
    def _declare_sensor_reliability(self) -> str:
        desc = ParameterDescriptor(
            description="reliability of the subscriptions to sensor inputs (imu/*): "
                        "best_effort (matches every publisher, e.g. real drivers) or reliable (a replay: "
                        "nothing dropped in DDS; a best-effort publisher then does not match)",
            read_only=True)
        value = self.declare_parameter(SENSOR_RELIABILITY_PARAM, "best_effort", desc).value
        if value not in RELIABILITY:
            raise ConfigError(f"{SENSOR_RELIABILITY_PARAM}: expected one of {sorted(RELIABILITY)}, got {value!r}")
        return str(value)

    def _subscribe(self, port: Any, topic: str, callback: Callable[[Any, Any], None], raw: bool = False,
                   qos: QoSProfile | None = None):
        """A subscription to ``port`` on ``topic`` with its QoS (overridable by parameters), or with
        ``qos`` as it is (a subscription made anew: its overrides are declared already)."""
        events = SubscriptionEventCallbacks(incompatible_qos=self._on_incompatible(topic, "publisher"))
        try:
            if qos is not None:
                return self.create_subscription(msg_class(port.type), topic, callback, qos, event_callbacks=events,
                                                raw=raw)
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
        self.user_subs[user] = [self._open_input(p, join_ns(ns, p.topic), user) for p in self.stage.inputs()]
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
        self._users_leaving(now, lambda user: any(
            self.count_publishers(join_ns(namespace_of_user(user), p.topic)) > 0 for p in self.stage.inputs()))

    def _users_leaving(self, now: float, publishing: Callable[[str], bool]) -> None:
        """Users whose input publishers have all been gone for the stage's ``user_timeout_s``: their
        end-of-input outputs published (:meth:`_before_user_finishes` first) and, for a discovered
        user, its subscriptions closed (followed again if it comes back)."""
        timeout = float(getattr(self.stage.params, "user_timeout_s", 10.0))
        for user in list(self.user_subs):
            if publishing(user):
                self._user_seen[user] = now
                self._finished_users.discard(user)
                continue
            if user in self._finished_users or now - self._user_seen[user] < timeout:
                continue
            self.get_logger().info(f"user {user!r} left (no publishers for {timeout:g} s)")
            self._before_user_finishes(user)
            self._finished_users.add(user)
            self._publish(self.stage.run_finish_user(user))
            self._log_rejections()
            if not self._fixed_users:
                for inp in self.user_subs.pop(user):
                    self._close_input(inp)
                self._user_seen.pop(user, None)
                self._finished_users.discard(user)

    def _before_user_finishes(self, user: str) -> None:
        """Called as a user leaves, before its end-of-input outputs (a node that queues input drains it)."""

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

    # -- the node's clock going back ---------------------------------------------------------------
    def _follow_clock_jumps(self) -> JumpHandle | None:
        """Call the stage's :meth:`Stage.run_clock_jump` when the node's clock goes back by at least
        its :meth:`Stage.clock_jump_threshold_ns` (0: never). Under ``use_sim_time`` that is ``/clock``
        going back (a bag played in a loop, a simulation restarted); the callback runs in the
        executor's thread (``/clock`` is this node's subscription), never beside a message callback."""
        threshold_ns = int(self.stage.clock_jump_threshold_ns())
        if threshold_ns <= 0:
            return None
        return self.get_clock().create_jump_callback(
            JumpThreshold(min_forward=None, min_backward=Duration(nanoseconds=-threshold_ns), on_clock_change=False),
            post_callback=self._on_clock_jump)

    def _on_clock_jump(self, jump: TimeJump) -> None:
        now_ns = self.get_clock().now().nanoseconds
        self._publish(self.stage.run_clock_jump(-jump.delta.nanoseconds, now_ns))
        self._log_rejections()

    def _on_timer(self) -> None:
        now_ns = self.get_clock().now().nanoseconds
        self._watch_inputs(now_ns)
        self._publish(self.stage.run_tick(now_ns))
        self._log_rejections()
        self._diag_pub.publish(self.diagnostics_msg(now_ns))
        self.diag_published_at = time.monotonic()

    def diagnostics_when_busy(self, now_ns: int) -> bool:
        """The /diagnostics status from :class:`~indoor_loc.nodes.responsive.Responsive`'s thread while this
        node's executor thread is busy with a long callback: the counters as they stand (the stage is
        not entered). Returns whether one was published."""
        msg = self.diagnostics_msg(now_ns)
        self._diag_pub.publish(msg)
        self.diag_published_at = time.monotonic()
        return True

    def diagnostics_msg(self, now_ns: int) -> DiagnosticArray:
        arr = stage_diagnostics(self.get_fully_qualified_name(), self.stage, now_ns)
        reports = [inp.watch.report(now_ns) for inp in self._inputs.values()]
        reports = [r._replace(state=LEFT) if inp.user in self._finished_users and r.state == STALLED else r
                   for inp, r in zip(self._inputs.values(), reports)]
        return with_inputs(arr, reports, now_ns)

    # -- the stop --------------------------------------------------------------------------------
    def finish_budget_s(self) -> float:
        """How long the stage's ``finish()`` may take (its ``finish_budget_s``; 0: not bounded by it)."""
        return float(getattr(self.stage.params, "finish_budget_s", 0.0) or 0.0)

    def shutdown(self) -> None:
        """Publish the stage's end-of-input outputs and a last /diagnostics status, then wait (until
        :attr:`stop_deadline`, or :data:`FINISH_ACK_TIMEOUT_S`) for reliable subscribers to
        acknowledge them (call while the context is still valid)."""
        deadline = self.stop_deadline if self.stop_deadline is not None else time.monotonic() + FINISH_ACK_TIMEOUT_S
        self._publish(self.stage.run_finish())
        self._log_rejections()
        try:
            self._diag_pub.publish(self.diagnostics_msg(self.get_clock().now().nanoseconds))
        except Exception as err:  # noqa: BLE001 - the last status is a courtesy; the outputs matter
            self.get_logger().warning(f"stopping: last /diagnostics status not published: {err}")
        self.await_acks(deadline)

    def await_acks(self, deadline: float) -> list[str]:
        """Wait until every reliable publisher's messages are acknowledged by its subscribers (a loaded
        machine can take seconds), all publishers together: one ``deadline`` (monotonic s) for them all
        (a publisher acknowledged is not waited for again; one still waiting when the time is up is
        checked without waiting). Logs and returns the topics whose subscribers did not acknowledge
        in time: they may have missed the end of the output."""
        pubs = [p for p in list(self._pubs.values()) + [self._diag_pub]
                if p.qos_profile.reliability == ReliabilityPolicy.RELIABLE and p.get_subscription_count() > 0]
        missed = []
        for pub in pubs:
            left = max(0.0, deadline - time.monotonic())
            if not pub.wait_for_all_acked(Duration(nanoseconds=int(left * 1e9))):
                missed.append(pub.topic_name)
        if missed:
            shown = ", ".join(missed[:10]) + (f" and {len(missed) - 10} more" if len(missed) > 10 else "")
            self.get_logger().warning(
                f"stopping: the subscribers of {len(missed)} of {len(pubs)} reliable outputs did not acknowledge "
                f"the last messages by the stop deadline; they may have missed the end of the output: {shown}")
        return missed
