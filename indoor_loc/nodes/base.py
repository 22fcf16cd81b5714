"""StageNode: runs a :class:`~indoor_loc.pipeline.stage.Stage` as an rclpy node.

- ROS parameters are declared from the stage's Params dataclass (defaults and docs in one place);
  invalid values stop start-up with a clear error, and later ``ros2 param set`` calls that would
  make the Params invalid are refused.
- Subscriptions/publishers come from the stage's ports with the contract's QoS.
- A bad message is logged (throttled), counted and dropped; the node keeps running.
- ``/diagnostics`` gets one DiagnosticStatus about once a second.
"""
from __future__ import annotations

import dataclasses
import sys
from typing import Any, Callable

import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from rcl_interfaces.msg import ParameterDescriptor, SetParametersResult
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.qos import (DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy)

from indoor_loc.contract import Qos, msg_class
from indoor_loc.errors import IndoorLocError
from indoor_loc.msg_adapters.diagnostics import stage_diagnostics
from indoor_loc.params import params_from_dict
from indoor_loc.pipeline.stage import Stage

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


def qos_profile(qos: Qos) -> QoSProfile:
    return QOS_PROFILES[qos]


def _ros_value(value: Any) -> Any:
    # rclpy cannot declare an empty list without a type; represent it as an empty string array.
    if isinstance(value, tuple):
        value = list(value)
    return value


class StageNode(Node):
    """An rclpy Node that feeds a Stage and publishes what it returns."""

    def __init__(self, stage_cls: type[Stage], **node_kwargs: Any) -> None:
        super().__init__(stage_cls.NODE_NAME, **node_kwargs)
        self._stage_cls = stage_cls
        values = self._declare_params(stage_cls.PARAMS)
        params = params_from_dict(stage_cls.PARAMS, values)   # raises ConfigError -> start-up fails
        self.stage: Stage = stage_cls(params, namespace=self.get_namespace())
        self.add_on_set_parameters_callback(self._on_set_params)
        self._pubs = {p.topic: self.create_publisher(msg_class(p.type), p.topic, qos_profile(p.qos))
                      for p in self.stage.outputs()}
        self._subs = [self.create_subscription(msg_class(p.type), p.topic, self._callback(p.topic),
                                               qos_profile(p.qos)) for p in self.stage.inputs()]
        self._diag_pub = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self._last_rejected = 0
        self.create_timer(1.0, self._on_timer)
        self.get_logger().info(
            f"{stage_cls.NODE_NAME} up: in {[p.topic for p in self.stage.inputs()]}, "
            f"out {[p.topic for p in self.stage.outputs()]}")

    # -- parameters ------------------------------------------------------------------------------
    def _declare_params(self, params_cls: type) -> dict[str, Any]:
        values: dict[str, Any] = {}
        for f in dataclasses.fields(params_cls):
            default = f.default if f.default is not dataclasses.MISSING else f.default_factory()  # type: ignore[misc]
            desc = ParameterDescriptor(description=f.metadata.get("doc", ""))
            if isinstance(default, (list, tuple)) and len(default) == 0:
                from rclpy.parameter import Parameter
                p = self.declare_parameter(f.name, Parameter.Type.STRING_ARRAY, desc)
                values[f.name] = list(p.value) if p.value is not None else []
                continue
            p = self.declare_parameter(f.name, _ros_value(default), desc)
            values[f.name] = list(p.value) if isinstance(p.value, (list, tuple)) else p.value
        return values

    def _on_set_params(self, changes: list) -> SetParametersResult:
        current = dataclasses.asdict(self.stage.params)
        current.update({p.name: p.value for p in changes})
        try:
            params_from_dict(self._stage_cls.PARAMS, current)
        except IndoorLocError as err:
            return SetParametersResult(successful=False, reason=str(err))
        # Parameters are read at start-up; changing them live needs a restart of the node.
        return SetParametersResult(successful=False, reason="parameters are read-only at run time; restart the node")

    # -- messages ----------------------------------------------------------------------------------
    def _callback(self, topic: str) -> Callable[[Any], None]:
        def cb(msg: Any) -> None:
            now_ns = self.get_clock().now().nanoseconds
            self._publish(self.stage.process(topic, msg, now_ns))
            self._log_rejections()
        return cb

    def _publish(self, outs: list) -> None:
        for topic, msg in outs:
            pub = self._pubs.get(topic)
            if pub is None:
                self.get_logger().error(f"stage returned undeclared output topic {topic!r}", throttle_duration_sec=5.0)
                continue
            pub.publish(msg)

    def _log_rejections(self) -> None:
        total = sum(self.stage.diag.rejected.values())
        if total != self._last_rejected:
            self._last_rejected = total
            self.get_logger().warning(
                f"dropped message ({self.stage.diag.last_error_reason}; {total} so far): "
                f"{self.stage.diag.last_error.splitlines()[0] if self.stage.diag.last_error else ''}",
                throttle_duration_sec=5.0)

    def _on_timer(self) -> None:
        now_ns = self.get_clock().now().nanoseconds
        self._publish(self.stage.tick(now_ns))
        self._diag_pub.publish(self.diagnostics_msg(now_ns))

    def diagnostics_msg(self, now_ns: int) -> DiagnosticArray:
        return stage_diagnostics(self.get_fully_qualified_name(), self.stage, now_ns)

    def shutdown(self) -> None:
        self._publish(self.stage.finish())


def run_stage_node(stage_cls: type[Stage], args: list[str] | None = None) -> int:
    """``main()`` of every stage node, in the Jazzy form."""
    argv = sys.argv if args is None else args
    if any(a in ("-h", "--help") for a in argv[1:]) and "--ros-args" not in argv:
        print(node_usage(stage_cls))
        return 0
    rclpy.init(args=argv)
    node = None
    try:
        node = StageNode(stage_cls)
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except IndoorLocError as err:
        print(f"[{stage_cls.NODE_NAME}] configuration error: {err}", file=sys.stderr)
        return 2
    finally:
        if node is not None:
            try:
                node.shutdown()
            except Exception:  # noqa: BLE001 - context may already be shut down
                pass
            node.destroy_node()
        rclpy.try_shutdown()
    return 0


def node_usage(stage_cls: type[Stage]) -> str:
    lines = [f"usage: ros2 run indoor_loc {stage_cls.NODE_NAME} [--ros-args -r __ns:=/USER "
             f"--params-file FILE -p NAME:=VALUE ...]", "", (stage_cls.__doc__ or "").strip(), "", "parameters:"]
    for f in dataclasses.fields(stage_cls.PARAMS):
        default = f.default if f.default is not dataclasses.MISSING else f.default_factory()  # type: ignore[misc]
        lines.append(f"  {f.name} (default {default!r}): {f.metadata.get('doc', '')}")
    stage = stage_cls(stage_cls.PARAMS(), namespace="")
    lines.append("")
    lines.append("subscribes: " + ", ".join(f"{p.topic} [{p.type}]" for p in stage.inputs()))
    lines.append("publishes:  " + ", ".join(f"{p.topic} [{p.type}]" for p in stage.outputs()) + ", /diagnostics")
    return "\n".join(lines)
