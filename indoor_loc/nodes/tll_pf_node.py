"""``ros2 run indoor_loc tll_pf``: the TLL particle filter on the building graph.

Besides the stage's topics the node offers ``~/global_localization`` (std_srvs/Empty, as
nav2_amcl): the particles are spread uniformly over the whole graph.
"""
from __future__ import annotations

from std_srvs.srv import Empty

from indoor_loc.nodes.lifecycle import node_factory
from indoor_loc.nodes.process import run_stage_node
from indoor_loc.nodes.set_pose import SetPoseMixin
from indoor_loc.nodes.stage_node import StageNode
from indoor_loc.nodes.tf_out import TfBroadcastMixin
from indoor_loc.pipeline.pf_stage import PfStage


#: parameter values that change the node's topics, named in its ``--help``
PORT_PARAMS = {"wifi_update": ("scan",), "motion_source": ("odom",)}


class TllPfNode(SetPoseMixin, TfBroadcastMixin, StageNode):
    PUBLISH_TF_DEFAULT = True          # the robot's localiser owns map -> odom, as nav2_amcl (tf_broadcast)

    def __init__(self) -> None:
        super().__init__(PfStage)
        self.create_service(Empty, "~/global_localization", self._on_global_localization)

    def _on_global_localization(self, request: Empty.Request, response: Empty.Response) -> Empty.Response:
        now = self.get_clock().now().nanoseconds
        try:
            self._publish(self.stage.global_localization(now))
            self.get_logger().info("global localisation: particles spread over the whole graph")
        except Exception as err:  # noqa: BLE001 - a node never dies on a request
            self.stage._reject("internal_error", f"global_localization: {type(err).__name__}: {err}")
            self.get_logger().error(f"global_localization failed: {err}", throttle_duration_sec=5.0)
        return response


def main(args: list[str] | None = None) -> int:
    return run_stage_node(PfStage, args, node_factory=node_factory(TllPfNode, args), port_params=PORT_PARAMS)


if __name__ == "__main__":
    raise SystemExit(main())
