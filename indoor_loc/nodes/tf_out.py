"""``/tf`` output of the estimators: their ``map -> <user>/odom`` corrections, as nav2_amcl broadcasts its own.

A stage with a correction (``Stage.MAP_ODOM``, :mod:`indoor_loc.pipeline.map_odom`) returns it as a
``geometry_msgs/TransformStamped`` output (``pf/map_odom``, latched, in every mode). A node with this
mixin also sends each one on ``/tf`` as ``tf2_msgs/TFMessage`` when its ``publish_tf`` parameter is
true (default: true for ``tll_pf``, the robot's localiser, as nav2_amcl's ``tf_broadcast``; false for
``pdr_kf_node`` and ``backend_node``, so only one node per robot owns ``map -> odom`` unless you
choose otherwise). Each transform on ``/tf`` is stamped ``transform_tolerance`` seconds after the
estimate it comes from, as nav2_amcl does: a tf user asking for ``map -> base_link`` at the
current time finds ``map -> odom`` valid until then instead of waiting for the next estimate (the
correction changes slowly; the odometry carries the motion in between).

Where ``tf2_msgs`` could not be built (``make venv`` says why), the node says once that ``/tf`` is not
published and the TransformStamped topics are the output.
"""
from __future__ import annotations

from typing import Any

from rcl_interfaces.msg import ParameterDescriptor

from indoor_loc.contract import Qos
from indoor_loc.errors import ConfigError
from indoor_loc.nodes.qos import qos_profile
from msg_adapters.tf import tf_message, tf_message_class

PUBLISH_TF_PARAM = "publish_tf"
TOLERANCE_PARAM = "transform_tolerance"
#: nav2_amcl's default ``transform_tolerance``, s
DEFAULT_TOLERANCE_S = 1.0
TF_TOPIC = "/tf"


class TfBroadcastMixin:
    """Mix in before :class:`~indoor_loc.nodes.stage_node.StageNode`; set ``PUBLISH_TF_DEFAULT``."""

    PUBLISH_TF_DEFAULT = False
    _tf_pub: Any = None
    _tf_tolerance_ns = 0

    def _declare_extra_params(self) -> None:
        super()._declare_extra_params()                          # type: ignore[misc]
        node: Any = self
        publish = node.declare_parameter(PUBLISH_TF_PARAM, bool(self.PUBLISH_TF_DEFAULT), ParameterDescriptor(
            description="send the map -> <user>/odom corrections on /tf (tf2_msgs/TFMessage) besides their "
                        "TransformStamped topic", read_only=True)).value
        tol = node.declare_parameter(TOLERANCE_PARAM, DEFAULT_TOLERANCE_S, ParameterDescriptor(
            description="s: each transform on /tf is stamped this much after its estimate (nav2_amcl's "
                        "transform_tolerance)", read_only=True)).value
        if not isinstance(publish, bool):
            raise ConfigError(f"{PUBLISH_TF_PARAM}: expected true or false, got {publish!r}")
        if not isinstance(tol, (int, float)) or isinstance(tol, bool) or not 0.0 <= float(tol) <= 60.0:
            raise ConfigError(f"{TOLERANCE_PARAM}: expected seconds in [0, 60], got {tol!r}")
        self._tf_tolerance_ns = int(float(tol) * 1e9)
        self._publish_tf = publish

    def _open_extra_outputs(self) -> None:
        """The /tf publisher (after the stage is built: only a stage with a correction has one)."""
        super()._open_extra_outputs()                            # type: ignore[misc]
        node: Any = self
        if not self._publish_tf or node.stage.MAP_ODOM is None:
            return
        cls = tf_message_class()
        if cls is None:
            node.get_logger().warning(
                "publish_tf is true but tf2_msgs is not installed (make venv builds it; see its output): "
                f"map -> odom is published on {node.stage.MAP_ODOM.out} only, NOT on /tf")
            return
        self._tf_pub = node.create_publisher(cls, TF_TOPIC, qos_profile(Qos.RELIABLE))

    def _publish(self, outs: list) -> None:
        super()._publish(outs)                                   # type: ignore[misc]
        if self._tf_pub is None:
            return
        node: Any = self
        spec = node.stage.MAP_ODOM
        ts = [m for t, m in outs if (p := node.stage.output_port(t)) is not None and p.topic == spec.out]
        if ts:
            try:
                self._tf_pub.publish(tf_message(ts, self._tf_tolerance_ns))
            except Exception as err:  # noqa: BLE001 - the estimates went out; /tf is an extra
                node.stage._reject("internal_error", f"/tf: {type(err).__name__}: {err}")
                node.get_logger().error(f"cannot publish on /tf: {err}", throttle_duration_sec=5.0)
