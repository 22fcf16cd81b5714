"""``ros2 run indoor_loc backend_node``: the multi-user factor-graph back-end (one node for all users).

Clock jumps back are said as one WARN each (the stage's notices): a user's own stamps going back
(:class:`~indoor_loc.pipeline.backend_stage.BackendStage`), and, under ``use_sim_time``, ``/clock``
going back by more than the stage's threshold (a bag played with ``--loop`` or a simulation
restarted; :class:`~indoor_loc.nodes.stage_node.StageNode` follows ``/clock`` for every stage).
"""
from __future__ import annotations

from indoor_loc.nodes.lifecycle import node_factory
from indoor_loc.nodes.process import run_stage_node
from indoor_loc.nodes.set_pose import SetPoseMixin
from indoor_loc.nodes.stage_node import StageNode
from indoor_loc.nodes.tf_out import TfBroadcastMixin
from indoor_loc.pipeline.backend_stage import BackendStage


#: parameter values that change the node's topics, named in its ``--help``
PORT_PARAMS = {"wifi_source": ("fix",), "motion_source": ("odom",)}   # (any: both motion topics)


class BackendNode(SetPoseMixin, TfBroadcastMixin, StageNode):
    """Besides the stage's topics: each user's ``map -> <user>/odom`` on ``/tf`` when ``publish_tf``
    (default false; ``backend/<user>/map_odom`` always), see :mod:`indoor_loc.nodes.tf_out`."""

    def __init__(self) -> None:
        super().__init__(BackendStage)


def main(args: list[str] | None = None) -> int:
    return run_stage_node(BackendStage, args, node_factory=node_factory(BackendNode, args), port_params=PORT_PARAMS)


if __name__ == "__main__":
    raise SystemExit(main())
