"""``ros2 run indoor_loc pdr_kf_node``: Raitoharju et al. 2015 linear PDR Kalman filter + RTS smoother.

Besides the stage's topics: ``map -> <user>/odom`` on ``/tf`` when ``publish_tf`` (default false;
``pdr_kf/map_odom`` always), see :mod:`indoor_loc.nodes.tf_out`.
"""
from __future__ import annotations

from indoor_loc.nodes.lifecycle import node_factory
from indoor_loc.nodes.process import run_stage_node
from indoor_loc.nodes.set_pose import SetPoseMixin
from indoor_loc.nodes.stage_node import StageNode
from indoor_loc.nodes.tf_out import TfBroadcastMixin
from indoor_loc.pipeline.pdr_kf_stage import PdrKfStage


#: parameter values that change the node's topics, named in its ``--help``
PORT_PARAMS = {"motion_source": ("odom",)}


class PdrKfNode(SetPoseMixin, TfBroadcastMixin, StageNode):
    def __init__(self) -> None:
        super().__init__(PdrKfStage)


def main(args: list[str] | None = None) -> int:
    return run_stage_node(PdrKfStage, args, node_factory=node_factory(PdrKfNode, args), port_params=PORT_PARAMS)


if __name__ == "__main__":
    raise SystemExit(main())
